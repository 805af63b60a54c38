"""The ``spacegrasp`` command line."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import json
import math
import shlex
import signal
import sys
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np
from jax.experimental import multihost_utils

matplotlib.use("Agg")  # the command line only writes figures to files; before pyplot is imported

import spacegrasp_jax as sg  # noqa: E402
from spacegrasp_jax import (
    anatomy,
    animation,
    batching,
    campaign,
    compilation,
    experiment,
    export,
    margins,
    metrics,
    paper,
    plausibility,
    plots,
    runfiles,
    spatial,
    stability,
    statistics,
    urdf,
    worstcase,
)
from spacegrasp_jax.control import (
    CONTROLLERS,
    PAPER_CONTROLLERS,
    GainsError,
    UnusedGainsWarning,
    law_named,
    load_gains,
    paper_gains,
)
from spacegrasp_jax.model import body_inertials, n_joints
from spacegrasp_jax.montecarlo import perturbed_loop
from spacegrasp_jax.perturbations import (
    FREE_TARGET_RANGES,
    PerturbationError,
    PerturbationRanges,
    from_units,
    load_ranges,
)
from spacegrasp_jax.realism import Realism, RealismError, ideal, load_realism
from spacegrasp_jax.scenario import ScenarioError, load_scenario, paper_scenario, scenario_from_dict
from spacegrasp_jax.simulate import Log
from spacegrasp_jax.tuning.gradients import HORIZONS as GRADIENT_HORIZONS
from spacegrasp_jax.tuning.gradients import central_differences, envelope_gradients, finite_rows
from spacegrasp_jax.tuning.gradients import report as gradient_report
from spacegrasp_jax.tuning.objective import OBJECTIVES, Objective, Weights
from spacegrasp_jax.tuning.run import ResumeMismatchError, TuneSetupError, record_robot, record_scenario, tune
from spacegrasp_jax.tuning.tune import METHODS, TUNING_RANGES, TuneConfig


class UsageError(ValueError):
    """A command-line option is invalid."""


class _Parser(argparse.ArgumentParser):
    """An argument parser whose every rejection is one line (exit 2), naming the option."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _whole(low: int, high: int):
    """An option's type: a whole number in ``[low, high]``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must be in [{low:,}, {high:,}], got {value:,}")
        return value

    parse.__name__ = "whole number"
    return parse


def _real(low: float, high: float, *, above: bool = False):
    """An option's type: a finite number in ``[low, high]`` (``(low, high]`` if ``above``)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not math.isfinite(value) or value < low or value > high or (above and value == low):
            bounds = f"{'(' if above else '['}{low:g}, {high:g}]"
            raise argparse.ArgumentTypeError(f"must be a finite number in {bounds}, got {text}")
        return value

    parse.__name__ = "number"
    return parse


#: Seeds are 32-bit (``jax.random.PRNGKey``).
_SEED = _whole(0, 2**32 - 1)


def _c_identifier(text: str) -> str:
    """An option's type: a C identifier (letters, digits and underscores, not starting with a digit)."""
    if not (text.isascii() and text.isidentifier()):
        raise argparse.ArgumentTypeError(f"expected a C identifier such as SG, got {text!r}")
    return text


def _info(args: argparse.Namespace) -> int:
    urdf_file = None if args.urdf is None else Path(args.urdf)
    if urdf_file is not None:
        if urdf_file.exists():
            raise UsageError(f"--urdf: {urdf_file} exists; name a new file (info never overwrites one)")
        folder = next(parent for parent in urdf_file.absolute().parents if parent.exists())
        if not folder.is_dir():
            raise UsageError(f"--urdf: {folder} is not a folder, so {urdf_file} cannot be written")
    robot = sg.load_robot(args.robot) if args.robot else sg.paper_robot()
    n = n_joints(robot)
    if args.scenario:
        q_init, where = load_scenario(robot, args.scenario).initial.q, f"the scenario's q_init ({args.scenario})"
    elif n == len(sg.PAPER_Q_INIT):
        q_init, where = sg.PAPER_Q_INIT, "the paper's q_init"
    else:
        q_init, where = np.zeros(n), "q = 0 (give --scenario for its q_init)"
    q = jnp.asarray(q_init, dtype=jnp.float64)
    p_base, R_base = jnp.zeros(3), jnp.eye(3)
    total_mass = float(robot.satellite_mass + jnp.sum(robot.link_mass) + robot.ee_mass)
    com = np.asarray(jax.jit(sg.system_com)(robot, p_base, R_base, q))
    p_ee, R_ee = jax.jit(sg.ee_pose)(robot, p_base, R_base, q)
    euler = np.asarray(spatial.euler_zyx(R_ee))
    M = np.asarray(jax.jit(sg.mass_matrix)(robot, R_base, q))
    source = args.robot or "paper robot (Tables 1-3)"
    print(f"robot: {source}, {n} joints")
    mount = np.asarray(robot.mount_position)
    print(
        f"satellite: {float(robot.satellite_mass):.3f} kg (with what is fixed to the arm's base), principal moments "
        f"{np.array2string(np.linalg.eigvalsh(np.asarray(robot.satellite_inertia)), precision=4)} kg m^2; "
        f"frame 0 at [{mount[0]: .4f}, {mount[1]: .4f}, {mount[2]: .4f}] m from its CoM"
    )
    mass, _, _ = body_inertials(robot)
    print(
        f"{'joint':>5}  {'link mass [kg]':>14}  {'range [rad]':>20}  {'rate limit [rad/s]':>18}  {'torque limit [N m]':>18}"
    )
    for i in range(n):
        lower, upper = np.asarray(robot.joint_position_limit)[i]
        span = "none" if np.isinf(lower) and np.isinf(upper) else f"[{lower:.4f}, {upper:.4f}]"
        print(
            f"{i + 1:>5}  {float(mass[i]):>14.4f}  {span:>20}  {float(robot.joint_rate_limit[i]):>18.4g}  "
            f"{float(robot.joint_torque_limit[i]):>18.4g}"
        )
    print(f"(link {n}'s mass includes the end-effector's and everything fixed to it)")
    print(
        f"configuration: {where} = {np.round(np.asarray(q), 6).tolist()} rad, satellite CoM at the origin, identity attitude"
    )
    print(f"total mass:               {total_mass:.3f} kg")
    print(f"system CoM (inertial):    [{com[0]: .6f}, {com[1]: .6f}, {com[2]: .6f}] m")
    print(f"EE position (inertial):   [{float(p_ee[0]): .6f}, {float(p_ee[1]): .6f}, {float(p_ee[2]): .6f}] m")
    print(f"EE ZYX angles [roll, pitch, yaw]: [{euler[0]: .6f}, {euler[1]: .6f}, {euler[2]: .6f}] rad")
    print("EE rotation (EE to inertial):")
    for row in np.asarray(R_ee):
        print(f"    [{row[0]: .6f}, {row[1]: .6f}, {row[2]: .6f}]")
    print(f"mass matrix ({6 + n}x{6 + n}) condition number: {np.linalg.cond(M):.6g}")
    if urdf_file is not None:
        urdf_file.parent.mkdir(parents=True, exist_ok=True)
        urdf_file.write_text(urdf.robot_to_urdf(robot))
        print(f"URDF written to {urdf_file} (it has no free joint: load it with a floating base)")
    return 0


def _export(args: argparse.Namespace) -> int:
    """``spacegrasp export``: a gain set with its units, equations and the loop's settings, as
    one file of ``--format`` (printed without ``--out``)."""
    robot, scenario, gains = _load_inputs(args)
    realism = _realism(args, scenario)
    settings = export.loop_settings(realism, scenario.dt, n_joints(robot))
    text = export.export_text(
        gains, args.controller, settings, args.format, source=args.gains or "paper_gains()", prefix=args.prefix
    )
    if args.out is None:
        sys.stdout.write(text)
        return 0
    out = Path(args.out)
    if out.is_dir():
        raise UsageError(f"--out {out}: is a folder; give a file name")
    if out.exists() and not args.overwrite:
        raise UsageError(f"--out {out}: exists; pass --overwrite to replace it")
    try:
        runfiles.write_atomically(out, lambda target: target.write_text(text))
    except OSError as error:
        raise UsageError(f"--out {out}: cannot write ({error.strerror or error})") from None
    print(f"wrote {out}: the {args.controller} gains, their units and equations, and the loop's settings")
    return 0


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
            f"--gains: required for the {controller} law (the paper's gains are for its "
            f"{' and '.join(PAPER_CONTROLLERS)} laws; configs/{controller}_gains.json is a start)"
        )
    if n_joints(robot) != len(paper_gains().kp):
        raise UsageError(
            f"--gains: required for an arm of {n_joints(robot)} joints (the paper's Table 4 gains are for its "
            f"{len(paper_gains().kp)}); give a gains file with kp, ki and kd for each joint"
        )
    return paper_gains()


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


def _capture_tolerances(criteria: campaign.CampaignConfig | None = None) -> dict:
    """A campaign's success criteria (default: the campaigns' defaults), as summary.json
    names them."""
    criteria = campaign.CampaignConfig(n=1) if criteria is None else criteria
    return {
        "final_position_m": criteria.position_tolerance_m,
        "final_orientation_rad": criteria.orientation_tolerance_rad,
        "torque_limit_Nm": criteria.torque_limit_Nm,
        "target_speed_mps": criteria.target_speed_limit_mps,
    }


def _capture_classes(summary: dict, criteria: campaign.CampaignConfig | None = None) -> dict:
    """``spacegrasp_jax.anatomy.failure_classes()`` of one run's summary (a one-sample batch)."""
    tolerances = _capture_tolerances(criteria)
    as_sample = {name: np.asarray([value], dtype=float) for name, value in summary.items() if name in _NUMERIC}
    return anatomy.failure_classes(
        as_sample,
        tolerances["final_position_m"],
        tolerances["final_orientation_rad"],
        tolerances["torque_limit_Nm"],
        tolerances["target_speed_mps"],
    )


_NUMERIC = (*metrics.METRICS, *metrics.TARGET_METRICS, *anatomy.ANATOMY_METRICS)


