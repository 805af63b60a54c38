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
from spacegrasp_jax.analysis import animation, worstcase
from spacegrasp_jax.cli.options import NAMED_RANGES, UsageError
from spacegrasp_jax.core import joint_limits
from spacegrasp_jax.core.model import n_joints
from spacegrasp_jax.core.robot_files import rate_limits_stated
from spacegrasp_jax.envelope.criteria import CaptureCriteria
from spacegrasp_jax.envelope.perturbations import (
    PerturbationError,
    PerturbationRanges,
    check_for_scenario,
    load_ranges,
)
from spacegrasp_jax.envelope.scenario import load_scenario, paper_scenario
from spacegrasp_jax.jobs import anatomy, campaign, paper, runfiles
from spacegrasp_jax.jobs.records import RunRecord
from spacegrasp_jax.loop.control import (
    GAINS_USED,
    PAPER_CONTROLLERS,
    Gains,
    law_named,
    load_gains,
    missing_groups,
    paper_gains,
)
from spacegrasp_jax.loop.control.schedule import (
    NAMED_GAIN_SETS,
    TUNED_IN_FLIGHT_LOOP,
    TUNED_SCHEDULE_FILES,
    VARIABLES,
    GainSchedule,
    gains_along,
    is_schedule_file,
    load_schedule,
    named_gain_set,
    regime_labels,
    schedule_curves,
    variable_series,
)
from spacegrasp_jax.loop.realism import Realism, RealismError, load_realism


def _robot_links(args) -> dict:
    """``--mount``, ``--base-link`` and ``--tip-link`` as ``load_robot``'s keywords (those given)."""
    given = {"mount": getattr(args, "mount", None), "base_link": getattr(args, "base_link", None)}
    given["tip_link"] = getattr(args, "tip_link", None)
    return {name: value for name, value in given.items() if value is not None}


def _load_robot(args):
    """The robot of ``--robot`` (the paper's by default), a URDF arm mounted and cut by
    ``--mount``, ``--base-link`` and ``--tip-link``; a one-line note when a URDF arm is
    mounted on the paper's satellite because no ``--mount`` was given."""
    links = _robot_links(args)
    if not args.robot:
        if links:
            option = "--" + next(iter(links)).replace("_", "-")
            raise UsageError(f"{option}: for a URDF arm given with --robot (the paper's robot is whole)")
        return sg.paper_robot()
    robot = sg.load_robot(args.robot, **links)
    if Path(args.robot).suffix.lower() == ".urdf" and "mount" not in links:
        print(
            f"spacegrasp: note: {args.robot}: the arm is mounted on the paper's 500 kg satellite at its mount point "
            f"(--mount urdf: the URDF is the whole servicer; --mount FILE: your satellite)",
            file=sys.stderr,
        )
    return robot


def _keep_inputs(args, out: Path, gains, realism, controllers) -> dict:
    """The run's inputs given as files, kept in its folder ``out`` so that it needs nothing
    outside it: the scenario file as written (``scenario.toml`` or ``.json``), the gains as
    they ran (``gains.json``, with any ``--fill-from`` groups) and the realism as it ran
    (``realism.json``), each only where ``--scenario``, ``--gains`` or a ``--realism`` file
    gave it. Returns the record's ``scenario_file``, ``gains_file`` and ``realism_file`` (names
    in the folder, ``None`` where not kept); the original paths stay in the record as sources."""
    kept = {"scenario_file": None, "gains_file": None, "realism_file": None}
    if getattr(args, "scenario", None):
        suffix = ".json" if Path(args.scenario).suffix.lower() == ".json" else ".toml"
        kept["scenario_file"] = "scenario" + suffix
        runfiles.write_text(out / kept["scenario_file"], Path(args.scenario).read_text())
    if getattr(args, "gains", None) and args.gains not in NAMED_GAIN_SETS:
        kept["gains_file"] = "gains.json"
        law = controllers[0] if len(controllers) == 1 else None
        runfiles.write_json(out / kept["gains_file"], gains.to_dict(law))
    if realism is not None and getattr(args, "realism", None) not in (None, "ideal", "flight"):
        kept["realism_file"] = "realism.json"
        runfiles.write_json(out / kept["realism_file"], realism.to_dict())
    return kept


