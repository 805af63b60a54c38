"""Per-sample metrics of closed-loop rollouts, accumulated inside the scan, and the batched
evaluation of a Monte-Carlo campaign's samples.

A full :class:`~spacegrasp_jax.simulate.Log` of a 17 s rollout is about 11 MB; a campaign
needs a few numbers per sample. :func:`rollout_metrics` runs the same scan body as
:func:`~spacegrasp_jax.simulate.rollout` but folds every log row into running maxima and
sums (:class:`RunningMetrics`), so a batch needs memory for its states only, plus, on
request, every ``every``-th log row. The metrics equal those of :mod:`spacegrasp_jax.metrics`
on the full log (same definitions; "final" is the last logged step, ``t = duration - dt``).

Everything here is pure: ``jit``, ``vmap`` and sharding are applied by the caller
(:mod:`spacegrasp_jax.campaign`).
"""

from __future__ import annotations

import dataclasses
import types

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax import metrics
from spacegrasp_jax.control.gains import Gains
from spacegrasp_jax.model import N_JOINTS, Robot
from spacegrasp_jax.perturbations import PerturbationRanges, sample
from spacegrasp_jax.scenario import Scenario
from spacegrasp_jax.simulate import Log, closed_loop_step, initial_state

#: Per-sample metrics returned by :func:`rollout_metrics`: name -> (shape, unit, meaning).
METRICS = {
    "final_position_error_m": ((), "m", "EE position error in LAR at the last step"),
    "final_orientation_error_rad": ((), "rad", "angle between desired and actual EE orientation at the last step"),
    "rms_position_error_m": ((), "m", "RMS EE position tracking error over the run"),
    "max_abs_torque_Nm": ((N_JOINTS,), "N m", "peak |u_i| per joint"),
    "max_contact_force_N": ((), "N", "peak contact force magnitude"),
    "max_linear_momentum_Ns": ((), "N s", "peak |P| of the whole system"),
    "max_angular_momentum_Nms": ((), "N m s", "peak |L| about the inertial origin"),
    "max_base_speed_mps": ((), "m/s", "peak satellite speed"),
    "max_base_rate_radps": ((), "rad/s", "peak satellite angular rate"),
    "first_contact_s": ((), "s", "first time the contact force is non-zero; NaN if never"),
    "first_nonfinite_s": ((), "s", "first step with a non-finite value; NaN if none"),
}


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RunningMetrics:
    """What the scan carries instead of the log. Maxima ignore NaN (``fmax``), so a
    diverging sample keeps the peaks it reached before its first non-finite step.

    Attributes:
        sum_squared_position_error: () m^2, over the steps so far.
        max_abs_torque: (7,) N m. max_contact_force: () N.
        max_linear_momentum: () N s. max_angular_momentum: () N m s.
        max_base_speed: () m/s. max_base_rate: () rad/s.
        first_contact_s, first_nonfinite_s: () s, ``inf`` until it happens.
        last_pose_ee, last_pose_des: (6,) the latest row's EE and desired pose in LAR.
    """

    sum_squared_position_error: jax.Array
    max_abs_torque: jax.Array
    max_contact_force: jax.Array
    max_linear_momentum: jax.Array
    max_angular_momentum: jax.Array
    max_base_speed: jax.Array
    max_base_rate: jax.Array
    first_contact_s: jax.Array
    first_nonfinite_s: jax.Array
    last_pose_ee: jax.Array
    last_pose_des: jax.Array


def _start(dtype) -> RunningMetrics:
    zero, never = jnp.zeros((), dtype), jnp.asarray(jnp.inf, dtype)
    return RunningMetrics(zero, jnp.zeros(N_JOINTS, dtype), zero, zero, zero, zero, zero, never, never, jnp.zeros(6, dtype), jnp.zeros(6, dtype))


def _norm(x):
    return jnp.sqrt(jnp.sum(x * x))


def _update(running: RunningMetrics, row: Log) -> RunningMetrics:
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree.leaves(row)]))
    force = _norm(row.contact_force)
    position_error = _norm(row.pose_ee[:3] - row.pose_des[:3])
    r = running
    return RunningMetrics(
        sum_squared_position_error=r.sum_squared_position_error + position_error**2,
        max_abs_torque=jnp.fmax(r.max_abs_torque, jnp.abs(row.u)),
        max_contact_force=jnp.fmax(r.max_contact_force, force),
        max_linear_momentum=jnp.fmax(r.max_linear_momentum, _norm(row.momentum[:3])),
        max_angular_momentum=jnp.fmax(r.max_angular_momentum, _norm(row.momentum[3:])),
        max_base_speed=jnp.fmax(r.max_base_speed, _norm(row.V_base[:3])),
        max_base_rate=jnp.fmax(r.max_base_rate, _norm(row.V_base[3:])),
        first_contact_s=jnp.where((force > 0.0) & jnp.isinf(r.first_contact_s), row.t, r.first_contact_s),
        first_nonfinite_s=jnp.where(~finite & jnp.isinf(r.first_nonfinite_s), row.t, r.first_nonfinite_s),
        last_pose_ee=row.pose_ee,
        last_pose_des=row.pose_des,
    )


