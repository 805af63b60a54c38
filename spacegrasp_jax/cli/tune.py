"""``spacegrasp tune``: tuning the gains, resumable."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path

import numpy as np

from spacegrasp_jax.cli.common import (
    _check_envelope,
    _check_joint_ranges,
    _claim,
    _load_robot,
    _paper_gains_for,
    _ranges,
    _rate_criterion,
    _realism,
    _robot_links,
    _run_caption,
    _save_schedule_figure,
    _warn,
)
from spacegrasp_jax.cli.options import (
    _SEED,
    TUNE_OPTIONS,
    UsageError,
    _add_command,
    _add_compile_cache_option,
    _add_overwrite_option,
    _add_realism_option,
    _real,
    _whole,
    add_gains_arguments,
    add_objective_arguments,
    add_ranges_arguments,
    add_robot_arguments,
    tune_setting_error,
)
from spacegrasp_jax.core.model import n_joints
from spacegrasp_jax.envelope import plausibility, statistics
from spacegrasp_jax.envelope.scenario import load_scenario, paper_scenario
from spacegrasp_jax.jobs import batching, runfiles
from spacegrasp_jax.loop.control import (
    CONTROLLERS,
)
from spacegrasp_jax.loop.control.schedule import NAMED_GAIN_SETS, VARIABLES, load_schedule
from spacegrasp_jax.loop.realism import load_realism
from spacegrasp_jax.tuning.cmaes import CMAESSettings
from spacegrasp_jax.tuning.estimators import AGGREGATES
from spacegrasp_jax.tuning.objective import Weights
from spacegrasp_jax.tuning.run import (
    OTHER_GAINS_FILES,
    ResumeMismatchError,
    TuneSetupError,
    run_record,
    start_gains,
    tune,
    tuned_base,
)
from spacegrasp_jax.tuning.tune import (
    KEEPS,
    METHODS,
    RECIPES,
    TUNING_RANGES,
    GradientSettings,
    TuneConfig,
    check_gradient_cut,
    default_recipe,
)


def _tune(args: argparse.Namespace) -> int:
    batching.use_all_cpu_cores()  # before anything touches a device: the batch shards over the cores
    try:
        if args.check:
            return _tune_finished(Path(args.out), _check_tune(args))
        if args.resume:
            _claim(args, Path(args.out))
            return _tune_finished(Path(args.out), _resume_tune(args))
        robot = _load_robot(args)
        config = _tune_config(args, robot)
    except ResumeMismatchError as error:
        raise UsageError(
            f"--resume: {args.out} holds another run: {error.listed(_tune_option)}. Resume with the run's options "
            f"(more --steps continue it, --holdout may change), or start a new run in another --out"
        ) from None
    except (TuneSetupError, ValueError) as error:
        raise tune_setting_error(error) from None
    # Every file read and checked now: tune() reads them again after writing run.json.
    scenario = load_scenario(robot, args.scenario) if args.scenario else paper_scenario(robot)
    _check_joint_ranges(args, robot, scenario)
    try:
        config.weights.check_target(scenario.free_target)
        check_gradient_cut(config, scenario)
    except ValueError as error:
        raise tune_setting_error(error) from None
    _realism(args, scenario, robot)
    _warn(plausibility.input_warnings(scenario))
    _check_envelope(args, scenario, config.ranges)
    if args.fill_from is not None and (args.gains is None or args.gains in NAMED_GAIN_SETS):
        raise UsageError(
            f"--fill-from: completes a gains file given with --gains; {args.gains or 'the paper'}'s gains are whole"
        )
    try:
        if args.gains:
            tuned_base(start_gains(args.gains, args.controller, n_joints(robot), args.fill_from), config)
    except TuneSetupError as error:
        raise UsageError(str(error)) from None
    if not args.gains:
        _paper_gains_for(robot, args.controller)
    _claim(args, Path(args.out))
    if args.method is None:
        _say_recipe(config)
    try:
        result = tune(
            Path(args.out),
            config=config,
            gains_file=args.gains,
            scenario_file=args.scenario,
            robot_file=args.robot,
            holdout=args.holdout,
            fill_from=args.fill_from,
            robot_links=_robot_links(args),
            command=getattr(args, "command_line", None),
            stop=args.stop,
        )
    except TuneSetupError as error:
        raise UsageError(str(error)) from None
    return _tune_finished(Path(args.out), result)


def _say_recipe(config: TuneConfig) -> None:
    """Which method ``tune`` without ``--method`` runs, and why (stderr)."""
    if config.method == "gradient":
        chosen = (
            f"the gradient method, {'fresh batches' if config.fresh_batches else 'one batch'} of {config.batch}, "
            f"{config.settings.aggregate}, {config.steps} steps, the {config.keep} step's gains: the measured winner "
            "in a flight-like loop"
        )
    else:
        chosen = "CMA-ES, the ideal loop's default (not raced)"
    print(f"no --method: {chosen} (--method gradient or cmaes to choose)", file=sys.stderr, flush=True)


#: The options ``tune --check`` takes besides itself.
_CHECK_OPTIONS = {"out", "check", "holdout", "compile_cache"}


def _check_tune(args: argparse.Namespace):
    """``tune --check``: the run in ``--out`` checked as it stands, on ``--holdout`` captures
    (default the run's), no step taken."""
    others = sorted(args.given - _CHECK_OPTIONS)
    if others:
        listed = ", ".join("--" + name.replace("_", "-") for name in others)
        raise UsageError(f"--check: checks the run in --out as it was set up; it takes --holdout only, not {listed}")
    if not (Path(args.out) / "run.json").exists():
        raise UsageError(f"--check: {args.out} holds no tuning run (no run.json)")
    return tune(Path(args.out), check=True, holdout=args.holdout if "holdout" in args.given else None)


def _resume_tune(args: argparse.Namespace):
    """``tune --resume``: the options given on the command line (not their defaults) must
    be the recorded run's, but for the ones a resume may change."""
    record = json.loads((Path(args.out) / "run.json").read_text()) if (Path(args.out) / "run.json").exists() else None
    given = args.given - {
        "out",
        "resume",
        "compile_cache",
        "overwrite",
        "holdout",
        "gains",
        "fill_from",
        "scenario",
        "robot",
        "mount",
        "base_link",
        "tip_link",
    }
    config = None
    if record is not None and given:
        # The options given replace the record's (checked together, as the run would be):
        # the command line's defaults of the others (CMA-ES's, say) are not the run's.
        fresh = _tune_fields(args, run_record(record).robot)
        asked = {_TUNE_FIELDS.get(dest, dest) for dest in given} & set(fresh)
        config = TuneConfig.from_dict(record["config"] | {field: runfiles.plain(fresh[field]) for field in asked})
    return tune(
        Path(args.out),
        resume=True,
        config=config,
        gains_file=args.gains,
        scenario_file=args.scenario,
        robot_file=args.robot,
        robot_links=_robot_links(args),
        holdout=args.holdout if "holdout" in args.given else None,
        stop=args.stop,
    )


#: The options of ``spacegrasp tune`` (their destinations) -> the TuneConfig fields they set.
_TUNE_FIELDS = {option[2:].replace("-", "_"): field for field, option in TUNE_OPTIONS.items()} | {"range": "ranges"}


def _tune_option(name: str) -> str:
    """The option of ``spacegrasp tune`` that sets a TuneConfig field (or a file) ``name``."""
    return TUNE_OPTIONS.get(name, "--" + name.replace("_", "-"))


#: The objective's parts ``tune`` prints before and after (history.csv's names -> label, scale, unit).
_TUNE_PARTS = {
    "loss": ("objective", 1.0, ""),
    "final_position_error_m": ("final position error", 1e3, "mm"),
    "final_orientation_error_rad": ("final orientation error", 180.0 / math.pi, "deg"),
    "rms_tracking_m": ("rms tracking error", 1e3, "mm"),
    "position_margin": ("position margin (error / tolerance)", 1.0, ""),
    "orientation_margin": ("orientation margin", 1.0, ""),
    "torque_margin": ("torque margin (peak / constraint)", 1.0, ""),
    "target_speed_margin": ("target speed margin", 1.0, ""),
    "largest_peak_torque_Nm": ("largest peak torque", 1.0, "N m"),
    "max_largest_peak_torque_Nm": ("largest peak torque, batch max", 1.0, "N m"),
    "peak_contact_hard_N": ("peak contact force", 1.0, "N"),
}


def _print_tune_report(out: Path, history: list) -> None:
    """What a tuning run did: each part of the objective over the training batch (mean)
    at the first and the last step, the nominal run's numbers, and the held-out result."""
    first, last = history[0], history[-1]
    print(f"\n{'training batch (means; max where said)':38} {'start':>12} {'tuned':>12}")
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
    ran = run_record(record)
    robot, gains_source = ran.robot, ran.sources["gains"]
    loop = "ideal loop (the paper's)" if ran.realism is None else "flight-like loop"
    start = "from the paper's gains" if gains_source == "paper_gains()" else f"from {Path(gains_source).name}"
    from spacegrasp_jax.analysis import plots

    plots.save_tuning_figures(
        result.history,
        result.log_before,
        result.log_after,
        out,
        runfiles.write_atomically,
        caption=_run_caption(loop, start, ran.scenario),
        torque_limit_Nm=np.asarray(robot.joint_torque_limit),
    )
    holds = json.loads((out / "summary.json").read_text()).get("gains_file", "tuned")
    other = OTHER_GAINS_FILES[holds] if (out / OTHER_GAINS_FILES[holds]).exists() else None
    words = "starting" if holds == "start" else "tuned"
    gains_files = f"gains.json (the {words} gains" + (f"; the other set in {other})" if other else ")")
    kept = json.loads((out / "gains.json").read_text())
    figures = "loss.png, peak_torques.png, ee_pose.png"
    if "schedule" in kept:
        _save_schedule_figure(out, load_schedule(out / "gains.json", record["config"]["controller"], n_joints(robot)))
        figures += ", gain_schedule.png"
    print(f"wrote {out}/: {gains_files}, history.csv, summary.json, {figures}", file=sys.stderr)
    checked = json.loads((out / "summary.json").read_text()).get("checked_after")
    if checked and checked["step"] < checked["of"]:
        print(
            f"checked the run as it stands after step {checked['step']} of {checked['of']}; "
            f"spacegrasp tune --out {out} --resume continues it",
            file=sys.stderr,
        )
    return 0


def _tune_config(args: argparse.Namespace, robot) -> TuneConfig:
    """The tuning options of the command line (validated by TuneConfig and Weights)."""
    return TuneConfig.of(**_tune_fields(args, robot))


def _tune_fields(args: argparse.Namespace, robot) -> dict:
    """TuneConfig's fields as the command line gives them, not yet checked together
    (``--realism flight``'s actuators ``robot``'s motors). Without ``--method``, the
    problem's recipe (``tuning.tune.default_recipe``) fills the options not given."""
    realism = load_realism(args.realism, robot).to_dict() if args.realism else None
    recipe = default_recipe(realism) if args.method is None else {}
    if recipe.get("method") == "gradient":
        cmaes_options = (
            ("--population", args.population),
            ("--step-size", args.step_size),
            ("--separable", args.separable or None),
            ("--noise-handling", args.noise_handling or None),
        )
        for option, value in cmaes_options:
            if value is not None:
                raise UsageError(
                    f"{option}: a setting of CMA-ES; without --method, tune in a flight-like loop runs the "
                    "gradient method, the measured winner there (choose --method cmaes)"
                )

    def given_or(value, field):
        if value is not None:
            return value
        return recipe.get(field, _DEFAULTS[field])

    method = given_or(args.method, "method")
    return dict(
        controller=args.controller,
        steps=given_or(args.steps, "steps"),
        learning_rate=args.lr,
        optimizer=args.optimizer,
        weights=Weights.parse(args.weights or ""),
        batch=given_or(args.batch, "batch"),
        cvar_alpha=args.cvar,
        seed=args.seed,
        frozen=tuple(filter(None, (args.freeze or "").split(","))),
        gradient=args.gradient,
        torque_guard_Nm=args.torque_guard,
        realism=realism,
        aggregate=args.aggregate
        or recipe.get("aggregate")
        or ("clip" if args.realism and method == "gradient" else "mean"),
        ranges=_ranges(args, TUNING_RANGES),
        objective=args.objective,
        method=method,
        population=args.population,
        step_size=given_or(args.step_size, "step_size"),
        separable=args.separable,
        noise_handling=args.noise_handling,
        torque_fraction=args.torque_fraction,
        torque_cap_Nm=args.torque_cap,
        fresh_batches=given_or(args.fresh_batches, "fresh_batches"),
        keep=given_or(args.keep, "keep"),
        patience=args.patience,
        validation_size=args.validation_size,
        joint_rate_limits_radps=_rate_criterion(args, robot),
        gradient_from_s=args.gradient_from,
        **(_schedule(args.schedule) if args.schedule else {}),
    )


#: Every field ``_tune_fields`` fills -> its default: the run's, or its method's settings'.
_DEFAULTS = {
    field.name: field.default
    for kind in (TuneConfig, GradientSettings, CMAESSettings)
    for field in dataclasses.fields(kind)
    if field.name != "settings"
}


def _schedule(text: str) -> dict:
    """``--schedule VARIABLE:X1,X2,...`` as TuneConfig's ``schedule_variable`` and ``schedule_knots``."""
    variable, _, knots = text.partition(":")
    if variable not in VARIABLES or not knots:
        raise UsageError(
            f"--schedule: expected VARIABLE:X1,X2,... with VARIABLE one of {', '.join(VARIABLES)}, got {text!r}"
        )
    try:
        values = tuple(float(x) for x in knots.split(","))
    except ValueError:
        raise UsageError(f"--schedule: the knots must be numbers, got {knots!r}") from None
    return {"schedule_variable": variable, "schedule_knots": values}


def add_parsers(commands) -> None:
    """The command's parser, added to ``commands``."""
    tune = _add_command(
        commands, "tune", help="tune the gains for capture success: CMA-ES or gradient descent (resumable)"
    )
    tune.add_argument("--out", required=True, help="output folder (also holds the checkpoint)")
    _add_overwrite_option(tune)
    tune.add_argument("--controller", choices=CONTROLLERS, default="admittance")
    tune.add_argument(
        "--steps",
        type=_whole(1, 1_000_000),
        default=None,
        help=f"optimiser steps or CMA-ES generations (default {TuneConfig.steps}; without --method in a flight-like loop, "
        f"{RECIPES['flight_like']['steps']})",
    )
    tune.add_argument(
        "--lr",
        type=_real(0.0, 10.0, above=True),
        default=0.15,
        help="initial step size in log-gain space (default 0.15)",
    )
    tune.add_argument(
        "--method",
        choices=METHODS,
        default=None,
        help="gradient: optax on the gradient; cmaes: CMA-ES, --steps generations of forward rollouts (default: "
        "the problem's measured winner; in a flight-like loop, --realism other than ideal, gradient with "
        f"--fresh-batches --aggregate median_of_means --batch {RECIPES['flight_like']['batch']} --steps "
        f"{RECIPES['flight_like']['steps']}; in the ideal loop, {RECIPES['ideal']['method']})",
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
        default=None,
        help=f"CMA-ES's initial step in log-gain units (default {CMAESSettings.step_size}: about +-30%% on every gain)",
    )
    tune.add_argument(
        "--separable",
        action="store_true",
        help="CMA-ES with a diagonal covariance (sep-CMA-ES): faster learning on hundreds of gains",
    )
    tune.add_argument(
        "--noise-handling",
        action="store_true",
        help="CMA-ES with pycma's noise handling (UH-CMA-ES, with --fresh-batches): a few candidates a "
        "generation evaluated again on the next batch, the step size raised where their ranks move by chance",
    )
    add_objective_arguments(tune)
    tune.add_argument(
        "--batch",
        type=_whole(1, 65_536),
        default=None,
        help=f"scenarios per step: nominal + batch-1 perturbed (default {TuneConfig.batch}; without --method in a "
        f"flight-like loop, {RECIPES['flight_like']['batch']})",
    )
    tune.add_argument(
        "--cvar",
        type=_real(0.0, 1.0),
        default=None,
        help="optimise CVaR at this level over the batch instead of the mean",
    )
    tune.add_argument("--seed", type=_SEED, default=0, help="seed of the perturbed scenarios")
    tune.add_argument("--optimizer", default="adam", help="any optax optimiser taking a learning rate (default adam)")
    tune.add_argument("--freeze", help="gain groups to keep fixed, e.g. kd,ki (default: none)")
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
    add_gains_arguments(tune)
    tune.add_argument("--scenario", help="scenario TOML/JSON (default: the paper's)")
    add_robot_arguments(tune)
    tune.add_argument(
        "--resume",
        action="store_true",
        help="continue the run in --out from its last completed step (--steps N: to N steps in all)",
    )
    tune.add_argument(
        "--check",
        action="store_true",
        help="take no step: check the run in --out as it stands, finished or interrupted (its kept gains on the "
        "nominal scenario and on the held-out captures; --holdout N: on N of them), written as a finished run's files",
    )
    add_ranges_arguments(tune, "tuning")
    _add_realism_option(tune)
    tune.add_argument(
        "--aggregate",
        choices=AGGREGATES,
        help="the gradient method under --realism: combine the samples' gradients as their mean; clip each to 3x "
        "the median norm first; their trimmed mean (10%% at each end, per gain); or the median of 4 group means "
        "(default: without --method, median_of_means there; with --method gradient, clip there; else mean)",
    )
    tune.add_argument(
        "--fresh-batches",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="under --realism: a new batch of the envelope for every step or CMA-ES generation (default: without "
        "--method, a new batch; with --method, one batch)",
    )
    tune.add_argument(
        "--gradient-from",
        type=_real(0.0, 1e6),
        default=None,
        metavar="SECONDS",
        help="the gradient method: truncated backpropagation, differentiating each capture from this time on "
        "only, the state there held: a cheaper, biased gradient of the same loss (default: the whole capture)",
    )
    tune.add_argument(
        "--patience",
        type=_whole(1, 1_000_000),
        default=None,
        metavar="STEPS",
        help="stop early once the objective on a validation set of captures of their own (exact contact law) "
        "has not improved for STEPS steps or generations, and keep the best by it (default: off)",
    )
    tune.add_argument(
        "--validation-size",
        type=_whole(1, 100_000),
        default=TuneConfig.validation_size,
        metavar="N",
        help=f"the validation set's captures, with --patience (default {TuneConfig.validation_size})",
    )
    tune.add_argument(
        "--keep",
        choices=KEEPS,
        help="the gains the run hands back: best, the least training objective it evaluated (CMA-ES's best "
        "candidate ever, the gradient method's best step), or last; either way gains.json holds the better of "
        "them and the starting gains on the held-out captures (default best; without --method in a flight-like "
        "loop, last, as the races measured)",
    )
    tune.add_argument(
        "--schedule",
        metavar="VARIABLE:X1,X2,...",
        help="tune a gain schedule: every tuned group but the damping gets these knots on VARIABLE "
        f"({', '.join(f'{name} in {unit}' for name, unit in VARIABLES.items())}), each starting at the starting "
        "gains, e.g. time:0,4,8,12,17 (default: constant gains; a schedule file given with --gains is tuned as it is)",
    )
    _add_compile_cache_option(tune)
    tune.set_defaults(run=_tune)