def _with_capture(summary: dict, criteria: campaign.CampaignConfig | None = None) -> dict:
    """``summary`` and whether the run is a capture by the Monte-Carlo campaigns' default
    criteria (``capture_success``, ``capture_criteria``), which criteria it missed and by
    how much (``capture_failure``, ``capture_margins``) and the parts of its final position
    error (``final_error_parts_m``). A diverged run's summary is returned as it is."""
    if summary.get("diverged"):
        return summary
    classes = _capture_classes(summary, criteria)
    parts = anatomy.error_decomposition(
        {name: np.asarray([summary[name]]) for name in ("final_position_error_lar_m", *anatomy.ANATOMY_METRICS)}
    )
    return summary | {
        "capture_success": bool(classes["failure"][0] == "success"),
        "capture_criteria": _capture_tolerances(criteria),
        "capture_failure": str(classes["failure"][0]),
        "capture_missed": [name for name in anatomy.FAILURE_CLASSES if classes[f"failed_{name}"][0]],
        "capture_margins": {
            name: (None if not np.isfinite(classes[name][0]) else float(classes[name][0]))
            for name in ("position_margin", "orientation_margin", "torque_margin", "target_speed_margin")
        },
        "final_error_parts_m": {
            name.removeprefix("final_error_").removesuffix("_m"): float(v[0]) for name, v in parts.items()
        },
    }


def _print_capture_verdicts(results: dict, criteria: campaign.CampaignConfig | None = None) -> None:
    """Each run's capture verdict by ``criteria`` (default: the campaigns' defaults): one line that says why
    a failed capture failed (a result, not an error: exit 0), or the margins of a success;
    with a free-floating target, one more line for the target's motion."""
    tolerances = _capture_tolerances(criteria)
    for controller, result in results.items():
        summary = result.summary
        if summary.get("diverged"):
            continue
        line = anatomy.verdict_line(summary, _capture_classes(summary, criteria), tolerances)
        if line is None:
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


def _run_caption(loop: str, gains: str, scenario) -> str:
    """The second title line of a run's figures: its loop, its gains and its target."""
    if scenario.target is None:
        target = "fixed target (the paper's)"
    else:
        target = f"free target {float(scenario.target.mass):g} kg"
    return f"{loop}, {gains}, {target}"


def _loop_words(realism_source: str | None) -> str:
    """``--realism``'s value as a caption says it."""
    return "ideal loop (the paper's)" if realism_source in (None, "ideal") else f"{Path(realism_source).stem} loop"


def _file_name(key: str) -> str:
    """A run's key (``admittance`` or a campaign variant's ``admittance/paper``) in a file name."""
    return key.replace("/", "_")


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
        out / "summary.json", {c: _with_capture(result.summary, criteria) for c, result in results.items()}
    )
    for c, result in results.items():
        runfiles.write_timeseries(out / f"timeseries_{_file_name(c)}.npz", result.log)
        if csv:
            runfiles.write_timeseries_csv(out / f"timeseries_{_file_name(c)}.csv", result.log)
    plots.save_figures(
        {c: result.log for c, result in results.items()},
        out,
        runfiles.write_atomically,
        caption=caption,
        torque_limit_Nm=torque_limit_Nm,
    )
    runfiles.write_json(out / "config.json", config | {"caption": caption})


def _warn(lines: list[str], prefix: str = "") -> None:
    """Each line as ``spacegrasp: warning: ...`` on stderr (``spacegrasp_jax.plausibility``)."""
    for line in lines:
        print(f"spacegrasp: warning: {prefix}{line}", file=sys.stderr, flush=True)


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


def _perturbed(path: str, robot, scenario, realism):
    """``--perturbation FILE``: the nominal robot, scenario and realism perturbed as the file
    says, as a campaign runs a sample (``montecarlo.perturbed_loop()``), and its noise key:
    ``(robot, scenario, realism, model_robot, key)``."""
    try:
        units, ranges, noise_key, identified = worstcase.load_perturbation(path)
    except worstcase.WorstCaseError as error:
        raise UsageError(f"--perturbation {error}") from None
    perturbation = from_units(jax.tree.map(jnp.asarray, units), ranges)
    plant, perturbed, loop_realism, model_robot = perturbed_loop(
        robot, scenario, perturbation, ranges, realism, identified
    )
    return plant, perturbed, loop_realism, model_robot, jnp.asarray(noise_key, dtype=jnp.uint32)


def _law(controller: str, args: argparse.Namespace):
    """The law ``controller`` with ``--pinv-damping`` (refused for a law with no pseudoinverse)."""
    try:
        return law_named(controller, getattr(args, "pinv_damping", 0.0))
    except ValueError as error:
        raise UsageError(f"--pinv-damping: {error}") from None


def _run_controllers(args, controllers) -> int:
    robot, scenario, gains = _load_inputs(args)
    laws = {controller: _law(controller, args) for controller in controllers}
    realism = _realism(args, scenario)
    _warn(plausibility.input_warnings(scenario))
    key = jax.random.PRNGKey(getattr(args, "seed", 0))
    model_robot = None
    if getattr(args, "perturbation", None):
        robot, scenario, realism, model_robot, key = _perturbed(args.perturbation, robot, scenario, realism)
    out = Path(args.out)
    _claim(args, out)  # before the first compile, not after the run
    results, diverged = {}, []
    for controller in controllers:
        print(
            f"running the {controller} controller over {scenario.duration:g} s (dt = {scenario.dt:g} s)...", flush=True
        )
        try:
            results[controller] = experiment.run(
                robot,
                scenario,
                gains,
                laws[controller],
                realism=realism,
                key=key,
                model_robot=model_robot,
            )
        except experiment.SimulationDiverged as error:  # keep what it has: written below
            results[controller] = error.result
            diverged.append(error)
    _print_table(results, beside_paper=_is_papers_run(args))
    _print_capture_verdicts(results)
    for controller, result in results.items():
        _warn(plausibility.result_warnings(result.summary), f"{controller}: ")
    config = experiment.run_config(
        args.robot or "paper_robot()", scenario, gains, controllers, args.pinv_damping, realism
    ) | {
        "gains_source": args.gains if "gains" in args else None,
        "realism_source": args.realism if "realism" in args else None,
        "perturbation_source": getattr(args, "perturbation", None),
    }
    _write_results(
        out,
        results,
        config,
        beside_paper=_is_papers_run(args),
        caption=_run_caption(
            _loop_words(config["realism_source"]),
            "the paper's gains" if config["gains_source"] is None else f"gains {Path(config['gains_source']).name}",
            scenario,
        ),
        torque_limit_Nm=np.asarray(robot.joint_torque_limit),
        csv=args.csv,
    )
    print(
        f"wrote {out}/: table5.csv, summary.json, figures, timeseries_*.npz{', .csv' if args.csv else ''}, config.json"
    )
    if getattr(args, "animate", False):
        failed = {error.controller for error in diverged}
        logs = {controller: result.log for controller, result in results.items() if controller not in failed}
        _films(args, out, list(logs), robot, scenario, logs)
    for error in diverged:
        print(
            f"spacegrasp: error: {error}; its log up to that step and the state there are in {out}/",
            file=sys.stderr,
        )
    return 3 if diverged else 0


def _replay(args: argparse.Namespace) -> int:
    """``spacegrasp replay CAMPAIGN --sample K``: one sample of a campaign again, with its
    full log, as the campaign ran it (plant, scenario, loop, noise), for each variant."""
    folder = Path(args.campaign)
    try:
        robot, scenario, variants, config = campaign.load_campaign(folder)
    except campaign.CampaignError as error:
        raise UsageError(str(error)) from None
    if args.sample >= config.n:
        raise UsageError(f"--sample: {args.sample} is beyond the campaign's {config.n} samples (0 to {config.n - 1})")
    if args.variant is not None:
        variants = [variant for variant in variants if variant.key == args.variant]
        if not variants:
            keys = ", ".join(
                item["controller"] + "/" + item["gains_label"] for item in _campaign_record(folder)["variants"]
            )
            raise UsageError(f"--variant: {folder} has no variant {args.variant!r}; it has {keys}")
    out = Path(args.out)
    _claim(args, out)
    results = {}
    for variant in variants:
        print(f"replaying sample {args.sample} of {folder} with {variant.key}...", flush=True)
        results[variant.key] = campaign.replay(robot, scenario, variant, config, args.sample)
    _print_table(results, beside_paper=False)
    _print_capture_verdicts(results, config)
    for key, result in results.items():
        _warn(plausibility.result_warnings(result.summary), f"{key}: ")
    loop = "ideal loop" if config.realism is None else "flight-like loop"
    record = {
        "campaign": str(folder),
        "sample": args.sample,
        "variants": [variant.key for variant in variants],
        "campaign_record": _campaign_record(folder),
        **runfiles.provenance(),
    }
    _write_results(
        out,
        results,
        record,
        beside_paper=False,
        caption=_run_caption(f"sample {args.sample} of the campaign {folder.name}: {loop}", "its gains", scenario),
        torque_limit_Nm=np.asarray(robot.joint_torque_limit),
        csv=args.csv,
        criteria=config,
    )
    print(
        f"wrote {out}/: table5.csv, summary.json, figures, timeseries_*.npz{', .csv' if args.csv else ''}, config.json"
    )
    return 0


def _run_descriptors(folder: Path, key: str, config: dict) -> dict:
    """What one run of a run folder (``key``: a law, or a campaign variant ``law/gains``)
    was: its law, loop, gains, target and folder, for ``compare`` to label runs by what
    differs between them."""
    if "campaign_record" in config:  # a replay: the campaign's settings
        record = config["campaign_record"]
        realism, scenario = record["config"]["realism"], record["scenario"]
        loop = "ideal" if realism == ideal().to_dict() else "flight-like"
        gains = key.split("/", 1)[1]
        loop += f" (sample {config['sample']})"
    else:
        scenario = config["scenario"]
        source = config.get("realism_source")
        loop = source if source else ("ideal" if config["realism"] == ideal().to_dict() else "custom")
        gains = Path(config["gains_source"]).stem if config.get("gains_source") else "paper"
    target = "fixed" if scenario.get("target") is None else f"free {scenario['target']['mass']:g} kg"
    return {"law": key.split("/", 1)[0], "loop": loop, "gains": gains, "target": target, "run": folder.name}


def _load_log(path: Path) -> Log:
    """A run's ``timeseries_*.npz`` as a Log (fields the run's loop did not fill: None)."""
    with np.load(path) as data:
        return Log(
            **{field.name: data[field.name] if field.name in data.files else None for field in dataclasses.fields(Log)}
        )


