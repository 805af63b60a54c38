"""Single rollouts on the host: compile once, time, check for divergence, summarise.

This is the edge of the library where ``jit`` happens (the core never calls it). The CLI,
the tests and the notebooks use [`run()`][spacegrasp_jax.jobs.experiment.run] on a [`RunSpec`][spacegrasp_jax.loop.simulate.RunSpec], so a rollout of a given controller, shapes and
static settings compiles once per process.
"""

from __future__ import annotations

import dataclasses
import math
import time

import jax
import numpy as np

from spacegrasp_jax.core import joint_limits
from spacegrasp_jax.core.model import Robot
from spacegrasp_jax.envelope import metrics
from spacegrasp_jax.envelope.scenario import Scenario
from spacegrasp_jax.jobs import anatomy, compilation, paper
from spacegrasp_jax.loop.control.gains import Gains
from spacegrasp_jax.loop.realism import Realism
from spacegrasp_jax.loop.simulate import (
    FullLog,
    Log,
    LoopOptions,
    RunSpec,
    closed_loop,
    first_nonfinite_step,
    loop_realism,
)


class SimulationDiverged(RuntimeError):
    """The closed loop produced non-finite values; ``time_s`` is the first bad step and
    ``result`` what the run had ([`run()`][spacegrasp_jax.jobs.experiment.run]): its log up to and including that step and
    the [`divergence_summary()`][spacegrasp_jax.jobs.experiment.divergence_summary]."""

    def __init__(self, controller: str, time_s: float, result: RunResult | None = None):
        super().__init__(f"the {controller} rollout diverged: first non-finite value at t = {time_s:.4f} s")
        self.controller = controller
        self.time_s = time_s
        self.result = result


@dataclasses.dataclass(frozen=True)
class RunResult:
    """One rollout on the host: its log as NumPy arrays, summary and timings (s)."""

    controller: str
    log: Log
    summary: dict
    compile_time_s: float
    run_time_s: float


def program_key(spec: RunSpec, gains: Gains, key=None) -> tuple:
    """What the compiled [`closed_loop()`][spacegrasp_jax.loop.simulate.closed_loop] of ``(spec, gains, key)`` depends on, and nothing
    else: the arguments' tree structure, which holds the spec's controller, observer and
    checkpointing and every static setting of its parts (a setting added to any of them is
    in it with nothing else to change), and their leaves' shapes, dtypes and placement
    ([`argument_signature()`][spacegrasp_jax.jobs.compilation.argument_signature]). Hashable; equal for specs and gains that differ only in numbers.

    Raises:
        ValueError: the spec's controller or observer is not hashable (they are the
            program's structure: make them frozen dataclasses).
    """
    for name in ("controller", "observer"):
        try:
            hash(getattr(spec, name))
        except TypeError:
            raise ValueError(
                f"{name}: {getattr(spec, name)!r} is not hashable; it is part of the program's structure "
                "(make it a frozen dataclass)"
            ) from None
    return ("closed_loop", compilation.argument_signature((spec, gains, key)))


def loop_options(checkpoint: bool = False) -> LoopOptions:
    """The [`LoopOptions`][spacegrasp_jax.loop.simulate.LoopOptions] this process compiles best,
    asked once on the host: with ``checkpoint``, a one-step period's RK4 reuses the
    controller's kinematics where XLA compiles loops whole
    ([`compilation.loops_compile_whole()`][spacegrasp_jax.jobs.compilation.loops_compile_whole])."""
    return LoopOptions(checkpoint=checkpoint, reuse_start_kinematics=checkpoint and compilation.loops_compile_whole())


def compiled_loop(spec: RunSpec, gains: Gains, key=None):
    """[`closed_loop()`][spacegrasp_jax.loop.simulate.closed_loop] compiled for ``(spec, gains, key)``, once per process, and its
    compile time (s). The program is looked up by [`program_key()`][spacegrasp_jax.jobs.experiment.program_key]: specs and gains that
    differ only in numbers share it."""

    def lower():
        return compilation.jit(closed_loop).lower(spec, gains, key)

    loop = "ideal" if spec.realism is None and spec.model_robot is None else "flight-like"
    kept = "rollout" if isinstance(spec.observer, FullLog) else f"loop ({type(spec.observer).__name__})"
    return compilation.compile_once(
        program_key(spec, gains, key),
        lower,
        label=f"the {spec.controller.name} law's {loop} {kept}",
    )


