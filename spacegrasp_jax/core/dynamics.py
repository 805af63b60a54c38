"""Free-floating dynamics: mass matrix, bias forces, forward dynamics, momentum and the
Dynamic Jacobian (paper eqs 3-8).

Equation of motion (modelling notes): ``M(x) xdot_v + bias(x, x_v) = Q`` with the generalised
velocity ``x_v = [v_s, w_s, qd]`` (13,), ``v_s`` the satellite CoM velocity and ``w_s`` its
angular velocity, both in the inertial frame, and ``Q = [f_s, tau_s, u]`` (13,) the force
on the satellite CoM, the torque on the satellite (inertial frame) and the joint torques.

Algorithm: composite-rigid-body (CRBA) and recursive Newton-Euler (RNEA) on spatial vectors
expressed in the inertial frame about the satellite CoM (MJX's ``smooth.py`` style). In those
coordinates a joint's motion axis ``S_j = (z_j, o_j x z_j)`` needs no transform between
bodies, so the RNEA velocity and velocity-product acceleration passes are cumulative sums
over the joints and the composite inertias a reverse cumulative sum: apart from the N
products of the kinematic chain nothing is sequential, which suits jit, vmap and GPUs.
The accelerations come by block elimination on ``M``'s satellite and joint blocks.
Their derivative is that of inverse dynamics ([`forward_dynamics_from_frames()`][spacegrasp_jax.core.dynamics.forward_dynamics_from_frames]).

Spatial vectors are pairs of 3-vectors ``(angular, linear)``: a motion ``(w, v)`` with ``v``
the velocity of the body point at the satellite CoM; a force ``(n, f)`` with ``n`` the moment
about the satellite CoM. A spatial inertia is ``(m, h, I_O)``: mass, first moment ``m c`` and
rotational inertia about the satellite CoM, all of which add up across bodies.
"""

from __future__ import annotations

import functools
import itertools

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero

from spacegrasp_jax.core import spatial
from spacegrasp_jax.core.kinematics import body_com_positions, forward_kinematics, point_jacobian_blocks
from spacegrasp_jax.core.linalg import cho_solve, cholesky, solve_spd
from spacegrasp_jax.core.model import Robot, body_inertials, n_joints
from spacegrasp_jax.core.spatial import cross, symmetric_inverse


def frames_at_base(robot: Robot, R_base, q):
    """Kinematics with the satellite CoM at the origin, as the ``*_from_frames`` functions
    expect: M, bias and J_dyn are invariant under translation of the whole system, and a
    caller that needs several of them computes the frames once."""
    return forward_kinematics(robot, jnp.zeros(3, dtype=R_base.dtype), R_base, q)