def _run_robot_and_scenario(folder: Path, config: dict):
    """The robot and scenario a run folder's ``config.json`` ran (a replay's: its campaign
    sample's plant and scenario, from the campaign folder)."""
    if "campaign_record" in config:
        try:
            robot, scenario, _, campaign_config = campaign.load_campaign(Path(config["campaign"]))
        except campaign.CampaignError as error:
            raise UsageError(f"{folder}: a replay of {config['campaign']}, which cannot be read: {error}") from None
        return campaign.replay_sample(robot, scenario, campaign_config, int(config["sample"]))
    source = config["robot"]
    try:
        robot = sg.paper_robot() if source == "paper_robot()" else sg.load_robot(source)
    except sg.RobotConfigError as error:
        raise UsageError(f"{folder}: its robot {source}: {error}") from None
    return robot, scenario_from_dict(config["scenario"])


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


def _animate(args: argparse.Namespace) -> int:
    """``spacegrasp animate RUN_DIR``: a film of a run's capture (and a poster of its key frame)."""
    folder = Path(args.run_dir)
    if not (folder / "config.json").is_file() or not (folder / "summary.json").is_file():
        raise UsageError(
            f"{folder}: not a run folder of simulate, reproduce or replay (no config.json and summary.json)"
        )
    config = json.loads((folder / "config.json").read_text())
    keys = [
        key
        for key in json.loads((folder / "summary.json").read_text())
        if (folder / f"timeseries_{_file_name(key)}.npz").is_file()
    ]
    if args.controller is not None:
        if args.controller not in keys:
            raise UsageError(f"--controller: {folder} has no run {args.controller!r}; it has {', '.join(keys)}")
        keys = [args.controller]
    if not keys:
        raise UsageError(f"{folder}: holds no time series (timeseries_*.npz) to animate")
    if args.out is not None:
        if len(keys) > 1:
            raise UsageError(
                f"--out: {folder} holds {len(keys)} runs ({', '.join(keys)}); choose one with --controller"
            )
        if Path(args.out).suffix.lower() not in (".gif", ".mp4"):
            raise UsageError(f"--out {args.out}: a film is a .gif or an .mp4")
    targets = [Path(args.out)] if args.out else [folder / f"capture_{_file_name(key)}.gif" for key in keys]
    for target in targets:
        for path in (target, target.with_name(target.stem + "_poster.png")):
            if path.exists() and not args.overwrite:
                raise UsageError(f"{path}: exists; pass --overwrite to replace it")
    if args.out and Path(args.out).suffix.lower() == ".mp4":
        try:
            import imageio_ffmpeg  # noqa: F401
        except ImportError:
            raise UsageError(
                "--out: an MP4 needs imageio-ffmpeg (pip install spacegrasp-jax[video]); a .gif needs nothing more"
            ) from None
    robot, scenario = _run_robot_and_scenario(folder, config)
    logs = {key: _load_log(folder / f"timeseries_{_file_name(key)}.npz") for key in keys}
    written = _films(args, folder, keys, robot, scenario, logs, Path(args.out) if args.out else None)
    print(f"wrote {', '.join(str(path) for path in written)}")
    return 0


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
    differing = [name for name in descriptors[0] if len({d[name] for d in descriptors}) > 1 and name != "run"]
    if not differing or len({tuple(d[name] for name in differing) for d in descriptors}) < len(runs):
        differing.append("run")
    labels = [", ".join(f"{name} {d[name]}" for name in differing) for d in descriptors]
    common = ", ".join(
        f"{name} {descriptors[0][name]}" for name in descriptors[0] if name not in differing and name != "run"
    )
    logs = {label: _load_log(path) for label, (_, _, _, _, path) in zip(labels, runs)}
    table = {}
    print(
        f"\n{'run':40} {'final pos [mm]':>15} {'orient [deg]':>13} {'peak |u| [N m]':>15} {'contact [N]':>12}  capture"
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
        print(f"{label[:40]:40} {' '.join(cells)}  {verdict}")
    caption = f"compared: {common}" if common else "compared"
    plots.save_figures(logs, out, runfiles.write_atomically, caption=caption)
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
    print(f"wrote {out}/: compare.json and the figures of {len(runs)} runs, labelled by {', '.join(differing)}")
    return 0


def _campaign_record(folder: Path) -> dict:
    return json.loads((folder / "campaign.json").read_text())


def _reproduce(args: argparse.Namespace) -> int:
    return _run_controllers(args, PAPER_CONTROLLERS)


def _simulate(args: argparse.Namespace) -> int:
    return _run_controllers(args, [args.controller])


def _tune(args: argparse.Namespace) -> int:
    batching.use_all_cpu_cores()  # before anything touches a device: the batch shards over the cores
    try:
        if args.resume:
            _claim(args, Path(args.out))
            return _tune_finished(Path(args.out), _resume_tune(args))
        config = _tune_config(args)
    except ResumeMismatchError as error:
        raise UsageError(
            f"--resume: {args.out} holds another run: {error.listed(_tune_option)}. Resume with the run's options "
            f"(more --steps may continue a CMA-ES run, --holdout may change), or start a new run in another --out"
        ) from None
    except (TuneSetupError, ValueError) as error:
        field, separator, rest = str(error).partition(": ")
        option = _TUNE_OPTIONS.get(field)
        raise UsageError(f"{option}: {rest}" if separator and option else str(error)) from None
    # Every file read and checked now: tune() reads them again after writing run.json.
    robot = sg.load_robot(args.robot) if args.robot else sg.paper_robot()
    scenario = load_scenario(robot, args.scenario) if args.scenario else paper_scenario(robot)
    _realism(args, scenario)
    _warn(plausibility.input_warnings(scenario))
    _check_envelope(args, scenario)
    if args.gains:
        load_gains(args.gains, args.controller, n_joints(robot))
    else:
        _paper_gains_for(robot, args.controller)
    _claim(args, Path(args.out))
    try:
        result = tune(
            Path(args.out),
            config=config,
            gains_file=args.gains,
            scenario_file=args.scenario,
            robot_file=args.robot,
            holdout=args.holdout,
            stop=args.stop,
        )
    except TuneSetupError as error:
        raise UsageError(str(error)) from None
    return _tune_finished(Path(args.out), result)


def _resume_tune(args: argparse.Namespace):
    """``tune --resume``: the options given on the command line (not their defaults) must
    be the recorded run's, but for the ones a resume may change."""
    record = json.loads((Path(args.out) / "run.json").read_text()) if (Path(args.out) / "run.json").exists() else None
    given = args.given - {"out", "resume", "compile_cache", "overwrite", "holdout", "gains", "scenario", "robot"}
    config = None
    if record is not None and given:
        # The options given replace the record's (checked together, as the run would be):
        # the command line's defaults of the others (CMA-ES's, say) are not the run's.
        fresh = _tune_fields(args)
        asked = {_TUNE_FIELDS.get(dest, dest) for dest in given} & set(fresh)
        config = TuneConfig.from_dict(record["config"] | {field: runfiles.plain(fresh[field]) for field in asked})
    return tune(
        Path(args.out),
        resume=True,
        config=config,
        gains_file=args.gains,
        scenario_file=args.scenario,
        robot_file=args.robot,
        holdout=args.holdout if "holdout" in args.given else None,
        stop=args.stop,
    )


#: TuneConfig's fields -> the options of ``spacegrasp tune`` that set them (for messages).
_TUNE_OPTIONS = {
    "frozen": "--freeze",
    "optimizer": "--optimizer",
    "cvar_alpha": "--cvar",
    "learning_rate": "--lr",
    "torque_guard_Nm": "--torque-guard",
    "aggregate": "--aggregate",
    "torque_fraction": "--torque-fraction",
    "torque_cap_Nm": "--torque-cap",
    "population": "--population",
    "step_size": "--step-size",
    "method": "--method",
    "gradient": "--gradient",
    "objective": "--objective",
    "weights": "--weights",
}

#: The options of ``spacegrasp tune`` (their destinations) -> the TuneConfig fields they set.
_TUNE_FIELDS = {option[2:].replace("-", "_"): field for field, option in _TUNE_OPTIONS.items()} | {"range": "ranges"}


def _tune_option(name: str) -> str:
    """The option of ``spacegrasp tune`` that sets a TuneConfig field (or a file) ``name``."""
    return _TUNE_OPTIONS.get(name, "--" + name.replace("_", "-"))


#: The objective's parts ``tune`` prints before and after (history.csv's names -> label, scale, unit).
_TUNE_PARTS = {
    "loss": ("objective", 1.0, ""),
    "final_position_m": ("final position error", 1e3, "mm"),
    "final_orientation_rad": ("final orientation error", 180.0 / math.pi, "deg"),
    "rms_tracking_m": ("rms tracking error", 1e3, "mm"),
    "position_margin": ("position margin (error / tolerance)", 1.0, ""),
    "orientation_margin": ("orientation margin", 1.0, ""),
    "torque_margin": ("torque margin (peak / constraint)", 1.0, ""),
    "target_speed_margin": ("target speed margin", 1.0, ""),
    "largest_peak_torque_Nm": ("largest peak torque", 1.0, "N m"),
    "peak_contact_hard_N": ("peak contact force", 1.0, "N"),
}


def _print_tune_report(out: Path, history: list) -> None:
    """What a tuning run did: each part of the objective over the training batch (mean)
    at the first and the last step, the nominal run's numbers, and the held-out result."""
    first, last = history[0], history[-1]
    print(f"\n{'training batch (mean)':38} {'start':>12} {'tuned':>12}")
    for name, (label, scale, unit) in _TUNE_PARTS.items():
        if name in first and name in last:
            label = f"{label} [{unit}]" if unit else label
            print(f"{label:38} {scale * float(first[name]):>12.4g} {scale * float(last[name]):>12.4g}")
    summary = json.loads((out / "summary.json").read_text())
    start = summary.get("paper_gains") or summary.get("starting_gains")
    tuned = summary["tuned_gains"]
    print(f"\n{'nominal run, exact contact':38} {'start':>12} {'tuned':>12}")
    for name, label, scale in (
        ("final_position_error_m", "final position error [mm]", 1e3),
        ("final_orientation_error_rad", "final orientation error [deg]", 180.0 / math.pi),
        ("largest_peak_torque_Nm", "largest peak torque [N m]", 1.0),
        ("max_contact_force_N", "peak contact force [N]", 1.0),
    ):
        print(f"{label:38} {scale * start[name]:>12.4g} {scale * tuned[name]:>12.4g}")
    holdout = summary.get("holdout")
    if holdout:
        paired = holdout["success_tuned_vs_start"]
        print(
            f"\nheld out ({holdout['scenarios']} samples, seed {holdout['seed']}): captured "
            f"{statistics.format_interval(holdout['success_start'])} with the starting gains, "
            f"{statistics.format_interval(holdout['success_tuned'])} tuned; exact McNemar p = {paired['p_value']:.2g} "
            f"({paired['only_candidate']} captures only the tuned gains make, {paired['only_reference']} only the starting)"
        )
        print(
            f"held-out objective: mean {holdout['mean_objective_start']:.4g} -> {holdout['mean_objective_tuned']:.4g}, "
            f"median largest peak torque {holdout['median_largest_peak_torque_Nm_start']:.3g} -> "
            f"{holdout['median_largest_peak_torque_Nm_tuned']:.3g} N m"
        )


def _tune_finished(out: Path, result) -> int:
    """The report and figures of a finished tuning run; the exit code (130: interrupted)."""
    if result.status == "interrupted":
        return 130
    _print_tune_report(out, result.history)
    record = json.loads((out / "run.json").read_text())
    robot = record_robot(record)
    realism = record["config"]["realism"]
    loop = "ideal loop (the paper's)" if realism is None or realism == ideal().to_dict() else "flight-like loop"
    start = (
        "from the paper's gains"
        if record["gains_source"] == "paper_gains()"
        else f"from {Path(record['gains_source']).name}"
    )
    plots.save_tuning_figures(
        result.history,
        result.log_before,
        result.log_after,
        out,
        runfiles.write_atomically,
        caption=_run_caption(loop, start, record_scenario(robot, record)),
        torque_limit_Nm=np.asarray(robot.joint_torque_limit),
    )
    print(
        f"wrote {out}/: gains.json, history.csv, summary.json, loss.png, peak_torques.png, ee_pose.png", file=sys.stderr
    )
    return 0


def _tune_config(args: argparse.Namespace) -> TuneConfig:
    """The tuning options of the command line (validated by TuneConfig and Weights)."""
    return TuneConfig(**_tune_fields(args))


def _tune_fields(args: argparse.Namespace) -> dict:
    """TuneConfig's fields as the command line gives them, not yet checked together."""
    return dict(
        controller=args.controller,
        steps=args.steps,
        learning_rate=args.lr,
        optimizer=args.optimizer,
        weights=Weights.parse(args.weights),
        batch=args.batch,
        cvar_alpha=args.cvar,
        seed=args.seed,
        frozen=tuple(filter(None, args.freeze.split(","))),
        gradient=args.gradient,
        torque_guard_Nm=args.torque_guard,
        realism=load_realism(args.realism).to_dict() if args.realism else None,
        aggregate=args.aggregate or ("clip" if args.realism and args.method == "gradient" else "mean"),
        ranges=_ranges(args, TUNING_RANGES),
        objective=args.objective,
        method=args.method,
        population=args.population,
        step_size=args.step_size,
        torque_fraction=args.torque_fraction,
        torque_cap_Nm=args.torque_cap,
    )


#: The envelopes ``--ranges`` knows by name: the campaigns' defaults, the tuning batch's and
#: free-floating targets of 200 to 2,000 kg (with a scenario that has a [target]).
NAMED_RANGES = {"montecarlo": PerturbationRanges(), "tuning": TUNING_RANGES, "free_target": FREE_TARGET_RANGES}


def add_ranges_arguments(parser: argparse.ArgumentParser, default: str) -> None:
    """``--ranges`` and ``--range`` on ``parser``, whose envelope is ``default`` (a name)."""
    parser.add_argument(
        "--ranges",
        metavar="montecarlo|tuning|free_target|FILE",
        help=f"perturbation half-widths: a named envelope or a TOML file whose missing keys keep the {default} "
        f"envelope's (default: {default}; documentation: File formats)",
    )
    parser.add_argument(
        "--range",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="override one half-width, e.g. q_init_rad=0.05 (repeatable)",
    )


def _check_envelope(args: argparse.Namespace, scenario) -> None:
    """``--ranges free_target`` draws targets: refused for a scenario without one."""
    if getattr(args, "ranges", None) == "free_target" and scenario.target is None:
        raise UsageError(
            "--ranges free_target: needs a scenario with a free-floating [target], e.g. --scenario configs/free_target_envelope.toml"
        )


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


def _montecarlo_variants(args: argparse.Namespace, robot) -> list[campaign.Variant]:
    """The paper's gains for each selected controller (for the paper's 7-joint arm), plus each
    ``--gains`` file."""
    controllers = PAPER_CONTROLLERS if args.controller == "both" else (args.controller,)
    n = n_joints(robot)
    papers = all(controller in PAPER_CONTROLLERS for controller in controllers)
    if not args.gains:
        _paper_gains_for(robot, None if papers else args.controller)
    gain_sets = [("paper", paper_gains())] if n == len(paper_gains().kp) and papers else []
    for path in args.gains:
        label = Path(path).stem
        if label in {existing for existing, _ in gain_sets}:
            raise UsageError(f"--gains {path}: two gain sets would both be called {label!r}; rename one file")
        gain_sets.append((label, load_gains(path, None if args.controller == "both" else args.controller, n)))
    return [campaign.Variant(controller, gains, label) for controller in controllers for label, gains in gain_sets]


def _montecarlo(args: argparse.Namespace) -> int:
    # Both before anything touches a device.
    if args.num_processes is not None and args.process_id is not None and args.process_id >= args.num_processes:
        raise UsageError(f"--process-id: must be below --num-processes ({args.num_processes}), got {args.process_id}")
    if args.distributed:
        jax.distributed.initialize(args.coordinator, args.num_processes, args.process_id)
    batching.use_all_cpu_cores()
    robot = sg.load_robot(args.robot) if args.robot else sg.paper_robot()
    try:
        ranges = _ranges(args, PerturbationRanges())
        variants = _montecarlo_variants(args, robot)
        devices = jax.device_count()
        chunk = batching.chunk_size(args.chunk, args.n)
        config = _criteria(
            args,
            n=args.n,
            seed=args.seed,
            chunk=chunk,
            ranges=ranges,
            timeseries_every=args.timeseries_every,
            device_batch=args.device_batch
            if args.device_batch is not None
            else (128 if jax.default_backend() == "cpu" else None),
            realism=load_realism(args.realism) if args.realism else None,
        )
    except (PerturbationError, campaign.CampaignError) as error:
        raise UsageError(str(error)) from None
    scenario = load_scenario(robot, args.scenario) if args.scenario else paper_scenario(robot)
    _realism(args, scenario)  # the control period against the scenario, before compiling
    _warn(plausibility.input_warnings(scenario))
    _check_envelope(args, scenario)
    out = Path(args.out)
    _claim(args, out)
    names = ", ".join(variant.key for variant in variants)
    print(
        f"Monte-Carlo: {args.n} samples x {len(variants)} variant(s) ({names}), {scenario.duration:g} s each, "
        f"chunks of {chunk} over {devices} device(s) in {jax.process_count()} process(es)",
        file=sys.stderr,
        flush=True,
    )
    try:
        result = campaign.run_campaign(
            robot,
            scenario,
            variants,
            config,
            out,
            resume=args.resume,
            robot_source=args.robot or "paper_robot()",
            stop=args.stop,
        )
    except campaign.CampaignError as error:
        raise UsageError(str(error)) from None
    if result.status == "interrupted":
        print(
            f"interrupted after chunk {result.summary['chunks_done']}/{result.summary['chunks_total']}; "
            f"finished chunks are in {out}/chunks. Continue with: spacegrasp montecarlo {shlex.join(sys.argv[2:]) if sys.argv[1:2] == ['montecarlo'] else '...'} --resume",
            file=sys.stderr,
        )
        return 130
    _print_campaign(result)
    if jax.process_index() == 0:
        tolerance_mm = 1e3 * result.summary["tolerances"]["final_position_m"]
        plots.save_campaign_figures(
            out,
            result.metrics,
            campaign.figure_title(result.summary),
            tolerance_mm,
            runfiles.write_atomically,
            torque_limit_Nm=config.torque_limit_Nm,
        )
        if args.csv:
            with np.load(out / "samples.npz") as samples:
                runfiles.write_csv(out / "samples.csv", {name: samples[name] for name in samples.files})
        print(
            f"wrote {out}/: samples.npz{', samples.csv' if args.csv else ''}, summary.json, histograms.png, "
            "torque_vs_error.png, failures.png" + (", timeseries_*.npz" if config.timeseries_every else "")
        )
    return 0


def _gradients(args: argparse.Namespace) -> int:
    batching.use_all_cpu_cores()  # before anything touches a device
    try:
        ranges = _ranges(args, PerturbationRanges())
        weights = Weights.parse(args.weights)
        horizons = _horizons(args.horizons)
    except ValueError as error:
        raise UsageError(str(error)) from None
    robot, scenario, gains = _load_inputs(args)
    law = _law(args.controller, args)
    realism = _realism(args, scenario)
    _warn(plausibility.input_warnings(scenario))
    _check_envelope(args, scenario)
    out = Path(args.out)
    _claim(args, out)
    # A fixed torque scale, so that reports at different gains compare: Table 5's row for the
    # paper's laws, 1 N m a joint for others.
    torque_scale = paper.MAX_ABS_TORQUE_NM.get(args.controller, (1.0,) * n_joints(robot))
    objective = Objective(
        weights=weights,
        torque_scale_Nm=tuple(float(x) for x in torque_scale),
        temperature=TuneConfig().temperature,
    )
    smooth = dataclasses.replace(scenario, contact_law="smooth")  # as tuning: gradients need the smooth law
    print(
        f"gradients on the nominal scenario and {args.n} perturbed ones, horizons {', '.join(f'{h:g}' for h in horizons)} "
        f"of {scenario.duration:g} s, over {jax.device_count()} device(s)...",
        file=sys.stderr,
        flush=True,
    )
    result, evaluate = envelope_gradients(
        robot,
        smooth,
        gains,
        law,
        objective,
        n=args.n,
        seed=args.seed,
        ranges=ranges,
        realism=realism,
        horizons=horizons,
        chunk=batching.chunk_size(args.chunk, args.n + 1),
        progress=sys.stderr,
    )
    document = gradient_report(result, outlier_factor=args.outlier_factor)
    checked = np.flatnonzero(finite_rows(result))[: args.fd_samples]  # the nominal first, if finite
    document["central_differences"] = central_differences(
        result, evaluate, gains, args.controller, samples=checked, seed=args.seed
    )
    document["settings"] = {
        "controller": args.controller,
        "gains": gains.to_dict(args.controller),
        "seed": args.seed,
        "ranges": ranges.to_dict(),
        "realism": realism.to_dict() if realism is not None else None,
        "weights": dataclasses.asdict(weights),
        "torque_scale_Nm": objective.torque_scale_Nm,
        "scenario_duration_s": scenario.duration,
        "pinv_damping": args.pinv_damping,
        "contact_law": "smooth",
        **runfiles.provenance(),
    }
    runfiles.write_json(out / "gradients.json", document)
    runfiles.write_arrays(
        out / "gradients.npz",
        {"horizons_s": result.horizons_s, "losses": result.losses}
        | {f"gradient.{name}": value for name, value in result.gradients.items()},
    )
    title = f"{args.controller}, {args.n} samples" + (f", realism {args.realism}" if args.realism else "")
    plots.save_gradient_figures(
        out,
        document["per_sample"]["norm_over_nominal"],
        document["per_sample"]["cosine_with_nominal"],
        document["horizon_growth"]["norms"],
        args.outlier_factor,
        title,
        runfiles.write_atomically,
    )
    _print_gradient_report(document)
    print(f"wrote {out}/: gradients.json, gradients.npz, gradients.png")
    return 0


def _margins(args: argparse.Namespace) -> int:
    """``spacegrasp margins``: the gain and delay margins of one gain set, by bisection on
    batched rollouts over envelope samples (``spacegrasp_jax.margins``)."""
    batching.use_all_cpu_cores()  # before anything touches a device
    try:
        margins.require_joint_servo(args.controller)
        ranges = _ranges(args, PerturbationRanges())
        settings = margins.MarginSettings(
            samples=args.samples,
            max_factor=args.max_factor,
            factor_resolution=args.factor_resolution,
            max_delay_periods=args.max_delay,
            max_servo_delay_ticks=args.max_servo_delay,
        )
    except (margins.MarginError, PerturbationError) as error:
        raise UsageError(str(error)) from None
    robot, scenario, gains = _load_inputs(args)
    realism = _realism(args, scenario)
    config = _criteria(args, n=args.samples, seed=args.seed, ranges=ranges, realism=realism)
    _warn(plausibility.input_warnings(scenario))
    _check_envelope(args, scenario)
    out = Path(args.out)
    _claim(args, out)
    period = margins.control_period(scenario, realism)
    print(
        f"margins of the {args.controller} law: probes of {args.samples} envelope samples, {scenario.duration:g} s each, "
        f"control period {period:g} s, over {jax.device_count()} device(s)...",
        file=sys.stderr,
        flush=True,
    )
    result = margins.find_margins(
        robot,
        scenario,
        gains,
        args.controller,
        config,
        settings,
        progress=lambda line: print(line, file=sys.stderr, flush=True),
    )
    result["linear"] = None
    if args.no_linear:
        result["linear_skipped"] = "--no-linear"
    elif scenario.target is not None:
        result["linear_skipped"] = "the linear analysis covers the paper's stationary target only"
        print(f"linear analysis skipped: {result['linear_skipped']}", file=sys.stderr)
    else:
        print(
            "linearising the loop at the end of the nominal capture (one compile, then one Jacobian a factor)...",
            file=sys.stderr,
            flush=True,
        )
        result["linear"] = stability.linear_analysis(
            robot,
            scenario,
            gains,
            _law(args.controller, args),
            realism,
            settings,
            growth_limit_per_s=args.growth_limit,
        )
    result["settings"] |= {
        "gains": gains.to_dict(args.controller),
        "gains_source": args.gains or "paper_gains()",
        "criteria": _capture_tolerances(config),
        "campaign": config.to_dict(),
        "scenario_duration_s": scenario.duration,
        **runfiles.provenance(),
    }
    runfiles.write_json(out / "margins.json", result)
    title = f"{args.controller}, {args.gains or 'paper gains'}, {args.samples} samples" + (
        f", realism {args.realism}" if args.realism else ""
    )
    plots.save_margin_figures(out, result, 1e3 * config.position_tolerance_m, title, runfiles.write_atomically)
    for line in margins.margin_lines(result) + (stability.linear_lines(result["linear"]) if result["linear"] else []):
        print(line)
    print(f"wrote {out}/: margins.json, margins.png" + (", eigenvalues.png" if result["linear"] else ""))
    return 0


def _worstcase(args: argparse.Namespace) -> int:
    """``spacegrasp worstcase``: the worst capture of the envelope by gradient ascent, against
    a campaign of the same rollouts (``spacegrasp_jax.worstcase``)."""
    batching.use_all_cpu_cores()  # before anything touches a device
    try:
        ranges = _ranges(args, PerturbationRanges())
        settings = worstcase.SearchSettings(budget=args.budget, measure=args.measure, starts=args.starts)
    except (worstcase.WorstCaseError, PerturbationError) as error:
        raise UsageError(str(error)) from None
    robot, scenario, gains = _load_inputs(args)
    realism = _realism(args, scenario)
    config = _criteria(args, n=1, seed=args.seed, ranges=ranges, realism=realism)
    if args.measure == "criteria" and config.torque_limit_Nm is None:
        _warn(["--measure criteria with --torque-limit 0: the peak torque is not among the criteria"])
    _warn(plausibility.input_warnings(scenario))
    _check_envelope(args, scenario)
    out = Path(args.out)
    _claim(args, out)
    unit, meaning = worstcase.MEASURES[args.measure]
    print(
        f"worst case of the {args.controller} law: {meaning}, {args.budget} rollouts "
        f"({settings.screening} screened, {settings.ascent_steps} ascent steps of {settings.starts} starts), "
        f"{scenario.duration:g} s each, over {jax.device_count()} device(s)...",
        file=sys.stderr,
        flush=True,
    )
    say = lambda line: print(line, file=sys.stderr, flush=True)
    found = worstcase.search(robot, scenario, gains, args.controller, config, settings, progress=say)
    say(f"the campaign of the same {args.budget} rollouts (its first {len(found.screening)} are the screening's)...")
    baseline = worstcase.compare_with_campaign(
        robot,
        scenario,
        gains,
        args.controller,
        config,
        args.budget,
        args.measure,
        chunk=settings.campaign_chunk,
        screened=found.screening,
    )
    units = jax.tree.map(jnp.asarray, found.units)
    replay_file = out / "worst_perturbation.json"
    runfiles.write_json(replay_file, worstcase.perturbation_document(found.units, ranges, found.key, config.identified))
    campaign_units = jax.tree.map(
        lambda x: x[0], worstcase.units_of_samples(args.seed, [baseline["sample"]], n_joints=n_joints(robot))
    )
    campaign_key = worstcase.noise_keys(args.seed, [baseline["sample"]])[0]
    runfiles.write_json(
        out / "campaign_worst_perturbation.json",
        worstcase.perturbation_document(campaign_units, ranges, campaign_key, config.identified),
    )
    plant, perturbed, loop_realism, model_robot = perturbed_loop(
        robot, scenario, from_units(units, ranges), ranges, realism, config.identified
    )
    say("the worst capture again, with its whole log...")
    result = experiment.run(
        plant,
        perturbed,
        gains,
        _law(args.controller, args),
        realism=loop_realism,
        key=jnp.asarray(found.key, dtype=jnp.uint32),
        model_robot=model_robot,
        check=False,
    )
    perturbation = jax.tree.map(lambda x: np.asarray(x).tolist(), vars(from_units(units, ranges)))
    replay_command = ["spacegrasp", "simulate", "--controller", args.controller]
    for option, value in (("--gains", args.gains), ("--scenario", args.scenario), ("--robot", args.robot)):
        if value:
            replay_command += [option, value]
    if args.realism:
        replay_command += ["--realism", args.realism]
    if args.pinv_damping:
        replay_command += ["--pinv-damping", f"{args.pinv_damping:g}"]
    replay_command += ["--perturbation", str(replay_file), "--out", str(out / "replay")]
    document = {
        "measure": args.measure,
        "unit": unit,
        "meaning": meaning,
        "worst_found": {
            "value": found.value,
            "start": found.start,
            "start_sample": None if found.start < 0 else found.start_samples[found.start],
            "units": worstcase.units_to_dict(found.units),
            "perturbation": perturbation,
            "noise_key": [int(x) for x in found.key],
            "summary": _with_capture(result.summary, config),
        },
        "campaign": {
            "n": args.budget,
            "seed": args.seed,
            "worst": baseline["value"],
            "worst_sample": baseline["sample"],
        },
        "worse_than_the_campaign": bool(found.value >= baseline["value"]),
        "rollouts": found.rollouts,
        "screening": int(len(found.screening)),
        "compile_s": found.compile_s,
        "search_s": found.search_s,
        "history": found.history,
        "replay": shlex.join(replay_command),
        "settings": dataclasses.asdict(settings)
        | {
            "controller": args.controller,
            "gains": gains.to_dict(args.controller),
            "gains_source": args.gains or "paper_gains()",
            "criteria": _capture_tolerances(config),
            "campaign": config.to_dict(),
            "scenario_duration_s": scenario.duration,
            **runfiles.provenance(),
        },
    }
    runfiles.write_json(out / "worstcase.json", document)
    loop = "ideal loop" if realism is None else "flight-like loop"
    _write_results(
        out,
        {args.controller: result},
        {"worstcase": str(out / "worstcase.json")},
        beside_paper=False,
        caption=_run_caption(f"the worst capture found ({args.measure}): {loop}", "its gains", scenario),
        torque_limit_Nm=np.asarray(robot.joint_torque_limit),
        criteria=config,
    )
    label = f"{args.measure} [{unit}]" if unit else args.measure
    title = f"worst case, {args.controller}, {args.gains or 'paper gains'}" + (
        f", realism {args.realism}" if args.realism else ""
    )
    plots.save(
        {
            "search.png": plots.figure_worst_case_search(
                found.history, baseline["values"], len(found.screening), label, title
            )
        },
        out,
        runfiles.write_atomically,
    )
    where = "a screened sample" if found.start < 0 else f"the ascent from start {found.start}"
    print(
        f"worst {args.measure} found: {found.value:.6g} {unit} ({where}); worst of a campaign of {args.budget}: "
        f"{baseline['value']:.6g} {unit} (sample {baseline['sample']})"
    )
    print(f"{found.rollouts} rollouts in {found.search_s:.1f} s, after {found.compile_s:.1f} s compiling")
    print(f"replay it: {shlex.join(replay_command)}")
    if baseline["value"] > found.value:
        print(
            "the campaign's worst sample is worse than the search's: replay it with --perturbation "
            f"{out / 'campaign_worst_perturbation.json'}"
        )
    print(
        f"wrote {out}/: worstcase.json, worst_perturbation.json, campaign_worst_perturbation.json, search.png, "
        "the worst capture's summary.json, figures, timeseries"
    )
    return 0


def _criteria(args: argparse.Namespace, **fields) -> campaign.CampaignConfig:
    """The campaign's settings with the capture criteria of ``_add_criteria_options()``."""
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


def _horizons(text: str) -> tuple[float, ...]:
    """``--horizons``: fractions of the scenario's duration, increasing, the last 1."""
    try:
        fractions = tuple(float(item) for item in text.split(","))
    except ValueError:
        raise UsageError(f"--horizons {text!r}: expected fractions such as 0.25,0.5,1") from None
    if not all(0.0 < f <= 1.0 for f in fractions) or list(fractions) != sorted(set(fractions)) or fractions[-1] != 1.0:
        raise UsageError(f"--horizons {text!r}: increasing fractions in (0, 1], the last 1")
    return fractions


def _print_gradient_report(document: dict) -> None:
    nominal = document["nominal"]
    print(f"nominal: loss {nominal['loss']:.4g}, |gradient| {nominal['gradient_norm']:.4g}")
    print(
        f"non-finite gradients: {document['nonfinite']['count']} of {document['samples']} perturbed samples"
        + ("" if nominal["finite"] else "; the nominal's is not finite either")
    )
    ratio, cosine, outliers = document["norm_over_nominal"], document["cosine_with_nominal"], document["outliers"]
    print(
        f"|gradient| / nominal: median {ratio['median']:.3g}, p95 {ratio['p95']:.3g}, largest {ratio['largest']:.3g}; "
        f"over {outliers['factor']:g}x: {outliers['count']} ({outliers['fraction']:.1%})"
    )
    print(
        f"cosine with the nominal gradient: median {cosine['median']:.3f}, 5th percentile {cosine['p05']:.3f}, "
        f"negative {cosine['fraction_negative']:.1%}"
    )
    print(f"{'group':>6} {'sign agreement (per entry)':>40}  median |gradient|")
    for name, group in document["groups"].items():
        agreement = " ".join(f"{value:.2f}" for value in np.asarray(group["sign_agreement"], dtype=float))
        print(f"{name:>6} {agreement:>40}  {group['norm_median']:.3g}")
    for row in document["horizon_growth"]["norms"]:
        print(
            f"horizon {row['horizon_s']:>7.3f} s: median |gradient| {row['median_norm']:.3g}, largest {row['largest_norm']:.3g}"
        )
    for check in document["central_differences"]:
        print(
            f"central differences, sample {check['sample']}: slope {check['gradient_slope']:.6g} vs "
            f"{check['finite_difference_slope']:.6g} (relative error {check['relative_error']:.1e})"
        )


def _benchmark(args: argparse.Namespace) -> int:
    try:
        import mujoco  # noqa: F401
        import pinocchio  # noqa: F401

        from spacegrasp_jax.benchmarks import suite
    except ImportError as error:  # the peers, or the benchmarks package outside a checkout
        raise UsageError(f"the benchmark needs the test extra (pip install -e '.[test]'): {error}") from None
    _claim(args, Path(args.out))
    return suite.main([*(["--quick"] if args.quick else []), "--out", args.out, "--repeats", str(args.repeats)])


def _print_campaign(result: campaign.CampaignResult) -> None:
    width = max(24, *(len(key) for key in result.summary["variants"]))
    header = f"{'variant':{width}} {'success [95% CI]':>22} {'diverged':>8} {'unstable':>8} {'final pos p50/p95 [mm]':>23} {'peak |u| p50/p95 [N m]':>23} {'contact p95 [N]':>16}"
    print(header)
    for key, summary in result.summary["variants"].items():
        stats = summary["statistics_over_non_diverged"]

        def pair(name, scale=1.0):
            s = stats[name]
            return f"{scale * s['p50']:.3f}/{scale * s['p95']:.3f}" if s.get("count") else "-"

        contact = stats["max_contact_force_N"]
        print(
            f"{key:{width}} {statistics.format_interval(summary['success_interval']):>22} {summary['diverged']:>8d} {summary['unstable']:>8d} {pair('final_position_error_m', 1e3):>23} "
            f"{pair('largest_peak_torque_Nm'):>23} {contact['p95'] if contact.get('count') else float('nan'):>16.3f}"
        )
    for name, comparison in result.summary.get("comparisons", {}).items():
        s, torque = comparison["success"], comparison["largest_peak_torque_Nm"]
        print(
            f"{name}: success {100 * s['rate_difference']:+.1f} points [{100 * s['rate_difference_low']:+.1f}, "
            f"{100 * s['rate_difference_high']:+.1f}] (captured by one only: {s['only_candidate']} vs {s['only_reference']}, "
            f"McNemar p = {s['p_value']:.2g}); largest peak torque median {torque['median_difference']:+.3f} N m "
            f"[{torque['low']:+.3f}, {torque['high']:+.3f}] (lower in {torque['candidate_lower']} vs {torque['reference_lower']}, "
            f"Wilcoxon p = {torque['p_value']:.2g})"
        )
    throughput = result.summary["throughput"]
    if throughput["rollouts_per_s"]:
        print(
            f"throughput: {throughput['rollouts_per_s']:.2f} rollouts/s, {throughput['simulated_s_per_wall_s']:.1f} simulated s per wall s "
            f"on {throughput['devices']} {throughput['platform']} device(s); compile {throughput['compile_s']:.1f} s"
        )


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


#: The help of every command's ``--robot``.
ROBOT_HELP = (
    "robot file (default: the paper's robot): a robot TOML, a URDF (its base link is the satellite), "
    "or a TOML whose [urdf] table mounts a URDF arm on a satellite"
)


def _add_overwrite_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the run that --out holds (default: refuse a folder that holds anything)",
    )


