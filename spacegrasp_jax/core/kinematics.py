"""Forward kinematics and Jacobians of the free-floating arm, in the inertial frame.

Naming: ``p_*`` positions (m), ``R_*`` rotation matrices (body to inertial), ``J*`` Jacobians
mapping the generalised velocity ``x_v = [v_s, w_s, qd]`` (6 + N,) (``v_s`` the
satellite CoM velocity and ``w_s`` its angular velocity, both in the inertial frame) to
velocities in the inertial frame. Bodies are numbered 0 (satellite) to N (link N with the
EE body merged into it); the paper's arm has N = 7.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from spacegrasp_jax.core import spatial
from spacegrasp_jax.core.model import Robot, body_inertials, n_joints


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Frames:
    """Poses of the frames 0..N and the EE frame in the inertial frame.

    The rotations are kept as frame 0's and frames 1..7's, not as one (8, 3, 3) stack: no
    array of the closed loop's step exceeds 64 numbers, which lets XLA's CPU runtime run the
    step's kernels one after the other instead of as a task graph where loops run kernel by
    kernel (documentation, Performance).
    The origins and axes the dynamics read are stacked as they are built, not sliced out of
    larger arrays: the derivative of a slice is a zero-padding, a kernel of its own.

    Attributes:
        joint_origin: (N, 3) m, origins of frames 0..N-1 (frame 0 is the mounting point): a
            point on each joint's axis.
        link_origin: (N, 3) m, origins of frames 1..N.
        joint_axis: (N, 3) unit axes of joints 1..N: the z axes of frames 0..N-1.
        R_mount: (3, 3) rotation of frame 0, the mounting frame (frame to inertial).
        R_link: (N, 3, 3) rotations of frames 1..N (frame to inertial).
        p_ee: (3,) m, origin of the EE frame.
        R_ee: (3, 3) rotation of the EE frame (EE to inertial), that of frame N (the EE
            offset is a translation).
    """

    joint_origin: jax.Array
    link_origin: jax.Array
    joint_axis: jax.Array
    R_mount: jax.Array
    R_link: jax.Array
    p_ee: jax.Array
    R_ee: jax.Array


def joint_transforms(robot: Robot, q: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Relative transforms of the chain, ``T_{i-1,i} = Rz(theta_i) F_i`` with ``theta_i = q_i +
    joint_offset_i`` and ``F_i`` the fixed ``(frame_rotation_i, frame_position_i)``.

    Args:
        q: (N,) rad, joint angles.

    Returns:
        R_rel: (N, 3, 3) rotation of frame i in frame i-1.
        p_rel: (N, 3) m, origin of frame i in frame i-1.
    """
    theta = q + robot.joint_offset
    ct, st = jnp.cos(theta), jnp.sin(theta)
    # Rz(theta) F: rows x and y of F turned about z, row z kept. For a DH table's Rx(alpha)
    # and (L, 0, lambda) the products with its exact zeros and ones give the DH formula's
    # numbers bit for bit.
    F, p = robot.frame_rotation, robot.frame_position
    c, s = ct[..., None], st[..., None]
    R_rel = jnp.stack([c * F[..., 0, :] - s * F[..., 1, :], s * F[..., 0, :] + c * F[..., 1, :], F[..., 2, :]], axis=-2)
    p_rel = jnp.stack(
        [ct * p[..., 0] - st * p[..., 1], st * p[..., 0] + ct * p[..., 1], p[..., 2] * jnp.ones_like(ct)], axis=-1
    )
    return R_rel, p_rel