def _link_inertias(robot: Robot, frames) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Spatial inertias of links 1..N about the satellite CoM, which ``frames`` places at the
    origin: mass (N,), first moment ``m c`` (N, 3) and rotational inertia about the origin
    (N, 3, 3), inertial axes."""
    mass, com_local, inertia_local = body_inertials(robot)
    R = frames.R_link
    com = frames.link_origin + spatial.matvec(R, com_local)
    inertia_com = spatial.matmul(spatial.matmul(R, inertia_local), jnp.swapaxes(R, -1, -2))
    # Parallel axes: I_O = I_c + m (|c|^2 1 - c c^T).
    inertia_origin = inertia_com + mass[:, None, None] * (
        jnp.sum(com * com, axis=-1)[:, None, None] * jnp.eye(3) - com[:, :, None] * com[:, None, :]
    )
    return mass, mass[:, None] * com, inertia_origin


def _satellite_inertia(robot: Robot, frames) -> jax.Array:
    """Rotational inertia (3, 3) of the satellite about its CoM, inertial axes (its first
    moment about its own CoM is zero)."""
    R_base = frames.R_mount
    return spatial.matmul(spatial.matmul(R_base, robot.satellite_inertia), R_base.T)


def _prefix_unrolled(x: jax.Array, reverse: bool) -> jax.Array:
    rows = [x[i] for i in range(x.shape[0])]
    if reverse:
        return jnp.stack(list(itertools.accumulate(rows[::-1]))[::-1])
    return jnp.stack(list(itertools.accumulate(rows)))


@functools.partial(jax.custom_jvp, nondiff_argnums=(1,))
def _prefix_sums(x: jax.Array, reverse: bool) -> jax.Array:
    """Cumulative sums of ``x`` (n, ...) down (or, if ``reverse``, up) its first axis,
    n <= 8. The values are written out as n - 1 additions, which XLA fuses into one loop
    (``lax.cumsum`` lowers to a reduce-window, slower on a CPU under vmap). The
    derivative is ``lax.cumsum``: one kernel each way, where the additions' derivative would
    be one kernel per row (the transposes of the row slices)."""
    return _prefix_unrolled(x, reverse)


@_prefix_sums.defjvp
def _prefix_sums_jvp(reverse, primals, tangents):
    (x,), (dx,) = primals, tangents
    return _prefix_sums(x, reverse), jax.lax.cumsum(dx, axis=0, reverse=reverse)


def _cumulative(arrays, reverse: bool):
    # Arrays are summed one by one, not packed side by side, so none exceeds 64 numbers.
    return tuple(_prefix_sums(x, reverse) for x in arrays)


def _chain_sums(*arrays):
    """Cumulative sums down the chain (link i gets the sum over joints 1..i), each array
    (N, ...) summed along its first axis."""
    return _cumulative(arrays, reverse=False)


def _subtree_sums(*arrays):
    """Sums over each link's subtree (link i gets the sum over links i..N), each array
    (N, ...) summed along its first axis."""
    return _cumulative(arrays, reverse=True)


def _apply_inertia(mass, moment, inertia, w, v):
    """Spatial inertia times motion: ``(L, p)`` with ``p = m v + w x h`` and
    ``L = I_O w + h x v``; broadcasts over leading axes."""
    p = mass[..., None] * v + cross(w, moment)
    L = spatial.matvec(inertia, w) + cross(moment, v)
    return L, p


def _joint_axes(frames) -> tuple[jax.Array, jax.Array]:
    """Motion axes ``S_j = (z_j, o_j x z_j)`` of the N joints: two (N, 3) arrays."""
    axis = frames.joint_axis
    return axis, cross(frames.joint_origin, axis)


def mass_matrix_parts_from_frames(robot: Robot, frames):
    """The mass matrix by composite rigid bodies, from [`frames_at_base()`][spacegrasp_jax.core.dynamics.frames_at_base], in parts:
    ``(m, h, I_O, M_coupling, M_joints)``. The satellite block
    ``M_base = [[m 1, -h x], [h x, I_O]]`` (6, 6) is the whole system's spatial inertia about
    the satellite CoM: mass ``m`` (), first moment ``h`` (3,) kg m, rotational inertia
    ``I_O`` (3, 3); ``M_coupling`` (6, N) couples ``[v_s, w_s]`` with ``qd``; ``M_joints``
    (N, N) is the joints' block."""
    mass, moment, inertia = _link_inertias(robot, frames)
    # Composite inertia of the subtree of each link: a reverse cumulative sum.
    c_mass, c_moment, c_inertia = _subtree_sums(mass, moment, inertia)
    S_w, S_v = _joint_axes(frames)
    # Force F_j = Ic_j S_j needed to move the subtree of joint j along its axis.
    F_n, F_f = _apply_inertia(c_mass, c_moment, c_inertia, S_w, S_v)
    # M_ij = S_i . F_max(i,j) for joints i, j.
    A = spatial.matmul(S_w, F_n.T) + spatial.matmul(S_v, F_f.T)  # A[i, j] = S_i . F_j
    upper = jnp.triu(jnp.ones(A.shape, dtype=bool))
    M_joints = jnp.where(upper, A, A.T)
    # Satellite rows (generalised velocities v_s, w_s): its columns are the whole system's
    # composite inertia applied to a pure translation and a pure rotation. Summed directly
    # rather than read as c_mass[0] etc., whose derivative would be a zero-padding.
    m, h = robot.satellite_mass + jnp.sum(mass), jnp.sum(moment, axis=0)
    I_O = _satellite_inertia(robot, frames) + jnp.sum(inertia, axis=0)
    M_coupling = jnp.concatenate([F_f.T, F_n.T])  # rows [force; moment] for [v_s; w_s]
    return m, h, I_O, M_coupling, M_joints