def _add_animate_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--animate",
        action="store_true",
        help="also film each capture: capture_<law>.gif and a poster (spacegrasp animate)",
    )
    _add_film_options(parser)


def _add_film_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--fps", type=_real(1.0, 120.0), default=30.0, help="frames a second of film (default 30)")
    parser.add_argument(
        "--speed", type=_real(0.01, 100.0), default=1.0, help="simulated seconds a second of film (default 1)"
    )


def _add_csv_option(parser: argparse.ArgumentParser, what: str) -> None:
    parser.add_argument("--csv", action="store_true", help=f"also write {what} as CSV (one row per row of the .npz)")


def _add_run_options(parser: argparse.ArgumentParser, default_out: str) -> None:
    parser.add_argument("--out", default=default_out, help=f"output folder (default {default_out})")
    _add_overwrite_option(parser)
    parser.add_argument("--robot", help=ROBOT_HELP)
    parser.add_argument(
        "--pinv-damping",
        type=_real(0.0, 1e3),
        default=0.0,
        help="damping of the pseudoinverse (0: exact, the paper)",
    )


def _add_command(commands, name: str, help: str) -> argparse.ArgumentParser:
    """A command's parser whose ``--help`` opens with the line ``spacegrasp --help`` lists."""
    return commands.add_parser(name, help=help, description=help[0].upper() + help[1:] + ".")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="spacegrasp", description=" ".join(sg.__doc__.split("\n\n")[0].split()))
    parser.add_argument("--version", action="version", version=f"spacegrasp-jax {sg.__version__}")
    commands = parser.add_subparsers(dest="command", required=True)
    parser.commands = commands.choices  # command name -> its parser
    info = _add_command(commands, "info", help="print the robot's mass, CoM, EE pose at q_init and cond(M)")
    info.add_argument("--robot", help=ROBOT_HELP)
    info.add_argument("--scenario", help="scenario TOML/JSON whose q_init to show the robot at")
    info.add_argument(
        "--urdf", metavar="FILE", help="also write the robot as URDF to FILE, a new file (for Pinocchio, Drake, ROS)"
    )
    info.set_defaults(run=_info)

    reproduce = _add_command(
        commands, "reproduce", help="run both controllers with the paper's gains: Table 5 and Figures 4-9"
    )
    _add_run_options(reproduce, "results/reproduce")
    _add_animate_option(reproduce)
    _add_csv_option(reproduce, "the time series")
    _add_compile_cache_option(reproduce)
    reproduce.set_defaults(run=_reproduce)

    simulate = _add_command(commands, "simulate", help="run one controller with any gains and scenario")
    simulate.add_argument("--controller", choices=CONTROLLERS, required=True)
    simulate.add_argument("--gains", help="gains JSON file (default: the paper's)")
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
    _add_compile_cache_option(simulate)
    simulate.set_defaults(run=_simulate)

    replay = _add_command(commands, "replay", help="run one sample of a campaign again with its full log and figures")
    replay.add_argument("campaign", metavar="CAMPAIGN_DIR", help="a montecarlo output folder")
    replay.add_argument("--sample", type=_whole(0, 100_000_000), required=True, metavar="K", help="the sample's index")
    replay.add_argument(
        "--variant", metavar="LAW/GAINS", help="one variant, e.g. admittance/paper (default: every one)"
    )
    replay.add_argument("--out", required=True, help="output folder")
    _add_overwrite_option(replay)
    _add_csv_option(replay, "the time series")
    _add_compile_cache_option(replay)
    replay.set_defaults(run=_replay)

    animate = _add_command(commands, "animate", help="film a run's capture in 3D: a GIF or an MP4, and a poster PNG")
    animate.add_argument("run_dir", metavar="RUN_DIR", help="a run folder of simulate, reproduce or replay")
    animate.add_argument("--controller", help="which of the folder's runs (default: each, one film apiece)")
    animate.add_argument(
        "--out", help="the film, .gif or .mp4 (default: RUN_DIR/capture_<run>.gif; the poster beside it, _poster.png)"
    )
    _add_film_options(animate)
    _add_overwrite_option(animate)
    animate.set_defaults(run=_animate)

    compare = _add_command(
        commands, "compare", help="overlay runs of simulate, reproduce or replay on the paper's figures"
    )
    compare.add_argument("runs", nargs="+", metavar="RUN_DIR", help="run folders (each may hold several runs)")
    compare.add_argument("--out", required=True, help="output folder")
    _add_overwrite_option(compare)
    compare.set_defaults(run=_compare)

    export_gains = _add_command(
        commands, "export", help="write gains for flight software: JSON, YAML, a C header or CSV, with units"
    )
    export_gains.add_argument("--gains", help="gains JSON file (default: the paper's)")
    export_gains.add_argument("--controller", choices=CONTROLLERS, default="admittance")
    export_gains.add_argument("--format", choices=export.FORMATS, required=True)
    _add_realism_option(export_gains)
    export_gains.add_argument("--scenario", help="scenario TOML or JSON file, for its step (default: the paper's)")
    export_gains.add_argument("--robot", help=ROBOT_HELP)
    export_gains.add_argument(
        "--prefix", type=_c_identifier, default="SG", help="the C header's names: PREFIX_kp, ... (default SG)"
    )
    export_gains.add_argument("--out", metavar="FILE", help="the file to write (default: print it)")
    export_gains.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    export_gains.set_defaults(run=_export)

    tune = _add_command(
        commands, "tune", help="tune the gains for capture success: CMA-ES or gradient descent (resumable)"
    )
    tune.add_argument("--out", required=True, help="output folder (also holds the checkpoint)")
    _add_overwrite_option(tune)
    tune.add_argument("--controller", choices=CONTROLLERS, default="admittance")
    tune.add_argument("--steps", type=_whole(1, 1_000_000), default=60, help="optimiser steps (default 60)")
    tune.add_argument(
        "--lr",
        type=_real(0.0, 10.0, above=True),
        default=0.15,
        help="initial step size in log-gain space (default 0.15)",
    )
    tune.add_argument(
        "--method",
        choices=METHODS,
        default=TuneConfig.method,
        help=f"gradient: optax on the gradient; cmaes: CMA-ES, --steps generations of forward rollouts (default {TuneConfig.method})",
    )
    tune.add_argument(
        "--population",
        type=_whole(2, 10_000),
        default=None,
        help="CMA-ES candidates per generation (default 4 + 3 ln(number of tuned gains))",
    )
    tune.add_argument(
        "--step-size",
        type=_real(0.0, 10.0, above=True),
        default=TuneConfig.step_size,
        help=f"CMA-ES's initial step in log-gain units (default {TuneConfig.step_size}: about +-30%% on every gain)",
    )
    tune.add_argument(
        "--objective",
        choices=OBJECTIVES,
        default=TuneConfig.objective,
        help=f"capture: the margins to the success criteria, torque a constraint at the motors' limits; weighted: "
        f"errors against torque relative to the starting gains (default {TuneConfig.objective})",
    )
    tune.add_argument(
        "--torque-fraction",
        type=_real(0.0, 10.0, above=True),
        default=1.0,
        help="the capture objective's torque constraint as a fraction of the motors' limits (default 1)",
    )
    tune.add_argument(
        "--torque-cap",
        type=_real(0.0, 1000.0, above=True),
        default=None,
        metavar="NM",
        help="the capture objective's torque budget in N m for every joint, where below its fraction of the "
        "limit (default: none)",
    )
    tune.add_argument(
        "--weights",
        default="",
        help="the weighted objective's weights, e.g. final_position=1,peak_torque=4 (documentation: Tuning the gains)",
    )
    tune.add_argument(
        "--batch", type=_whole(1, 65_536), default=4, help="scenarios per step: nominal + batch-1 perturbed (default 4)"
    )
    tune.add_argument(
        "--cvar",
        type=_real(0.0, 1.0),
        default=None,
        help="optimise CVaR at this level over the batch instead of the mean",
    )
    tune.add_argument("--seed", type=_SEED, default=0, help="seed of the perturbed scenarios")
    tune.add_argument("--optimizer", default="adam", help="any optax optimiser taking a learning rate (default adam)")
    tune.add_argument("--freeze", default="", help="gain groups to keep fixed, e.g. kd,ki")
    tune.add_argument("--gradient", choices=("reverse", "forward"), default="reverse")
    tune.add_argument(
        "--torque-guard",
        type=_real(0.0, 1e6, above=True),
        default=100.0,
        help="reject steps whose peak torque exceeds this (N m)",
    )
    tune.add_argument(
        "--holdout",
        type=_whole(0, 1_000_000),
        default=100,
        help="held-out perturbed scenarios for the final evaluation",
    )
    tune.add_argument("--gains", help="starting gains JSON (default: the paper's)")
    tune.add_argument("--scenario", help="scenario TOML/JSON (default: the paper's)")
    tune.add_argument("--robot", help=ROBOT_HELP)
    tune.add_argument("--resume", action="store_true", help="continue the run in --out from its last completed step")
    add_ranges_arguments(tune, "tuning")
    _add_realism_option(tune)
    tune.add_argument(
        "--aggregate",
        choices=("mean", "clip"),
        help="the gradient method under --realism: combine the samples' gradients as their mean, or clip each to 3x "
        "the median norm first (default: clip there, else mean)",
    )
    _add_compile_cache_option(tune)
    tune.set_defaults(run=_tune)

    montecarlo = _add_command(
        commands, "montecarlo", help="robustness campaign over perturbed captures (sharded, resumable)"
    )
    montecarlo.add_argument("--n", type=_whole(1, 100_000_000), required=True, help="number of perturbed samples")
    montecarlo.add_argument(
        "--controller", choices=(*CONTROLLERS, "both"), default="both", help="a law, or both of the paper's (default)"
    )
    montecarlo.add_argument(
        "--gains",
        action="append",
        default=[],
        metavar="FILE",
        help="gains JSON to compare with the paper's (repeatable; labelled by file name)",
    )
    montecarlo.add_argument("--seed", type=_SEED, default=0, help="campaign seed (default 0)")
    montecarlo.add_argument(
        "--chunk",
        type=_whole(1, 1_000_000),
        default=256,
        help="samples per compiled call, a multiple of the device count (default 256)",
    )
    montecarlo.add_argument(
        "--device-batch",
        type=_whole(1, 1_000_000),
        default=None,
        metavar="K",
        help="samples each device simulates at once (default 128 on CPU, its whole share on GPU)",
    )
    montecarlo.add_argument("--out", default="results/montecarlo", help="output folder (default results/montecarlo)")
    _add_overwrite_option(montecarlo)
    _add_csv_option(montecarlo, "samples.npz")
    add_ranges_arguments(montecarlo, "montecarlo")
    _add_criteria_options(montecarlo)
    montecarlo.add_argument(
        "--timeseries-every",
        type=_whole(1, 100_000_000),
        default=None,
        metavar="K",
        help="also keep every K-th log row of every sample",
    )
    montecarlo.add_argument("--scenario", help="nominal scenario TOML/JSON (default: the paper's)")
    montecarlo.add_argument("--robot", help=ROBOT_HELP)
    montecarlo.add_argument(
        "--pinv-damping", type=_real(0.0, 1e3), default=0.0, help="damping of the pseudoinverse (0: exact, the paper)"
    )
    montecarlo.add_argument("--resume", action="store_true", help="continue the campaign in --out chunk by chunk")
    _add_realism_option(montecarlo)
    cluster = montecarlo.add_argument_group("several hosts (jax.distributed; run the same command on every host)")
    cluster.add_argument(
        "--distributed",
        action="store_true",
        help="call jax.distributed.initialize (auto-detects SLURM and similar without the options below)",
    )
    cluster.add_argument("--coordinator", help="HOST:PORT of process 0")
    cluster.add_argument("--num-processes", type=_whole(1, 65_536), help="number of processes")
    cluster.add_argument("--process-id", type=_whole(0, 65_535), help="this process's rank, 0 .. num-processes - 1")
    _add_compile_cache_option(montecarlo)
    montecarlo.set_defaults(run=_montecarlo)

    gradient_health = _add_command(
        commands, "gradients", help="the tuning objective's gradient over perturbed scenarios: is it trustworthy?"
    )
    gradient_health.add_argument("--n", type=_whole(1, 1_000_000), required=True, help="perturbed scenarios")
    gradient_health.add_argument("--controller", choices=CONTROLLERS, default="admittance")
    gradient_health.add_argument("--gains", help="gains JSON file (default: the paper's)")
    gradient_health.add_argument("--scenario", help="nominal scenario TOML/JSON (default: the paper's)")
    _add_realism_option(gradient_health)
    add_ranges_arguments(gradient_health, "montecarlo")
    gradient_health.add_argument("--seed", type=_SEED, default=0, help="seed of the samples (default 0)")
    gradient_health.add_argument(
        "--weights", default="", help="objective weights, as for tune (default: tune's defaults)"
    )
    gradient_health.add_argument(
        "--horizons",
        default=",".join(f"{h:g}" for h in GRADIENT_HORIZONS),
        help="fractions of the duration at which the gradient is taken, the last 1 (default %(default)s)",
    )
    gradient_health.add_argument(
        "--fd-samples",
        type=_whole(0, 100),
        default=3,
        help="samples checked against central differences (default 3)",
    )
    gradient_health.add_argument(
        "--outlier-factor",
        type=_real(1.0, 1e300, above=True),
        default=100.0,
        help="list the samples whose gradient norm exceeds this many times the nominal's (default 100)",
    )
    gradient_health.add_argument(
        "--chunk", type=_whole(1, 1_000_000), default=16, help="samples per compiled call (default 16)"
    )
    _add_run_options(gradient_health, "results/gradients")
    _add_compile_cache_option(gradient_health)
    gradient_health.set_defaults(run=_gradients)

    margin = _add_command(
        commands, "margins", help="gain and delay margins of a gain set, by bisection on envelope samples"
    )
    _add_envelope_options(margin, seed_help="campaign seed of the samples (default 0)")
    margin.add_argument(
        "--samples",
        type=_whole(1, 100_000),
        default=margins.MarginSettings.samples,
        help=f"envelope samples every probe runs (default {margins.MarginSettings.samples})",
    )
    margin.add_argument(
        "--max-factor",
        type=_real(1.0, 1e6, above=True),
        default=margins.MarginSettings.max_factor,
        help=f"search the gain factors in [1/F, F] (default {margins.MarginSettings.max_factor:g})",
    )
    margin.add_argument(
        "--factor-resolution",
        type=_real(1.0, 1e6, above=True),
        default=margins.MarginSettings.factor_resolution,
        metavar="RATIO",
        help="stop bisecting when the factor that holds and the one that fails differ by at most this ratio "
        f"(default {margins.MarginSettings.factor_resolution:g})",
    )
    margin.add_argument(
        "--max-delay",
        type=_whole(1, 100_000),
        default=margins.MarginSettings.max_delay_periods,
        metavar="PERIODS",
        help=f"the largest extra delay searched, in control periods (default {margins.MarginSettings.max_delay_periods})",
    )
    margin.add_argument(
        "--max-servo-delay",
        type=_whole(1, 100_000),
        default=margins.MarginSettings.max_servo_delay_ticks,
        metavar="TICKS",
        help="the largest delay at the servo's input searched, in servo ticks, where the servos run at their own "
        f"rate (default {margins.MarginSettings.max_servo_delay_ticks})",
    )
    margin.add_argument(
        "--growth-limit",
        type=_real(0.0, 1e6),
        default=1.0,
        metavar="PER_S",
        help="the linear analysis counts a mode growing faster than this (1/s) as unstable (default 1)",
    )
    margin.add_argument(
        "--no-linear",
        action="store_true",
        help="skip the linear analysis (the period map's eigenvalues and the linear gain margins)",
    )
    _add_criteria_options(margin)
    _add_run_options(margin, "results/margins")
    _add_compile_cache_option(margin)
    margin.set_defaults(run=_margins)

    worst = _add_command(
        commands, "worstcase", help="the worst capture of the envelope by gradient ascent, against a campaign"
    )
    _add_envelope_options(worst, seed_help="campaign seed of the screening (default 0)")
    worst.add_argument(
        "--budget",
        type=_whole(1, 10_000_000),
        default=worstcase.SearchSettings.budget,
        help=f"rollouts in all, a gradient counting {worstcase.GRADIENT_COST} (default {worstcase.SearchSettings.budget})",
    )
    worst.add_argument(
        "--measure",
        choices=tuple(worstcase.MEASURES),
        default=worstcase.SearchSettings.measure,
        help="what makes a capture worse: its final position error, its largest peak torque, or its largest "
        "ratio to the success criteria (default %(default)s)",
    )
    worst.add_argument(
        "--starts",
        type=_whole(1, 1_000),
        default=worstcase.SearchSettings.starts,
        help=f"ascents side by side: the screening's worst and a random corner (default {worstcase.SearchSettings.starts})",
    )
    _add_criteria_options(worst)
    _add_run_options(worst, "results/worstcase")
    _add_compile_cache_option(worst)
    worst.set_defaults(run=_worstcase)

    benchmark = _add_command(
        commands, "benchmark", help="speed and memory against MuJoCo and a Pinocchio loop (needs the test extra)"
    )
    benchmark.add_argument(
        "--quick",
        action="store_true",
        help="toy sizes: exercises every part in about two minutes; numbers mean nothing",
    )
    benchmark.add_argument(
        "--out", default="results/benchmarks", help="folder for benchmark.json (default results/benchmarks)"
    )
    _add_overwrite_option(benchmark)
    benchmark.add_argument(
        "--repeats", type=_whole(1, 1000), default=3, help="repeats per timing, median reported (default 3)"
    )
    benchmark.set_defaults(run=_benchmark)
    return parser


