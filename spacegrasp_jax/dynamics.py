"""Free-floating dynamics: mass matrix, bias forces, forward dynamics, momentum and the
Dynamic Jacobian (paper eqs 3-8).

Equation of motion (DESIGN.md): ``M(x) xdot_v + bias(x, x_v) = Q`` with the generalised
velocity ``x_v = [v_s, w_s, qd]`` (13,), ``v_s`` the satellite CoM velocity and ``w_s`` its
angular velocity, both in the inertial frame, and ``Q = [f_s, tau_s, u]`` (13,) the force
on the satellite CoM, the torque on the satellite (inertial frame) and the joint torques.

Algorithm. With 8 bodies and 13 velocities every quantity is a handful of small dense
products, so the dynamics are written on the bodies' CoM Jacobians ``J_k`` (6, 13):
``M = sum_k J_k^T diag(m_k 1, I_k) J_k`` (composite inertia in Jacobian form) and, by
Kane's method, ``bias = sum_k J_k^T [m_k a_k; I_k alpha_k + w_k x I_k w_k]``, where
``a_k, alpha_k`` are the velocity-product (zero ``xdot_v``) accelerations from one
recursive Newton-Euler forward pass. The Jacobians are built in one vectorised step (no
recursion); only the kinematic chain and the 7-step velocity pass are sequential, both
unrolled at trace time. ``M`` is factorised by Cholesky. Everything is in the inertial
frame, so no frame changes are needed between bodies.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jax.scipy.linalg

from spacegrasp_jax import spatial
from spacegrasp_jax.kinematics import (
    N_DOF,
    body_com_positions,
    body_jacobians,
    forward_kinematics,
    point_jacobian,
)
from spacegrasp_jax.model import N_JOINTS, Robot, body_inertials


def _world_inertials(robot: Robot, frames) -> tuple[jax.Array, jax.Array]:
    """Masses (8,) kg and inertia tensors about each CoM in the inertial frame (8, 3, 3)."""
    mass, _, inertia_local = body_inertials(robot)
    R = frames.R_frame  # frame 0 is parallel to the satellite frame
    inertia = jnp.concatenate(
        [
            (R[0] @ robot.satellite_inertia @ R[0].T)[None],
            jnp.einsum("kia,kab,kjb->kij", R[1:], inertia_local, R[1:]),
        ]
    )
    return jnp.concatenate([robot.satellite_mass[None], mass]), inertia


def _origin_frames(robot: Robot, R_base, q):
    """Kinematics with the satellite CoM at the origin: M, bias and J_dyn are invariant
    under translation of the whole system."""
    p_base = jnp.zeros(3, dtype=R_base.dtype)
    return p_base, forward_kinematics(robot, p_base, R_base, q)


def _mass_matrix(mass, inertia, J_v, J_w):
    return jnp.einsum("k,kai,kaj->ij", mass, J_v, J_v) + jnp.einsum(
        "kai,kab,kbj->ij", J_w, inertia, J_w
    )


def mass_matrix(robot: Robot, R_base: jax.Array, q: jax.Array) -> jax.Array:
    """Generalised mass matrix ``M`` (13, 13), symmetric positive definite, SI units.

    Args:
        R_base: (3, 3) satellite attitude, satellite to inertial. q: (7,) rad.
    """
    p_base, frames = _origin_frames(robot, R_base, q)
    mass, inertia = _world_inertials(robot, frames)
    J_v, J_w = body_jacobians(robot, frames, p_base)
    return _mass_matrix(mass, inertia, J_v, J_w)


def _bias(robot: Robot, frames, p_base, mass, inertia, J_v, J_w, V_base, qd):
    """Kane's method: project each body's velocity-product inertial load on its Jacobian."""
    w_s = V_base[3:]
    p_com = body_com_positions(robot, frames)
    axes, origins = frames.joint_axis, frames.joint_origin

    # Forward pass (velocity products only): angular velocity w, angular acceleration
    # alpha and linear acceleration a_point of a reference point on each body.
    w, alpha = w_s, jnp.zeros(3, dtype=V_base.dtype)
    # The satellite CoM acceleration is a generalised acceleration: its bias is zero.
    point, a_point = p_base, jnp.zeros(3, dtype=V_base.dtype)
    w_body, alpha_body, a_com = [], [], []
    for k in range(N_JOINTS):
        lever = origins[k] - point
        a_point = a_point + jnp.cross(alpha, lever) + jnp.cross(w, jnp.cross(w, lever))
        point = origins[k]  # the joint point belongs to both bodies k-1 and k
        alpha = alpha + jnp.cross(w, axes[k]) * qd[k]
        w = w + axes[k] * qd[k]
        lever = p_com[k] - point
        a_com.append(a_point + jnp.cross(alpha, lever) + jnp.cross(w, jnp.cross(w, lever)))
        w_body.append(w)
        alpha_body.append(alpha)
    w_all = jnp.stack([w_s] + w_body)
    alpha_all = jnp.concatenate([jnp.zeros((1, 3), dtype=V_base.dtype), jnp.stack(alpha_body)])
    a_all = jnp.concatenate([jnp.zeros((1, 3), dtype=V_base.dtype), jnp.stack(a_com)])

    force = mass[:, None] * a_all
    Iw = jnp.einsum("kab,kb->ka", inertia, w_all)
    torque = jnp.einsum("kab,kb->ka", inertia, alpha_all) + jnp.cross(w_all, Iw)
    return jnp.einsum("kai,ka->i", J_v, force) + jnp.einsum("kai,ka->i", J_w, torque)


def bias_forces(robot: Robot, R_base, q, V_base, qd) -> jax.Array:
    """Coriolis and centrifugal forces ``bias(x, x_v)`` (13,), so that
    ``M xdot_v + bias = Q``.

    Args:
        R_base: (3, 3) satellite to inertial. q: (7,) rad.
        V_base: (6,) ``[v_s (m/s), w_s (rad/s)]`` in the inertial frame. qd: (7,) rad/s.
    """
    p_base, frames = _origin_frames(robot, R_base, q)
    mass, inertia = _world_inertials(robot, frames)
    J_v, J_w = body_jacobians(robot, frames, p_base)
    return _bias(robot, frames, p_base, mass, inertia, J_v, J_w, V_base, qd)


def mass_matrix_and_bias(robot: Robot, R_base, q, V_base, qd) -> tuple[jax.Array, jax.Array]:
    """``(M (13, 13), bias (13,))`` sharing one kinematics pass; arguments as
    :func:`bias_forces`."""
    p_base, frames = _origin_frames(robot, R_base, q)
    mass, inertia = _world_inertials(robot, frames)
    J_v, J_w = body_jacobians(robot, frames, p_base)
    M = _mass_matrix(mass, inertia, J_v, J_w)
    return M, _bias(robot, frames, p_base, mass, inertia, J_v, J_w, V_base, qd)


def forward_dynamics(robot: Robot, R_base, q, V_base, qd, Q) -> jax.Array:
    """Generalised acceleration ``xdot_v = M^-1 (Q - bias)`` (13,).

    Args:
        R_base, q, V_base, qd: as :func:`bias_forces`.
        Q: (13,) ``[f_s (N), tau_s (N m), u (N m)]``, satellite force and torque in the
            inertial frame, joint torques.

    Returns:
        (13,) ``[dv_s/dt (m/s^2), dw_s/dt (rad/s^2), qdd (rad/s^2)]``, inertial frame.
    """
    M, bias = mass_matrix_and_bias(robot, R_base, q, V_base, qd)
    factor = jax.scipy.linalg.cho_factor(M)
    return jax.scipy.linalg.cho_solve(factor, Q - bias)


def kinetic_energy(robot: Robot, R_base, q, V_base, qd) -> jax.Array:
    """Kinetic energy ``x_v^T M x_v / 2`` (J) of the whole system."""
    x_v = jnp.concatenate([V_base, qd])
    return 0.5 * x_v @ mass_matrix(robot, R_base, q) @ x_v


def _momentum_rows(robot: Robot, frames, p_base, mass, inertia, J_v, J_w) -> jax.Array:
    """(6, 13) map from x_v to [P; L about the inertial origin]."""
    p_com = jnp.concatenate([p_base[None], body_com_positions(robot, frames)])
    linear = jnp.einsum("k,kai->ai", mass, J_v)
    moment_arm = jax.vmap(spatial.skew)(p_com) * mass[:, None, None]
    angular = jnp.einsum("kab,kbi->ai", moment_arm, J_v) + jnp.einsum("kab,kbi->ai", inertia, J_w)
    return jnp.concatenate([linear, angular])


def momentum_matrix(robot: Robot, p_base, R_base, q) -> jax.Array:
    """``H = [H2 H3]`` (6, 13) with ``[P; L] = H x_v`` (eq 6): ``P`` the total linear
    momentum (N s) and ``L`` the total angular momentum about the inertial origin (N m s),
    both in the inertial frame.

    Args:
        p_base: (3,) m, satellite CoM. R_base: (3, 3) satellite to inertial. q: (7,) rad.
    """
    frames = forward_kinematics(robot, p_base, R_base, q)
    mass, inertia = _world_inertials(robot, frames)
    J_v, J_w = body_jacobians(robot, frames, p_base)
    return _momentum_rows(robot, frames, p_base, mass, inertia, J_v, J_w)


def momentum_jacobians(robot: Robot, p_base, R_base, q) -> tuple[jax.Array, jax.Array]:
    """``H2`` (6, 6) and ``H3`` (6, 7) of eq 6 (momentum about the inertial origin);
    arguments as :func:`momentum_matrix`."""
    H = momentum_matrix(robot, p_base, R_base, q)
    return H[:, :6], H[:, 6:]


def system_momentum(robot: Robot, p_base, R_base, q, V_base, qd) -> jax.Array:
    """``[P; L]`` (6,): total linear momentum (N s) and angular momentum about the
    inertial origin (N m s), inertial frame. Arguments as :func:`momentum_matrix` plus
    ``V_base`` (6,) ``[v_s, w_s]`` and ``qd`` (7,)."""
    return momentum_matrix(robot, p_base, R_base, q) @ jnp.concatenate([V_base, qd])


def system_com(robot: Robot, p_base, R_base, q) -> jax.Array:
    """(3,) m, centre of mass of the whole system in the inertial frame."""
    frames = forward_kinematics(robot, p_base, R_base, q)
    mass, _, _ = body_inertials(robot)
    p_com = body_com_positions(robot, frames)
    total = robot.satellite_mass + jnp.sum(mass)
    return (robot.satellite_mass * p_base + mass @ p_com) / total


def dynamic_jacobian(robot: Robot, R_base, q) -> jax.Array:
    """Dynamic (generalised) Jacobian ``J_dyn = J_m - J_s H2^-1 H3`` (6, 7) of eq 8.

    Maps ``qd`` to the EE twist ``[v_ee; w_ee]`` (inertial frame) when the system's
    linear and angular momenta are zero.

    Args:
        R_base: (3, 3) satellite to inertial. q: (7,) rad.
    """
    p_base, frames = _origin_frames(robot, R_base, q)
    J_ee = point_jacobian(frames, p_base, frames.p_ee, N_JOINTS)
    mass, inertia = _world_inertials(robot, frames)
    J_v, J_w = body_jacobians(robot, frames, p_base)
    # Zero momentum about the origin (here the satellite CoM) is the constraint of eq 6.
    H = _momentum_rows(robot, frames, p_base, mass, inertia, J_v, J_w)
    base_velocity_per_qd = -jnp.linalg.solve(H[:, :6], H[:, 6:])  # (6, 7)
    return J_ee[:, 6:] + J_ee[:, :6] @ base_velocity_per_qd


def dynamic_jacobian_ee(robot: Robot, R_base, q) -> jax.Array:
    """``J_dyn^(EE)`` (6, 7): the Dynamic Jacobian mapping ``qd`` to the EE twist expressed
    in the EE frame (used by eqs 17 and 21). Arguments as :func:`dynamic_jacobian`."""
    _, frames = _origin_frames(robot, R_base, q)
    R_ee_T = frames.R_ee.T
    J_dyn = dynamic_jacobian(robot, R_base, q)
    return jnp.concatenate([R_ee_T @ J_dyn[:3], R_ee_T @ J_dyn[3:]])


__all__ = [
    "N_DOF",
    "bias_forces",
    "dynamic_jacobian",
    "dynamic_jacobian_ee",
    "forward_dynamics",
    "kinetic_energy",
    "mass_matrix",
    "mass_matrix_and_bias",
    "momentum_jacobians",
    "momentum_matrix",
    "system_com",
    "system_momentum",
]