def mass_matrix_from_frames(robot: Robot, frames) -> jax.Array:
    """Mass matrix (13, 13) by composite rigid bodies, from [`frames_at_base()`][spacegrasp_jax.core.dynamics.frames_at_base]."""
    m, h, I_O, M_coupling, M_joints = mass_matrix_parts_from_frames(robot, frames)
    h_skew = spatial.skew(h)
    M_base = jnp.block([[m * jnp.eye(3), -h_skew], [h_skew, I_O]])
    return jnp.block([[M_base, M_coupling], [M_coupling.T, M_joints]])


def bias_from_frames(robot: Robot, frames, V_base, qd) -> jax.Array:
    """Bias forces (13,) by Newton-Euler with zero generalised acceleration, from
    [`frames_at_base()`][spacegrasp_jax.core.dynamics.frames_at_base]."""
    return _newton_euler(robot, frames, V_base, qd, None)


def inverse_dynamics_from_frames(robot: Robot, frames, V_base, qd, xdd) -> jax.Array:
    """Generalised force ``Q = M xdd + bias`` (13,) by Newton-Euler (RNEA), from
    [`frames_at_base()`][spacegrasp_jax.core.dynamics.frames_at_base]; ``xdd`` (13,) ``[dv_s/dt, dw_s/dt, qdd]``, inertial frame."""
    return _newton_euler(robot, frames, V_base, qd, xdd)


def _newton_euler(robot: Robot, frames, V_base, qd, xdd) -> jax.Array:
    """``M xdd + bias`` (13,), or ``bias`` alone when ``xdd`` is None."""
    mass, moment, inertia = _link_inertias(robot, frames)
    v_s, w_s = jnp.split(V_base, 2)
    S_w, S_v = _joint_axes(frames)
    # Link velocities: the satellite's plus the joint rates up the chain.
    w_chain, v_chain = _chain_sums(S_w * qd[:, None], S_v * qd[:, None])
    w, v = w_s + w_chain, v_s + v_chain
    # Link accelerations. Each joint adds S_j qdd_j and (v_j x S_j) qd_j, the rate of
    # change of its moving axis. The satellite's spatial acceleration is
    # (dw_s/dt, dv_s/dt - w_s x v_s), since v_s is its CoM's classical velocity.
    dS_w = cross(w, S_w)
    dS_v = cross(w, S_v) + cross(v, S_w)
    joint_w, joint_v = dS_w * qd[:, None], dS_v * qd[:, None]
    if xdd is not None:
        dv_s, dw_s, qdd = jnp.split(xdd, [3, 6])
        joint_w, joint_v = joint_w + S_w * qdd[:, None], joint_v + S_v * qdd[:, None]
    a_w, a_v_chain = _chain_sums(joint_w, joint_v)
    a_v = -cross(w_s, v_s) + a_v_chain
    if xdd is not None:
        a_w, a_v = dw_s + a_w, dv_s + a_v
    # Newton-Euler per link: f = I a + v x* (I v), with (w, v) x* (n, f) = (w x n + v x f, w x f).
    inertial_n, inertial_f = _apply_inertia(mass, moment, inertia, a_w, a_v)
    momentum_n, momentum_f = _apply_inertia(mass, moment, inertia, w, v)
    f_n = inertial_n + cross(w, momentum_n) + cross(v, momentum_f)
    f_f = inertial_f + cross(w, momentum_f)
    # The satellite, about its own CoM (zero first moment), with acceleration
    # (dw_s/dt, dv_s/dt - w_s x v_s): f = m dv_s/dt (the -m w_s x v_s cancels the velocity
    # term w_s x m v_s) and n = I_s dw_s/dt + w_s x I_s w_s (v_s x m v_s = 0).
    I_s = _satellite_inertia(robot, frames)
    satellite_n = cross(w_s, spatial.matvec(I_s, w_s))
    if xdd is not None:
        satellite_n = satellite_n + spatial.matvec(I_s, dw_s)
    # Backward pass: each joint carries the load of its subtree.
    sub_n, sub_f = _subtree_sums(f_n, f_f)
    joints = jnp.sum(S_w * sub_n, axis=-1) + jnp.sum(S_v * sub_f, axis=-1)
    # The satellite carries every link's load: the sums over all links.
    force = jnp.sum(f_f, axis=0) if xdd is None else robot.satellite_mass * dv_s + jnp.sum(f_f, axis=0)
    return jnp.concatenate([force, satellite_n + jnp.sum(f_n, axis=0), joints])