def _add_realism_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--realism",
        metavar="ideal|flight|FILE",
        help="the loop's realism: ideal (the paper's, default), flight, or a TOML file (documentation: Flight-like loop)",
    )


#: The file in the compile cache's folder that keeps each program's last compile time, for
#: the line printed before the program compiles again (``compilation.CompileAnnouncer``).
COMPILE_TIMES = "spacegrasp-compile-times.json"


def _add_envelope_options(parser: argparse.ArgumentParser, seed_help: str) -> None:
    """The gain set, its law and loop, and the envelope and seed its captures are drawn from
    (``margins`` and ``worstcase``)."""
    parser.add_argument("--controller", choices=CONTROLLERS, default="admittance")
    parser.add_argument("--gains", help="gains JSON file (default: the paper's)")
    parser.add_argument("--scenario", help="nominal scenario TOML/JSON (default: the paper's)")
    _add_realism_option(parser)
    add_ranges_arguments(parser, "montecarlo")
    parser.add_argument("--seed", type=_SEED, default=0, help=seed_help)


def _add_criteria_options(parser: argparse.ArgumentParser) -> None:
    """A capture's success criteria, as a campaign's (``campaign.CampaignConfig``), and what
    the controller is told of each sample."""
    parser.add_argument(
        "--tolerance-mm",
        type=_real(0.0, 1e6, above=True),
        default=5.0,
        help="success: final position error at most this (default 5 mm)",
    )
    parser.add_argument(
        "--tolerance-deg",
        type=_real(0.0, 180.0, above=True),
        default=1.0,
        help="success: final orientation error at most this (default 1 deg)",
    )
    parser.add_argument(
        "--torque-limit",
        type=_real(0.0, 1e6),
        default=100.0,
        metavar="NM",
        help="success: peak |u_i| at most this, else the sample counts as unstable (default 100 N m; 0: no limit)",
    )
    parser.add_argument(
        "--target-speed-limit",
        type=_real(0.0, 100.0, above=True),
        default=0.005,
        metavar="MPS",
        help="success, with a free-floating target: its final speed at most this (default 0.005 m/s)",
    )
    parser.add_argument(
        "--identified",
        action="store_true",
        help="tell the controller each sample's perturbed satellite (default: it believes the nominal robot)",
    )


