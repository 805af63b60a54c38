"""The target: a rigid body that carries the LAR frame and the contact sphere.

Every scenario has one, and every state carries its [`TargetState`][spacegrasp_jax.core.target.TargetState]:

* **Fixed** (the paper's): at rest in inertial space, an infinitely heavy body
  ([`fixed_target_body()`][spacegrasp_jax.core.target.fixed_target_body],
  [`fixed_target_state()`][spacegrasp_jax.core.target.fixed_target_state]). Its state's ``free``
  flag is ``False``: its rate is zero, its state never changes, and the LAR frame is the
  scenario's ``p_lar``, ``R_lar`` exactly.
* **Free-floating** (documentation, modelling notes): its body frame is the LAR frame moved
  to the target's centre of mass, ``com_in_lar`` (LAR coordinates), so its axes are the LAR
  axes and its inertia is about its CoM in those axes. Torque-free except for the contact,
  whose force acts on the EE and, opposite, on the target at the same point (the EE point).
  Its state is integrated in the same RK4 step as the chaser's.

The flag is static (part of the state's structure): it is decided once, when the scenario
is made, and a compiled program serves one kind of target.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax.core import spatial


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TargetBody:
    """The target's mass properties (array leaves: vmappable, differentiable).

    Attributes:
        mass: () kg.
        inertia: (3, 3) kg m^2, about the target's CoM, in its body (= LAR) axes.
        com_in_lar: (3,) m, the target's CoM in LAR coordinates.
    """

    mass: jax.Array
    inertia: jax.Array
    com_in_lar: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TargetState:
    """Position and velocity of the target.

    Attributes:
        p: (3,) m, the target's CoM, inertial frame (a fixed target's: the LAR origin).
        quat: (4,) unit quaternion ``[w, x, y, z]``, body (LAR axes) to inertial.
        v: (3,) m/s, the CoM's velocity, inertial frame.
        w: (3,) rad/s, angular velocity in body (LAR) axes.
        free: ``True`` for a free-floating target, ``False`` for the paper's fixed one
            (static).
    """

    p: jax.Array
    quat: jax.Array
    v: jax.Array
    w: jax.Array
    free: bool = dataclasses.field(default=True, metadata=dict(static=True))

    @property
    def R(self) -> jax.Array:
        """(3, 3) body (LAR axes) to inertial rotation."""
        return spatial.quat_to_rotation(self.quat)

    def projected(self) -> TargetState:
        """The state back on its manifold after an integration step: a free target's
        quaternion renormalised; a fixed target's state as it is (it never moves)."""
        if not self.free:
            return self
        return dataclasses.replace(self, quat=self.quat / jnp.linalg.norm(self.quat))

    def at_rest(self) -> TargetState:
        """The rate of a fixed target: zeros, in this state's structure."""
        return jax.tree.map(jnp.zeros_like, self)


def fixed_target_body(dtype=jnp.float64) -> TargetBody:
    """The paper's fixed target as a body: infinite mass and inertia, its CoM at the LAR
    origin. Nothing reads them: a fixed state's rate is zero
    ([`TargetState.at_rest()`][spacegrasp_jax.core.target.TargetState.at_rest])."""
    return TargetBody(
        mass=jnp.asarray(np.inf, dtype),
        inertia=jnp.asarray(np.diag(np.full(3, np.inf)), dtype),
        com_in_lar=jnp.zeros(3, dtype),
    )


def fixed_target_state(p_lar, R_lar) -> TargetState:
    """The paper's fixed target with its LAR frame at ``p_lar`` (3,) m, ``R_lar`` (3, 3)
    (inertial), at rest."""
    zero = jnp.zeros_like(p_lar)
    return TargetState(p=p_lar, quat=spatial.rotation_to_quat(R_lar), v=zero, w=zero, free=False)


def initial_target_state(body: TargetBody, p_lar, R_lar, velocity_lar, angular_velocity_lar) -> TargetState:
    """The target's state with its LAR frame at ``p_lar`` (3,) m, ``R_lar`` (3, 3) (inertial),
    its CoM moving at ``velocity_lar`` (3,) m/s and rotating at ``angular_velocity_lar`` (3,)
    rad/s, both in LAR axes."""
    return TargetState(
        p=p_lar + spatial.matvec(R_lar, body.com_in_lar),
        quat=spatial.rotation_to_quat(R_lar),
        v=spatial.matvec(R_lar, velocity_lar),
        w=jnp.asarray(angular_velocity_lar, dtype=p_lar.dtype),
    )


def lar_frame(body: TargetBody, state: TargetState) -> tuple[jax.Array, jax.Array]:
    """``(p_lar (3,) m, R_lar (3, 3))``: the LAR frame the target carries, inertial frame."""
    R = state.R
    return state.p - spatial.matvec(R, body.com_in_lar), R


def lar_velocity(body: TargetBody, state: TargetState) -> tuple[jax.Array, jax.Array]:
    """``(v_lar (3,) m/s, w (3,) rad/s)``: the velocity of the LAR origin and the target's
    angular velocity, both inertial frame."""
    R = state.R
    w = spatial.matvec(R, state.w)
    return state.v - spatial.cross(w, spatial.matvec(R, body.com_in_lar)), w


def target_rate(body: TargetBody, state: TargetState, force: jax.Array, point: jax.Array) -> TargetState:
    """The rate of ``state`` under ``force`` (3,) N (inertial) applied at ``point`` (3,) m
    (inertial): Newton for the CoM, Euler's equations ``I dw/dt = n - w x I w`` in body axes."""
    R = state.R
    torque_body = spatial.matvec(R.T, spatial.cross(point - state.p, force))
    spin = spatial.cross(state.w, spatial.matvec(body.inertia, state.w))
    return TargetState(
        p=state.v,
        quat=spatial.quat_derivative(state.quat, spatial.matvec(R, state.w)),
        v=force / body.mass,
        w=spatial.matvec(spatial.symmetric_inverse(body.inertia), torque_body - spin),
    )


def target_momentum(body: TargetBody, state: TargetState) -> jax.Array:
    """``[P (N s); L about the inertial origin (N m s)]`` (6,), inertial frame; zeros for a
    fixed target (it is the inertial frame's anchor: what it absorbs is not counted)."""
    if not state.free:
        return jnp.zeros(6, state.p.dtype)
    P = body.mass * state.v
    L = spatial.matvec(state.R, spatial.matvec(body.inertia, state.w)) + spatial.cross(state.p, P)
    return jnp.concatenate([P, L])


__all__ = [
    "TargetBody",
    "TargetState",
    "fixed_target_body",
    "fixed_target_state",
    "initial_target_state",
    "lar_frame",
    "lar_velocity",
    "target_momentum",
    "target_rate",
]