def solve_base(m, h, I_O, rhs: jax.Array) -> jax.Array:
    """``M_base^-1 rhs`` for the satellite block ``M_base = [[m 1, -h x], [h x, I_O]]``
    ([`mass_matrix_parts_from_frames()`][spacegrasp_jax.core.dynamics.mass_matrix_parts_from_frames]), ``rhs`` (6,) or (6, k), in closed form.

    For ``M_base [v; w] = [f; n]``: ``I_c w = n - c x f`` with ``c = h / m`` and
    ``I_c = I_O + (h x)(c x) = I_O + c h^T - (h . c) 1`` the inertia about the system's CoM
    (parallel axes), then ``v = f / m + c x w``. The 3x3 solve is by the adjugate; all of it
    is elementwise (no matrix products), so that XLA fuses it, derivative included.
    """
    c = h / m
    I_c = I_O + c[:, None] * h[None, :] - jnp.sum(h * c) * jnp.eye(3)
    I_c_inv = symmetric_inverse(I_c)
    f, n = jnp.split(rhs, 2)
    if rhs.ndim == 2:  # columns
        moment = n - cross(c, f.T).T
        w = jnp.sum(I_c_inv[:, :, None] * moment[None], axis=1)
        return jnp.concatenate([f / m + cross(c, w.T).T, w])
    moment = n - cross(c, f)
    w = jnp.sum(I_c_inv * moment[None], axis=1)
    return jnp.concatenate([f / m + cross(c, w), w])


def solve_mass_blocks(base, M_coupling, M_joints, base_per_joint, rhs) -> jax.Array:
    """``M^-1 rhs`` (13,) by block elimination, given the parts of
    [`mass_matrix_parts_from_frames()`][spacegrasp_jax.core.dynamics.mass_matrix_parts_from_frames] (``base = (m, h, I_O)``) and
    ``base_per_joint = M_base^-1 M_coupling`` (6, N) ([`solve_base()`][spacegrasp_jax.core.dynamics.solve_base]): the joint
    accelerations from the Schur complement ``M_joints - M_coupling^T M_base^-1 M_coupling``
    (N, N), symmetric positive definite, by Cholesky, then the satellite's."""
    schur = M_joints - spatial.matmul(M_coupling.T, base_per_joint)
    return _solve_blocks(base, M_coupling, base_per_joint, rhs, lambda b: solve_spd(schur, b))


def _solve_blocks(base, M_coupling, base_per_joint, rhs, solve_schur) -> jax.Array:
    rhs_base, rhs_joints = jnp.split(rhs, [6])
    y = solve_base(*base, rhs_base)
    qdd = solve_schur(rhs_joints - spatial.matvec(M_coupling.T, y))
    return jnp.concatenate([y - spatial.matvec(base_per_joint, qdd), qdd])


def mass_blocks_from_frames(robot: Robot, frames):
    """The mass matrix's blocks as the solves use them, from [`frames_at_base()`][spacegrasp_jax.core.dynamics.frames_at_base]:
    ``((m, h, I_O), M_coupling, M_joints, base_per_joint)``, the parts of
    [`mass_matrix_parts_from_frames()`][spacegrasp_jax.core.dynamics.mass_matrix_parts_from_frames] and ``base_per_joint = M_base^-1 M_coupling``
    (6, N) ([`solve_base()`][spacegrasp_jax.core.dynamics.solve_base])."""
    m, h, I_O, M_coupling, M_joints = mass_matrix_parts_from_frames(robot, frames)
    return (m, h, I_O), M_coupling, M_joints, solve_base(m, h, I_O, M_coupling)