def _check_joint_ranges(args, robot, scenario) -> None:
    """Refuse a scenario whose initial joint angles lie outside ``robot``'s joint ranges, one
    line naming each such joint, unless ``--allow-outside-limits`` (then a warning says it)."""
    outside = joint_limits.outside_ranges(robot, scenario.initial.q)
    if not outside:
        return
    where = "the scenario's" if getattr(args, "scenario", None) is None else f"{args.scenario}'s"
    joints = "; ".join(
        f"joint {item['joint']} at {item['angle_rad']:.4g} rad, its range [{item['range_rad'][0]:.4g}, "
        f"{item['range_rad'][1]:.4g}]"
        for item in outside
    )
    message = f"q_init: {where} initial joint angles lie outside the robot's joint ranges: {joints}"
    if not getattr(args, "allow_outside_limits", False):
        raise UsageError(f"{message} (choose angles inside them, or pass --allow-outside-limits)")
    _warn([f"{message} (--allow-outside-limits)"])


def _load_inputs(args, schedules: bool = False):
    """Robot, scenario and gains from the command line, validated before any compile;
    ``schedules``: the command runs gain schedules too."""
    robot = _load_robot(args)
    scenario = load_scenario(robot, args.scenario) if getattr(args, "scenario", None) else paper_scenario(robot)
    _check_joint_ranges(args, robot, scenario)
    controller = getattr(args, "controller", None)
    return robot, scenario, _gains_option(getattr(args, "gains", None), args, robot, controller, schedules)


#: The commands that run gain schedules (``--gains`` a schedule file).
RUNS_SCHEDULES = ("simulate", "montecarlo", "tune", "margins", "export")


def _gains_option(value: str | None, args, robot, controller, schedules: bool = False):
    """The gains ``--gains value`` names for ``controller`` (a law, several, or ``None``):
    the paper's by default, a shipped set by name, or a file whose missing groups come from
    ``--fill-from``; with ``schedules``, a schedule file's ``GainSchedule``
    ([`control.schedule`][spacegrasp_jax.loop.control.schedule]), which other commands refuse."""
    if getattr(args, "fill_from", None) is not None and (value is None or value in NAMED_GAIN_SETS):
        raise UsageError(
            f"--fill-from: completes a gains file given with --gains; {value or 'the paper'}'s gains are whole"
        )
    if value == "paper" and n_joints(robot) != len(paper_gains().kp):
        raise UsageError(
            f"--gains paper: the paper's Table 4 gains are for its {len(paper_gains().kp)}-joint arm, not this "
            f"{n_joints(robot)}-joint one; give a gains file (spacegrasp gains --start writes a start)"
        )
    if value is None or value == "paper":
        return _paper_gains_for(robot, controller if isinstance(controller, str) else None)
    if value in NAMED_GAIN_SETS:
        if n_joints(robot) != len(paper_gains().kp):
            raise UsageError(
                f"--gains {value}: the shipped tuned sets are for the paper's {len(paper_gains().kp)}-joint arm, "
                f"not this {n_joints(robot)}-joint one; give a gains file (spacegrasp gains --start writes a start)"
            )
        if value in TUNED_SCHEDULE_FILES and not schedules:
            raise UsageError(
                f"--gains {value}: a gain schedule; this command takes constant gains (schedules run in "
                f"{', '.join(RUNS_SCHEDULES[:-1])} and {RUNS_SCHEDULES[-1]})"
            )
        if value in TUNED_IN_FLIGHT_LOOP and hasattr(args, "realism") and args.realism in (None, "ideal"):
            print(
                f"spacegrasp: notice: --gains {value}: tuned in the flight-like loop (--realism flight); "
                "this run's loop is the ideal one",
                file=sys.stderr,
            )
        return named_gain_set(value)
    fill_from = getattr(args, "fill_from", None)
    if is_schedule_file(value):
        if not schedules:
            raise UsageError(
                f"--gains {value}: a gain schedule; this command takes constant gains (schedules run in "
                f"{', '.join(RUNS_SCHEDULES[:-1])} and {RUNS_SCHEDULES[-1]})"
            )
        gains = load_schedule(value, controller, n_joints(robot), fill_from=fill_from)
    else:
        gains = load_gains(value, controller, n_joints(robot), fill_from=fill_from)
    filled = missing_groups(value, controller) if fill_from else []
    if filled:
        print(f"spacegrasp: notice: {value}: {', '.join(filled)} from {fill_from} (--fill-from)", file=sys.stderr)
    return gains