def _add_compile_cache_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--compile-cache",
        metavar="DIR|none",
        help="keep compiled programs in DIR for later runs (default: $JAX_COMPILATION_CACHE_DIR, "
        "else ~/.cache/spacegrasp-jax/xla; 'none': compile everything afresh)",
    )
    parser.add_argument(
        "--verbose",
        action="store_true",
        help="show XLA's and JAX's own log (XLA's slow-compile banner among it; hidden by default)",
    )


#: The commands that stop cleanly at a safe point on a first signal -> the unit they finish.
_SAFE_POINTS = {"montecarlo": "chunk", "tune": "step"}


def _given_options(parser: argparse.ArgumentParser, argv: list[str]) -> set[str]:
    """The destinations of the options that ``argv`` gives explicitly (not by default): the
    command's parser run again with every default suppressed."""
    command, rest = None, []
    for index, token in enumerate(argv):
        if token in parser.commands:
            command, rest = parser.commands[token], argv[index + 1 :]
            break
    if command is None:
        return set()
    defaults = {action: action.default for action in command._actions}
    try:
        for action in defaults:
            action.default = argparse.SUPPRESS
        given, _ = command.parse_known_args(rest)
    finally:
        for action, default in defaults.items():
            action.default = default
    return set(vars(given)) & {action.dest for action in defaults}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exit:  # --help, --version (0) or a rejected option (2, one line printed)
        return exit.code
    args.given = _given_options(parser, argv)
    # The command owns its process: float64 and loops compiled whole, before anything runs,
    # and compiled programs kept on disk for the next run.
    compilation.enable_float64()
    compilation.compile_loops_whole()
    announcer = None
    if "compile_cache" in args:
        if not args.verbose:  # XLA's C++ log, its "Very slow compile?" banner among it, and JAX's
            jax.config.update("jax_logging_level", "CRITICAL")
        cache = compilation.use_compile_cache(args.compile_cache)
        print(f"compilation cache: {cache if cache else 'off'}", file=sys.stderr)
        announcer = compilation.CompileAnnouncer(sys.stderr, cache / COMPILE_TIMES if cache else None)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", UnusedGainsWarning)
            show_warning = warnings.showwarning

            def notice(message, category, *rest, **keywords):
                if issubclass(category, UnusedGainsWarning):
                    print(f"spacegrasp: notice: {message}", file=sys.stderr)
                else:
                    show_warning(message, category, *rest, **keywords)

            warnings.showwarning = notice
            # Commands with safe points (montecarlo, tune) stop at the next one on a first
            # signal, the others at once; then a signal ends the process at once (130).
            unit = _SAFE_POINTS.get(args.command)
            listening = compilation.listening(announcer) if announcer else contextlib.nullcontext()
            stop = runfiles.StopRequest(unit or "run", patience=1 if unit else 0, hard_exit=True)
            with listening, stop as args.stop:
                code = args.run(args)
                if getattr(args, "distributed", False):
                    jax.distributed.shutdown()  # with every process, before a late signal can interrupt it
                return code
    except (
        sg.RobotConfigError,
        GainsError,
        ScenarioError,
        PerturbationError,
        RealismError,
        UsageError,
        animation.AnimationError,
        runfiles.OutputFolderError,
    ) as error:
        print(f"spacegrasp: error: {error}", file=sys.stderr)
        return 2
    except experiment.SimulationDiverged as error:
        print(f"spacegrasp: error: {error}", file=sys.stderr)
        return 3


def run_command() -> None:
    """The process's entry point (``spacegrasp``, ``python -m spacegrasp_jax.cli``): exits
    with [`main()`][spacegrasp_jax.cli.main]'s code."""
    code = main()
    # The command is over and its files are written. A signal that lands while the
    # interpreter shuts down (one sent to every process of a campaign, after this one had
    # already stopped with the others) would otherwise end it by the signal, not this code.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    sys.exit(code)


if __name__ == "__main__":
    run_command()
