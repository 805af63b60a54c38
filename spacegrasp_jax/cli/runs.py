"""``spacegrasp reproduce``, ``simulate`` and ``replay``: closed-loop runs, with their torque
table, verdicts, figures and files."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import jax
import numpy as np

from spacegrasp_jax.cli.common import (
    _claim,
    _films,
    _gains_option,
    _gains_record,
    _is_papers_run,
    _keep_inputs,
    _law,
    _load_inputs,
    _loop_words,
    _perturbed,
    _print_capture_verdicts,
    _print_table,
    _rate_criterion,
    _realism,
    _robot_links,
    _run_caption,
    _save_schedule_figure,
    _warn,
    _write_results,
    gains_label,
)
from spacegrasp_jax.cli.options import (
    _SEED,
    CAPTURE_FAILED,
    UsageError,
    _add_animate_option,
    _add_command,
    _add_compile_cache_option,
    _add_csv_option,
    _add_overwrite_option,
    _add_realism_option,
    _add_run_options,
    _add_strict_option,
    _whole,
    add_gains_arguments,
)
from spacegrasp_jax.envelope import plausibility
from spacegrasp_jax.envelope.criteria import CaptureCriteria
from spacegrasp_jax.jobs import campaign, experiment, records, runfiles
from spacegrasp_jax.jobs.records import Variant, make_record
from spacegrasp_jax.loop.control import (
    CONTROLLERS,
    PAPER_CONTROLLERS,
)
from spacegrasp_jax.loop.control.schedule import GainSchedule
from spacegrasp_jax.loop.simulate import RunSpec


def _same_reproduction(out: Path, args: argparse.Namespace) -> bool:
    """Whether ``out`` holds a ``reproduce`` run of exactly this command line and nothing the
    tool did not write."""
    marker = runfiles.read_run_marker(out)
    if not marker or marker.get("command") != "reproduce" or marker.get("kept_files"):
        return False
    try:
        recorded = json.loads((out / "config.json").read_text())["record"]["command"]
    except (OSError, ValueError, KeyError, TypeError):
        return False
    return recorded == list(getattr(args, "command_line", None) or [])


def _run_controllers(args, controllers) -> int:
    robot, scenario, gains = _load_inputs(args, schedules=True)
    rate_limits = _rate_criterion(args, robot)
    criteria = CaptureCriteria(joint_rate_limits_radps=rate_limits)
    laws = {controller: _law(controller, args) for controller in controllers}
    realism = _realism(args, scenario, robot)
    _warn(plausibility.input_warnings(scenario))
    key = jax.random.PRNGKey(getattr(args, "seed", 0))
    nominal = RunSpec(robot, scenario, realism=realism)
    if getattr(args, "perturbation", None):
        nominal, key = _perturbed(args.perturbation, nominal)
    robot, scenario, realism = nominal.robot, nominal.scenario, nominal.realism
    out = Path(args.out)
    if args.command == "reproduce" and not args.overwrite and _same_reproduction(out, args):
        # The paper's reproduction run again by the same command writes the same files:
        # replacing them loses nothing (the README's warm rerun).
        print(f"replacing the reproduction in {out} (the same command's; --out DIR keeps it)", flush=True)
        args = argparse.Namespace(**vars(args))
        args.overwrite = True
    _claim(args, out)  # before the first compile, not after the run
    results, diverged = {}, []
    for controller in controllers:
        print(
            f"running the {controller} controller over {scenario.duration:g} s (dt = {scenario.dt:g} s)...", flush=True
        )
        try:
            results[controller] = experiment.run(
                dataclasses.replace(nominal, controller=laws[controller]), gains, key=key
            )
        except experiment.SimulationDiverged as error:  # keep what it has: written below
            results[controller] = error.result
            diverged.append(error)
    _print_table(results, beside_paper=_is_papers_run(args))
    failed_captures = _print_capture_verdicts(results, criteria)
    for controller, result in results.items():
        _warn(plausibility.result_warnings(result.summary), f"{controller}: ")
    gains_value = getattr(args, "gains", None)
    sources = {
        "robot": args.robot or "paper_robot()",
        "robot_links": _robot_links(args) or None,
        "scenario": getattr(args, "scenario", None) or "paper_scenario()",
        **_gains_record(gains_value, args, list(controllers)),
        "realism": args.realism if "realism" in args else None,
        "perturbation": getattr(args, "perturbation", None),
    }
    record = make_record(
        robot,
        scenario,
        [Variant(controller, gains, gains_label(gains_value)) for controller in controllers],
        realism=realism,
        criteria=criteria,
        pinv_damping=args.pinv_damping,
        model_robot=nominal.model_robot,
        key=key,
        command=getattr(args, "command_line", None),
        sources=sources,
    )
    config = {"record": record.to_dict(), "robot_file": None}
    if args.robot or getattr(args, "perturbation", None):  # the robot as it ran, for --robot
        source = args.robot or "paper_robot()"
        if getattr(args, "perturbation", None):
            source += f", perturbed as {args.perturbation} says"
        config["robot_file"] = runfiles.write_robot(
            out, robot, source, _robot_links(args), rate_limits_stated=rate_limits is not None
        )
    config |= _keep_inputs(args, out, gains, realism, controllers)
    _write_results(
        out,
        results,
        config,
        beside_paper=_is_papers_run(args),
        caption=_run_caption(
            _loop_words(sources["realism"]),
            "the paper's gains" if gains_value is None else f"gains {Path(gains_value).name}",
            scenario,
        ),
        torque_limit_Nm=np.asarray(robot.joint_torque_limit),
        csv=args.csv,
        criteria=criteria,
    )
    if isinstance(gains, GainSchedule):
        _save_schedule_figure(out, gains, {controller: result.log for controller, result in results.items()})
    print(
        f"wrote {out}/: table5.csv, summary.json, figures, timeseries_*.npz{', .csv' if args.csv else ''}, config.json"
    )
    if getattr(args, "animate", False):
        ran_away = {error.controller for error in diverged}
        logs = {controller: result.log for controller, result in results.items() if controller not in ran_away}
        schedule = gains if isinstance(gains, GainSchedule) else None
        _films(args, out, list(logs), robot, scenario, logs, schedule=schedule)
    for error in diverged:
        print(
            f"spacegrasp: error: {error}; its log up to that step and the state there are in {out}/",
            file=sys.stderr,
        )
    return 3 if diverged else _strict_code(args, failed_captures)


def _strict_code(args: argparse.Namespace, failed: list[str]) -> int:
    """0, or under ``--strict`` ``CAPTURE_FAILED`` with one line naming the failed captures."""
    if args.strict and failed:
        print(f"spacegrasp: capture failed ({', '.join(failed)}): exit {CAPTURE_FAILED} (--strict)", file=sys.stderr)
        return CAPTURE_FAILED
    return 0


def _reproduce(args: argparse.Namespace) -> int:
    return _run_controllers(args, PAPER_CONTROLLERS)


def _simulate(args: argparse.Namespace) -> int:
    return _run_controllers(args, [args.controller])


def _replay(args: argparse.Namespace) -> int:
    """``spacegrasp replay CAMPAIGN --sample K``: one sample of a campaign again, with its
    full log, as the campaign ran it (plant, scenario, loop, noise), for each variant."""
    folder = Path(args.campaign)
    try:
        nominal, config = campaign.campaign_record(folder)
    except campaign.CampaignError as error:
        raise UsageError(str(error)) from None
    if args.sample >= config.n:
        raise UsageError(f"--sample: {args.sample} is beyond the campaign's {config.n} samples (0 to {config.n - 1})")
    variants = nominal.variants
    if args.variant is not None:
        variants = [variant for variant in variants if variant.key == args.variant]
        if not variants:
            keys = ", ".join(variant.key for variant in nominal.variants)
            raise UsageError(f"--variant: {folder} has no variant {args.variant!r}; it has {keys}")
    if args.gains is not None:  # the sample with other gains (the ceiling's, tuned for it)
        laws = sorted({variant.controller for variant in variants})
        if len(laws) != 1:
            raise UsageError(f"--gains: {folder} runs the laws {', '.join(laws)}; name one variant with --variant")
        gains = _gains_option(args.gains, args, nominal.robot, laws[0], schedules=True)
        variants = [Variant(laws[0], gains, gains_label(args.gains))]
    out = Path(args.out)
    _claim(args, out)
    sample = campaign.sample_record(nominal, config, args.sample, variants)
    sample = dataclasses.replace(
        sample,
        command=getattr(args, "command_line", None),
        sources=nominal.sources | {"campaign": str(folder), "sample": args.sample},
    )
    results = {}
    for variant in variants:
        print(f"replaying sample {args.sample} of {folder} with {variant.key}...", flush=True)
        results |= records.replay(dataclasses.replace(sample, variants=(variant,)), check=False)
    _print_table(results, beside_paper=False)
    failed = _print_capture_verdicts(results, config.criteria)
    for key, result in results.items():
        _warn(plausibility.result_warnings(result.summary), f"{key}: ")
    loop = "ideal loop" if config.realism is None else "flight-like loop"
    record = {"record": sample.to_dict(), "campaign": str(folder), "sample": args.sample}
    robot, scenario = nominal.robot, nominal.scenario
    _write_results(
        out,
        results,
        record,
        beside_paper=False,
        caption=_run_caption(f"sample {args.sample} of the campaign {folder.name}: {loop}", "its gains", scenario),
        torque_limit_Nm=np.asarray(robot.joint_torque_limit),
        csv=args.csv,
        criteria=config.criteria,
    )
    scheduled = [variant for variant in variants if isinstance(variant.gains, GainSchedule)]
    for variant in scheduled:  # the regime each schedule's replay was in; its curves when it is the only one
        logs = {variant.key: results[variant.key].log}
        _save_schedule_figure(out, variant.gains, logs, with_curves=len(scheduled) == 1)
    print(
        f"wrote {out}/: table5.csv, summary.json, figures, timeseries_*.npz{', .csv' if args.csv else ''}, config.json"
    )
    return _strict_code(args, failed)


def add_parsers(commands) -> None:
    """The command's parsers, added to ``commands``."""
    reproduce = _add_command(
        commands, "reproduce", help="run both controllers with the paper's gains: Table 5 and Figures 4-9"
    )
    _add_run_options(reproduce, "results/reproduce")
    _add_animate_option(reproduce)
    _add_csv_option(reproduce, "the time series")
    _add_strict_option(reproduce)
    _add_compile_cache_option(reproduce)
    reproduce.set_defaults(run=_reproduce)
    simulate = _add_command(commands, "simulate", help="run one controller with any gains and scenario")
    simulate.add_argument(
        "--controller",
        choices=CONTROLLERS,
        default="admittance",
        help="the control law (default: admittance, the paper's active force/torque law)",
    )
    add_gains_arguments(simulate)
    simulate.add_argument("--scenario", help="scenario TOML or JSON file (default: the paper's)")
    _add_realism_option(simulate)
    simulate.add_argument("--seed", type=_SEED, default=0, help="seed of the sensors' noise key (default 0)")
    simulate.add_argument(
        "--perturbation",
        metavar="FILE",
        help="run the capture a perturbation file describes (worstcase's worst_perturbation.json), "
        "with its noise key, on the nominal robot and scenario",
    )
    _add_run_options(simulate, "results/simulate")
    _add_animate_option(simulate)
    _add_csv_option(simulate, "the time series")
    _add_strict_option(simulate)
    _add_compile_cache_option(simulate)
    simulate.set_defaults(run=_simulate)
    replay = _add_command(commands, "replay", help="run one sample of a campaign again with its full log and figures")
    replay.add_argument("campaign", metavar="CAMPAIGN_DIR", help="a montecarlo output folder")
    replay.add_argument("--sample", type=_whole(0, 100_000_000), required=True, metavar="K", help="the sample's index")
    replay.add_argument(
        "--variant", metavar="LAW/GAINS", help="one variant, e.g. admittance/paper (default: every one)"
    )
    replay.add_argument(
        "--gains",
        metavar="NAME|FILE",
        help="run the sample with these gains (a shipped set, a gains or schedule file: ceiling's gains/) instead of "
        "the variant's, in the variant's law",
    )
    replay.add_argument("--out", required=True, help="output folder")
    _add_overwrite_option(replay)
    _add_csv_option(replay, "the time series")
    _add_strict_option(replay)
    _add_compile_cache_option(replay)
    replay.set_defaults(run=_replay)