def _save_schedule_figure(
    out: Path, schedule: GainSchedule, logs: dict | None = None, *, with_curves: bool = True
) -> list[str]:
    """``gain_schedule.png`` in ``out`` (with ``with_curves``): each scheduled group against
    its variable; with ``logs`` (a run's name -> its log), ``regime_<name>.png``: the variable
    along each run and the gains it ran with. Returns the files' names."""
    from spacegrasp_jax.analysis import plots

    unit = VARIABLES[schedule.variable]
    figures = {}
    if with_curves:
        figures["gain_schedule.png"] = plots.figure_gain_schedule(schedule_curves(schedule), schedule.variable, unit)
    knots = {name: np.asarray(schedule.knots[name]) for name, count in schedule.knot_counts().items() if count > 1}
    for controller, log in (logs or {}).items():
        x = variable_series(schedule.variable, log)
        figures[f"regime_{_file_name(controller)}.png"] = plots.figure_schedule_regime(
            np.asarray(log.t), x, knots, gains_along(schedule, x), schedule.variable, unit, caption=controller
        )
    return plots.save(figures, out, runfiles.write_atomically)


def _gains_record(value: str | None, args, controller) -> dict:
    """What a run's record says of its gains (``sources``): where they came from
    (``"paper_gains()"``, a shipped set's name or the file as given) and, for a file that left
    groups out, which ones ``--fill-from`` gave and from where."""
    fill_from = getattr(args, "fill_from", None)
    filled = [] if value is None or value in NAMED_GAIN_SETS else missing_groups(value, controller)
    return {
        "gains": value or "paper_gains()",
        "gains_filled": {"groups": filled, "from": fill_from} if filled else None,
    }


def gains_label(value: str | None) -> str:
    """The label a run's record gives the gains ``--gains value`` names: ``"paper"``, a
    shipped set's name, or the file's stem (letters, digits, ``-``, ``_`` and ``.``; any other
    character as ``_``)."""
    if value is None:
        return "paper"
    if value in NAMED_GAIN_SETS:
        return value
    return _label_characters(Path(value).stem) or "gains"


def _label_characters(text: str) -> str:
    """``text`` as a label may hold it: letters, digits, ``-``, ``_`` and ``.``; any other
    character as ``_``."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in text)


def gain_set_labels(names: list[str]) -> list[str]:
    """A label for each ``--gains`` value, unique among them: a shipped set's name, else the
    file's stem, with as many of its parent folders (joined by ``-``) as it takes to tell two
    files apart (``results/a/gains.json`` and ``results/b/gains.json``: ``a-gains`` and ``b-gains``)."""
    parts = [[name] if name in NAMED_GAIN_SETS else [*Path(name).parent.parts, Path(name).stem] for name in names]
    depth = [1] * len(names)
    while True:
        labels = ["-".join(part for part in p[-d:] if part not in ("", ".", "..", "/")) for p, d in zip(parts, depth)]
        clashes = {label for label in labels if labels.count(label) > 1}
        grown = False
        for i, label in enumerate(labels):
            if label in clashes and depth[i] < len(parts[i]):
                depth[i] += 1
                grown = True
        if not clashes:
            return [_label_characters(label) for label in labels]
        if not grown:
            first = next(name for name, label in zip(names, labels) if label in clashes)
            raise UsageError(f"--gains {first}: given twice")


def _paper_gains_for(robot, controller: str | None = None) -> Gains:
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


def _realism(args, scenario, robot=None) -> Realism | None:
    """``--realism`` (a preset or a file; ``flight``'s actuators ``robot``'s motors), checked
    against the scenario before compiling."""
    if getattr(args, "realism", None) is None:
        return None
    realism = load_realism(args.realism, robot)
    try:
        realism.check_timing(scenario.dt, scenario.n_steps)
        realism.check_joints(scenario.initial.q.shape[-1])
    except RealismError as error:
        raise RealismError(f"--realism {args.realism}: {error}") from None
    return realism


def _perturbed(path: str, spec):
    """``--perturbation FILE``: the nominal run ``spec`` perturbed as the file says and its
    noise key ([`worstcase.perturbed_spec()`][spacegrasp_jax.analysis.worstcase.perturbed_spec])."""
    try:
        return worstcase.perturbed_spec(spec, path)
    except worstcase.WorstCaseError as error:
        raise UsageError(f"--perturbation {error}") from None


def _ranges(args: argparse.Namespace, default: PerturbationRanges) -> PerturbationRanges:
    """``default``, or the ``--ranges`` envelope (a name of ``NAMED_RANGES`` or a TOML
    file whose missing keys are ``default``'s), scaled by ``--scale``, then each
    ``--range NAME=VALUE``."""
    if args.ranges in NAMED_RANGES:
        ranges = NAMED_RANGES[args.ranges]
    else:
        ranges = load_ranges(args.ranges, base=default) if args.ranges else default
    if getattr(args, "scale", None) is not None:
        try:
            ranges = ranges.scaled(args.scale)
        except PerturbationError as error:
            raise UsageError(f"--scale {args.scale:g}: {error}") from None
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


def _check_envelope(args: argparse.Namespace, scenario, ranges: PerturbationRanges | None = None) -> None:
    """``--ranges free_target`` (or ``free_target_fast``) draws targets: refused for a scenario
    without one; ``ranges`` that cannot perturb ``scenario`` (``check_for_scenario()``) too."""
    if getattr(args, "ranges", None) in ("free_target", "free_target_fast") and not scenario.free_target:
        raise UsageError(
            f"--ranges {args.ranges}: needs a scenario with a free-floating [target], e.g. --scenario configs/free_target_envelope.toml"
        )
    if ranges is not None:
        try:
            check_for_scenario(ranges, scenario)
        except PerturbationError as error:
            raise UsageError(str(error)) from None


def _rate_criterion(args: argparse.Namespace, robot) -> tuple[float, ...] | None:
    """``robot``'s joint rate limits (rad/s) as a success criterion where ``--robot``'s file
    states them (``robot_files.rate_limits_stated()``); ``None`` for the paper's arm, whose rate
    limits are assumed and only detect runaways."""
    if not args.robot:
        return None
    try:
        stated = rate_limits_stated(args.robot)
    except sg.RobotConfigError as error:
        raise UsageError(str(error)) from None
    return tuple(float(x) for x in robot.joint_rate_limit) if stated else None


def _criteria(args: argparse.Namespace, robot, **fields) -> campaign.CampaignConfig:
    """The campaign's settings with the capture criteria of ``_add_criteria_options()`` and
    ``robot``'s stated rate limits (``_rate_criterion()``); the law's damping checked
    (``--pinv-damping``) before anything compiles."""
    if args.controller != "both":
        _law(args.controller, args)
    try:
        criteria = CaptureCriteria(
            position_tolerance_m=args.tolerance_mm * 1e-3,
            orientation_tolerance_rad=math.radians(args.tolerance_deg),
            torque_threshold_Nm=args.torque_threshold if args.torque_threshold > 0 else None,
            target_speed_limit_mps=args.target_speed_limit,
            joint_rate_limits_radps=_rate_criterion(args, robot),
        )
        return campaign.CampaignConfig(
            criteria=criteria, pinv_damping=args.pinv_damping, identified=args.identified, **fields
        )
    except (ValueError, campaign.CampaignError) as error:
        raise UsageError(str(error)) from None


def _claim(args: argparse.Namespace, out: Path) -> None:
    """The command's output folder, refused if it holds anything (another run, or files
    this tool did not write) unless ``--overwrite`` or ``--resume`` says what to do
    (``spacegrasp_jax.jobs.runfiles.claim_output_folder()``). Several processes: every one
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