def _finish(running: RunningMetrics, final_state, n_steps: int, duration: float) -> dict[str, jax.Array]:
    # A state that turns non-finite in the very last step shows in no logged row.
    final_finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree.leaves(final_state)]))
    first_nonfinite = jnp.where(jnp.isinf(running.first_nonfinite_s) & ~final_finite, duration, running.first_nonfinite_s)
    # The metrics module's definitions, applied to the last row alone.
    final_rows = types.SimpleNamespace(pose_ee=running.last_pose_ee[None], pose_des=running.last_pose_des[None])
    never = lambda s: jnp.where(jnp.isinf(s), jnp.nan, s)
    return {
        "final_position_error_m": metrics.final_position_error(final_rows),
        "final_orientation_error_rad": metrics.final_orientation_error(final_rows),
        "rms_position_error_m": jnp.sqrt(running.sum_squared_position_error / n_steps),
        "max_abs_torque_Nm": running.max_abs_torque,
        "max_contact_force_N": running.max_contact_force,
        "max_linear_momentum_Ns": running.max_linear_momentum,
        "max_angular_momentum_Nms": running.max_angular_momentum,
        "max_base_speed_mps": running.max_base_speed,
        "max_base_rate_radps": running.max_base_rate,
        "first_contact_s": never(running.first_contact_s),
        "first_nonfinite_s": never(first_nonfinite),
    }


def rollout_metrics(
    robot: Robot,
    scenario: Scenario,
    gains: Gains,
    controller: str,
    pinv_damping: float = 0.0,
    every: int | None = None,
) -> tuple[dict[str, jax.Array], Log | None]:
    """One closed-loop rollout reduced to its :data:`METRICS`, in one ``lax.scan``.

    Args:
        robot, scenario, gains, controller, pinv_damping: as :func:`~spacegrasp_jax.simulate.rollout`.
        every: if set (static; must divide ``scenario.n_steps``), also return every
            ``every``-th log row, i.e. the rows at ``t = 0, every dt, 2 every dt, ...``.

    Returns:
        ``(metrics, rows)``: a dict of the :data:`METRICS` arrays and the decimated
        :class:`~spacegrasp_jax.simulate.Log` (``None`` without ``every``).
    """
    step = closed_loop_step(robot, scenario, gains, controller, pinv_damping)
    n_steps = scenario.n_steps
    dtype = scenario.initial.q.dtype

    # The step number rides in the carry rather than being scanned over: the loop then reads
    # no array longer than 64 numbers, and XLA's CPU runtime runs its body as a sequence.
    def step_and_fold(carry, _):
        state, running, k = carry
        state, row = step(state, k)
        return (state, _update(running, row), k + 1), row

    carry = (initial_state(scenario), _start(dtype), jnp.zeros((), dtype))
    if every is None:
        (final, running, _), _ = jax.lax.scan(lambda c, _: (step_and_fold(c, None)[0], None), carry, None, length=n_steps)
        rows = None
    else:
        if every < 1 or n_steps % every:
            raise ValueError(f"every: {every} must be a positive divisor of the {n_steps} steps")

        def block(carry, _):
            carry, rows = jax.lax.scan(step_and_fold, carry, None, length=every)
            return carry, jax.tree.map(lambda x: x[0], rows)

        (final, running, _), rows = jax.lax.scan(block, carry, None, length=n_steps // every)
    return _finish(running, final, n_steps, scenario.duration), rows


def evaluate_samples(
    robot: Robot,
    scenario: Scenario,
    gains: Gains,
    seed,
    indices: jax.Array,
    *,
    controller: str,
    ranges: PerturbationRanges,
    pinv_damping: float = 0.0,
    every: int | None = None,
):
    """Samples ``indices`` (n,) of the campaign ``seed`` (see
    :mod:`~spacegrasp_jax.perturbations`), each simulated and reduced to its metrics.

    Returns:
        ``(perturbations, metrics, rows)``, each with leading axis n: the drawn
        :class:`~spacegrasp_jax.perturbations.Perturbation`, the :data:`METRICS` dict and
        the decimated logs (``None`` without ``every``). A sample that diverges has NaN
        final errors and a finite ``first_nonfinite_s``; the others are unaffected.
    """
    robots, scenarios, perturbations = sample(robot, scenario, seed, indices, ranges)
    one = lambda r, s: rollout_metrics(r, s, gains, controller, pinv_damping, every)
    sample_metrics, rows = jax.vmap(one)(robots, scenarios)
    return perturbations, sample_metrics, rows


def over_torque_limit(sample_metrics: dict, torque_limit_Nm: float | None):
    """(n,) bool: the sample's peak |u_i| on some joint exceeded ``torque_limit_Nm`` (N m;
    ``None``: never). NaN peaks (diverged samples) are not over it (NumPy)."""
    peak = np.asarray(sample_metrics["max_abs_torque_Nm"]).max(axis=-1)
    limit = np.inf if torque_limit_Nm is None else torque_limit_Nm
    with np.errstate(invalid="ignore"):
        return peak > limit


def success(sample_metrics: dict, position_tolerance_m: float, orientation_tolerance_rad: float, torque_limit_Nm: float | None = None):
    """(n,) bool: the sample did not diverge, its peak |u_i| stayed at or below
    ``torque_limit_Nm`` (N m; ``None``: no limit), and it ended within both tolerances (NumPy)."""
    position = np.asarray(sample_metrics["final_position_error_m"])
    orientation = np.asarray(sample_metrics["final_orientation_error_rad"])
    diverged = np.isfinite(np.asarray(sample_metrics["first_nonfinite_s"]))
    with np.errstate(invalid="ignore"):
        within = (position <= position_tolerance_m) & (orientation <= orientation_tolerance_rad)
    return ~diverged & ~over_torque_limit(sample_metrics, torque_limit_Nm) & within
