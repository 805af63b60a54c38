"""Scalar measures of a rollout, one definition each, from a whole
[`Log`][spacegrasp_jax.loop.simulate.Log] or folded step by step inside the scan.

Two views of the same definitions:

* ``METRICS`` are the per-run numbers of ``summary.json``, Monte-Carlo campaigns and
  sweeps. They are computed by folding log rows into [`RunningMetrics`][spacegrasp_jax.envelope.metrics.RunningMetrics]
  ([`accumulate()`][spacegrasp_jax.envelope.metrics.accumulate], then [`finish()`][spacegrasp_jax.envelope.metrics.finish]): a rollout that keeps no log folds each step's
  row as it goes (``spacegrasp_jax.jobs.montecarlo.rollout_metrics``), and [`log_metrics()`][spacegrasp_jax.envelope.metrics.log_metrics]
  folds a whole log at once. Both paths run the same functions. A metric with no value
  ("never touched", "never diverged") is NaN (``null`` in JSON files).
* The differentiable functions of a log ([`position_error()`][spacegrasp_jax.envelope.metrics.position_error], [`final_position_error()`][spacegrasp_jax.envelope.metrics.final_position_error],
  [`rms_position_error()`][spacegrasp_jax.envelope.metrics.rms_position_error], [`contact_force_norm()`][spacegrasp_jax.envelope.metrics.contact_force_norm], ...) are what the tuning objective
  is built from. Their gradients are finite wherever the values are ([`safe_norm()`][spacegrasp_jax.envelope.metrics.safe_norm]).

Pure ``jnp`` functions: they run on NumPy arrays too, and under ``jit``/``vmap``/``grad``.
"Final" means the last logged step, ``t = duration - dt``.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from spacegrasp_jax.core import spatial

#: The per-run metrics: name -> (shape, unit, meaning).
METRICS = {
    "final_position_error_m": ((), "m", "EE position error in LAR at the last step"),
    "final_orientation_error_rad": ((), "rad", "angle between desired and actual EE orientation at the last step"),
    "rms_position_error_m": ((), "m", "RMS EE position tracking error over the run"),
    "max_abs_torque_Nm": (("N",), "N m", "peak |u_i| per joint (Table 5)"),
    "largest_peak_torque_Nm": ((), "N m", "the largest peak |u_i| over the joints"),
    "max_contact_force_N": ((), "N", "peak contact force magnitude"),
    "max_linear_momentum_Ns": ((), "N s", "peak |P| of the whole system"),
    "max_angular_momentum_Nms": ((), "N m s", "peak |L| about the inertial origin"),
    "max_base_speed_mps": ((), "m/s", "peak satellite speed"),
    "max_base_rate_radps": ((), "rad/s", "peak satellite angular rate"),
    "first_contact_s": ((), "s", "first time the contact force is non-zero; NaN if never"),
    "first_nonfinite_s": ((), "s", "first step with a non-finite value; NaN if none"),
    "max_joint_rate_radps": (("N",), "rad/s", "peak |qd_i| per joint"),
    "first_runaway_s": (
        (),
        "s",
        "first time a joint's rate or torque exceeded RUNAWAY_FACTOR times the robot's limit; NaN if never",
    ),
    "final_position_error_lar_m": ((3,), "m", "EE minus desired position at the last step, LAR axes (z: approach)"),
    "final_contact_force_N": ((3,), "N", "contact force on the EE at the last step, LAR axes"),
    "max_range_excess_rad": (
        ("N",),
        "rad",
        "how far beyond its range each joint went (negative: its closest approach to a limit); NaN for a joint "
        "without a range",
    ),
    "first_range_exit_s": ((), "s", "first time a joint left its range; NaN if never"),
}

#: A run whose joint rate or torque exceeds this many times the robot's limit
#: (``Robot.joint_rate_limit``, ``Robot.joint_torque_limit``) has run away: no motor or
#: gearbox follows it, whatever the simulated numbers say next.
RUNAWAY_FACTOR = 10.0


def safe_norm(x, axis=-1):
    """Euclidean norm along ``axis`` whose gradient is 0 (not NaN) at exactly zero: errors
    and forces do hit exact zeros (the start of a run; a contact force that underflows).
    A non-finite ``x`` gives a non-finite norm."""
    squared = jnp.sum(x * x, axis=axis)
    positive = squared > 0.0
    # Not positive: 0 (whose branch has gradient 2x = 0) or NaN, passed through.
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, squared, 1.0)), squared)


# ---- differentiable functions of a log (leading axis: the N rows) ----------------------


def pose_position_error(pose_ee, pose_des):
    """(...) m, norm of the position error between EE poses ``pose_ee`` and desired poses
    ``pose_des`` (..., 6) ``[p (m); roll, pitch, yaw (rad)]`` in LAR."""
    return safe_norm(pose_ee[..., :3] - pose_des[..., :3])


def pose_orientation_error(pose_ee, pose_des):
    """() rad, angle of the rotation between one EE pose and one desired pose (6,)."""
    R_error = spatial.euler_zyx_to_rotation(pose_des[3:]).T @ spatial.euler_zyx_to_rotation(pose_ee[3:])
    return safe_norm(spatial.rotation_log(R_error))


def position_error(log):
    """(N,) m, norm of the EE position error in LAR at every step."""
    return pose_position_error(log.pose_ee, log.pose_des)


def orientation_error(log):
    """(N,) rad, angle of the rotation between the desired and the actual EE orientation."""
    return jax.vmap(pose_orientation_error)(log.pose_ee, log.pose_des)


def final_position_error(log):
    """() m, EE position error in LAR at the end of the run."""
    return position_error(log)[-1]


def final_orientation_error(log):
    """() rad, EE orientation error at the end of the run."""
    return orientation_error(log)[-1]


def rms_position_error(log):
    """() m, root-mean-square EE position tracking error over the run."""
    return jnp.sqrt(jnp.mean(position_error(log) ** 2))


def max_abs_torque(log):
    """(N,) N m, ``max_t |u_i(t)|`` per joint (Table 5)."""
    return jnp.max(jnp.abs(log.u), axis=0)


def contact_force_norm(log):
    """(N,) N, magnitude of the contact force."""
    return safe_norm(log.contact_force)


#: The per-run metrics of a free-floating target, reported beside ``METRICS`` where the
#: scenario has one (every run folds them; the paper's fixed target's speeds, rates and
#: displacement are zero and are not reported): name -> (shape, unit, meaning).
TARGET_METRICS = {
    "final_target_speed_mps": ((), "m/s", "the target CoM's speed at the last step"),
    "max_target_speed_mps": ((), "m/s", "the target CoM's peak speed"),
    "final_target_rate_radps": ((), "rad/s", "the target's angular rate at the last step"),
    "max_target_rate_radps": ((), "rad/s", "the target's peak angular rate"),
    "target_displacement_m": ((), "m", "how far the target's CoM moved over the run"),
    "target_impulse_Ns": ((), "N s", "magnitude of the impulse the contact gave the target"),
}


def first_contact_time(log):
    """() s, first time the contact force is non-zero; NaN if the EE never touches."""
    touching = contact_force_norm(log) > 0.0
    return jnp.where(jnp.any(touching), log.t[jnp.argmax(touching)], jnp.nan)


# ---- the per-run metrics, folded over log rows -------------------------------------------


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RunningTargetMetrics:
    """The ``TARGET_METRICS`` of the rows folded so far.

    Attributes:
        first_position, last_position: (3,) m, the target's CoM at the first and latest row.
        last_speed, last_rate: () m/s, rad/s. max_speed, max_rate: () m/s, rad/s.
        force_sum: (3,) N, the sum over rows of the contact's force on the target (inertial).
        first_t, last_t: () s, the first and latest rows' times (their spacing is the step).
    """

    first_position: jax.Array
    last_position: jax.Array
    last_speed: jax.Array
    last_rate: jax.Array
    max_speed: jax.Array
    max_rate: jax.Array
    force_sum: jax.Array
    first_t: jax.Array
    last_t: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RunningMetrics:
    """The metrics of the rows folded so far. Maxima ignore NaN, so a diverging run keeps
    the peaks it reached before its first non-finite step.

    Attributes:
        rows: () number of rows folded. sum_squared_position_error: () m^2.
        max_abs_torque: (N,) N m. max_contact_force: () N.
        max_linear_momentum: () N s. max_angular_momentum: () N m s.
        max_base_speed: () m/s. max_base_rate: () rad/s.
        first_contact_s, first_nonfinite_s: () s, ``inf`` until it happens.
        last_pose_ee, last_pose_des: (6,) the latest row's EE and desired pose in LAR.
        max_joint_rate: (N,) rad/s. first_runaway_s: () s, ``inf`` until it happens.
        last_contact_force: (3,) N, the latest row's contact force, LAR axes.
        runaway_rate, runaway_torque: (N,) rad/s, N m, the thresholds of a runaway
            (``inf``: none).
        max_range_excess: (N,) rad, the furthest each joint went beyond its range
            (``-inf``: a joint without one). first_range_exit_s: () s, ``inf`` until it happens.
        range_low, range_high: (N,) rad, the joints' ranges (``-inf``, ``inf``: none).
        target: the target's ([`RunningTargetMetrics`][spacegrasp_jax.envelope.metrics.RunningTargetMetrics]).
    """

    rows: jax.Array
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
    max_joint_rate: jax.Array
    first_runaway_s: jax.Array
    last_contact_force: jax.Array
    runaway_rate: jax.Array
    runaway_torque: jax.Array
    max_range_excess: jax.Array
    first_range_exit_s: jax.Array
    range_low: jax.Array
    range_high: jax.Array
    target: RunningTargetMetrics


def start(dtype=jnp.float64, robot=None, n_joints: int = 7) -> RunningMetrics:
    """Nothing folded yet; ``robot``: the [`Robot`][spacegrasp_jax.core.model.Robot] whose
    limits define a runaway and whose joint ranges are watched (``None``: neither, for an arm
    of ``n_joints`` joints)."""
    zero, never = jnp.zeros((), dtype), jnp.asarray(jnp.inf, dtype)
    if robot is not None:
        n_joints = robot.link_mass.shape[-1]
    if robot is None:
        runaway_rate = runaway_torque = jnp.full(n_joints, jnp.inf, dtype)
        range_low, range_high = jnp.full(n_joints, -jnp.inf, dtype), jnp.full(n_joints, jnp.inf, dtype)
    else:
        runaway_rate = RUNAWAY_FACTOR * jnp.asarray(robot.joint_rate_limit, dtype)
        runaway_torque = RUNAWAY_FACTOR * jnp.asarray(robot.joint_torque_limit, dtype)
        limits = jnp.asarray(robot.joint_position_limit, dtype)
        range_low, range_high = limits[..., 0], limits[..., 1]
    nothing = jnp.full(3, jnp.nan, dtype)
    target = RunningTargetMetrics(nothing, nothing, zero, zero, zero, zero, jnp.zeros(3, dtype), never, never)
    return RunningMetrics(
        zero,
        zero,
        jnp.zeros(n_joints, dtype),
        zero,
        zero,
        zero,
        zero,
        zero,
        never,
        never,
        jnp.zeros(6, dtype),
        jnp.zeros(6, dtype),
        jnp.zeros(n_joints, dtype),
        never,
        jnp.zeros(3, dtype),
        runaway_rate,
        runaway_torque,
        jnp.full(n_joints, -jnp.inf, dtype),
        never,
        range_low,
        range_high,
        target,
    )


def _peak(running, values):
    """``max(running, max over rows of values)``, NaN ignored."""
    return jnp.fmax(running, jnp.max(jnp.where(jnp.isnan(values), -jnp.inf, values), axis=0))


def _first(running, happened, t):
    """The first time of ``t`` (rows,) where ``happened`` (rows,), unless one is known."""
    return jnp.where(jnp.any(happened) & jnp.isinf(running), t[jnp.argmax(happened)], running)


def accumulate(running: RunningMetrics, rows) -> RunningMetrics:
    """Fold ``rows`` (a [`Log`][spacegrasp_jax.loop.simulate.Log] with a leading axis of one or
    more rows, in time order) into ``running``."""
    finite = jnp.stack(
        [jnp.all(jnp.isfinite(leaf.reshape(leaf.shape[0], -1)), axis=1) for leaf in jax.tree.leaves(rows)]
    ).all(axis=0)
    force = contact_force_norm(rows)
    r = running
    runaway = jnp.any(jnp.abs(rows.qd) > r.runaway_rate, axis=1) | jnp.any(jnp.abs(rows.u) > r.runaway_torque, axis=1)
    range_excess = jnp.maximum(r.range_low - rows.q, rows.q - r.range_high)  # (rows, N) rad, -inf: no range
    return RunningMetrics(
        rows=r.rows + rows.t.shape[0],
        sum_squared_position_error=r.sum_squared_position_error + jnp.sum(position_error(rows) ** 2),
        max_abs_torque=_peak(r.max_abs_torque, jnp.abs(rows.u)),
        max_contact_force=_peak(r.max_contact_force, force),
        max_linear_momentum=_peak(r.max_linear_momentum, safe_norm(rows.momentum[:, :3])),
        max_angular_momentum=_peak(r.max_angular_momentum, safe_norm(rows.momentum[:, 3:])),
        max_base_speed=_peak(r.max_base_speed, safe_norm(rows.V_base[:, :3])),
        max_base_rate=_peak(r.max_base_rate, safe_norm(rows.V_base[:, 3:])),
        first_contact_s=_first(r.first_contact_s, force > 0.0, rows.t),
        first_nonfinite_s=_first(r.first_nonfinite_s, ~finite, rows.t),
        last_pose_ee=rows.pose_ee[-1],
        last_pose_des=rows.pose_des[-1],
        max_joint_rate=_peak(r.max_joint_rate, jnp.abs(rows.qd)),
        first_runaway_s=_first(r.first_runaway_s, runaway, rows.t),
        last_contact_force=rows.contact_force[-1],
        runaway_rate=r.runaway_rate,
        runaway_torque=r.runaway_torque,
        max_range_excess=_peak(r.max_range_excess, range_excess),
        first_range_exit_s=_first(r.first_range_exit_s, jnp.any(range_excess > 0.0, axis=1), rows.t),
        range_low=r.range_low,
        range_high=r.range_high,
        target=_accumulate_target(r.target, rows),
    )


def _accumulate_target(running: RunningTargetMetrics, rows) -> RunningTargetMetrics:
    speed = safe_norm(rows.target_velocity)
    rate = safe_norm(rows.target_angular_velocity)
    R = jax.vmap(spatial.quat_to_rotation)(rows.target_quat)  # LAR axes to inertial
    force_on_target = -jnp.einsum("nij,nj->ni", R, rows.contact_force)
    first = jnp.isinf(running.first_t)
    return RunningTargetMetrics(
        first_position=jnp.where(first, rows.target_position[0], running.first_position),
        last_position=rows.target_position[-1],
        last_speed=speed[-1],
        last_rate=rate[-1],
        max_speed=_peak(running.max_speed, speed),
        max_rate=_peak(running.max_rate, rate),
        force_sum=running.force_sum + jnp.sum(force_on_target, axis=0),
        first_t=jnp.where(first, rows.t[0], running.first_t),
        last_t=rows.t[-1],
    )


def finish(running: RunningMetrics, nonfinite_after_s=None, *, free_target: bool) -> dict[str, jax.Array]:
    """The ``METRICS`` of everything folded into ``running`` (NaN where a time never
    came), and the ``TARGET_METRICS`` with ``free_target`` (static, required: the scenario's
    target floats free; ``scenario.free_target``). ``nonfinite_after_s``: a time (s) to report as ``first_nonfinite_s`` if no
    row was non-finite (a state that turns non-finite in the last step shows in no row)."""
    first_nonfinite = running.first_nonfinite_s
    if nonfinite_after_s is not None:
        first_nonfinite = jnp.where(jnp.isinf(first_nonfinite), nonfinite_after_s, first_nonfinite)
    never = lambda s: jnp.where(jnp.isinf(s), jnp.nan, s)
    r = running.target
    step = (r.last_t - r.first_t) / jnp.maximum(running.rows - 1, 1)  # the log's dt
    target = {
        "final_target_speed_mps": r.last_speed,
        "max_target_speed_mps": r.max_speed,
        "final_target_rate_radps": r.last_rate,
        "max_target_rate_radps": r.max_rate,
        "target_displacement_m": safe_norm(r.last_position - r.first_position),
        "target_impulse_Ns": safe_norm(r.force_sum * step),
    }
    return {
        "final_position_error_m": pose_position_error(running.last_pose_ee, running.last_pose_des),
        "final_orientation_error_rad": pose_orientation_error(running.last_pose_ee, running.last_pose_des),
        "rms_position_error_m": jnp.sqrt(running.sum_squared_position_error / running.rows),
        "max_abs_torque_Nm": running.max_abs_torque,
        "largest_peak_torque_Nm": jnp.max(running.max_abs_torque),
        "max_contact_force_N": running.max_contact_force,
        "max_linear_momentum_Ns": running.max_linear_momentum,
        "max_angular_momentum_Nms": running.max_angular_momentum,
        "max_base_speed_mps": running.max_base_speed,
        "max_base_rate_radps": running.max_base_rate,
        "first_contact_s": never(running.first_contact_s),
        "first_nonfinite_s": never(first_nonfinite),
        "max_joint_rate_radps": running.max_joint_rate,
        "first_runaway_s": never(running.first_runaway_s),
        "final_position_error_lar_m": running.last_pose_ee[:3] - running.last_pose_des[:3],
        "final_contact_force_N": running.last_contact_force,
        "max_range_excess_rad": jnp.where(jnp.isneginf(running.max_range_excess), jnp.nan, running.max_range_excess),
        "first_range_exit_s": never(running.first_range_exit_s),
    } | (target if free_target else {})


def log_metrics(log, robot=None, *, free_target: bool) -> dict[str, jax.Array]:
    """The ``METRICS`` of a whole log (arrays), and the ``TARGET_METRICS`` with
    ``free_target`` (required: ``scenario.free_target``; every log has the target's fields, so
    they cannot say); ``robot``: whose limits define a runaway ([`start()`][spacegrasp_jax.envelope.metrics.start])."""
    n_joints = jnp.shape(log.u)[-1]
    return finish(accumulate(start(jnp.asarray(log.t).dtype, robot, n_joints), log), free_target=free_target)


#: [`log_metrics()`][spacegrasp_jax.envelope.metrics.log_metrics] as one compiled program (one per log
#: length, robot and target kind): a log on the host is summarised by one compile, which the
#: persistent compilation cache keeps, instead of some ninety compiles of single operations.
_log_metrics_program = jax.jit(log_metrics, static_argnames="free_target")


def summary(log, robot=None, *, free_target: bool) -> dict:
    """The ``METRICS`` (and, with ``free_target``, ``TARGET_METRICS``) of a whole log as
    plain floats and lists (``summary.json``; NaN where a metric has no value); ``robot`` as
    [`log_metrics()`][spacegrasp_jax.envelope.metrics.log_metrics]."""
    metrics = _log_metrics_program(log, robot, free_target=free_target)
    declared = (*METRICS, *TARGET_METRICS)  # the program's outputs come back by sorted name
    return {name: jnp.asarray(metrics[name]).tolist() for name in sorted(metrics, key=declared.index)}


__all__ = [
    "METRICS",
    "RUNAWAY_FACTOR",
    "TARGET_METRICS",
    "RunningMetrics",
    "RunningTargetMetrics",
    "accumulate",
    "contact_force_norm",
    "final_orientation_error",
    "final_position_error",
    "finish",
    "first_contact_time",
    "log_metrics",
    "max_abs_torque",
    "orientation_error",
    "pose_orientation_error",
    "pose_position_error",
    "position_error",
    "rms_position_error",
    "safe_norm",
    "start",
    "summary",
]
