"""The ``spacegrasp tune`` job: set up, optimise (resumably), evaluate, write files.

Files in ``--out`` (all written atomically):
* ``run.json`` - the run's definition (config, starting gains, scenario and robot sources);
  ``--resume`` reads it, so a resumed run is the same run.
* ``checkpoint.npz`` - the loop's state after the last completed step.
* ``history.csv`` - one row per step: loss, every part, gradient norm, step size, rejections.
* ``gains.json`` - the tuned gains (``spacegrasp simulate --gains gains.json``).
* ``summary.json`` - starting vs tuned gains on the nominal scenario with the EXACT contact
  law, and their mean and median objective over held-out perturbed scenarios;
  ``holdout.npz`` - every part of the objective for each held-out sample, both gain sets.

The command line adds the figures (``loss.png``, ``peak_torques.png``, ``ee_pose.png``) from
the [`TuneResult`][tuning.run.TuneResult] that [`tune()`][tuning.run.tune] returns.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import functools
import io
import json
import sys
import tomllib
from pathlib import Path

import jax
import numpy as np

import spacegrasp_jax as sg
from spacegrasp_jax.core.model import n_joints, robot_to_toml
from spacegrasp_jax.core.robot_files import load_robot, robot_from_text, robot_from_toml
from spacegrasp_jax.envelope import statistics
from spacegrasp_jax.envelope.criteria import CaptureCriteria
from spacegrasp_jax.envelope.scenario import load_scenario, paper_scenario, scenario_from_mapping, scenario_to_dict
from spacegrasp_jax.jobs import batching, experiment, runfiles
from spacegrasp_jax.jobs.experiment import loop_options
from spacegrasp_jax.jobs.montecarlo import SampleLoops, success
from spacegrasp_jax.jobs.records import RecordError, RunRecord, Variant, make_record
from spacegrasp_jax.loop.control import (
    GainsError,
    missing_groups,
    paper_gains,
    require_joints,
)
from spacegrasp_jax.loop.control.schedule import (
    NAMED_GAIN_SETS,
    GainSchedule,
    gain_set_from_dict,
    load_gains_or_schedule,
    named_gain_set,
    schedule_of,
)
from spacegrasp_jax.loop.simulate import LoopOptions, RunSpec
from spacegrasp_jax.tuning import cmaes, driver
from spacegrasp_jax.tuning.objective import VERDICT_METRICS, Objective, objective_spec, scenario_parts
from spacegrasp_jax.tuning.parameters import GROUPS
from spacegrasp_jax.tuning.tune import (
    CHECKPOINT,
    VALIDATION_SEED_OFFSET,
    TuneConfig,
    check_gradient_cut,
    envelope_batch,
    make_method,
    make_problem,
)

HOLDOUT_SEED_OFFSET = 1_000_003  # held-out samples never coincide with training samples


class TuneSetupError(ValueError):
    """The tuning run cannot start (bad options, or an output folder in the wrong state)."""


class ResumeMismatchError(TuneSetupError):
    """A resume asked for another run than the one in the folder. ``differences``: one
    ``(name, asked, recorded)`` for each, ``name`` a [`TuneConfig`][tuning.tune.TuneConfig] field or one of
    ``gains``, ``scenario``, ``robot``."""

    def __init__(self, out: Path, differences: list[tuple[str, object, object]]):
        self.differences = differences
        super().__init__(f"{out}: cannot resume another run than the one there: {self.listed()}")

    def listed(self, name_of=lambda name: name) -> str:
        """``"batch 8 (the run's: 32); ..."``, each name as ``name_of`` writes it."""
        return "; ".join(
            f"{name_of(name)} {_shown(asked)} (the run's: {_shown(recorded)})"
            for name, asked, recorded in self.differences
        )


def _shown(value) -> str:
    text = json.dumps(runfiles.plain(value), sort_keys=True)
    return text if len(text) <= 40 else text[:37] + "..."


def _same(a, b) -> bool:
    return json.dumps(runfiles.plain(a), sort_keys=True) == json.dumps(runfiles.plain(b), sort_keys=True)


def resume_differences(
    document: dict,
    config: TuneConfig | None,
    gains_file: str | None,
    scenario_file: str | None,
    robot_file: str | None,
    robot_links: dict | None = None,
) -> list[tuple[str, object, object]]:
    """What a resume asks for that differs from the recorded run (``document``, its
    ``run.json``): every field of ``config`` (None: nothing asked), and the gains, scenario
    and robot of the files given, each by what it is (not by its file's path or text). More
    ``steps`` is not a difference: the run continues. A CMA-ES run then continues to exactly
    the run of that many generations from the start; a gradient run's learning rate from then
    on follows its cosine schedule over the new number of steps (the steps taken keep theirs)."""
    differences = []
    if config is not None:
        recorded = TuneConfig.from_dict(document["config"]).to_dict()
        for field, asked in config.to_dict().items():
            if _same(asked, recorded.get(field)):
                continue
            if field == "steps" and asked > recorded["steps"]:
                continue
            differences.append((field, asked, recorded.get(field)))
    if robot_file is None and gains_file is None and scenario_file is None:
        return differences
    record = run_record(document)
    robot = record.robot
    if robot_file is not None:
        robot = load_robot(robot_file, **(robot_links or {}))
        if robot_to_toml(robot) != robot_to_toml(record.robot):
            differences.append(("robot", robot_file, record.sources.get("robot")))
    if gains_file is not None:
        n = n_joints(record.robot)
        fill_from = (record.sources.get("gains_filled") or {}).get("from")
        asked = start_gains(gains_file, document["config"]["controller"], n, fill_from).to_dict()
        if not _same(asked, record.variants[0].gains.to_dict()):
            differences.append(("gains", gains_file, record.sources.get("gains")))
    if scenario_file is not None:
        asked = scenario_to_dict(load_scenario(robot, scenario_file))
        if not _same(asked, scenario_to_dict(record.scenario)):
            differences.append(("scenario", scenario_file, record.sources.get("scenario")))
    return differences


def _older_run_record(document: dict) -> RunRecord:
    """The record of a tuning run of an older version, from its ``run.json``'s sources: the
    robot as recorded (``robot_frames``; older still, its file's text, a mounting TOML's URDF
    read from beside its file again), the scenario file's text, the starting gains."""
    if document["robot_toml"] is None:
        robot = sg.paper_robot()
    elif document.get("robot_frames") is not None:
        robot = robot_from_toml(document["robot_frames"], source=f"{document['robot_source']} (as recorded)")
    else:
        robot = robot_from_text(document["robot_toml"], source=document["robot_source"])
    if document["scenario_text"] is None:
        scenario = paper_scenario(robot)
    else:
        text = document["scenario_text"]
        mapping = json.loads(text) if document["scenario_is_json"] else tomllib.loads(text)
        scenario = scenario_from_mapping(robot, mapping)
    config = TuneConfig.from_dict(document["config"])
    base = gain_set_from_dict(document["base_gains"], n_joints(robot))
    sources = {
        "robot": document["robot_source"],
        "robot_links": document.get("robot_links"),
        "scenario": document["scenario_source"],
        "gains": document["gains_source"],
        "gains_filled": (
            {"groups": document["gains_filled"], "from": document["gains_fill_from"]}
            if document.get("gains_filled")
            else None
        ),
    }
    return _record_of(robot, scenario, base, config, sources)


def run_record(document: dict) -> RunRecord:
    """The [`RunRecord`][spacegrasp_jax.jobs.records.RunRecord] of a tuning run's ``run.json``
    (``document``, read; one of an older version too): the robot, the nominal scenario, the
    starting gains (its one variant), the loop, the criteria, where they came from."""
    if "record" not in document:
        return _older_run_record(document)
    try:
        return RunRecord.from_dict(document["record"], source="run.json: record")
    except RecordError as error:
        raise TuneSetupError(str(error)) from None


def _record_of(robot, scenario, base, config: TuneConfig, sources: dict, command=None) -> RunRecord:
    realism = config.loop_realism
    return make_record(
        robot,
        scenario,
        [Variant(config.controller, base, "start")],
        realism=realism,
        criteria=CaptureCriteria(joint_rate_limits_radps=config.joint_rate_limits_radps),
        key=jax.random.PRNGKey(config.seed) if realism is not None else None,
        command=command,
        sources=sources,
    )


def start_gains(gains_file: str, controller: str, n: int, fill_from: str | None = None):
    """The starting gains ``gains_file`` names: a shipped set by name (``NAMED_GAIN_SETS``, a
    shipped schedule included) or a gains file for ``controller`` on an arm of ``n`` joints,
    its missing groups from ``fill_from``."""
    if gains_file in NAMED_GAIN_SETS:
        if n != len(paper_gains().kp):
            raise TuneSetupError(
                f"--gains {gains_file}: the shipped sets are for the paper's 7-joint arm, not {n} joints"
            )
        return named_gain_set(gains_file)
    return load_gains_or_schedule(gains_file, controller, n, fill_from=fill_from)


def tuned_base(base, config: TuneConfig):
    """What the run tunes from the starting ``base``: a schedule on ``config``'s variable and
    knots for every tuned group but the pseudoinverse's damping (``TuneConfig.schedule_variable``),
    else ``base`` as it is (a gain set, or a starting schedule file's schedule)."""
    if config.schedule_variable is None:
        return base
    if isinstance(base, GainSchedule):
        raise TuneSetupError("--schedule: the starting gains are a schedule already; tune it as it is")
    groups = [name for name in GROUPS[config.controller] if name != "pinv_damping" and name not in config.frozen]
    return schedule_of(base, config.schedule_variable, config.schedule_knots, groups)


def new_record(
    config: TuneConfig,
    gains_file,
    scenario_file,
    robot_file,
    holdout: int,
    fill_from: str | None = None,
    robot_links: dict | None = None,
    command=None,
) -> dict:
    """The run's ``run.json``: its [`RunRecord`][spacegrasp_jax.jobs.records.RunRecord] (the robot
    and scenario as they run, the starting gains, the loop, the criteria, the sources and the
    command), its settings (``config``) and the held-out samples."""
    robot = load_robot(robot_file, **(robot_links or {})) if robot_file else sg.paper_robot()
    filled = []
    if gains_file:
        base = start_gains(gains_file, config.controller, n_joints(robot), fill_from)
        tuned_base(base, config)  # refused here, before anything compiles
        filled = [] if gains_file in NAMED_GAIN_SETS else missing_groups(gains_file, config.controller)
    else:
        try:
            require_joints(paper_gains(), n_joints(robot), "the paper's gains")
        except GainsError as error:
            raise TuneSetupError(f"--gains: required: {error}") from None
        base = paper_gains()
    scenario = load_scenario(robot, scenario_file) if scenario_file else paper_scenario(robot)
    sources = {
        "robot": robot_file or "paper_robot()",
        "robot_links": robot_links or None,
        "scenario": scenario_file or "paper_scenario()",
        "gains": gains_file or "paper_gains()",
        "gains_filled": {"groups": filled, "from": fill_from} if filled else None,
    }
    record = _record_of(robot, scenario, base, config, sources, command)
    return {"record": record.to_dict(), "config": config.to_dict(), "holdout": holdout}


def _samples_parts(model_robot, gains, objective: Objective, samples, *, controller: str, options: LoopOptions):
    """[`scenario_parts()`][tuning.objective.scenario_parts] of each sample of a batch
    ``samples = (robots, scenarios, realisms, keys)`` (vmapped; realisms and keys ``None`` in
    the ideal loop), with the campaign's verdict metrics."""

    def one(robot, scenario, realism, key):
        spec = objective_spec(robot, scenario, controller, realism=realism, model_robot=model_robot, options=options)
        return scenario_parts(spec, gains, objective, key, verdict=True)

    return jax.vmap(one)(*samples)


def evaluate(
    batch: SampleLoops, gains, controller: str, objective: Objective, chunk: int = 10
) -> dict[str, np.ndarray]:
    """Objective parts, with the campaign's verdict metrics, for each sample of a batch (a
    [`SampleLoops`][spacegrasp_jax.jobs.montecarlo.SampleLoops] of the flight-like or the ideal loop,
    [`envelope_batch()`][tuning.tune.envelope_batch]; exact or smooth contact per its scenarios),
    by vmapped rollouts in chunks of ``chunk`` ([`spacegrasp_jax.jobs.batching.map_in_chunks()`][spacegrasp_jax.jobs.batching.map_in_chunks]);
    NaN marks a diverged sample. The gains and the objective are arguments of the compiled
    program, so evaluating another gain set or objective reuses it."""
    function = functools.partial(_samples_parts, controller=controller, options=loop_options(checkpoint=True))
    samples = (batch.robots, batch.scenarios, batch.realisms, batch.keys)
    return batching.map_in_chunks(
        "tuning.evaluate", function, (batch.model_robot, gains, objective), samples, chunk=chunk, progress=None
    )


def _write_history(path: Path, history: list) -> None:
    buffer = io.StringIO()
    columns = list(dict.fromkeys(name for row in history for name in row))  # a resumed older run adds some
    writer = csv.DictWriter(buffer, fieldnames=columns, restval="")
    writer.writeheader()
    writer.writerows(history)
    runfiles.write_text(path, buffer.getvalue())


#: The parts a held-out verdict reads: the campaign's metrics by the campaign's names (the
#: objective's own, and ``objective.VERDICT_METRICS``), a free target's final speed where
#: the run has one.
VERDICT_PARTS = (
    "final_position_error_m",
    "final_orientation_error_rad",
    "largest_peak_torque_Nm",
    "final_target_speed_mps",
    *VERDICT_METRICS,
)


def captured(parts: dict, criteria: CaptureCriteria) -> np.ndarray:
    """(n,) bool: each held-out sample's capture by ``criteria`` (the run's, a campaign's
    [`CaptureCriteria`][spacegrasp_jax.envelope.criteria.CaptureCriteria]), judged by the campaign's own
    [`success()`][spacegrasp_jax.jobs.montecarlo.success] on the campaign's metrics of each sample
    (``VERDICT_PARTS``; [`scenario_parts(verdict=True)`][tuning.objective.scenario_parts] computes
    them as a campaign does): a sample that ran away or diverged fails, and so does one whose
    objective is not finite."""
    sample_metrics = {name: np.asarray(parts[name]) for name in VERDICT_PARTS if name in parts}
    diverged = np.where(np.isfinite(parts["loss"]), np.nan, 0.0)
    sample_metrics["first_nonfinite_s"] = np.fmin(
        np.asarray(sample_metrics["first_nonfinite_s"], dtype=float), diverged
    )
    return np.asarray(success(sample_metrics, criteria), dtype=bool)


def holdout_success(before_parts: dict, after_parts: dict, criteria: CaptureCriteria) -> dict:
    """The held-out success rates of the starting and tuned gains by ``criteria`` with their
    95% Wilson intervals, and the exact McNemar test of tuned against starting on the same
    samples."""
    start, tuned = captured(before_parts, criteria), captured(after_parts, criteria)
    return {
        "success_start": statistics.success_interval(start.sum(), start.size),
        "success_tuned": statistics.success_interval(tuned.sum(), tuned.size),
        "success_tuned_vs_start": statistics.compare_success(start, tuned),
    }


def _comparison(result: experiment.RunResult) -> dict:
    summary = result.summary
    return {
        "max_abs_torque_Nm": summary["max_abs_torque_Nm"],
        "largest_peak_torque_Nm": summary["largest_peak_torque_Nm"],
        "final_position_error_m": summary["final_position_error_m"],
        "final_orientation_error_rad": summary["final_orientation_error_rad"],
        "rms_position_error_m": summary["rms_position_error_m"],
        "max_contact_force_N": summary["max_contact_force_N"],
    }


@dataclasses.dataclass(frozen=True)
class TuneResult:
    """What a tuning run leaves besides its files.

    Attributes:
        status: ``"done"``, ``"stopped_early"``, ``"diverged"`` (the gradient method could
            take no further step), ``"interrupted"`` or ``"checked"`` (``tune(check=True)``:
            no step taken, the run checked as it stood; its summary says how it stood).
        history: one dict per step (the rows of ``history.csv``).
        log_before, log_after: the nominal rollouts (exact contact law) with the starting and
            the tuned gains (``log_after`` is ``None`` when interrupted).
    """

    status: str
    history: list
    log_before: object
    log_after: object | None = None


def _validator(robot, smooth, config: TuneConfig, objective: Objective, to_gains):
    """Early stopping's validation objective of a point (``to_gains`` makes it gains): the
    batch objective over ``config.validation_size`` captures of their own seed, with the
    exact contact law as the held-out set; ``None`` without ``config.patience``."""
    if config.patience is None:
        return None
    exact = dataclasses.replace(smooth, contact_law="exact")
    samples = envelope_batch(robot, exact, config, config.seed + VALIDATION_SEED_OFFSET, config.validation_size)

    def validate(point) -> float:
        losses = np.asarray(evaluate(samples, to_gains(point), config.controller, objective)["loss"])
        return float(cmaes.batch_objective(losses[None], config.cvar_alpha)[0])

    return validate


def _optimise(robot, smooth, base, config, before, out, resume, progress, stop, checking=False):
    """The run's method ([`make_method()`][tuning.tune.make_method]) on its problem
    ([`make_problem()`][tuning.tune.make_problem]), by the one driver
    ([`tuning.driver.optimise()`][tuning.driver.optimise]): ``(objective, kept gains,
    history, events, steps done, status, kept)``."""
    checkpoint_path = out / CHECKPOINT
    problem = make_problem(robot, smooth, base, config, before.summary["max_abs_torque_Nm"])
    method = make_method(config)
    resume_state = None
    if resume and checkpoint_path.exists():
        try:
            resume_state = driver.load_checkpoint(checkpoint_path, method, problem.start, problem.mask, config.seed)
        except ValueError as error:
            raise TuneSetupError(str(error)) from None
        verb = "checking the run as it stands" if checking else "resuming"
        print(f"{verb} after {method.unit} {resume_state.step}/{config.steps}", file=progress, flush=True)

    def on_step(state, row):
        runfiles.show_progress(progress, method.progress(state.method_state, row, config.steps))
        _write_history(out / "history.csv", state.history)

    numbers = sum(int(np.sum(entries)) for entries in jax.tree.leaves(problem.mask))
    print(
        f"{method.title[:1].upper() + method.title[1:]} on the {config.controller} {config.objective} objective over {config.batch} scenario(s), "
        f"{numbers} numbers, {method.describe()}{', a new batch every ' + method.unit if config.fresh_batches else ''}...",
        file=progress,
        flush=True,
    )
    result = driver.optimise(
        problem,
        method,
        problem.start,
        problem.mask,
        steps=config.steps,
        seed=config.seed,
        keep=config.keep,
        patience=config.patience,
        validate=_validator(robot, smooth, config, problem.objective, problem.gains),
        checkpoint_path=checkpoint_path,
        settings=config.to_dict(),
        write_atomically=runfiles.write_atomically,
        resume=resume_state,
        on_step=on_step,
        stop=stop,
    )
    state, status = result.state, result.status
    if status == "stopped_early":
        print(
            f"stopped early: the validation objective has not improved for {config.patience} {method.unit}s "
            f"(its best after {method.unit} {state.best_step})",
            file=progress,
            flush=True,
        )
    if status == "diverged":
        print(
            f"stopped after step {state.step}: every candidate of step {state.step + 1} was rejected "
            f"(non-finite, over the torque guard or over {config.settings.loss_guard:g} times the starting objective) down to "
            f"1e-6 of the step size; the run hands back its {config.keep} step",
            file=progress,
            flush=True,
        )
    return problem.objective, problem.gains(result.point), state.history, state.events, state.step, status, result.kept


def tune(
    out: Path,
    *,
    config: TuneConfig | None = None,
    gains_file: str | None = None,
    scenario_file: str | None = None,
    robot_file: str | None = None,
    holdout: int | None = None,
    fill_from: str | None = None,
    robot_links: dict | None = None,
    resume: bool = False,
    check: bool = False,
    command=None,
    progress=None,
    stop: runfiles.StopRequest | None = None,
) -> TuneResult:
    """Run the job (or, with ``resume``, continue it) and write its files in ``out``.

    ``gains_file``: the starting gains, a gains file (its missing groups from ``fill_from``:
    ``"paper"`` or another file) or a shipped set by name (``NAMED_GAINS``); default the paper's.
    ``robot_links``: ``load_robot``'s ``mount``, ``base_link`` and ``tip_link`` for a URDF arm.
    ``holdout``: held-out scenarios of the final evaluation (default 100). With
    ``resume``, ``config`` and the files, where given, must be the recorded run's
    ([`resume_differences()`][tuning.run.resume_differences], else [`ResumeMismatchError`][tuning.run.ResumeMismatchError]); what may change is
    ``holdout`` and more ``config.steps``: the run then continues.

    ``check``: take no step, but check the run in ``out`` as it stands, finished or not: its
    gains after its last completed step (the ones ``config.keep`` keeps) on the nominal
    scenario and on ``holdout`` held-out captures (default the run's), written as a finished
    run writes them (``summary.json`` with ``"checked_after"``, ``gains.json``); a later
    ``resume`` continues the run as if no check had happened.

    ``command``: the command line that runs it, for its record (``None``: a call from Python).
    ``progress``: where progress lines go (default: ``sys.stderr`` at the call).
    ``stop``: the signal guard of the caller (the command line's); by default the job
    installs its own for the optimisation (SIGINT/SIGTERM stop it after the current step)."""
    out = Path(out)
    progress = sys.stderr if progress is None else progress  # the stream of the moment, not of the import
    record_path = out / "run.json"
    if check:
        if not record_path.exists():
            raise TuneSetupError(f"--check: {out} holds no tuning run (no run.json)")
        if not (out / CHECKPOINT).exists():
            raise TuneSetupError(f"--check: {out} holds no completed step yet (no {CHECKPOINT}); nothing to check")
        if holdout is not None and holdout < 0:
            raise TuneSetupError(f"--holdout: must be >= 0, got {holdout}")
        record = json.loads(record_path.read_text())
        config = TuneConfig.from_dict(record["config"])
        holdout = record["holdout"] if holdout is None else holdout
        resume = True
        stop = runfiles.StopRequest()
        stop.requested = True  # the optimiser loads its checkpoint and stops before a step
    elif resume:
        if not record_path.exists():
            raise TuneSetupError(f"--resume: {out} holds no tuning run (no run.json)")
        record = json.loads(record_path.read_text())
        differences = resume_differences(record, config, gains_file, scenario_file, robot_file, robot_links)
        if differences:
            raise ResumeMismatchError(out, differences)
        if holdout is not None and holdout < 0:
            raise TuneSetupError(f"--holdout: must be >= 0, got {holdout}")
        changed = dict(holdout=holdout if holdout is not None else record["holdout"])
        if config is not None:
            changed["config"] = record["config"] | {"steps": max(config.steps, record["config"]["steps"])}
        if any(not _same(value, record[key]) for key, value in changed.items()):
            record |= changed
            runfiles.write_json(record_path, record)
        config = TuneConfig.from_dict(record["config"])
        holdout = record["holdout"]
    else:
        holdout = 100 if holdout is None else holdout
        if record_path.exists():
            raise TuneSetupError(
                f"{out} already holds a tuning run: pass --resume to continue it, or choose another --out"
            )
        if holdout < 0:
            raise TuneSetupError(f"--holdout: must be >= 0, got {holdout}")
        config = config or TuneConfig()
        record = new_record(config, gains_file, scenario_file, robot_file, holdout, fill_from, robot_links, command)
        try:
            scenario = run_record(record).scenario
            config.weights.check_target(scenario.free_target)
            check_gradient_cut(config, scenario)
        except ValueError as error:
            raise TuneSetupError(str(error)) from None
        out.mkdir(parents=True, exist_ok=True)
        runfiles.write_json(record_path, record)

    ran = run_record(record)
    robot, gains_source = ran.robot, ran.sources["gains"]
    base = tuned_base(ran.variants[0].gains, config)
    exact = dataclasses.replace(ran.scenario, contact_law="exact")
    smooth = dataclasses.replace(exact, contact_law="smooth")  # gradients need the smooth law

    print(
        f"evaluating the starting gains ({gains_source}) on the nominal scenario...",
        file=progress,
        flush=True,
    )
    realism = config.loop_realism
    key = jax.random.PRNGKey(config.seed) if realism is not None else None
    before = experiment.run(RunSpec(robot, exact, config.controller, realism=realism), base, key=key)
    with runfiles.StopRequest() if stop is None else contextlib.nullcontext(stop) as stop:
        objective, tuned, history, events, steps_done, status, kept = _optimise(
            robot, smooth, base, config, before, out, resume, progress, stop, checking=check
        )
    runfiles.end_progress(progress)
    _write_history(out / "history.csv", history)
    runfiles.write_json(out / "gains.json", tuned.to_dict(config.controller))
    if status == "interrupted" and not check:
        print(
            f"interrupted after step {steps_done}/{config.steps}; continue with: spacegrasp tune --out {out} --resume "
            f"(more steps: --steps N); check the gains so far with: spacegrasp tune --out {out} --check",
            file=progress,
        )
        return TuneResult(status, history, before.log)

    print("evaluating the tuned gains with the exact contact law...", file=progress, flush=True)
    after = experiment.run(RunSpec(robot, exact, config.controller, realism=realism), tuned, key=key)
    summary = {
        "status": status,
        "controller": config.controller,
        "steps": steps_done,
        "method": config.method,
        "objective_kind": config.objective,
        "evaluated_with": "exact contact law (eq 20), nominal scenario"
        + (", the run's realism, noise key of --seed" if realism is not None else ""),
        "paper_gains" if gains_source == "paper_gains()" else "starting_gains": _comparison(before),
        "tuned_gains": _comparison(after),
        "rejected_steps": events,
        "objective": dataclasses.asdict(objective),
        "kept": kept,
        "gains_file": "tuned",
    }
    if check:
        summary["checked_after"] = {"step": steps_done, "of": config.steps}
    start_key = next(key for key in summary if key in ("paper_gains", "starting_gains"))
    summary["largest_peak_torque_change"] = (
        summary["tuned_gains"]["largest_peak_torque_Nm"] / summary[start_key]["largest_peak_torque_Nm"] - 1.0
    )
    summary["joints_with_higher_peak"] = [
        joint + 1
        for joint, (old, new) in enumerate(
            zip(summary[start_key]["max_abs_torque_Nm"], summary["tuned_gains"]["max_abs_torque_Nm"])
        )
        if new > old
    ]
    if holdout:
        print(f"evaluating both on {holdout} held-out perturbed scenarios...", file=progress, flush=True)
        # under a realism: the same realism, new noise keys and satellites
        samples = envelope_batch(robot, exact, config, config.seed + HOLDOUT_SEED_OFFSET, holdout)
        before_parts = evaluate(samples, base, config.controller, objective)
        after_parts = evaluate(samples, tuned, config.controller, objective)
        summary["holdout"] = {
            "scenarios": holdout,
            "seed": config.seed + HOLDOUT_SEED_OFFSET,
            "contact_law": "exact",
            "mean_objective_start": float(np.nanmean(before_parts["loss"])),
            "mean_objective_tuned": float(np.nanmean(after_parts["loss"])),
            "median_objective_start": float(np.nanmedian(before_parts["loss"])),
            "median_objective_tuned": float(np.nanmedian(after_parts["loss"])),
            "tuned_better_fraction": float(np.mean(after_parts["loss"] < before_parts["loss"])),
            "mean_largest_peak_torque_Nm_start": float(np.nanmean(before_parts["largest_peak_torque_Nm"])),
            "mean_largest_peak_torque_Nm_tuned": float(np.nanmean(after_parts["largest_peak_torque_Nm"])),
            "median_largest_peak_torque_Nm_start": float(np.nanmedian(before_parts["largest_peak_torque_Nm"])),
            "median_largest_peak_torque_Nm_tuned": float(np.nanmedian(after_parts["largest_peak_torque_Nm"])),
            "mean_final_position_error_m_start": float(np.nanmean(before_parts["final_position_error_m"])),
            "mean_final_position_error_m_tuned": float(np.nanmean(after_parts["final_position_error_m"])),
            "median_final_position_error_m_start": float(np.nanmedian(before_parts["final_position_error_m"])),
            "median_final_position_error_m_tuned": float(np.nanmedian(after_parts["final_position_error_m"])),
            "diverged_start": int(np.sum(~np.isfinite(before_parts["loss"]))),
            "diverged_tuned": int(np.sum(~np.isfinite(after_parts["loss"]))),
            "per_sample": "holdout.npz",
        }
        summary["holdout"] |= holdout_success(before_parts, after_parts, ran.criteria)
        samples = {f"start_{name}": value for name, value in before_parts.items()}
        samples.update({f"tuned_{name}": value for name, value in after_parts.items()})
        runfiles.write_arrays(out / "holdout.npz", samples)
        summary["gains_file"] = _keep_the_better(out, summary["holdout"], base, tuned, config.controller, progress)
    runfiles.write_json(out / "summary.json", summary)
    return TuneResult("checked" if check else status, history, before.log, after.log)


#: Beside ``gains.json``, the gain set of the two it does not hold.
OTHER_GAINS_FILES = {"tuned": "gains_start.json", "start": "gains_tuned.json"}


def _keep_the_better(out: Path, holdout: dict, start, tuned, controller: str, progress) -> str:
    """``gains.json``: the tuned gains where their held-out objective is below the starting
    gains', else the starting gains with one line that says so; the other set beside it
    (``OTHER_GAINS_FILES``). Returns which set ``gains.json`` holds, ``"tuned"`` or ``"start"``."""
    better = holdout["mean_objective_tuned"] < holdout["mean_objective_start"]
    chosen = "tuned" if better else "start"
    gains, other = (tuned, start) if better else (start, tuned)
    runfiles.write_json(out / "gains.json", gains.to_dict(controller))
    runfiles.write_json(out / OTHER_GAINS_FILES[chosen], other.to_dict(controller))
    if not better:
        rates = ""
        if "success_start" in holdout:
            tuned_rate, start_rate = holdout["success_tuned"]["rate"], holdout["success_start"]["rate"]
            rates = f", captures {100 * tuned_rate:.1f}% against {100 * start_rate:.1f}%"
        print(
            f"spacegrasp: the tuned gains are not better than the starting gains on the {holdout['scenarios']} "
            f"held-out captures (objective {holdout['mean_objective_tuned']:.4g} against "
            f"{holdout['mean_objective_start']:.4g}{rates}): gains.json holds the starting gains, the tuned ones "
            f"are in {OTHER_GAINS_FILES[chosen]}",
            file=progress,
            flush=True,
        )
    return chosen
