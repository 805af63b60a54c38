"""The mechanical state of the free-floating system and its fixed-step RK4 integration.

The satellite attitude is a unit quaternion (no Euler-angle singularity in the state); it
is renormalised after every step ([`PlantState.projected()`][spacegrasp_jax.core.integrator.PlantState.projected]),
a projection that keeps RK4's 4th order.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from spacegrasp_jax.core import spatial
from spacegrasp_jax.core.dynamics import forward_dynamics
from spacegrasp_jax.core.model import Robot
from spacegrasp_jax.core.target import TargetState, fixed_target_state


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PlantState:
    """Position and velocity of the satellite-manipulator system.

    Attributes:
        p_base: (3,) m, satellite CoM in the inertial frame.
        quat_base: (4,) unit quaternion ``[w, x, y, z]``, satellite to inertial.
        q: (N,) rad, joint angles.
        V_base: (6,) ``[v_s (m/s), w_s (rad/s)]``, satellite CoM velocity and angular
            velocity in the inertial frame.
        qd: (N,) rad/s, joint rates.
        target: the target's state ([`TargetState`][spacegrasp_jax.core.target.TargetState]):
            the paper's fixed target or a free-floating one.
    """

    p_base: jax.Array
    quat_base: jax.Array
    q: jax.Array
    V_base: jax.Array
    qd: jax.Array
    target: TargetState

    @property
    def R_base(self) -> jax.Array:
        """(3, 3) satellite attitude, satellite to inertial."""
        return spatial.quat_to_rotation(self.quat_base)

    def projected(self) -> PlantState:
        """The state back on its manifold after an integration step: the attitude
        quaternions renormalised (the satellite's; a free target's)."""
        return dataclasses.replace(
            self, quat_base=self.quat_base / jnp.linalg.norm(self.quat_base), target=self.target.projected()
        )


def plant_state(p_base, R_base, q, V_base, qd, target: TargetState | None = None) -> PlantState:
    """A [`PlantState`][spacegrasp_jax.core.integrator.PlantState] from a rotation-matrix attitude
    ``R_base`` (3, 3); ``target``: the target's state (by default a fixed target with its LAR
    frame at the inertial origin, for a chaser on its own)."""
    if target is None:
        target = fixed_target_state(jnp.zeros(3, jnp.float64), jnp.eye(3, dtype=jnp.float64))
    return PlantState(
        p_base=jnp.asarray(p_base, dtype=jnp.float64),
        quat_base=spatial.rotation_to_quat(jnp.asarray(R_base, dtype=jnp.float64)),
        q=jnp.asarray(q, dtype=jnp.float64),
        V_base=jnp.asarray(V_base, dtype=jnp.float64),
        qd=jnp.asarray(qd, dtype=jnp.float64),
        target=target,
    )


def free_floating_derivative(robot: Robot, state: PlantState, Q: jax.Array) -> PlantState:
    """Time derivative of ``state`` under the generalised force ``Q`` (13,)
    ``[f_s, tau_s, u]`` (inertial frame, N and N m), for a chaser beside a fixed target (the
    default of [`plant_state()`][spacegrasp_jax.core.integrator.plant_state]); returned as a
    [`PlantState`][spacegrasp_jax.core.integrator.PlantState] whose fields hold the rates.

    Raises:
        ValueError: ``state`` holds a free-floating target, whose motion needs its body and
            the contact (``spacegrasp_jax.loop.simulate.plant_derivative``).
    """
    if state.target.free:
        raise ValueError(
            "state: a free-floating target moves with its body and the contact; "
            "integrate it with spacegrasp_jax.loop.simulate.plant_derivative"
        )
    xdd = forward_dynamics(robot, state.R_base, state.q, state.V_base, state.qd, Q)
    return state_rate(state, xdd, state.target.at_rest())


def state_rate(state: PlantState, xdd: jax.Array, target_rate: TargetState) -> PlantState:
    """The rate of ``state`` given the chaser's generalised acceleration ``xdd`` (13,) and
    the target's rate."""
    v_s, w_s = jnp.split(state.V_base, 2)
    V_base_rate, qd_rate = jnp.split(xdd, [6])
    return PlantState(
        p_base=v_s,
        quat_base=spatial.quat_derivative(state.quat_base, w_s),
        q=state.qd,
        V_base=V_base_rate,
        qd=qd_rate,
        target=target_rate,
    )


#: RK4's four stages: the fraction of ``dt`` at which each is evaluated along the previous
#: stage's rate (the first at the step's start), and its weight (over 6) in the step's
#: average rate.
_STAGES = ((0.0, 1.0), (0.5, 2.0), (0.5, 2.0), (1.0, 1.0))


def _advance(base, rate, h):
    """``base + h rate``, leaf by leaf (a state moved along a rate for a time ``h``)."""
    return jax.tree.map(lambda x, dx: x + h * dx, base, rate)