def forward_dynamics_from_frames(robot: Robot, frames, V_base, qd, Q, mass_blocks=None) -> jax.Array:
    """Generalised acceleration ``xdd = M^-1 (Q - bias)`` (13,) from [`frames_at_base()`][spacegrasp_jax.core.dynamics.frames_at_base],
    by composite rigid bodies and the block elimination of [`solve_mass_blocks()`][spacegrasp_jax.core.dynamics.solve_mass_blocks].

    ``mass_blocks``, if given, must be ``mass_blocks_from_frames(robot, frames)``, computed
    by a caller that needs it too (the closed loop's controller). Derivatives do not flow
    through it but through ``frames``.

    The derivative is that of inverse dynamics, not of the solve: differentiating
    ``M(x) xdd + bias(x, x_v) = Q`` at the solution gives
    ``d xdd = M^-1 (dQ - d[M xdd + bias]|xdd held)``, the bracket being Newton-Euler
    ([`inverse_dynamics_from_frames()`][spacegrasp_jax.core.dynamics.inverse_dynamics_from_frames]) at fixed ``xdd`` (as Carpentier and Mansard,
    RSS 2018, for Pinocchio). Neither autodiff mode goes through the composite inertias,
    the Schur complement or its factorisation, and the tangent's solve reuses the factor.
    """
    if mass_blocks is None:
        mass_blocks = mass_blocks_from_frames(robot, frames)
    return _forward_dynamics(robot, frames, V_base, qd, Q, mass_blocks)


@jax.custom_jvp
def _forward_dynamics(robot, frames, V_base, qd, Q, mass_blocks):
    return solve_mass_blocks(*mass_blocks, Q - bias_from_frames(robot, frames, V_base, qd))


@functools.partial(_forward_dynamics.defjvp, symbolic_zeros=True)
def _forward_dynamics_jvp(primals, tangents):
    robot, frames, V_base, qd, Q, (base, M_coupling, M_joints, base_per_joint) = primals
    L = cholesky(M_joints - spatial.matmul(M_coupling.T, base_per_joint))
    blocks = (base, M_coupling, base_per_joint)
    xdd = _solve_blocks(*blocks, Q - bias_from_frames(robot, frames, V_base, qd), lambda b: cho_solve(L, b))

    # d[M xdd + bias] with xdd held, over the inputs that carry a tangent (the mass
    # blocks' tangent is ignored: they are functions of the frames).
    is_zero = lambda t: isinstance(t, SymbolicZero)  # noqa: E731
    inputs, structure = jax.tree.flatten(primals[:4])
    input_tangents = jax.tree.leaves(tangents[:4], is_leaf=is_zero)
    active = [i for i, t in enumerate(input_tangents) if not is_zero(t)]

    def newton_euler_at(*active_inputs):
        leaves = list(inputs)
        for i, x in zip(active, active_inputs):
            leaves[i] = x
        return inverse_dynamics_from_frames(*jax.tree.unflatten(structure, leaves), xdd)

    rhs_dot = jnp.zeros_like(xdd) if is_zero(tangents[4]) else tangents[4]
    if active:
        _, id_dot = jax.jvp(newton_euler_at, [inputs[i] for i in active], [input_tangents[i] for i in active])
        rhs_dot = rhs_dot - id_dot
    return xdd, _solve_blocks(*blocks, rhs_dot, lambda b: cho_solve(L, b))


def mass_matrix(robot: Robot, R_base: jax.Array, q: jax.Array) -> jax.Array:
    """Generalised mass matrix ``M`` (13, 13), symmetric positive definite, SI units.

    Args:
        R_base: (3, 3) satellite attitude, satellite to inertial. q: (N,) rad.
    """
    frames = frames_at_base(robot, R_base, q)
    return mass_matrix_from_frames(robot, frames)


