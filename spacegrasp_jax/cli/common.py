"""What several commands share: reading their inputs before anything compiles, claiming the
output folder, warnings, the capture verdicts and the run files."""

from __future__ import annotations

import argparse
import functools
import math
import sys
from pathlib import Path

import jax
import numpy as np
from jax.experimental import multihost_utils

import spacegrasp_jax as sg
from spacegrasp_jax import (
    anatomy,
    animation,
    campaign,
    paper,
    runfiles,
    worstcase,
)
from spacegrasp_jax.cli.options import NAMED_RANGES, UsageError
from spacegrasp_jax.control import (
    GAINS_USED,
    PAPER_CONTROLLERS,
    law_named,
    load_gains,
    paper_gains,
)
from spacegrasp_jax.model import n_joints
from spacegrasp_jax.perturbations import (
    PerturbationRanges,
    load_ranges,
)
from spacegrasp_jax.realism import Realism, RealismError, load_realism
from spacegrasp_jax.scenario import load_scenario, paper_scenario


def _load_inputs(args):
    """Robot, scenario and gains from the command line, validated before any compile."""
    robot = sg.load_robot(args.robot) if args.robot else sg.paper_robot()
    scenario = load_scenario(robot, args.scenario) if getattr(args, "scenario", None) else paper_scenario(robot)
    controller = getattr(args, "controller", None)
    gains = (
        load_gains(args.gains, controller, n_joints(robot))
        if getattr(args, "gains", None)
        else _paper_gains_for(robot, controller)
    )
    return robot, scenario, gains


def _paper_gains_for(robot, controller: str | None = None) -> sg.control.Gains:
    """The paper's gains, when the arm is the paper's 7-joint one (Table 4 is for it) and the
    law one of the paper's (``None``: any)."""
    if controller is not None and controller not in PAPER_CONTROLLERS:
        raise UsageError(
            f"--gains: required for the {controller} law, a file with its {', '.join(GAINS_USED[controller])} "
            f"(the paper's gains are for its {' and '.join(PAPER_CONTROLLERS)} laws)"
        )
    if n_joints(robot) != len(paper_gains().kp):
        raise UsageError(
            f"--gains: required for an arm of {n_joints(robot)} joints (the paper's Table 4 gains are for its "
            f"{len(paper_gains().kp)}); give a gains file with kp, ki and kd for each joint"
        )
    return paper_gains()


def _law(controller: str, args: argparse.Namespace):
    """The law ``controller`` with ``--pinv-damping`` (refused for a law with no pseudoinverse)."""
    try:
        return law_named(controller, getattr(args, "pinv_damping", 0.0))
    except ValueError as error:
        raise UsageError(f"--pinv-damping: {error}") from None


def _realism(args, scenario) -> Realism | None:
    """``--realism`` (a preset or a file), checked against the scenario before compiling."""
    if getattr(args, "realism", None) is None:
        return None
    realism = load_realism(args.realism)
    try:
        realism.check_timing(scenario.dt, scenario.n_steps)
        realism.check_joints(scenario.initial.q.shape[-1])
    except RealismError as error:
        raise RealismError(f"--realism {args.realism}: {error}") from None
    return realism


def _perturbed(path: str, spec):
    """``--perturbation FILE``: the nominal run ``spec`` perturbed as the file says and its
    noise key ([`worstcase.perturbed_spec()`][spacegrasp_jax.worstcase.perturbed_spec])."""
    try:
        return worstcase.perturbed_spec(spec, path)
    except worstcase.WorstCaseError as error:
        raise UsageError(f"--perturbation {error}") from None


def _ranges(args: argparse.Namespace, default: PerturbationRanges) -> PerturbationRanges:
    """``default``, or the ``--ranges`` envelope (a name of ``NAMED_RANGES`` or a TOML
    file whose missing keys are ``default``'s), then each ``--range NAME=VALUE``."""
    if args.ranges in NAMED_RANGES:
        ranges = NAMED_RANGES[args.ranges]
    else:
        ranges = load_ranges(args.ranges, base=default) if args.ranges else default
    overrides = {}
    for item in args.range:
        name, separator, value = item.partition("=")
        if not separator:
            raise UsageError(f"--range {item!r}: expected NAME=VALUE, e.g. q_init_rad=0.05")
        try:
            overrides[name.strip()] = float(value)
        except ValueError:
            raise UsageError(f"--range {item!r}: {value!r} is not a number") from None
    return PerturbationRanges.from_mapping(overrides, base=ranges)


def _check_envelope(args: argparse.Namespace, scenario) -> None:
    """``--ranges free_target`` draws targets: refused for a scenario without one."""
    if getattr(args, "ranges", None) == "free_target" and not scenario.free_target:
        raise UsageError(
            "--ranges free_target: needs a scenario with a free-floating [target], e.g. --scenario configs/free_target_envelope.toml"
        )