def rk4_step(
    kinematics: Callable[[PlantState], Any],
    rate: Callable[[PlantState, Any, Any], PlantState],
    state: PlantState,
    dt,
    held=None,
    *,
    at_start: Callable[[Any], tuple[Any, Any]] | None = None,
    start_kinematics=None,
    checkpoint: bool = False,
) -> tuple[PlantState, Any, Any]:
    """One classical Runge-Kutta step of length ``dt`` (s) of ``d state/dt = rate(state,
    kinematics(state), held)``, ``held`` (the joint torques) held over the step (zero-order
    hold); forces that belong to the plant (contact) are evaluated inside ``rate``, at every
    stage.

    The four stages are one ``lax.scan``: the compiled step holds one copy of ``kinematics``
    and of ``rate``, and its derivative one copy of their adjoints, where a first stage
    written beside the later ones would hold two. XLA's CPU runtime pays for every distinct
    kernel of a loop body, so one copy compiles faster and makes a faster gradient
    (documentation, Performance). The closed loop's three ways to run a step are options:

    - ``at_start(kinematics) -> (held, out)``: ``held`` is computed at the first stage from
      its kinematics (a ``lax.cond``: the controller and the log row of a one-step control
      period, run once a step) and held over the four stages; ``held`` is not passed.
    - ``checkpoint``: the stage's body is under ``jax.checkpoint`` for reverse mode: the
      tape keeps each stage's input (and ``start_kinematics``) and the backward pass
      recomputes each stage once. ``prevent_cse=False``: inside a loop there is nothing for
      XLA to merge the recomputation with, and the optimisation barriers that the default
      inserts would keep XLA from fusing across them.
    - ``start_kinematics``: ``kinematics(state)`` where the caller has computed it already
      (for its controller or its log): the first stage reads it through a ``lax.cond``.

    The options change the program, never the arithmetic or its order.

    Args:
        kinematics: ``state -> what rate reads of it`` (anything; ``lambda s: ()`` for a
            plain ODE).
        rate: ``(state, kinematics, held) -> d state/dt``.
        state, dt: the state at the step's start and the step (s).
        held: held over the step (``None`` with ``at_start``).

    Returns:
        ``(next state (projected on its manifold), held, out)``: ``out`` is ``at_start``'s,
        or without it the kinematics at the step's start (``None`` with ``checkpoint``,
        whose tape would keep every stage's).
    """
    if at_start is not None:
        held_and_out = jax.eval_shape(at_start, jax.eval_shape(kinematics, state))
        held = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), held_and_out)
    keeps_kinematics = at_start is None and not checkpoint

    # With at_start, (held, out) ride in the carry: the later stages pass them on.
    def stage(carry, coefficients):
        previous_rate, weighted_sum, carried = carry
        fraction, weight, first = coefficients
        stage_state = _advance(state, previous_rate, fraction * dt)
        if start_kinematics is None:
            stage_kinematics = kinematics(stage_state)
        else:
            stage_kinematics = jax.lax.cond(first, lambda _: start_kinematics, kinematics, stage_state)
        if at_start is not None:
            carried = jax.lax.cond(first, at_start, lambda _: carried, stage_kinematics)
        stage_rate = rate(stage_state, stage_kinematics, carried if at_start is None else carried[0])
        carry = (stage_rate, _advance(weighted_sum, stage_rate, weight), carried)
        return carry, (stage_kinematics if keeps_kinematics else None)

    if checkpoint:
        stage = jax.checkpoint(stage, prevent_cse=False)
    fractions, weights = jnp.asarray(_STAGES, dtype=state.q.dtype).T
    first = jnp.arange(len(_STAGES)) == 0
    zero = jax.tree.map(jnp.zeros_like, state)
    (_, weighted_sum, carried), stage_kinematics = jax.lax.scan(stage, (zero, zero, held), (fractions, weights, first))
    next_state = _advance(state, weighted_sum, dt / 6).projected()
    if at_start is not None:
        return next_state, carried[0], carried[1]
    out = jax.tree.map(lambda x: x[0], stage_kinematics) if keeps_kinematics else None
    return next_state, carried, out


def simulate_free_floating(
    robot: Robot, state: PlantState, joint_torques: jax.Array, dt
) -> tuple[PlantState, PlantState]:
    """Integrate the free-floating system (no force on the satellite) with the joint
    torques ``joint_torques`` (N, 7) N m, each held over one step of ``dt`` s.

    Returns:
        ``(final_state, trajectory)``, ``trajectory`` a [`PlantState`][spacegrasp_jax.core.integrator.PlantState] of stacked
        states (N + 1 leading entries, the initial state first).
    """

    def step(current, u):
        Q = jnp.concatenate([jnp.zeros(6, dtype=u.dtype), u])
        new, _, _ = rk4_step(lambda s: (), lambda s, _, Q: free_floating_derivative(robot, s, Q), current, dt, Q)
        return new, new

    final, path = jax.lax.scan(step, state, joint_torques)
    trajectory = jax.tree.map(lambda first, rest: jnp.concatenate([first[None], rest]), state, path)
    return final, trajectory
