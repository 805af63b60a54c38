"""The flight-like loop's stages ([`spacegrasp_jax.realism`][spacegrasp_jax.realism]), each a
small pure function of the realism's settings and its inputs: what the sensors read, how
the F/T reading is filtered, where the controller believes the LAR frame is, and how the
commands wait in the delay line. A stage that the realism leaves off
(``Realism.stages``, decided once from the values) returns its input unchanged, at no cost
in the compiled program.

The other stages are the control laws' and the plant's own: the saturation with anti-windup
is the joint PID's ([`PID.update()`][spacegrasp_jax.control.pid.PID.update]), the
controller's model is [`believed_robot()`][spacegrasp_jax.stages.believed_robot].
[`loop_body()`][spacegrasp_jax.simulate.loop_body] strings them together.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

from spacegrasp_jax import spatial
from spacegrasp_jax.model import Robot
from spacegrasp_jax.realism import Realism, Stage


def wrench_reading(realism: Realism, force: jax.Array, torque: jax.Array, noise: jax.Array) -> jax.Array:
    """The F/T sensor's reading ``[f (N); n (N m)]`` (6,), sensor axes: the true ``force`` and
    ``torque`` (3,) plus the bias and white noise of the ``sensors`` stage (``noise``: standard
    normals, the first six the wrench's)."""
    if Stage.SENSORS in realism.stages:
        force = force + realism.force_bias + realism.force_noise_std * noise[:3]
        torque = torque + realism.torque_bias + realism.torque_noise_std * noise[3:6]
    return jnp.concatenate([force, torque])


def low_pass_gain(realism: Realism, period: float) -> float:
    """The first-order low-pass's gain per sample at ``period`` (s), discretised exactly:
    ``1 - exp(-2 pi f_c period)`` (1: no filter, ``cutoff_hz`` = 0)."""
    return 1.0 - math.exp(-2.0 * math.pi * realism.cutoff_hz * period) if realism.cutoff_hz > 0.0 else 1.0


def low_pass(realism: Realism, previous: jax.Array, reading: jax.Array, gain: float) -> jax.Array:
    """The filtered reading: ``previous + gain (reading - previous)`` with the cutoff on,
    ``reading`` without (``gain``: [`low_pass_gain()`][spacegrasp_jax.stages.low_pass_gain])."""
    if realism.cutoff_hz > 0.0:
        return previous + gain * (reading - previous)
    return reading


def joint_reading(realism: Realism, q: jax.Array, qd: jax.Array, noise: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The joint sensors' ``(q (N,) rad, qd (N,) rad/s)``: the encoder's grid on ``q`` and
    white noise on ``qd`` (``noise``: (N,) standard normals) with the ``sensors`` stage on.

    The grid has a straight-through gradient: ``round()`` is flat between steps, so its exact
    derivative would cut the position feedback out of every gradient (an open loop whose
    sensitivity grows without bound). Averaged over where the grid falls, ``d E[reading] /
    dq = 1``.
    """
    if Stage.SENSORS in realism.stages:
        quantum = realism.angle_resolution_rad
        safe = jnp.where(quantum > 0.0, quantum, 1.0)
        grid_error = jnp.round(q / safe) * safe - q
        q = q + jnp.where(quantum > 0.0, jax.lax.stop_gradient(grid_error), 0.0)
        qd = qd + realism.rate_noise_std_radps * noise
    return q, qd


def lar_estimate(realism: Realism, p_lar: jax.Array, R_lar: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The LAR pose the controller believes, ``(p (3,) m, R (3, 3))`` inertial: the true one
    moved by the ``estimate`` stage's constant errors (position in LAR axes, rotation vector)."""
    if Stage.ESTIMATE in realism.stages:
        p_lar = p_lar + spatial.matvec(R_lar, realism.lar_position_error_m)
        R_lar = spatial.matmul(R_lar, spatial.rotation_exp(realism.lar_angle_error_rad))
    return p_lar, R_lar


def delay_line(realism: Realism, in_flight: jax.Array, command: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``(the command applied now (N,), the line after (delay_periods, N))``: ``command`` enters
    a line of ``realism.delay_periods`` whole control periods (oldest first) and the oldest
    leaves it; without a delay, ``command`` itself."""
    if realism.delay_periods:
        queue = jnp.concatenate([in_flight, command[None]])
        return queue[0], queue[1:]
    return command, in_flight


def believed_robot(robot: Robot, realism: Realism) -> Robot:
    """The robot the controller believes: ``robot`` with the satellite's mass and inertia
    times the realism's factors."""
    return dataclasses.replace(
        robot,
        satellite_mass=robot.satellite_mass * realism.satellite_mass_factor,
        satellite_inertia=robot.satellite_inertia * realism.satellite_inertia_factor,
    )


__all__ = [
    "believed_robot",
    "delay_line",
    "joint_reading",
    "lar_estimate",
    "low_pass",
    "low_pass_gain",
    "wrench_reading",
]
