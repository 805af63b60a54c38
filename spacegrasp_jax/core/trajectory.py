"""Desired end-effector trajectory in the LAR frame: a quintic (minimum-jerk) profile from a
start pose to an end pose over ``[0, duration]``, then held.

A pose is ``[x, y, z, roll, pitch, yaw]`` (6,): the EE position in the LAR frame (m) and the
ZYX Euler angles of ``R_lar_ee`` (rad). Velocities and accelerations are returned as twists
in the LAR frame, ``[v; w]`` (6,): the Euler-angle rates become angular velocities through
eqs 10-13.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from spacegrasp_jax.core import spatial


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Trajectory:
    """The desired end-effector pose over time, in the LAR frame.

    Attributes:
        start_pose: (6,) ``[m, m, m, rad, rad, rad]`` at t = 0.
        end_pose: (6,) reached at ``t = duration`` and held afterwards.
        duration: () s, length of the move (10 s in the paper).
    """

    start_pose: jax.Array
    end_pose: jax.Array
    duration: jax.Array


def minimum_jerk(t, duration):
    """Quintic profile ``s(t)`` from 0 to 1 and its first two time derivatives (1/s, 1/s^2);
    constant 0 before ``t = 0`` and 1 after ``t = duration``."""
    tau = jnp.clip(t / duration, 0.0, 1.0)
    s = tau**3 * (10.0 - 15.0 * tau + 6.0 * tau**2)
    ds = 30.0 * tau**2 * (1.0 - tau) ** 2 / duration
    dds = 60.0 * tau * (1.0 - tau) * (1.0 - 2.0 * tau) / duration**2
    return s, ds, dds


def desired_state(trajectory: Trajectory, t) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Desired pose, twist and twist rate at time ``t`` (s).

    Returns:
        pose: (6,) ``[p (m), roll, pitch, yaw (rad)]`` in the LAR frame.
        twist: (6,) ``[v (m/s); w (rad/s)]`` in the LAR frame (eqs 10, 12).
        twist_rate: (6,) ``[a (m/s^2); dw/dt (rad/s^2)]`` in the LAR frame (eqs 11, 13).
    """
    s, ds, dds = minimum_jerk(t, trajectory.duration)
    delta = trajectory.end_pose - trajectory.start_pose
    pose = trajectory.start_pose + s * delta
    pose_rate, pose_acceleration = ds * delta, dds * delta
    angles, angle_rates, angle_accelerations = pose[3:], pose_rate[3:], pose_acceleration[3:]

    R_lar_ee = spatial.euler_zyx_to_rotation(angles)
    # Eq 10: w_ee = T_eul(angles) angles_dot; eq 11: its derivative.
    T_eul, T_eul_rate = jax.jvp(spatial.euler_rates_to_body, (angles,), (angle_rates,))
    w_ee = spatial.matvec(T_eul, angle_rates)
    dw_ee = spatial.matvec(T_eul_rate, angle_rates) + spatial.matvec(T_eul, angle_accelerations)
    # Eqs 12-13 (dR/dt w_ee = R (w_ee x w_ee) = 0, so only the rotation remains).
    twist = jnp.concatenate([pose_rate[:3], spatial.matvec(R_lar_ee, w_ee)])
    twist_rate = jnp.concatenate([pose_acceleration[:3], spatial.matvec(R_lar_ee, dw_ee)])
    return pose, twist, twist_rate