def bias_forces(robot: Robot, R_base, q, V_base, qd) -> jax.Array:
    """Coriolis and centrifugal forces ``bias(x, x_v)`` (13,), so that
    ``M xdot_v + bias = Q``.

    Args:
        R_base: (3, 3) satellite to inertial. q: (N,) rad.
        V_base: (6,) ``[v_s (m/s), w_s (rad/s)]`` in the inertial frame. qd: (N,) rad/s.
    """
    frames = frames_at_base(robot, R_base, q)
    return bias_from_frames(robot, frames, V_base, qd)


def mass_matrix_and_bias(robot: Robot, R_base, q, V_base, qd) -> tuple[jax.Array, jax.Array]:
    """``(M (13, 13), bias (13,))`` sharing one kinematics pass; arguments as
    [`bias_forces()`][spacegrasp_jax.core.dynamics.bias_forces]."""
    frames = frames_at_base(robot, R_base, q)
    return mass_matrix_from_frames(robot, frames), bias_from_frames(robot, frames, V_base, qd)


def forward_dynamics(robot: Robot, R_base, q, V_base, qd, Q) -> jax.Array:
    """Generalised acceleration ``xdot_v = M^-1 (Q - bias)`` (13,), by the block
    elimination of [`solve_mass_blocks()`][spacegrasp_jax.core.dynamics.solve_mass_blocks] (the closed loop's own solve).

    Args:
        R_base, q, V_base, qd: as [`bias_forces()`][spacegrasp_jax.core.dynamics.bias_forces].
        Q: (13,) ``[f_s (N), tau_s (N m), u (N m)]``, satellite force and torque in the
            inertial frame, joint torques.

    Returns:
        (13,) ``[dv_s/dt (m/s^2), dw_s/dt (rad/s^2), qdd (rad/s^2)]``, inertial frame.
    """
    return forward_dynamics_from_frames(robot, frames_at_base(robot, R_base, q), V_base, qd, Q)


def inverse_dynamics(robot: Robot, R_base, q, V_base, qd, xdd) -> jax.Array:
    """Generalised force ``Q = M xdd + bias`` (13,) ``[f_s (N), tau_s (N m), u (N m)]``
    that gives the acceleration ``xdd`` (13,) ``[dv_s/dt, dw_s/dt, qdd]`` (inertial frame),
    by recursive Newton-Euler; the inverse of [`forward_dynamics()`][spacegrasp_jax.core.dynamics.forward_dynamics]. Other arguments as
    [`bias_forces()`][spacegrasp_jax.core.dynamics.bias_forces]."""
    return inverse_dynamics_from_frames(robot, frames_at_base(robot, R_base, q), V_base, qd, xdd)


def kinetic_energy(robot: Robot, R_base, q, V_base, qd) -> jax.Array:
    """Kinetic energy ``x_v^T M x_v / 2`` (J) of the whole system."""
    x_v = jnp.concatenate([V_base, qd])
    return 0.5 * x_v @ mass_matrix(robot, R_base, q) @ x_v


def momentum_matrix(robot: Robot, p_base, R_base, q) -> jax.Array:
    """``H = [H2 H3]`` (6, 13) with ``[P; L] = H x_v`` (eq 6): ``P`` the total linear
    momentum (N s) and ``L`` the total angular momentum about the inertial origin (N m s),
    both in the inertial frame.

    Args:
        p_base: (3,) m, satellite CoM. R_base: (3, 3) satellite to inertial. q: (N,) rad.
    """
    # The first six rows of M are [P; L about the satellite CoM]; shift L to the origin.
    H = mass_matrix(robot, R_base, q)[:6]
    return H.at[3:].add(spatial.skew(p_base) @ H[:3])


def momentum_jacobians(robot: Robot, p_base, R_base, q) -> tuple[jax.Array, jax.Array]:
    """``H2`` (6, 6) and ``H3`` (6, N) of eq 6 (momentum about the inertial origin);
    arguments as [`momentum_matrix()`][spacegrasp_jax.core.dynamics.momentum_matrix]."""
    H = momentum_matrix(robot, p_base, R_base, q)
    return H[:, :6], H[:, 6:]


