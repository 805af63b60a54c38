"""Joint PID loops on the joint-rate error, with the paper's t^2 gain ramp."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp

from spacegrasp_jax.loop.control.groups import PER_JOINT, GainGroup, group, groups_of


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PIDGains:
    """The joint PID loops' gains, one a joint (N,); defaults: Table 4, for the paper's 7-joint arm.

    Attributes:
        kp: (N,) N m s/rad, on the joint-rate error.
        ki: (N,) N m/rad, on its integral (0: no integral action).
        kd: (N,) N m s^2/rad, on its derivative.
    """

    kp: jax.Array = group(
        GainGroup(
            PER_JOINT,
            "N m s/rad",
            "joint PID proportional gain on the joint-rate error, one a joint",
            "Table 4",
            default=(140.0, 210.0, 140.0, 105.0, 105.0, 21.0, 21.0),
        )
    )
    ki: jax.Array = group(
        GainGroup(
            PER_JOINT,
            "N m/rad",
            "joint PID integral gain, one a joint",
            "Table 4",
            default=(10.0, 10.0, 10.0, 1.0, 1.0, 1.0, 1.0),
            positive=False,
        )
    )
    kd: jax.Array = group(
        GainGroup(
            PER_JOINT, "N m s^2/rad", "joint PID derivative gain, one a joint", "Table 4", default=0.01, positive=False
        )
    )


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PIDState:
    """The joint PID loops' memory.

    Attributes:
        integral: (N,) rad, running integral of the rate error.
        previous_error: (N,) rad/s, rate error at the previous control step.
    """

    integral: jax.Array
    previous_error: jax.Array


def pid_init(n_joints: int, dtype=jnp.float64) -> PIDState:
    """Integral and previous error of ``n_joints`` loops start at zero (modelling notes)."""
    return PIDState(integral=jnp.zeros(n_joints, dtype=dtype), previous_error=jnp.zeros(n_joints, dtype=dtype))


def gain_ramp(t):
    """``min(t, 1)^2``: all PID gains grow from 0 to their value over the first second."""
    return jnp.minimum(t, 1.0) ** 2


def _command(gains: PIDGains, ramp, rate_error, integral, derivative) -> jax.Array:
    """The PID law's torques (N,) N m before any limit: ramp (kp e + ki integral + kd derivative)."""
    return ramp * (gains.kp * rate_error + gains.ki * integral + gains.kd * derivative)


def pid_torque(gains: PIDGains, state: PIDState, rate_error: jax.Array, t, dt) -> tuple[jax.Array, PIDState]:
    """Joint torques (N,) N m from the rate error ``qd_des - qd`` (N,) rad/s at time ``t`` (s).

    Discrete at the control period ``dt`` (s): the integral accumulates ``error dt``
    (including this step's error) and the derivative is the backward difference
    ``(error - previous_error) / dt``.
    """
    return PID().update(gains, rate_error, state, t, dt)


def saturate(torque: jax.Array, limit: jax.Array, law: str = "hard") -> jax.Array:
    """Joint torques (N,) N m limited to ``[-limit, limit]`` (N,) N m (``inf``: none).

    ``law``: ``"hard"`` clips; ``"smooth"`` is ``limit tanh(torque / limit)``, which has a
    gradient everywhere and tends to the clip as the torque moves away from the limit."""
    if law == "hard":
        return jnp.clip(torque, -limit, limit)
    finite = jnp.isfinite(limit)
    safe = jnp.where(finite, limit, 1.0)
    return jnp.where(finite, safe * jnp.tanh(torque / safe), torque)


@dataclasses.dataclass(frozen=True)
class PID:
    """The joint PID stage as a controller: ``init`` and ``update``.

    Attributes:
        saturation: ``"hard"`` or ``"smooth"`` ([`saturate()`][spacegrasp_jax.loop.control.pid.saturate]), when ``update`` gets a
            torque limit (static).
        anti_windup: with a limit, hold the integral while the unlimited torque exceeds the
            limit and the error drives it further out (conditional integration; static).
    """

    saturation: str = "hard"
    anti_windup: bool = True
    gains_type: ClassVar[type] = PIDGains
    #: The gain groups the joint PID reads (Table 4), one gain a joint each.
    gain_groups: ClassVar[tuple[str, ...]] = tuple(groups_of(PIDGains))

    def init(self, n_joints: int, dtype=jnp.float64) -> PIDState:
        return pid_init(n_joints, dtype)

    def update(
        self, gains: PIDGains, rate_error: jax.Array, state: PIDState, t, dt, limit=None
    ) -> tuple[jax.Array, PIDState]:
        """``(torque (N,) N m, next state)`` from the rate error ``qd_des - qd`` (N,) rad/s at
        time ``t`` (s), control period ``dt`` (s) ([`pid_torque()`][spacegrasp_jax.loop.control.pid.pid_torque]).
        ``limit``: (N,) N m torque limits, or ``None`` for the paper's unlimited motors."""
        integral = state.integral + rate_error * dt
        derivative = (rate_error - state.previous_error) / dt
        ramp = gain_ramp(t)
        command = _command(gains, ramp, rate_error, integral, derivative)
        if limit is None:
            return command, PIDState(integral=integral, previous_error=rate_error)
        if self.anti_windup:
            winding = (jnp.abs(command) > limit) & (rate_error * command > 0.0)
            integral = jnp.where(winding, state.integral, integral)
            command = _command(gains, ramp, rate_error, integral, derivative)
        return saturate(command, limit, self.saturation), PIDState(integral=integral, previous_error=rate_error)
