"""Time-domain stability margins of a gain set: how much extra loop gain and how much extra
delay the closed loop takes before a capture fails.

Each margin is found by bisection on *probes*. A probe runs the same ``samples`` envelope
samples of a Monte-Carlo campaign (``CampaignConfig``'s seed, ranges, realism and
criteria; samples 0 .. samples-1) with one change to the loop, in one batched call of one
compiled program: every probe of a margin search differs from the others in values only.

The changes probed:

* **PID gain factor** ``c``: the joint PID's ``kp``, ``ki`` and ``kd`` times ``c`` (the
  servo loop's gain times ``c``).
* **Law gain factor** ``c``: the law's loop gain times ``c``. The Cartesian law's ``K_lin``
  and ``K_eul`` are multiplied by ``c``; the admittance law's ``Md``, ``Bd`` and ``Kd`` are
  divided by ``c``, which multiplies the motion it commands per newton of contact force by
  ``c`` and leaves its pose-tracking dynamics (``Md^-1 Bd``, ``Md^-1 Kd``) as they are.
* **Extra delay** of ``d`` whole control periods at the controller's output, between the
  law and the joint PID (on top of the realism's own ``delay_periods``), in a delay line of
  ``max_delay_periods + 1`` entries whose length in use is a value: every ``d`` runs one
  program. The line starts full of zero commands, as the realism's does.
* **Extra delay at the servo's input** of ``d`` whole servo ticks, between the joint
  sensors and the joint PID, where the realism runs the servos faster than the controller
  (``servo_period`` below ``control_period``): the PID reads the joint sensors' reading of ``d``
  ticks before (``stages.DelayLine``, ``max_servo_delay_ticks + 1`` entries, one
  program for every ``d``; the line starts full of zero readings).

A probe *fails* when a sample that captures at the nominal gains no longer captures (the
campaign's criteria: tolerances, torque threshold, target speed, no runaway), or a sample that
stays bounded at the nominal gains runs away or diverges (``RUNAWAY_FACTOR`` times a joint
limit, or a non-finite state). A sample that already fails at the nominal gains can only
make a probe fail by running away. The gain margins are searched in both directions
(increase and decrease) on a logarithmic scale, first doubling (halving) the factor until a
probe fails or ``max_factor`` (``1 / max_factor``) holds, then bisecting until the factor
that holds and the one that fails differ by at most ``factor_resolution`` (a ratio). The
delay margin doubles the delay from 1 period until a probe fails, then bisects to the
period: the result is the smallest failing delay if failures are monotone in the delay
(check with a sweep: ``sweep_delays()``).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Callable

import numpy as np

from spacegrasp_jax.core.model import Robot
from spacegrasp_jax.envelope.scenario import Scenario
from spacegrasp_jax.jobs import batching
from spacegrasp_jax.jobs.anatomy import FAILURE_CLASSES, failure_classes
from spacegrasp_jax.jobs.campaign import CampaignConfig, CampaignError
from spacegrasp_jax.jobs.montecarlo import FoldedMetrics, evaluate_samples, lost, success
from spacegrasp_jax.loop.control.gains import Gains
from spacegrasp_jax.loop.control.law import Output
from spacegrasp_jax.loop.control.pid import PID
from spacegrasp_jax.loop.control.registry import LAWS, as_controller, law_named
from spacegrasp_jax.loop.control.schedule import GainSchedule, scheduled_knots
from spacegrasp_jax.loop.simulate import RunSpec, loop_realism
from spacegrasp_jax.loop.stages import DelayLine

#: The loops whose gain is probed: the joint PID's and the law's.
LOOPS = ("pid", "law")
#: The gain groups the joint PID loop's factor scales (all multiplied by it).
PID_LOOP_GROUPS = dict.fromkeys(PID.gain_groups, 1)


class MarginError(ValueError):
    """An invalid margin setting; names the cause."""


def loop_groups(controller, loop: str) -> dict[str, int]:
    """The gain groups ``loop``'s factor scales for ``controller`` (a law's name or object),
    and how: ``+1`` multiplies by the factor, ``-1`` divides by it (the law's own
    ``loop_gain``)."""
    if loop not in LOOPS:
        raise MarginError(f"loop: expected one of {', '.join(LOOPS)}, got {loop!r}")
    return PID_LOOP_GROUPS if loop == "pid" else as_controller(controller).law.loop_gain


def require_joint_servo(controller) -> None:
    """Raise ``MarginError`` unless ``controller``'s law (a name or object) commands joint
    rates to the joint PID: the margins are those of that two-loop structure (the PID's
    gain, the delay between the law and the PID, the delay at the PID's input)."""
    control = as_controller(controller)
    if control.servo is None:
        raise MarginError(
            f"controller: the {control.name} law commands joint torques; margins are searched for laws "
            f"that command joint rates to the joint PID ({', '.join(n for n, c in LAWS.items() if c.output is Output.JOINT_RATES)})"
        )


@dataclasses.dataclass(frozen=True)
class MarginSettings:
    """How the margins are searched.

    Attributes:
        samples: envelope samples each probe runs (samples 0 .. samples-1 of the campaign).
        max_factor: the gain factors searched, ``[1 / max_factor, max_factor]``.
        factor_resolution: the bisection stops when the factor that holds and the one that
            fails differ by at most this ratio (> 1).
        max_delay_periods: the largest extra delay searched, in control periods.
        max_servo_delay_ticks: the largest delay at the servo's input searched, in servo
            ticks (where the servos run at their own rate).
    """

    samples: int = 8
    max_factor: float = 64.0
    factor_resolution: float = 1.05
    max_delay_periods: int = 64
    max_servo_delay_ticks: int = 64

    def __post_init__(self):
        if isinstance(self.samples, bool) or not isinstance(self.samples, int) or self.samples < 1:
            raise MarginError(f"samples: must be a positive integer, got {self.samples!r}")
        if not (math.isfinite(self.max_factor) and self.max_factor > 1.0):
            raise MarginError(f"max_factor: must be finite and above 1, got {self.max_factor!r}")
        if not (math.isfinite(self.factor_resolution) and 1.0 < self.factor_resolution < self.max_factor):
            raise MarginError(
                f"factor_resolution: must be a ratio above 1 and below max_factor, got {self.factor_resolution!r}"
            )
        if (
            isinstance(self.max_delay_periods, bool)
            or not isinstance(self.max_delay_periods, int)
            or self.max_delay_periods < 1
        ):
            raise MarginError(f"max_delay_periods: must be a positive integer, got {self.max_delay_periods!r}")
        if (
            isinstance(self.max_servo_delay_ticks, bool)
            or not isinstance(self.max_servo_delay_ticks, int)
            or self.max_servo_delay_ticks < 1
        ):
            raise MarginError(f"max_servo_delay_ticks: must be a positive integer, got {self.max_servo_delay_ticks!r}")


# ---- probes ---------------------------------------------------------------------------


def scaled_loop(gains: Gains, controller: str, loop: str, factor: float) -> Gains:
    """``gains`` with ``loop``'s gain (``"pid"`` or ``"law"``; module docstring) times ``factor``."""
    groups = loop_groups(controller, loop)
    return dataclasses.replace(
        gains,
        **{name: np.asarray(getattr(gains, name), float) * factor**power for name, power in groups.items()},
    )


def delayed_spec(spec: RunSpec, capacity: int, delay_periods, servo_capacity: int | None, servo_delay_ticks) -> RunSpec:
    """``spec`` with the probes' two delay lines added to its stages: ``delay_periods`` control
    periods at the law's output (a line of ``capacity``) and, with a ``servo_capacity``,
    ``servo_delay_ticks`` servo ticks at the servo's input (``stages.DelayLine``)."""
    added = (DelayLine(capacity, delay_periods, "command"),)
    if servo_capacity is not None:
        added += (DelayLine(servo_capacity, servo_delay_ticks, "servo_joints"),)
    return dataclasses.replace(spec, stages=tuple(spec.stages) + added)


def _probe(
    spec, gains, seed, ranges, delay_periods, servo_delay_ticks, indices, *, capacity, servo_capacity, identified
):
    spec = delayed_spec(spec, capacity, delay_periods, servo_capacity, servo_delay_ticks)
    _, sample_metrics, _ = evaluate_samples(spec, gains, seed, indices, ranges=ranges, identified=identified)
    return sample_metrics


def servo_runs_at_its_own_rate(scenario: Scenario, realism) -> bool:
    """Whether ``realism`` ticks the joint PID more than once a control period."""
    return realism is not None and realism.steps_per_servo(scenario.dt) < realism.steps_per_period(scenario.dt)


@dataclasses.dataclass
class Prober:
    """Runs probes of one gain set and one controller and keeps each outcome.

    Attributes:
        probes: one dict a probe run: ``loop`` (``"pid"``, ``"law"``, ``"delay"`` or
            ``"servo_delay"``), ``value`` (the factor, the delay in control periods or in servo
            ticks), ``holds``, and per sample
            ``success``, ``bounded``, ``final_position_error_m``, ``largest_peak_torque_Nm``.
        compile_s: the time the probes' program took to build in this process (s; a load
            from the compilation cache counts its load).
        nominal: the nominal gains' probe (``outcome()``'s dict), run at the first probe.
    """

    robot: Robot
    scenario: Scenario
    gains: Gains
    controller: str
    config: CampaignConfig
    settings: MarginSettings
    probes: list = dataclasses.field(default_factory=list)
    compile_s: float = 0.0
    nominal: dict | None = None
    progress: Callable[[str], None] | None = None

    def __post_init__(self):
        chunk = batching.chunk_size(self.settings.samples, self.settings.samples)
        self._indices = np.minimum(np.arange(chunk), self.settings.samples - 1).astype(np.uint32)
        self.servo_delay = servo_runs_at_its_own_rate(self.scenario, self.config.realism)
        servo_capacity = self.settings.max_servo_delay_ticks + 1 if self.servo_delay else None
        function = functools.partial(
            _probe,
            capacity=self.settings.max_delay_periods + 1,
            servo_capacity=servo_capacity,
            identified=self.config.identified,
        )
        try:
            realism = self.config.realism
            loop = "ideal loop" if loop_realism(realism, self.scenario) is None else "flight-like loop"
            self._executable, self.compile_s = batching.compile_chunk(
                f"margins, {self.controller}, {loop}", function, self._replicated(self.gains, 0), self._indices
            )
        except batching.BatchingError as error:
            raise CampaignError(str(error)) from None

    def _replicated(self, gains, delay_periods, servo_delay_ticks=0):
        config = self.config
        spec = RunSpec(
            self.robot,
            self.scenario,
            law_named(self.controller, config.pinv_damping),
            realism=config.realism,
            observer=FoldedMetrics(),
        )
        return (
            spec,
            gains,
            np.uint32(config.seed),
            config.ranges,
            np.int32(delay_periods),
            np.int32(servo_delay_ticks),
        )

    def outcome(self, gains: Gains, delay_periods: int = 0, servo_delay_ticks: int = 0) -> dict[str, np.ndarray]:
        """The samples' metrics with ``gains``, an extra delay of ``delay_periods`` at the
        controller's output and one of ``servo_delay_ticks`` at the servo's input, plus
        ``success`` and ``bounded`` (n,) bool."""
        if not 0 <= delay_periods <= self.settings.max_delay_periods:
            raise MarginError(f"delay: {delay_periods} periods is outside 0 .. {self.settings.max_delay_periods}")
        if servo_delay_ticks and not self.servo_delay:
            raise MarginError("servo delay: the servos run at the control period here; use the controller's delay")
        if not 0 <= servo_delay_ticks <= self.settings.max_servo_delay_ticks:
            raise MarginError(
                f"servo delay: {servo_delay_ticks} ticks is outside 0 .. {self.settings.max_servo_delay_ticks}"
            )
        sample_metrics = batching.run_chunk(
            self._executable, self._replicated(gains, delay_periods, servo_delay_ticks), self._indices
        )
        sample_metrics = {name: value[: self.settings.samples] for name, value in sample_metrics.items()}
        captured = success(sample_metrics, self.config.criteria)
        bounded = ~lost(sample_metrics)
        return sample_metrics | {"success": captured, "bounded": bounded}

    def holds(self, loop: str, value) -> bool:
        """Run one probe (``loop``: ``"pid"`` or ``"law"`` with a gain factor, ``"delay"``
        with periods) and say whether the loop holds (module docstring)."""
        if self.nominal is None:
            self.nominal = self.outcome(self.gains)
            self._record("nominal", 1.0, self.nominal, True)
        if loop == "delay":
            result = self.outcome(self.gains, int(value))
        elif loop == "servo_delay":
            result = self.outcome(self.gains, servo_delay_ticks=int(value))
        else:
            result = self.outcome(scaled_loop(self.gains, self.controller, loop, value))
        nominal = self.nominal
        held = bool(np.all(result["success"] | ~nominal["success"]) and np.all(result["bounded"] | ~nominal["bounded"]))
        self._record(loop, value, result, held)
        return held

    def limit_at(self, loop: str, value) -> dict | None:
        """What made the last probe of ``loop`` at ``value`` fail (``limited_by()``), or ``None``."""
        failing = [p for p in self.probes if p["loop"] == loop and p["value"] == value and not p["holds"]]
        return failing[-1]["limited_by"] if failing else None

    def limited_by(self, result: dict) -> dict:
        """What made a probe fail: ``"stability"`` where a sample that stays bounded at the
        nominal gains ran away or diverged, else ``"capture criteria"``; ``criteria``, the
        criteria the samples that captured at the nominal gains missed, with their counts
        (``anatomy.FAILURE_CLASSES``)."""
        nominal = self.nominal
        lost_now = nominal["bounded"] & ~result["bounded"]
        missed_now = nominal["success"] & ~result["success"]
        classes = failure_classes(result, self.config.criteria)
        counts = {
            name: int(np.sum(classes[f"failed_{name}"] & (missed_now | lost_now)))
            for name in FAILURE_CLASSES
            if np.any(classes[f"failed_{name}"] & (missed_now | lost_now))
        }
        return {"kind": "stability" if np.any(lost_now) else "capture criteria", "criteria": counts}

    def _record(self, loop, value, result, held):
        self.probes.append(
            {
                "loop": loop,
                "value": int(value) if loop in ("delay", "servo_delay") else float(value),
                "holds": held,
                "limited_by": None if held else self.limited_by(result),
                "success": result["success"].tolist(),
                "bounded": result["bounded"].tolist(),
                "final_position_error_m": [_finite_or_none(x) for x in result["final_position_error_m"]],
                "largest_peak_torque_Nm": [_finite_or_none(x) for x in result["largest_peak_torque_Nm"]],
            }
        )
        if self.progress is not None:
            what = {
                "nominal": "nominal gains",
                "delay": f"extra delay {int(value)} periods",
                "servo_delay": f"servo input delay {int(value)} ticks",
            }.get(loop, f"{loop} gain x{value:.4g}")
            self.progress(
                f"probe {len(self.probes)}: {what}: {int(np.sum(result['success']))}/{len(result['success'])} captured, "
                f"{int(np.sum(~result['bounded']))} ran away -> {'holds' if held else 'fails'}"
            )


def _finite_or_none(x) -> float | None:
    return float(x) if np.isfinite(x) else None


# ---- the searches -------------------------------------------------------------------------


def gain_margin(prober: Prober, loop: str, direction: str) -> dict:
    """The factor on ``loop``'s gain (``"pid"`` or ``"law"``) at which the capture fails,
    searched upward (``direction="increase"``) or downward (``"decrease"``).

    Returns:
        ``holds``: the factor furthest from 1 found to hold; ``fails``: the nearest found to
        fail (``None`` if every factor up to ``max_factor`` holds); ``margin_db``: ``20
        log10(holds)``, the gain margin in dB (negative for a decrease); ``probes``: the
        probes this search ran.
    """
    if direction not in ("increase", "decrease"):
        raise MarginError(f"direction: expected increase or decrease, got {direction!r}")
    settings = prober.settings
    sign = 1.0 if direction == "increase" else -1.0
    start = len(prober.probes)
    held, failed = 0.0, None  # log2 of the factors
    step = 1.0
    limit = math.log2(settings.max_factor)
    while failed is None and held < limit:
        trial = min(held + step, limit)
        if prober.holds(loop, 2.0 ** (sign * trial)):
            held = trial
        else:
            failed = trial
        step *= 2.0
    if failed is not None:
        while failed - held > math.log2(settings.factor_resolution):
            middle = 0.5 * (held + failed)
            if prober.holds(loop, 2.0 ** (sign * middle)):
                held = middle
            else:
                failed = middle
    holds = 2.0 ** (sign * held)
    fails = None if failed is None else 2.0 ** (sign * failed)
    return {
        "holds": holds,
        "fails": fails,
        "margin_db": 20.0 * math.log10(holds),
        "probes": len(prober.probes) - start,
        "limited_by": _limit_at(prober, loop, fails),
    }


def _limit_at(prober, loop: str, value) -> dict | None:
    """What made the probe of ``loop`` at ``value`` fail (``Prober.limit_at()``); ``None``
    where nothing failed (the search's limit holds) or the prober does not say (the linear
    probers' probes fail by a growing mode: stability)."""
    limit_at = getattr(prober, "limit_at", None)
    return None if value is None or limit_at is None else limit_at(loop, value)


def limit_words(limit: dict | None) -> str:
    """``limit`` in words: ``limited by stability (a capture ran away)`` or ``limited by
    accuracy, not stability (captures missed: position 3)``."""
    if limit is None:
        return "not limited within the search"
    missed = ", ".join(f"{name} {count}" for name, count in limit["criteria"].items())
    if limit["kind"] == "stability":
        return f"limited by stability (a capture ran away or diverged; missed: {missed})"
    return f"limited by the capture criteria, not stability (captures missed: {missed})"


def delay_margin(prober: Prober, period_s: float, loop: str = "delay") -> dict:
    """The extra delay at which the capture fails: at the controller's output (``loop =
    "delay"``, whole control periods of ``period_s`` seconds) or at the servo's input
    (``"servo_delay"``, whole servo ticks of ``period_s`` seconds).

    Returns:
        ``holds_periods``: the largest delay found to hold; ``fails_periods``: the smallest
        found to fail (``None`` if every delay up to the settings' limit holds), both in
        ``period_s``; the same in seconds (``holds_s``, ``fails_s``); ``probes``.
    """
    start = len(prober.probes)
    limit = prober.settings.max_delay_periods if loop == "delay" else prober.settings.max_servo_delay_ticks
    held, failed, trial = 0, None, 1
    while failed is None and held < limit:
        trial = min(trial, limit)
        if prober.holds(loop, trial):
            held = trial
        else:
            failed = trial
        trial *= 2
    if failed is not None:
        while failed - held > 1:
            middle = (held + failed) // 2
            if prober.holds(loop, middle):
                held = middle
            else:
                failed = middle
    return {
        "holds_periods": held,
        "fails_periods": failed,
        "holds_s": held * period_s,
        "fails_s": None if failed is None else failed * period_s,
        "probes": len(prober.probes) - start,
        "limited_by": _limit_at(prober, loop, failed),
    }


def sweep_delays(prober: Prober, delays, loop: str = "delay") -> list[bool]:
    """Whether the loop holds at each extra delay of ``delays`` (control periods, or servo
    ticks with ``loop="servo_delay"``): the brute-force check of ``delay_margin()``."""
    return [prober.holds(loop, int(d)) for d in delays]


def control_period(scenario: Scenario, realism) -> float:
    """The controller's period (s): the realism's, or the scenario's ``dt``."""
    return scenario.dt * (1 if realism is None else realism.steps_per_period(scenario.dt))


def find_margins(
    robot: Robot,
    scenario: Scenario,
    gains: Gains,
    controller: str,
    config: CampaignConfig,
    settings: MarginSettings = MarginSettings(),
    progress: Callable[[str], None] | None = None,
) -> dict:
    """Every margin of one gain set and controller (module docstring).

    Args:
        robot, scenario, gains, controller: the nominal loop.
        config: the envelope (``seed``, ``ranges``), the realism and the success criteria;
            its ``n`` and ``chunk`` are not used (``settings.samples`` are).
        settings: the searches' extents and resolution.
        progress: called with one line per probe (``None``: silent).

    Returns:
        A JSON-ready dict: ``gain_margins`` (loop -> direction -> ``gain_margin()``'s
        result), ``delay_margin`` (``delay_margin()``'s), ``servo_delay_margin`` (the same at
        the servo's input, in servo ticks, where the servos run at their own rate; else
        ``None``), ``nominal`` (the nominal probe's samples), ``probes`` (every probe),
        ``rollouts``, ``compile_s``, ``search_s``, ``control_period_s``, ``servo_period_s``,
        ``realism_delay_periods``.
    """
    require_joint_servo(controller)
    started = time.perf_counter()
    prober = Prober(robot, scenario, gains, controller, config, settings, progress=progress)
    gain_margins = {
        loop: {direction: gain_margin(prober, loop, direction) for direction in ("increase", "decrease")}
        for loop in LOOPS
    }
    period = control_period(scenario, config.realism)
    delay = delay_margin(prober, period)
    servo_period = period if config.realism is None else config.realism.steps_per_servo(scenario.dt) * scenario.dt
    servo_delay = delay_margin(prober, servo_period, "servo_delay") if prober.servo_delay else None
    return {
        "controller": controller,
        "samples": settings.samples,
        "settings": dataclasses.asdict(settings),
        "control_period_s": period,
        "servo_period_s": servo_period,
        "realism_delay_periods": 0 if config.realism is None else config.realism.delay_periods,
        "gain_margins": gain_margins,
        "delay_margin": delay,
        "servo_delay_margin": servo_delay,
        "nominal": prober.probes[0],
        "probes": prober.probes,
        "rollouts": len(prober.probes) * settings.samples,
        "compile_s": prober.compile_s,
        "search_s": time.perf_counter() - started - prober.compile_s,
    }


def schedule_knots(schedule: GainSchedule) -> list[float]:
    """Every knot of every scheduled group, once, in increasing order: where a schedule's
    margins are checked (``[0.0]`` for a schedule of constant groups)."""
    return scheduled_knots(schedule) or [0.0]


def frozen_gains(schedule: GainSchedule, x: float) -> Gains:
    """The schedule's gains frozen at ``x``, as a constant gain set (NumPy leaves)."""
    frozen = schedule.at(x)
    return Gains(**{field.name: np.asarray(getattr(frozen, field.name)) for field in dataclasses.fields(frozen)})


def margin_size(result: dict) -> dict[str, float]:
    """Each margin of one ``find_margins()`` result as one number, larger the safer: a gain
    margin's ``|log10|`` of the factor that holds (a search that met its limit counts as that
    limit), a delay's periods or ticks that hold."""
    sizes = {}
    for loop in LOOPS:
        for direction in ("increase", "decrease"):
            sizes[f"{loop}_{direction}"] = abs(math.log10(result["gain_margins"][loop][direction]["holds"]))
    sizes["delay"] = float(result["delay_margin"]["holds_periods"])
    if result.get("servo_delay_margin") is not None:
        sizes["servo_delay"] = float(result["servo_delay_margin"]["holds_periods"])
    return sizes


def worst_knots(per_knot: list[dict]) -> dict[str, dict]:
    """For each margin, the knot where it is smallest: margin name -> ``{"x": the knot,
    "size": margin_size()'s number}`` (``per_knot``: ``{"x", "margins"}`` items)."""
    worst = {}
    for item in per_knot:
        for name, size in margin_size(item["margins"]).items():
            if name not in worst or size < worst[name]["size"]:
                worst[name] = {"x": item["x"], "size": size}
    return worst


def margin_lines(result: dict) -> list[str]:
    """The margins in words, with their units."""

    def factor(entry):
        if entry["fails"] is None:
            return f"holds to x{entry['holds']:.3g} (the search's limit)"
        limit = f"; {limit_words(entry['limited_by'])}" if "limited_by" in entry else ""
        return f"x{entry['holds']:.3g} ({entry['margin_db']:+.1f} dB; fails at x{entry['fails']:.3g}{limit})"

    def delay_limit(entry):
        return f"; {limit_words(entry['limited_by'])}" if entry.get("limited_by") else ""

    lines = []
    for loop, title in (("pid", "joint PID gain"), ("law", f"{result['controller']} law gain")):
        margins = result["gain_margins"][loop]
        lines.append(f"{title}: increase {factor(margins['increase'])}")
        lines.append(f"{' ' * len(title)}  decrease {factor(margins['decrease'])}")
    delay = result["delay_margin"]
    if delay["fails_periods"] is None:
        lines.append(
            f"extra delay at the controller's output: holds to {delay['holds_periods']} periods "
            f"({delay['holds_s']:.4g} s, the search's limit)"
        )
    else:
        lines.append(
            f"extra delay at the controller's output: {delay['holds_periods']} control periods "
            f"({delay['holds_s']:.4g} s) holds, {delay['fails_periods']} ({delay['fails_s']:.4g} s) fails{delay_limit(delay)}"
        )
    servo = result.get("servo_delay_margin")
    if servo is None:
        lines.append("delay at the servo's input: not searched (the servos run at the control period)")
    elif servo["fails_periods"] is None:
        lines.append(
            f"extra delay at the servo's input: holds to {servo['holds_periods']} servo ticks "
            f"({servo['holds_s']:.4g} s, the search's limit)"
        )
    elif servo is not None:
        lines.append(
            f"extra delay at the servo's input: {servo['holds_periods']} servo ticks ({servo['holds_s']:.4g} s) holds, "
            f"{servo['fails_periods']} ({servo['fails_s']:.4g} s) fails{delay_limit(servo)}"
        )
    lines.append(
        f"{len(result['probes'])} probes of {result['samples']} samples ({result['rollouts']} rollouts) in "
        f"{result['search_s']:.1f} s, after {result['compile_s']:.1f} s compiling"
    )
    return lines


__all__ = [
    "LOOPS",
    "frozen_gains",
    "margin_size",
    "schedule_knots",
    "worst_knots",
    "PID_LOOP_GROUPS",
    "MarginError",
    "MarginSettings",
    "Prober",
    "control_period",
    "delayed_spec",
    "loop_groups",
    "require_joint_servo",
    "delay_margin",
    "find_margins",
    "gain_margin",
    "margin_lines",
    "limit_words",
    "scaled_loop",
    "servo_runs_at_its_own_rate",
    "sweep_delays",
]