def replay_command(args: argparse.Namespace, perturbation: Path, out: Path) -> list[str]:
    """The ``spacegrasp simulate`` command line that runs this command's nominal capture (its
    law, gains, scenario, robot, loop and damping) perturbed as the perturbation file
    ``perturbation`` says, into ``out``."""
    command = ["spacegrasp", "simulate", "--controller", args.controller]
    for option, value in (
        ("--gains", args.gains),
        ("--fill-from", args.fill_from),
        ("--scenario", args.scenario),
        ("--robot", args.robot),
        ("--mount", args.mount),
        ("--base-link", args.base_link),
        ("--tip-link", args.tip_link),
    ):
        if value:
            command += [option, value]
    if args.allow_outside_limits:
        command.append("--allow-outside-limits")
    if args.realism:
        command += ["--realism", args.realism]
    if args.pinv_damping:
        command += ["--pinv-damping", f"{args.pinv_damping:g}"]
    return command + ["--perturbation", str(perturbation), "--out", str(out)]


def _warn(lines: list[str], prefix: str = "") -> None:
    """Each line as ``spacegrasp: warning: ...`` on stderr (``spacegrasp_jax.envelope.plausibility``)."""
    for line in lines:
        print(f"spacegrasp: warning: {prefix}{line}", file=sys.stderr, flush=True)