def run(spec: RunSpec, gains: Gains, *, key=None, check: bool = True) -> RunResult:
    """Run one closed-loop rollout and bring its log back as NumPy arrays.

    Args:
        spec: the run ([`RunSpec`][spacegrasp_jax.loop.simulate.RunSpec]: ``RunSpec(robot, scenario, "admittance")`` is the
            paper's loop; a law object carries its settings, a realism and a model robot
            make the flight-like loop); its observer must keep the whole log
            ([`FullLog`][spacegrasp_jax.loop.simulate.FullLog], the default). A realism that runs the paper's loop is run as
            none ([`loop_realism()`][spacegrasp_jax.loop.simulate.loop_realism]: one program for both).
        gains: the gains.
        key: the sensors' noise key; ``PRNGKey(0)`` by default where the loop is
            flight-like.
        check: raise on divergence.

    A run whose state becomes non-finite has a [`divergence_summary()`][spacegrasp_jax.jobs.experiment.divergence_summary] for summary;
    the result names the law.

    Raises:
        ValueError: the spec's observer does not keep the whole log.
        SimulationDiverged: (when ``check``) the state became non-finite; the error gives
            the first non-finite time and, as ``result``, the log up to and including it.
    """
    if not isinstance(spec.observer, FullLog):
        raise ValueError(f"run: the spec's observer must keep the whole log (FullLog), got {spec.observer!r}")
    spec = dataclasses.replace(spec, realism=loop_realism(spec.realism, spec.scenario))
    if (spec.realism is not None or spec.model_robot is not None) and key is None:
        key = jax.random.PRNGKey(0)
    executable, compile_time = compiled_loop(spec, gains, key)
    controller = spec.controller.name
    robot, scenario = spec.robot, spec.scenario
    start = time.perf_counter()
    _, log = executable(spec, gains, key)
    log = jax.tree.map(np.asarray, jax.block_until_ready(log))
    run_time = time.perf_counter() - start
    bad_step = first_nonfinite_step(log)
    if bad_step is None:
        summary = run_summary(log, robot, scenario, spec.realism) | dict(
            compile_time_s=compile_time, run_time_s=run_time
        )
        return RunResult(controller, log, summary, compile_time, run_time)
    summary = divergence_summary(log, bad_step, robot, free_target=scenario.free_target) | dict(
        compile_time_s=compile_time, run_time_s=run_time
    )
    summary["joint_limits"] = joint_limits.first_crossings(log.t[:bad_step], log.q[:bad_step], log.qd[:bad_step], robot)
    if check:
        kept = jax.tree.map(lambda series: series[: bad_step + 1], log)
        raise SimulationDiverged(
            controller, summary["first_nonfinite_s"], RunResult(controller, kept, summary, compile_time, run_time)
        )
    return RunResult(controller, log, summary, compile_time, run_time)


def read_log(path) -> Log:
    """A run's ``timeseries_*.npz`` ([`runfiles.write_timeseries()`][spacegrasp_jax.jobs.runfiles.write_timeseries])
    as a [`Log`][spacegrasp_jax.loop.simulate.Log] of NumPy arrays; a field the file does not hold
    (one the run's loop did not fill, or one added to the log after the file was written) is
    ``None``."""
    with np.load(path) as data:
        return Log(
            **{field.name: data[field.name] if field.name in data.files else None for field in dataclasses.fields(Log)}
        )


class RunFolderError(ValueError):
    """A run folder whose robot or campaign cannot be read; names the folder and the cause."""


# One small program rather than some six single operations, each compiled apart; at LLVM's
# -O0 nothing fuses a multiply with an add, so its numbers are theirs, bit for bit.
_error_parts = jax.jit(anatomy.error_parts, compiler_options={"xla_backend_optimization_level": 0})


def run_summary(log: Log, robot: Robot, scenario: Scenario, realism: Realism | None = None) -> dict:
    """The metrics of a whole log ([`spacegrasp_jax.envelope.metrics.summary()`][spacegrasp_jax.envelope.metrics.summary], runaways by
    ``robot``'s limits), the parts of its final error ([`spacegrasp_jax.jobs.anatomy.error_parts()`][spacegrasp_jax.jobs.anatomy.error_parts]),
    as plain floats and lists, and when it first crossed ``robot``'s joint ranges and rate limits
    (``joint_limits``, [`first_crossings()`][spacegrasp_jax.core.joint_limits.first_crossings])."""
    summary = metrics.summary(log, robot, free_target=scenario.free_target)
    parts = _error_parts({"final_contact_force_N": np.asarray(summary["final_contact_force_N"])}, scenario, realism)
    crossings = joint_limits.first_crossings(log.t, log.q, log.qd, robot)
    return summary | {name: np.asarray(value).tolist() for name, value in parts.items()} | {"joint_limits": crossings}