def _criteria(args: argparse.Namespace, **fields) -> campaign.CampaignConfig:
    """The campaign's settings with the capture criteria of ``_add_criteria_options()``; the
    law's damping checked (``--pinv-damping``) before anything compiles."""
    if args.controller != "both":
        _law(args.controller, args)
    try:
        return campaign.CampaignConfig(
            position_tolerance_m=args.tolerance_mm * 1e-3,
            orientation_tolerance_rad=math.radians(args.tolerance_deg),
            torque_limit_Nm=args.torque_limit if args.torque_limit > 0 else None,
            target_speed_limit_mps=args.target_speed_limit,
            pinv_damping=args.pinv_damping,
            identified=args.identified,
            **fields,
        )
    except campaign.CampaignError as error:
        raise UsageError(str(error)) from None


def _claim(args: argparse.Namespace, out: Path) -> None:
    """The command's output folder, refused if it holds anything (another run, or files
    this tool did not write) unless ``--overwrite`` or ``--resume`` says what to do
    (``spacegrasp_jax.runfiles.claim_output_folder()``). Several processes: every one
    checks the folder, then the first claims it."""
    claim = functools.partial(
        runfiles.claim_output_folder,
        out,
        args.command,
        overwrite=args.overwrite,
        resume=bool(getattr(args, "resume", False)),
    )
    if not getattr(args, "distributed", False):  # one process (no device query: backends stay uninitialised)
        claim()
        return
    claim(write=False)
    multihost_utils.sync_global_devices("spacegrasp: output folder checked")
    if jax.process_index() == 0:
        claim()
    multihost_utils.sync_global_devices("spacegrasp: output folder claimed")


def _warn(lines: list[str], prefix: str = "") -> None:
    """Each line as ``spacegrasp: warning: ...`` on stderr (``spacegrasp_jax.plausibility``)."""
    for line in lines:
        print(f"spacegrasp: warning: {prefix}{line}", file=sys.stderr, flush=True)


def _print_capture_verdicts(results: dict, criteria: campaign.CampaignConfig | None = None) -> list[str]:
    """Each run's capture verdict by ``criteria`` (default: the campaigns' defaults): one line that says why
    a failed capture failed (a result, not an error: exit 0 unless ``--strict``), or the margins of a
    success; with a free-floating target, one more line for the target's motion. Returns the keys
    of ``results`` whose capture failed (a diverged run is not among them: it has its own exit code)."""
    tolerances = campaign.capture_criteria(criteria)
    failed = []
    for controller, result in results.items():
        summary = result.summary
        if summary.get("diverged"):
            continue
        line = anatomy.verdict_line(summary, campaign.run_failure_classes(summary, criteria), tolerances)
        if line is not None:
            failed.append(controller)
        else:
            line = (
                f"capture succeeded: final position error {1e3 * summary['final_position_error_m']:.2f} mm <= "
                f"{1e3 * tolerances['final_position_m']:g}, orientation {np.degrees(summary['final_orientation_error_rad']):.3f} deg <= "
                f"{np.degrees(tolerances['final_orientation_rad']):g}, peak torque {summary['largest_peak_torque_Nm']:.3g} N m"
                + (f" <= {tolerances['torque_limit_Nm']:g}" if tolerances["torque_limit_Nm"] is not None else "")
            )
        print(f"{controller:>10}: {line}")
        if "final_target_speed_mps" in summary:
            print(
                f"{controller:>10}: target: final speed {1e3 * summary['final_target_speed_mps']:.2f} mm/s "
                f"(limit {1e3 * tolerances['target_speed_mps']:g}), rate {np.degrees(summary['final_target_rate_radps']):.3f} deg/s, "
                f"drifted {1e3 * summary['target_displacement_m']:.1f} mm, contact impulse {summary['target_impulse_Ns']:.3g} N s"
            )
    return failed


def _run_caption(loop: str, gains: str, scenario) -> str:
    """The second title line of a run's figures: its loop, its gains and its target."""
    if scenario.free_target:
        target = f"free target {float(scenario.target.mass):g} kg"
    else:
        target = "fixed target (the paper's)"
    return f"{loop}, {gains}, {target}"


def _loop_words(realism_source: str | None) -> str:
    """``--realism``'s value as a caption says it."""
    return "ideal loop (the paper's)" if realism_source in (None, "ideal") else f"{Path(realism_source).stem} loop"


def _file_name(key: str) -> str:
    """A run's key (``admittance`` or a campaign variant's ``admittance/paper``) in a file name."""
    return key.replace("/", "_")


def _is_papers_run(args: argparse.Namespace) -> bool:
    """Whether the run is the paper's: its robot, scenario, gains and ideal loop (the one
    run that Table 5's "paper" column compares with)."""
    realism = getattr(args, "realism", None)
    return (
        not getattr(args, "robot", None)
        and not getattr(args, "scenario", None)
        and not getattr(args, "gains", None)
        and realism in (None, "ideal")
        and getattr(args, "pinv_damping", 0.0) == 0.0
    )