def forward_kinematics(robot: Robot, p_base: jax.Array, R_base: jax.Array, q: jax.Array) -> Frames:
    """Poses of all the chain's frames and of the EE frame.

    Args:
        p_base: (3,) m, satellite CoM in the inertial frame.
        R_base: (3, 3) satellite attitude (satellite to inertial).
        q: (N,) rad, joint angles.
    """
    R_rel, p_rel = joint_transforms(robot, q)
    R, p = spatial.matmul(R_base, robot.mount_rotation), p_base + spatial.matvec(R_base, robot.mount_position)
    R_mount = R
    R_link, p_frame = [], [p]
    # The chain is short and fixed: unrolled at trace time. jnp.unstack, not x[i]: its
    # derivative is one stack, where each x[i]'s is a zero-padding of its own.
    for R_joint, p_joint in zip(jnp.unstack(R_rel), jnp.unstack(p_rel)):
        p = p + spatial.matvec(R, p_joint)
        R = spatial.matmul(R, R_joint)
        R_link.append(R)
        p_frame.append(p)
    z_axis = jnp.array([0.0, 0.0, 1.0], dtype=R.dtype)
    return Frames(
        joint_origin=jnp.stack(p_frame[:-1]),
        link_origin=jnp.stack(p_frame[1:]),
        joint_axis=jnp.stack([spatial.matvec(R_frame, z_axis) for R_frame in [R_mount] + R_link[:-1]]),
        R_mount=R_mount,
        R_link=jnp.stack(R_link),
        p_ee=p + spatial.matvec(R, robot.ee_offset),
        R_ee=R,
    )


def ee_pose(robot: Robot, p_base: jax.Array, R_base: jax.Array, q: jax.Array):
    """EE frame pose in the inertial frame.

    Args:
        p_base: (3,) m, satellite CoM. R_base: (3, 3) satellite to inertial. q: (N,) rad.

    Returns:
        p_ee: (3,) m, EE frame origin. R_ee: (3, 3) EE to inertial.
    """
    frames = forward_kinematics(robot, p_base, R_base, q)
    return frames.p_ee, frames.R_ee


def body_com_positions(robot: Robot, frames: Frames) -> jax.Array:
    """(N, 3) m, CoM of moving bodies 1..N in the inertial frame."""
    _, com_local, _ = body_inertials(robot)
    return frames.link_origin + spatial.matvec(frames.R_link, com_local)


def point_jacobian_blocks(
    frames: Frames, p_base: jax.Array, point: jax.Array, last_joint: int
) -> tuple[jax.Array, jax.Array]:
    """[`point_jacobian()`][spacegrasp_jax.core.kinematics.point_jacobian] as its satellite block (6, 6), for ``[v_s, w_s]``, and its
    joint block (6, N), for ``qd``."""
    r_base = point - p_base
    axes = frames.joint_axis
    lever = spatial.cross(axes, point - frames.joint_origin)  # (N, 3)
    moves = (jnp.arange(axes.shape[0]) < last_joint)[:, None]
    J_base = jnp.block([[jnp.eye(3), -spatial.skew(r_base)], [jnp.zeros((3, 3)), jnp.eye(3)]])
    J_joints = jnp.concatenate([jnp.where(moves, lever, 0.0).T, jnp.where(moves, axes, 0.0).T])
    return J_base, J_joints


def point_jacobian(frames: Frames, p_base: jax.Array, point: jax.Array, last_joint: int) -> jax.Array:
    """Jacobian (6, 6 + N) of a body point: maps x_v to ``[velocity of point; angular
    velocity]`` (inertial frame) of the body that carries ``point`` (3,) m, a body moved by
    joints 1..``last_joint`` (the satellite is ``last_joint = 0``, the EE body N)."""
    return jnp.concatenate(point_jacobian_blocks(frames, p_base, point, last_joint), axis=1)


def ee_jacobians(robot: Robot, R_base: jax.Array, q: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The Jacobians of eq 5, ``V_EE = J_s V_s + J_m qd``, in the inertial frame.

    ``V_EE = [v_ee; w_ee]`` (6,) is the velocity of the EE frame origin and the EE angular
    velocity; ``V_s = [v_s; w_s]``.

    Args:
        R_base: (3, 3) satellite to inertial. q: (N,) rad.

    Returns:
        J_s: (6, 6) satellite Jacobian. J_m: (6, N) fixed-base manipulator Jacobian.
    """
    p_base = jnp.zeros(3, dtype=R_base.dtype)  # Jacobians depend on relative positions only
    frames = forward_kinematics(robot, p_base, R_base, q)
    J = point_jacobian(frames, p_base, frames.p_ee, n_joints(robot))
    return J[:, :6], J[:, 6:]