def _print_capture_verdicts(results: dict, criteria: CaptureCriteria | None = None) -> list[str]:
    """Each run's capture verdict by ``criteria`` (default: the campaigns' defaults): one line that says why
    a failed capture failed (a result, not an error: exit 0 unless ``--strict``), or the margins of a
    success; with a free-floating target, one more line for the target's motion. Returns the keys
    of ``results`` whose capture failed (a diverged run is not among them: it has its own exit code)."""
    criteria = CaptureCriteria() if criteria is None else criteria
    failed = []
    for controller, result in results.items():
        summary = result.summary
        for words in joint_limits.crossing_words(
            summary.get("joint_limits") or {}
        ):  # before the verdict: it came first
            print(f"{controller:>10}: joint limits: {words}")
        if summary.get("diverged"):
            continue
        line = anatomy.verdict_line(summary, campaign.run_failure_classes(summary, criteria), criteria)
        if line is not None:
            failed.append(controller)
        else:
            line = (
                f"capture succeeded: final position error {1e3 * summary['final_position_error_m']:.2f} mm <= "
                f"{1e3 * criteria.position_tolerance_m:g}, orientation {np.degrees(summary['final_orientation_error_rad']):.3f} deg <= "
                f"{np.degrees(criteria.orientation_tolerance_rad):g}, peak torque {summary['largest_peak_torque_Nm']:.3g} N m"
                + (f" <= {criteria.torque_threshold_Nm:g}" if criteria.torque_threshold_Nm is not None else "")
            )
        print(f"{controller:>10}: {line}")
        if "final_target_speed_mps" in summary:
            print(
                f"{controller:>10}: target: final speed {1e3 * summary['final_target_speed_mps']:.2f} mm/s "
                f"(limit {1e3 * criteria.target_speed_limit_mps:g}), rate {np.degrees(summary['final_target_rate_radps']):.3f} deg/s, "
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
        and getattr(args, "gains", None) in (None, "paper")
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
    criteria: CaptureCriteria | None = None,
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
    from spacegrasp_jax.analysis import plots

    plots.save_figures(
        {c: result.log for c, result in results.items()},
        out,
        runfiles.write_atomically,
        caption=caption,
        torque_limit_Nm=torque_limit_Nm,
    )
    runfiles.write_json(out / "config.json", config | {"caption": caption})


def _run_schedule(folder: Path, config: dict, law: str, n: int) -> GainSchedule | None:
    """The gain schedule a run folder's run ran with (its kept ``gains.json``, or a shipped
    schedule it names), ``None`` for constant gains; ``n`` the arm's joints."""
    if "record" in config:
        for variant in RunRecord.from_dict(config["record"], f"{folder}: config.json's record").variants:
            if variant.controller == law and isinstance(variant.gains, GainSchedule):
                return variant.gains
        return None
    if config.get("gains_file"):
        kept = folder / config["gains_file"]
        return load_schedule(kept, law, n) if is_schedule_file(kept) else None
    source = config.get("gains_source")
    return named_gain_set(source) if source in TUNED_SCHEDULE_FILES else None


def _films(
    args: argparse.Namespace,
    folder: Path,
    keys: list[str],
    robot,
    scenario,
    logs: dict,
    film: Path | None = None,
    schedule: GainSchedule | None = None,
) -> list[Path]:
    """Write the film (and its poster) of each run ``keys`` of ``folder``, to ``film`` (one run)
    or to ``capture_<run>.gif`` in ``folder``; with a gain ``schedule``, each frame says which of
    its regimes the capture was in. Returns the files written."""
    written = []
    for key in keys:
        out = film if film is not None else folder / f"capture_{_file_name(key)}.gif"
        poster = out.with_name(out.stem + "_poster.png")
        rows = animation.frame_rows(logs[key].t, args.fps, args.speed)
        print(f"drawing {len(rows)} frames of the {key} capture into {out}...", flush=True)
        regime = None
        if schedule is not None:
            regime = regime_labels(schedule, variable_series(schedule.variable, logs[key]))
        scene = animation.capture_scene(robot, scenario, logs[key], rows, regime=regime)
        title = f"{key}: {folder.name}"
        runfiles.write_atomically(out, lambda target: animation.write_film(scene, target, args.fps, title=title))
        runfiles.write_atomically(poster, lambda target: animation.write_poster(scene, target, title))
        written += [out, poster]
    return written


def _write_out_file(args, text: str, what: str) -> None:
    """Write ``text`` to the file ``--out`` names, atomically (an existing file only with
    ``--overwrite``), and say ``wrote FILE: what``; without ``--out``, print ``text``."""
    if args.out is None:
        sys.stdout.write(text)
        return
    out = Path(args.out)
    if out.is_dir():
        raise UsageError(f"--out {out}: is a folder; give a file name")
    if out.exists() and not args.overwrite:
        raise UsageError(f"--out {out}: exists; pass --overwrite to replace it")
    try:
        runfiles.write_atomically(out, lambda target: target.write_text(text))
    except OSError as error:
        raise UsageError(f"--out {out}: cannot write ({error.strerror or error})") from None
    print(f"wrote {out}: {what}")