def _print_table(results: dict, beside_paper: bool) -> None:
    """The runs' largest |u_i| per joint, and Table 5's beside them when ``beside_paper``."""
    controllers = list(results)
    header = "joint" + "".join(
        f"  {c + ' [N m]':>16}" + (f"  {'paper':>7}" if beside_paper else "") for c in controllers
    )
    print("\nTable 5: maximal absolute joint torques" if beside_paper else "\nmaximal absolute joint torques")
    print(header)
    for joint in range(len(next(iter(results.values())).log.u[0])):
        row = f"{joint + 1:>5}"
        for c in controllers:
            peak = results[c].summary.get("max_abs_torque_Nm")
            ours = f"{peak[joint]:>16.3f}" if peak else f"{'diverged':>16}"
            row += f"  {ours}" + (f"  {paper.MAX_ABS_TORQUE_NM[c][joint]:>7.3f}" if beside_paper else "")
        print(row)
    print()
    for c in controllers:
        summary = results[c].summary
        if summary.get("diverged"):
            print(
                f"{c:>10}: diverged at t = {summary['first_nonfinite_s']:.4f} s ({', '.join(summary['nonfinite_fields'])})"
            )
            continue
        print(
            f"{c:>10}: final position error {1e3 * summary['final_position_error_m']:.3f} mm, "
            f"orientation error {np.degrees(summary['final_orientation_error_rad']):.4f} deg, "
            f"max contact force {summary['max_contact_force_N']:.2f} N, "
            f"compile {summary['compile_time_s']:.1f} s, run {summary['run_time_s']:.2f} s"
        )


def _write_results(
    out: Path,
    results: dict,
    config: dict,
    beside_paper: bool,
    caption: str | None = None,
    torque_limit_Nm=None,
    csv: bool = False,
    criteria: campaign.CampaignConfig | None = None,
) -> None:
    """Every file of a ``reproduce``, ``simulate`` or ``replay`` run; ``table5.csv`` has Table 5's
    columns beside the run's only for the paper's run (``_is_papers_run()``)."""
    out.mkdir(parents=True, exist_ok=True)
    columns = [f"{c}_Nm" for c in results] + ([f"paper_{c}_Nm" for c in results] if beside_paper else [])
    lines = ["joint," + ",".join(columns)]
    for joint in range(np.shape(next(iter(results.values())).log.u)[-1]):  # a diverged run's cells are empty
        ours = [
            f"{results[c].summary['max_abs_torque_Nm'][joint]:.6g}" if "max_abs_torque_Nm" in results[c].summary else ""
            for c in results
        ]
        reference = [f"{paper.MAX_ABS_TORQUE_NM[c][joint]:.6g}" for c in results] if beside_paper else []
        lines.append(",".join([str(joint + 1)] + ours + reference))
    runfiles.write_text(out / "table5.csv", "\n".join(lines) + "\n")
    runfiles.write_json(
        out / "summary.json",
        {c: campaign.with_capture_verdict(result.summary, criteria) for c, result in results.items()},
    )
    for c, result in results.items():
        runfiles.write_timeseries(out / f"timeseries_{_file_name(c)}.npz", result.log)
        if csv:
            runfiles.write_timeseries_csv(out / f"timeseries_{_file_name(c)}.csv", result.log)
    from spacegrasp_jax import plots  # matplotlib: imported where figures are drawn

    plots.save_figures(
        {c: result.log for c, result in results.items()},
        out,
        runfiles.write_atomically,
        caption=caption,
        torque_limit_Nm=torque_limit_Nm,
    )
    runfiles.write_json(out / "config.json", config | {"caption": caption})


def _films(
    args: argparse.Namespace, folder: Path, keys: list[str], robot, scenario, logs: dict, film: Path | None = None
) -> list[Path]:
    """Write the film (and its poster) of each run ``keys`` of ``folder``, to ``film`` (one run)
    or to ``capture_<run>.gif`` in ``folder``; returns the files written."""
    written = []
    for key in keys:
        out = film if film is not None else folder / f"capture_{_file_name(key)}.gif"
        poster = out.with_name(out.stem + "_poster.png")
        rows = animation.frame_rows(logs[key].t, args.fps, args.speed)
        print(f"drawing {len(rows)} frames of the {key} capture into {out}...", flush=True)
        scene = animation.capture_scene(robot, scenario, logs[key], rows)
        title = f"{key}: {folder.name}"
        runfiles.write_atomically(out, lambda target: animation.write_film(scene, target, args.fps, title=title))
        runfiles.write_atomically(poster, lambda target: animation.write_poster(scene, target, title))
        written += [out, poster]
    return written
