"""``spacegrasp compare``: runs overlaid on the paper's figures."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from spacegrasp_jax.cli.common import _claim, _file_name, _run_schedule, _save_schedule_figure, gain_set_labels
from spacegrasp_jax.cli.options import UsageError, _add_command, _add_overwrite_option
from spacegrasp_jax.jobs import experiment, runfiles
from spacegrasp_jax.loop.realism import ideal


def _run_descriptors(folder: Path, key: str, config: dict) -> dict:
    """What one run of a run folder (``key``: a law, or a campaign variant ``law/gains``)
    was: its law, robot, loop, gains, target and folder, for ``compare`` to label runs by
    what differs between them."""
    if "record" in config:
        record = config["record"]
        scenario, sources = record["scenario"], record["sources"]
        realism = "ideal" if record["realism"] == ideal().to_dict() else "custom"
        loop = sources.get("realism") or realism
        law, _, label = key.partition("/")
        labels = [v["label"] for v in record["variants"] if v["controller"] == law and label in ("", v["label"])]
        gains = labels[0] if labels else "?"
        gains_source = sources.get("gains")
        if "sample" in sources:  # a replay of a campaign's sample
            loop = ("ideal" if realism == "ideal" else "flight-like") + f" (sample {sources['sample']})"
        robot_source = sources.get("robot")
    elif "campaign_record" in config:  # a replay of an older version: the campaign's settings
        record = config["campaign_record"]
        realism, scenario = record["config"]["realism"], record["scenario"]
        robot_source = record.get("robot")
        loop = "ideal" if realism == ideal().to_dict() else "flight-like"
        gains = gains_source = key.split("/", 1)[1]
        loop += f" (sample {config['sample']})"
    else:
        scenario = config["scenario"]
        source = config.get("realism_source")
        loop = source if source else ("ideal" if config["realism"] == ideal().to_dict() else "custom")
        gains = Path(config["gains_source"]).stem if config.get("gains_source") else "paper"
        gains_source = config.get("gains_source")
        robot_source = config.get("robot")
    target = "fixed" if scenario.get("target") is None else f"free {scenario['target']['mass']:g} kg"
    robot = "paper" if robot_source in (None, "paper_robot()") else Path(robot_source).stem
    return {
        "law": key.split("/", 1)[0],
        "robot": robot,
        "loop": loop,
        "gains": gains,
        "target": target,
        "run": folder.name,
        "gains_source": gains_source or gains,
    }


def _tell_gains_apart(descriptors: list[dict]) -> None:
    """Gains of one label read from different files (two tuning runs' ``gains.json``) are
    labelled by as many of their folders as it takes to tell them apart."""
    for label in {d["gains"] for d in descriptors}:
        same = [d for d in descriptors if d["gains"] == label]
        sources = list(dict.fromkeys(d["gains_source"] for d in same))
        if len(sources) > 1:
            told = dict(zip(sources, gain_set_labels(sources)))
            for d in same:
                d["gains"] = told[d["gains_source"]]


def _compare(args: argparse.Namespace) -> int:
    """``spacegrasp compare RUN_DIR...``: the runs of several run folders (``simulate``,
    ``reproduce``, ``replay``) on the paper's figures and in one table, each labelled by
    what differs between them."""
    runs = []
    for name in args.runs:
        folder = Path(name)
        if not (folder / "config.json").is_file() or not (folder / "summary.json").is_file():
            raise UsageError(
                f"{folder}: not a run folder of simulate, reproduce or replay (no config.json and summary.json)"
            )
        config = json.loads((folder / "config.json").read_text())
        summaries = json.loads((folder / "summary.json").read_text())
        for key in summaries:
            path = folder / f"timeseries_{_file_name(key)}.npz"
            if path.is_file():
                runs.append((folder, key, config, summaries[key], path))
    if len(runs) < 2:
        raise UsageError(f"compare: needs at least two runs, found {len(runs)} in {', '.join(args.runs)}")
    out = Path(args.out)
    _claim(args, out)
    descriptors = [_run_descriptors(folder, key, config) for folder, key, config, _, _ in runs]
    _tell_gains_apart(descriptors)
    for d in descriptors:
        del d["gains_source"]
    differing = [name for name in descriptors[0] if len({d[name] for d in descriptors}) > 1 and name != "run"]
    if not differing or len({tuple(d[name] for name in differing) for d in descriptors}) < len(runs):
        differing.append("run")
    labels = [", ".join(f"{name} {d[name]}" for name in differing) for d in descriptors]
    common = ", ".join(
        f"{name} {descriptors[0][name]}" for name in descriptors[0] if name not in differing and name != "run"
    )
    logs = {label: experiment.read_log(path) for label, (_, _, _, _, path) in zip(labels, runs)}
    table = {}
    width = max(40, *(len(label) for label in labels))
    print(
        f"\n{'run':{width}} {'final pos [mm]':>15} {'orient [deg]':>13} {'peak |u| [N m]':>15} {'contact [N]':>12}  capture"
    )
    for label, (_, _, _, summary, _) in zip(labels, runs):
        numbers = {
            "final_position_error_m": summary.get("final_position_error_m"),
            "final_orientation_error_rad": summary.get("final_orientation_error_rad"),
            "largest_peak_torque_Nm": summary.get("largest_peak_torque_Nm"),
            "max_contact_force_N": summary.get("max_contact_force_N"),
            "capture_success": summary.get("capture_success"),
            "max_abs_torque_Nm": summary.get("max_abs_torque_Nm"),
        }
        table[label] = numbers
        cells = [
            f"{1e3 * numbers['final_position_error_m']:>15.3f}"
            if numbers["final_position_error_m"] is not None
            else f"{'-':>15}",
            f"{np.degrees(numbers['final_orientation_error_rad']):>13.4f}"
            if numbers["final_orientation_error_rad"] is not None
            else f"{'-':>13}",
            f"{numbers['largest_peak_torque_Nm']:>15.3f}"
            if numbers["largest_peak_torque_Nm"] is not None
            else f"{'-':>15}",
            f"{numbers['max_contact_force_N']:>12.2f}" if numbers["max_contact_force_N"] is not None else f"{'-':>12}",
        ]
        verdict = {True: "yes", False: "no", None: "-"}[numbers["capture_success"]]
        print(f"{label:{width}} {' '.join(cells)}  {verdict}")
    caption = f"compared: {common}" if common else "compared"
    from spacegrasp_jax.analysis import plots

    plots.save_figures(logs, out, runfiles.write_atomically, caption=caption)
    regimes = []  # the runs of a gain schedule: the regime each was in
    for index, ((folder, key, config, _, _), descriptor) in enumerate(zip(runs, descriptors), start=1):
        schedule = _run_schedule(folder, config, descriptor["law"], np.shape(logs[labels[index - 1]].u)[-1])
        if schedule is not None:
            regimes += _save_schedule_figure(
                out, schedule, {f"run_{index}": logs[labels[index - 1]]}, with_curves=False
            )
    runfiles.write_json(
        out / "compare.json",
        {
            "runs": [
                {"label": label, "folder": str(folder), "key": key, **d}
                for label, (folder, key, *_), d in zip(labels, runs, descriptors)
            ],
            "differing": differing,
            "common": common,
            "table": table,
            **runfiles.provenance(),
        },
    )
    figures = f"the figures of {len(runs)} runs" + (
        f" ({', '.join(regimes)}: the schedules' regimes)" if regimes else ""
    )
    print(f"wrote {out}/: compare.json and {figures}, labelled by {', '.join(differing)}")
    return 0


def add_parsers(commands) -> None:
    """The command's parser, added to ``commands``."""
    compare = _add_command(
        commands, "compare", help="overlay runs of simulate, reproduce or replay on the paper's figures"
    )
    compare.add_argument("runs", nargs="+", metavar="RUN_DIR", help="run folders (each may hold several runs)")
    compare.add_argument("--out", required=True, help="output folder")
    _add_overwrite_option(compare)
    compare.set_defaults(run=_compare)
