"""The tuning objectives, from a rollout log: ``"capture"`` (the default) and ``"weighted"``.

**capture**: how far a run is from failing its capture. Each success criterion gives a
margin, the value over its tolerance (above 1: the capture fails; the campaigns' criteria,
[`spacegrasp_jax.jobs.anatomy`][spacegrasp_jax.jobs.anatomy]): ``m_p = e_p / 5 mm``, ``m_o = e_o / 1 deg``, the torque
``m_u = smoothmax_{t, i} |u_i(t)| / limit_i`` against the motors' limits (the robot's
``joint_torque_limit``: torque is a constraint, not a cost), with a free-floating
target ``m_v = |v_target(T)| / 5 mm/s``, for a robot with joint ranges their margin, and
where rate limits are criteria ``m_q = smoothmax_{t, i} |qd_i(t)| / rate_limit_i``. With
the worst margin in log units

    w = S log sum_c exp(log(m_c) / S)          (a smooth maximum, S = 0.05)

the run's loss is a softplus hinge at the safety level ``1 - d``:

    loss = tau softplus((w - log(1 - d)) / tau),    d = 0.2, tau = 0.1

It is about 0 for a run that meets every criterion with 20% to spare, grows like
``log(worst margin / 0.8)`` beyond, and is smooth, so its gradient pushes each failing or
marginal sample back inside the tolerances. In logs, a run far outside (a runaway at 100
times a limit) weighs ``log 100``, not 100: no single sample steers the batch. The batch
mean of the losses is the expected excess of the worst margin over the safety level, a
smooth stand-in for the failure probability that still points somewhere when every sample
fails; ``--cvar`` makes it the mean over the worst samples.

**weighted** (the objective before ``capture``): with ``e_p`` the final EE position error in LAR (m), ``e_o`` the final orientation error (rad),
``rms`` the RMS position tracking error over the run (m), ``|u_i(t)|`` the joint torques and
``|F(t)|`` the contact force:

    loss = w_position    * e_p / position_scale
         + w_orientation * e_o / orientation_scale
         + w_rms         * rms / rms_scale
         + w_torque      * smoothmax_{t, i} |u_i(t)| / torque_scale_i
         + w_contact     * smoothmax_t |F(t)| / contact_scale
         + w_target      * |v_target(T)| / target_speed_scale      (free-floating target only)

``smoothmax(x) = T log sum exp(x / T)`` over every sample (temperature ``T``) is a smooth upper
bound of the hard maximum, exceeding it by at most ``T log(count)``; the hard maximum and the
gap are always reported beside it. With ``torque_scale_i`` the peaks of the initial gains,
the torque term is the largest peak relative to where the tuning started: below 1 means every
joint's peak went down. ``|v_target(T)|`` is a free-floating target's final speed ("do not
push it away"); its weight is 0 by default.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax.core import joint_limits
from spacegrasp_jax.core.model import Robot
from spacegrasp_jax.envelope import metrics
from spacegrasp_jax.envelope.criteria import CaptureCriteria
from spacegrasp_jax.envelope.scenario import Scenario
from spacegrasp_jax.loop.control.gains import Gains
from spacegrasp_jax.loop.realism import Realism
from spacegrasp_jax.loop.simulate import FullLog, LoopOptions, RunSpec, closed_loop

#: The objectives by name (``--objective``).
OBJECTIVES = ("capture", "weighted")


def _concrete(*values) -> bool:
    """Whether every value is a number known now: the objects below are pytrees, rebuilt
    by JAX with placeholders (tracers, argument descriptions) inside compiled programs,
    whose numbers were checked when the object was first made."""
    numbers = (int, float, np.ndarray, np.generic)
    return all(
        isinstance(leaf, numbers) or (isinstance(leaf, jax.Array) and not isinstance(leaf, jax.core.Tracer))
        for leaf in jax.tree.leaves(values)
    )


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Weights:
    """Weights of the objective's parts (dimensionless; each part is scaled first). A
    pytree of numbers: programs take them as arguments, so other weights reuse a program."""

    final_position: float = 1.0
    final_orientation: float = 0.1
    rms_tracking: float = 0.1
    peak_torque: float = 10.0
    contact_force: float = 0.0
    target_speed: float = 0.0

    @classmethod
    def parse(cls, text: str) -> Weights:
        """``"final_position=1,peak_torque=2"`` -> Weights; unknown names or negative or
        non-finite values raise ``ValueError`` naming them."""
        values = {}
        known = {field.name for field in dataclasses.fields(cls)}
        for item in filter(None, (part.strip() for part in text.split(","))):
            name, _, number = item.partition("=")
            if name not in known:
                raise ValueError(f"--weights: unknown weight {name!r}; expected {', '.join(sorted(known))}")
            try:
                value = float(number)
            except ValueError:
                raise ValueError(f"--weights: {name} needs a number, got {number!r}") from None
            if not value >= 0.0 or value == float("inf"):
                raise ValueError(f"--weights: {name} must be finite and non-negative, got {number}")
            values[name] = value
        return cls(**values)

    def check_target(self, free_target: bool) -> None:
        """Raise ``ValueError`` if a weight needs a free-floating target and the scenario
        (``free_target``: whether its target floats) has none."""
        if self.target_speed > 0.0 and not free_target:
            raise ValueError("--weights target_speed: needs a scenario with a free-floating [target]")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Objective:
    """The objective (module docstring): which, and its weights, scales and tolerances.

    A pytree whose numbers are leaves and whose ``kind`` is static: a compiled program takes
    the objective as an argument, so weights, scales and tolerances are values (another
    set reuses the program) and only ``kind`` shapes it.

    Attributes:
        weights: the ``weighted`` objective's weights.
        torque_scale_Nm: (N,) per-joint torque scale of the ``weighted`` objective;
            ``tuning`` sets it to the peaks of the initial gains on the nominal scenario.
        kind: ``"capture"`` or ``"weighted"``.
        torque_constraint_Nm: (N,) N m, the ``capture`` objective's torque constraint, one a
            joint like ``torque_scale_Nm`` (the run's: ``min(torque_fraction * limit_i,
            torque_cap_Nm)`` of the robot's torque limits; by default the paper's arm's
            limits).
        criteria: the ``capture`` objective's success criteria
            ([`CaptureCriteria`][spacegrasp_jax.envelope.criteria.CaptureCriteria], the campaigns'
            defaults): its tolerances, its target speed limit and, where they are criteria,
            its rate limits (``joint_rate_margin``, the smooth largest |qd_i| over its limit,
            as the torque margin); its torque threshold is not the objective's, whose torque
            margin is against ``torque_constraint_Nm``.
        safety: ``d``, the share of each tolerance kept in reserve (the hinge sits at
            ``1 - d`` of it).
        hinge_width: ``tau``, the softplus hinge's width in log-margin units.
        margin_temperature: ``S``, the smooth maximum's temperature over the log margins.
        joint_ranges: the robot's joint ranges, static
            ([`finite_ranges()`][spacegrasp_jax.core.joint_limits.finite_ranges]): each is a margin of
            the ``capture`` objective ([`range_margin()`][spacegrasp_jax.core.joint_limits.range_margin]);
            empty (the paper's arm): none.
    """

    weights: Weights
    torque_scale_Nm: tuple[float, ...]
    position_scale_m: float = 1e-3
    orientation_scale_rad: float = 1e-2
    rms_scale_m: float = 1e-2
    contact_scale_N: float = 10.0
    target_speed_scale_mps: float = 1e-3
    temperature: float = 0.02
    kind: str = dataclasses.field(default="weighted", metadata=dict(static=True))
    torque_constraint_Nm: tuple[float, ...] = (10.0, 10.0, 10.0, 5.0, 5.0, 2.0, 2.0)
    criteria: CaptureCriteria = CaptureCriteria()
    safety: float = 0.2
    hinge_width: float = 0.1
    margin_temperature: float = 0.05
    joint_ranges: tuple = dataclasses.field(default=(), metadata=dict(static=True))

    def __post_init__(self):
        if self.kind not in OBJECTIVES:
            raise ValueError(f"objective: expected one of {', '.join(OBJECTIVES)}, got {self.kind!r}")
        numbers = [getattr(self, field.name) for field in dataclasses.fields(self) if not field.metadata.get("static")]
        if not _concrete(numbers):
            return
        n = len(self.torque_scale_Nm)
        if n < 6 or min(self.torque_scale_Nm) <= 0.0:
            raise ValueError(f"torque_scale_Nm: need one positive number a joint, got {self.torque_scale_Nm}")
        if len(self.torque_constraint_Nm) != n or min(self.torque_constraint_Nm) <= 0.0:
            raise ValueError(
                f"torque_constraint_Nm: need {n} positive numbers (one a joint), got {self.torque_constraint_Nm}"
            )
        rates = self.criteria.joint_rate_limits_radps
        if rates is not None and len(rates) != n:
            raise ValueError(f"criteria.joint_rate_limits_radps: need {n} numbers (one a joint) or None, got {rates}")
        if not self.temperature > 0.0:
            raise ValueError(f"temperature: must be positive, got {self.temperature}")
        if not 0.0 <= self.safety < 1.0:
            raise ValueError(f"safety: must be in [0, 1), got {self.safety}")
        if not (self.hinge_width > 0.0 and self.margin_temperature > 0.0):
            raise ValueError("hinge_width and margin_temperature: must be positive")


def tail_count(cvar_alpha: float, count: int) -> int:
    """How many samples of a batch of ``count`` the batch objective's CVaR at ``cvar_alpha``
    averages: the worst ``ceil((1 - cvar_alpha) * count)``, at least one."""
    return max(1, math.ceil((1.0 - cvar_alpha) * count))


def smooth_max(values: jax.Array, temperature: float) -> jax.Array:
    """``T log sum exp(values / T)`` over all entries: an upper bound of ``max(values)``."""
    return temperature * jax.nn.logsumexp(values.ravel() / temperature)


#: Added to the final errors before their logarithm (m, rad): the margins' gradient stays
#: finite at an exact zero error and no capture is judged finer than a micrometre.
_LOG_FLOOR = 1e-6


def capture_margins(
    parts: dict[str, jax.Array], log, objective: Objective, *, free_target: bool
) -> dict[str, jax.Array]:
    """The ``capture`` objective's margins (value over tolerance; above 1 the capture
    fails) from the ``weighted`` parts and the log: ``position_margin``,
    ``orientation_margin``, ``torque_margin`` (smooth), with ``free_target`` (static:
    the scenario's target floats free) ``target_speed_margin``, for a robot with joint
    ranges (``objective.joint_ranges``) ``joint_range_margin``, and where rate limits are
    criteria (``objective.criteria.joint_rate_limits_radps``) ``joint_rate_margin``."""
    criteria = objective.criteria
    torque_ratio = jnp.abs(log.u) / jnp.asarray(objective.torque_constraint_Nm)
    margins = {
        "position_margin": (parts["final_position_error_m"] + _LOG_FLOOR) / criteria.position_tolerance_m,
        "orientation_margin": (parts["final_orientation_error_rad"] + _LOG_FLOOR) / criteria.orientation_tolerance_rad,
        "torque_margin": smooth_max(torque_ratio, objective.temperature),
    }
    if free_target:
        speed = metrics.safe_norm(log.target_velocity[-1])
        margins["target_speed_margin"] = (speed + _LOG_FLOOR) / criteria.target_speed_limit_mps
    if objective.joint_ranges:
        margins["joint_range_margin"] = joint_limits.range_margin(log.q, objective.joint_ranges, objective.temperature)
    if criteria.joint_rate_limits_radps is not None:
        rate_ratio = jnp.abs(log.qd) / jnp.asarray(criteria.joint_rate_limits_radps)
        margins["joint_rate_margin"] = smooth_max(rate_ratio, objective.temperature)
    return margins


def capture_loss(margins: dict[str, jax.Array], objective: Objective) -> jax.Array:
    """``tau softplus((smoothmax_c log m_c - log(1 - d)) / tau)`` (module docstring)."""
    logs = jnp.stack([jnp.log(value) for value in margins.values()])
    worst = smooth_max(logs, objective.margin_temperature)
    return objective.hinge_width * jax.nn.softplus((worst - jnp.log1p(-objective.safety)) / objective.hinge_width)


def objective_parts(log, objective: Objective, *, free_target: bool) -> dict[str, jax.Array]:
    """Every part of the objective, unweighted, the ``capture`` objective's margins
    ([`capture_margins()`][tuning.objective.capture_margins]) and its ``capture_loss``, the ``weighted_loss``, and ``loss``,
    the one ``objective.kind`` names; with ``free_target`` (static, required:
    ``scenario.free_target``), the target's final speed ``final_target_speed_mps`` too, its
    weight and its margin."""
    w = objective.weights
    torque_ratio = jnp.abs(log.u) / jnp.asarray(objective.torque_scale_Nm)
    contact = metrics.contact_force_norm(log)
    parts = {
        "final_position_error_m": metrics.final_position_error(log),
        "final_orientation_error_rad": metrics.final_orientation_error(log),
        "rms_tracking_m": metrics.rms_position_error(log),
        "peak_torque_smooth": smooth_max(torque_ratio, objective.temperature),
        "peak_torque_hard": jnp.max(torque_ratio),
        "peak_contact_smooth_N": smooth_max(contact, objective.temperature * objective.contact_scale_N),
        "peak_contact_hard_N": jnp.max(contact),
    }
    parts["peak_torque_gap"] = parts["peak_torque_smooth"] - parts["peak_torque_hard"]
    parts["loss"] = (
        w.final_position * parts["final_position_error_m"] / objective.position_scale_m
        + w.final_orientation * parts["final_orientation_error_rad"] / objective.orientation_scale_rad
        + w.rms_tracking * parts["rms_tracking_m"] / objective.rms_scale_m
        + w.peak_torque * parts["peak_torque_smooth"]
        + w.contact_force * parts["peak_contact_smooth_N"] / objective.contact_scale_N
    )
    if free_target:
        parts["final_target_speed_mps"] = metrics.safe_norm(log.target_velocity[-1])
        parts["loss"] = (
            parts["loss"] + w.target_speed * parts["final_target_speed_mps"] / objective.target_speed_scale_mps
        )
    margins = capture_margins(parts, log, objective, free_target=free_target)
    parts |= margins
    parts["weighted_loss"] = parts["loss"]
    parts["capture_loss"] = capture_loss(margins, objective)
    parts["loss"] = parts["capture_loss"] if objective.kind == "capture" else parts["weighted_loss"]
    return parts


# ---- the objective of one run ----------------------------------------------------------------


#: The campaign's metrics ([`metrics.METRICS`][spacegrasp_jax.envelope.metrics.METRICS]) a held-out
#: evaluation adds to the objective's parts (``scenario_parts(verdict=True)``) so that its
#: verdict is a campaign's ([`captured()`][tuning.run.captured]): the final errors, the largest
#: peak torque and a free target's final speed are parts of the objective already, by the
#: same names.
VERDICT_METRICS = ("first_runaway_s", "first_nonfinite_s", "max_joint_rate_radps", "max_range_excess_rad")


def scenario_parts(
    spec: RunSpec, gains: Gains, objective: Objective, key: jax.Array | None = None, *, verdict: bool = False
) -> dict:
    """Every part of the objective on the run ``spec`` ([`objective_parts()`][tuning.objective.objective_parts]),
    plus ``largest_peak_torque_Nm``, the hard largest peak |u_i| (N m). ``spec`` keeps the
    whole log ([`objective_spec()`][tuning.objective.objective_spec]); ``key``: the sensors' noise key of a
    flight-like loop. With ``verdict`` (static), the campaign's own ``VERDICT_METRICS`` of the
    run too ([`metrics.log_metrics()`][spacegrasp_jax.envelope.metrics.log_metrics]; the per-joint
    ones shaped (N,)), for a held-out verdict that is a campaign's ([`captured()`][tuning.run.captured])."""
    _, log = closed_loop(spec, gains, key)
    parts = objective_parts(log, objective, free_target=spec.scenario.free_target)
    parts["largest_peak_torque_Nm"] = jnp.max(jnp.abs(log.u))
    if verdict:
        run = metrics.log_metrics(log, spec.robot, free_target=spec.scenario.free_target)
        parts |= {name: run[name] for name in VERDICT_METRICS}
    return parts


def objective_spec(
    robot: Robot,
    scenario: Scenario,
    controller,
    segment: int | None = None,
    realism: Realism | None = None,
    model_robot: Robot | None = None,
    options: LoopOptions = LoopOptions(checkpoint=True),
) -> RunSpec:
    """The run the objective reads: the whole log, each control period checkpointed for
    reverse mode ([`rollout()`][spacegrasp_jax.loop.simulate.rollout]'s loop); ``segment``: its
    ``block_steps``; ``options``: the loop's (checkpointed; the host's choice,
    [`experiment.loop_options()`][spacegrasp_jax.jobs.experiment.loop_options])."""
    return RunSpec(
        robot,
        scenario,
        controller,
        realism=realism,
        model_robot=model_robot,
        observer=FullLog(segment),
        options=options,
    )


#: The history column (``history.csv``, a step's aux) of the largest peak torque over the
#: whole batch: the largest of the captures' largest peaks (N m), the torque guard's measure.
#: Every other part in the history is its batch mean.
BATCH_MAX_PEAK_TORQUE = "max_largest_peak_torque_Nm"


#: The objective's parts that older versions named otherwise (their name -> today's, the
#: campaign's): history rows, checkpoints and held-out files of older runs are read with
#: today's names.
OLDER_PART_NAMES = {
    "final_position_m": "final_position_error_m",
    "final_orientation_rad": "final_orientation_error_rad",
}


def history_of_older_version(rows: list[dict]) -> list[dict]:
    """A checkpoint's history rows with today's column names: before the batch maximum's
    column said what it holds, it was ``largest_peak_torque_Nm`` (a row of today has both,
    that one the batch mean); the final errors had names of their own (``OLDER_PART_NAMES``)."""

    def renamed(row: dict) -> dict:
        row = {OLDER_PART_NAMES.get(name, name): value for name, value in row.items()}
        if BATCH_MAX_PEAK_TORQUE in row:
            return row
        return {(BATCH_MAX_PEAK_TORQUE if name == "largest_peak_torque_Nm" else name): v for name, v in row.items()}

    return [renamed(row) for row in rows]