def divergence_summary(log: Log, step: int, robot: Robot | None = None, *, free_target: bool) -> dict:
    """What a diverged run tells: when (``first_nonfinite_s``, ``first_nonfinite_step``),
    which logged quantities were non-finite then (``nonfinite_fields``), every logged
    quantity at that step and at the step before (``state_at_divergence``,
    ``state_before_divergence``; units of [`Log`][spacegrasp_jax.loop.simulate.Log]), and the
    metrics of the finite steps (``before_divergence``, [`metrics.summary()`][spacegrasp_jax.envelope.metrics.summary], runaways
    by ``robot``'s limits; the target's with ``free_target``)."""

    def row(index: int) -> dict:
        return {name: np.asarray(series)[index] for name, series in vars(log).items() if series is not None}

    at_step = row(step)
    return {
        "diverged": True,
        "first_nonfinite_s": float(np.asarray(log.t)[step]),
        "first_nonfinite_step": step,
        "nonfinite_fields": [name for name, value in at_step.items() if not np.all(np.isfinite(value))],
        "state_at_divergence": at_step,
        "state_before_divergence": row(step - 1) if step > 0 else None,
        "before_divergence": metrics.summary(
            jax.tree.map(lambda series: series[:step], log), robot, free_target=free_target
        )
        if step > 0
        else None,
    }


def table5_markdown(results: dict) -> str:
    """Table 5 (peak |u_i| per joint, N m) of ``results`` (controller -> [`RunResult`][spacegrasp_jax.jobs.experiment.RunResult])
    beside the paper's, with the relative difference, as a Markdown table."""
    header = "| joint |" + "".join(f" {c} (ours) | {c} (paper) | difference |" for c in results)
    lines = [header, "|" + " --- |" * (1 + 3 * len(results))]
    for joint in range(7):
        cells = []
        for controller, result in results.items():
            ours, reference = result.summary["max_abs_torque_Nm"][joint], paper.MAX_ABS_TORQUE_NM[controller][joint]
            cells.append(f" {ours:.3f} | {reference:.3g} | {100.0 * (ours / reference - 1.0):+.0f}% |")
        lines.append(f"| {joint + 1} |" + "".join(cells))
    return "\n".join(lines)


#: Rows of [`summary_markdown()`][spacegrasp_jax.jobs.experiment.summary_markdown]: label, summary key, scale to the display unit, format.
_SUMMARY_ROWS = [
    ("final EE position error [mm]", "final_position_error_m", 1e3, "{:.2f}"),
    ("final EE orientation error [deg]", "final_orientation_error_rad", math.degrees(1.0), "{:.3f}"),
    ("RMS position tracking error [mm]", "rms_position_error_m", 1e3, "{:.1f}"),
    ("first contact [s]", "first_contact_s", 1.0, "{:.2f}"),
    ("peak contact force [N]", "max_contact_force_N", 1.0, "{:.2f}"),
    ("peak linear momentum [N s]", "max_linear_momentum_Ns", 1.0, "{:.2f}"),
    ("peak angular momentum [N m s]", "max_angular_momentum_Nms", 1.0, "{:.2f}"),
    ("peak satellite speed [mm/s]", "max_base_speed_mps", 1e3, "{:.1f}"),
    ("peak satellite rate [deg/s]", "max_base_rate_radps", math.degrees(1.0), "{:.1f}"),
]


def summary_markdown(results: dict) -> str:
    """The end-of-run errors and the peaks of ``results`` (controller -> [`RunResult`][spacegrasp_jax.jobs.experiment.RunResult])
    side by side, as a Markdown table."""
    lines = ["| |" + "".join(f" {c} |" for c in results), "|" + " --- |" * (1 + len(results))]
    for label, key, scale, number in _SUMMARY_ROWS:
        values = [result.summary.get(key) for result in results.values()]
        lines.append(
            f"| {label} |"
            + "".join(" never |" if v is None or math.isnan(v) else f" {number.format(scale * v)} |" for v in values)
        )
    return "\n".join(lines)