def system_momentum(robot: Robot, p_base, R_base, q, V_base, qd) -> jax.Array:
    """``[P; L]`` (6,): total linear momentum (N s) and angular momentum about the
    inertial origin (N m s), inertial frame. Arguments as [`momentum_matrix()`][spacegrasp_jax.core.dynamics.momentum_matrix] plus
    ``V_base`` (6,) ``[v_s, w_s]`` and ``qd`` (N,)."""
    return momentum_matrix(robot, p_base, R_base, q) @ jnp.concatenate([V_base, qd])


def system_com(robot: Robot, p_base, R_base, q) -> jax.Array:
    """(3,) m, centre of mass of the whole system in the inertial frame."""
    frames = forward_kinematics(robot, p_base, R_base, q)
    mass, _, _ = body_inertials(robot)
    p_com = body_com_positions(robot, frames)
    total = robot.satellite_mass + jnp.sum(mass)
    return (robot.satellite_mass * p_base + mass @ p_com) / total


def dynamic_jacobian(robot: Robot, R_base, q) -> jax.Array:
    """Dynamic (generalised) Jacobian ``J_dyn = J_m - J_s H2^-1 H3`` (6, N) of eq 8.

    Maps ``qd`` to the EE twist ``[v_ee; w_ee]`` (inertial frame) when the system's
    linear and angular momenta are zero.

    Args:
        R_base: (3, 3) satellite to inertial. q: (N,) rad.
    """
    return _dynamic_jacobian_at(robot, frames_at_base(robot, R_base, q))


def _dynamic_jacobian_at(robot: Robot, frames) -> jax.Array:
    _, J_joints = point_jacobian_blocks(frames, jnp.zeros(3, dtype=frames.p_ee.dtype), frames.p_ee, n_joints(robot))
    m, h, I_O, M_coupling, _ = mass_matrix_parts_from_frames(robot, frames)
    return dynamic_jacobian_from_parts(solve_base(m, h, I_O, M_coupling), J_joints, frames.p_ee)


def dynamic_jacobian_from_parts(base_per_joint: jax.Array, J_joints: jax.Array, r_ee: jax.Array) -> jax.Array:
    """``J_dyn = J_m - J_s M_base^-1 M_coupling`` (6, N), inertial frame, from
    ``base_per_joint = M_base^-1 M_coupling`` (6, N) ([`solve_base()`][spacegrasp_jax.core.dynamics.solve_base]), the joint block
    ``J_m`` (6, N) of the EE point Jacobian and ``r_ee`` (3,) m, the EE point from the
    satellite CoM. Zero momentum about the satellite CoM (rows 0-5 of ``M``) is the
    constraint of eq 6; ``J_s X = [X_v + X_w x r_ee; X_w]`` is applied as cross products."""
    X_v, X_w = jnp.split(base_per_joint, 2)
    return J_joints - jnp.concatenate([X_v + cross(X_w.T, r_ee).T, X_w])


def dynamic_jacobian_ee(robot: Robot, R_base, q) -> jax.Array:
    """``J_dyn^(EE)`` (6, N): the Dynamic Jacobian mapping ``qd`` to the EE twist expressed
    in the EE frame (used by eqs 17 and 21). Arguments as [`dynamic_jacobian()`][spacegrasp_jax.core.dynamics.dynamic_jacobian]."""
    frames = frames_at_base(robot, R_base, q)
    R_ee_T = frames.R_ee.T
    J_dyn = _dynamic_jacobian_at(robot, frames)
    return jnp.concatenate([R_ee_T @ J_dyn[:3], R_ee_T @ J_dyn[3:]])


__all__ = [
    "bias_forces",
    "bias_from_frames",
    "dynamic_jacobian",
    "dynamic_jacobian_ee",
    "dynamic_jacobian_from_parts",
    "forward_dynamics_from_frames",
    "frames_at_base",
    "inverse_dynamics",
    "inverse_dynamics_from_frames",
    "mass_blocks_from_frames",
    "mass_matrix_from_frames",
    "forward_dynamics",
    "kinetic_energy",
    "mass_matrix",
    "mass_matrix_and_bias",
    "momentum_jacobians",
    "momentum_matrix",
    "system_com",
    "system_momentum",
]
