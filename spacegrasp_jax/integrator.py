"""The mechanical state of the free-floating system and its fixed-step RK4 integration.

The satellite attitude is a unit quaternion (no Euler-angle singularity in the state); it
is renormalised after every step ([`PlantState.projected()`][spacegrasp_jax.integrator.PlantState.projected]),
a projection that keeps RK4's 4th order.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from spacegrasp_jax import spatial
from spacegrasp_jax.dynamics import forward_dynamics
from spacegrasp_jax.model import Robot
from spacegrasp_jax.target import TargetState, fixed_target_state


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
        target: the target's state ([`TargetState`][spacegrasp_jax.target.TargetState]):
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
    """A [`PlantState`][spacegrasp_jax.integrator.PlantState] from a rotation-matrix attitude
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
    default of [`plant_state()`][spacegrasp_jax.integrator.plant_state]); returned as a
    [`PlantState`][spacegrasp_jax.integrator.PlantState] whose fields hold the rates.

    Raises:
        ValueError: ``state`` holds a free-floating target, whose motion needs its body and
            the contact (``spacegrasp_jax.simulate.plant_derivative``).
    """
    if state.target.free:
        raise ValueError(
            "state: a free-floating target moves with its body and the contact; "
            "integrate it with spacegrasp_jax.simulate.plant_derivative"
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


#: RK4's stages 2-4: the fraction of ``dt`` at which each is evaluated along the previous
#: stage's rate, and its weight (over 6) in the step's average rate.
_LATER_STAGES = ((0.5, 2.0), (0.5, 2.0), (1.0, 1.0))


def _advance(base, rate, h):
    """``base + h rate``, leaf by leaf (a state moved along a rate for a time ``h``)."""
    return jax.tree.map(lambda x, dx: x + h * dx, base, rate)


def rk4_step(derivative: Callable[[PlantState], PlantState], state: PlantState, dt) -> PlantState:
    """One classical Runge-Kutta step of length ``dt`` (s) of ``d state/dt = derivative(state)``.

    ``derivative`` closes over anything held constant during the step (zero-order hold of
    the joint torques); forces that belong to the plant (contact) are evaluated inside it,
    at every stage.

    Stages 2-4 are one ``lax.scan`` over their coefficients, its body under
    ``jax.checkpoint``: the compiled step holds one copy of ``derivative`` for them instead
    of three, and its derivative one copy of the stage's adjoint. XLA's CPU runtime pays
    for every distinct kernel of a loop body, so one copy makes a faster gradient
    (documentation, Performance). The checkpoint limits what the loop
    saves to the stage's input state, so the backward loop's arrays stay within 64
    numbers, like the forward step's. ``prevent_cse=False``: inside a loop there is nothing
    for XLA to merge the recomputation with, and the optimisation barriers that the default
    inserts would keep XLA from fusing across them.
    """

    @functools.partial(jax.checkpoint, prevent_cse=False)
    def later_stage(carry, coefficients):
        previous_rate, weighted_sum = carry
        fraction, weight = coefficients
        rate = derivative(_advance(state, previous_rate, fraction * dt))
        return (rate, _advance(weighted_sum, rate, weight)), None

    k1 = derivative(state)
    coefficients = jnp.asarray(_LATER_STAGES, dtype=state.q.dtype).T
    (_, weighted_sum), _ = jax.lax.scan(later_stage, (k1, k1), tuple(coefficients))
    return _advance(state, weighted_sum, dt / 6).projected()


#: RK4's four stages: the first at the step's start (fraction 0 along a zero rate, weight 1),
#: then ``_LATER_STAGES``.
_ALL_STAGES = ((0.0, 1.0),) + _LATER_STAGES


def _four_stages(stage, state: PlantState, dt, held, extra_xs=()):
    """RK4's four stages as one ``lax.scan`` of ``stage((previous rate, weighted sum,
    held), (fraction, weight, *extra_xs)) -> (carry, out)``; ``(next state, held, outs)``."""
    fractions, weights = jnp.asarray(_ALL_STAGES, dtype=state.q.dtype).T
    zero = jax.tree.map(jnp.zeros_like, state)
    (_, weighted_sum, held), outs = jax.lax.scan(stage, (zero, zero, held), (fractions, weights, *extra_xs))
    return _advance(state, weighted_sum, dt / 6).projected(), held, outs


def rk4_step_sharing_kinematics(
    kinematics: Callable[[PlantState], Any],
    rate: Callable[[PlantState, Any, Any], PlantState],
    state: PlantState,
    dt,
    u,
) -> tuple[PlantState, Any]:
    """One classical Runge-Kutta step of ``d state/dt = rate(state, kinematics(state), u)``
    (``u``, the joint torques, held over the step), its four stages one ``lax.scan``, and
    the kinematics at the step's start, for the caller's log.

    The compiled step holds one copy of ``kinematics`` and of ``rate`` for the four stages,
    where a first stage written beside the caller's own use of the start's kinematics and
    the later stages in a scan hold two: less code to compile for the same arithmetic in the
    same order. A forward loop's step: reverse mode would keep every stage's kinematics, so
    the checkpointed loop uses
    [`rk4_step_from_start_kinematics()`][spacegrasp_jax.integrator.rk4_step_from_start_kinematics].

    Returns:
        ``(next state, kinematics(state))``.
    """

    def stage(carry, coefficients):
        previous_rate, weighted_sum, held = carry
        fraction, weight = coefficients
        stage_state = _advance(state, previous_rate, fraction * dt)
        stage_kinematics = kinematics(stage_state)
        stage_rate = rate(stage_state, stage_kinematics, held)
        return (stage_rate, _advance(weighted_sum, stage_rate, weight), held), stage_kinematics

    next_state, _, stages = _four_stages(stage, state, dt, u)
    return next_state, jax.tree.map(lambda x: x[0], stages)


def rk4_step_from_start_kinematics(
    kinematics: Callable[[PlantState], Any],
    rate: Callable[[PlantState, Any, Any], PlantState],
    state: PlantState,
    dt,
    u,
    start_kinematics=None,
) -> PlantState:
    """One classical Runge-Kutta step of ``d state/dt = rate(state, kinematics(state), u)``
    (``u``, the joint torques, held over the step), the step of a loop that is
    differentiated; ``start_kinematics``: ``kinematics(state)`` where the caller has
    computed it already (for its controller and its log), else ``None``.

    The four stages are one ``lax.scan`` whose body is under ``jax.checkpoint``
    (``prevent_cse=False``, as in [`rk4_step()`][spacegrasp_jax.integrator.rk4_step]); the
    first stage reads ``start_kinematics`` through a ``lax.cond`` where given, and every
    other stage computes its own. The compiled step and its derivative hold one copy of
    ``rate`` where a first stage written beside the controller and the later stages in a
    scan hold two, so the program is smaller and compiles faster (documentation,
    Performance); the tape keeps each stage's input (and ``start_kinematics``) and the
    backward pass recomputes each stage once, as there.

    Returns:
        The state after the step (projected on its manifold).
    """

    @functools.partial(jax.checkpoint, prevent_cse=False)
    def stage(carry, coefficients):
        previous_rate, weighted_sum, held = carry
        fraction, weight, first = coefficients
        stage_state = _advance(state, previous_rate, fraction * dt)
        if start_kinematics is None:
            stage_kinematics = kinematics(stage_state)
        else:
            stage_kinematics = jax.lax.cond(first, lambda _: start_kinematics, kinematics, stage_state)
        stage_rate = rate(stage_state, stage_kinematics, held)
        return (stage_rate, _advance(weighted_sum, stage_rate, weight), held), None

    first = jnp.arange(len(_ALL_STAGES)) == 0
    next_state, _, _ = _four_stages(stage, state, dt, u, (first,))
    return next_state


def rk4_step_with_start(
    kinematics: Callable[[PlantState], Any],
    rate: Callable[[PlantState, Any, Any], PlantState],
    at_start: Callable[[Any], tuple[Any, Any]],
    state: PlantState,
    dt,
) -> tuple[PlantState, Any, Any]:
    """One classical Runge-Kutta step of ``d state/dt = rate(state, kinematics(state), held)``
    whose ``held`` (the joint torques) is computed at the step's start from its kinematics:
    the closed loop's controller.

    As [`rk4_step_sharing_kinematics()`][spacegrasp_jax.integrator.rk4_step_sharing_kinematics],
    four stages in one scan; at the first, ``at_start(kinematics) -> (held, out)`` runs on
    that stage's kinematics (a ``lax.cond``: the controller and the log row once a step),
    and ``held`` is held over the four stages. One copy of ``kinematics``, of ``rate`` and
    of ``at_start`` in the compiled step.

    Returns:
        ``(next state, held, out)``.
    """
    held_and_out = jax.eval_shape(at_start, jax.eval_shape(kinematics, state))
    nothing = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), held_and_out)

    # (held, out) ride in the carry: the later stages pass them on, writing nothing.
    def stage(carry, coefficients):
        previous_rate, weighted_sum, started = carry
        fraction, weight, first = coefficients
        stage_state = _advance(state, previous_rate, fraction * dt)
        stage_kinematics = kinematics(stage_state)
        started = jax.lax.cond(first, at_start, lambda _: started, stage_kinematics)
        stage_rate = rate(stage_state, stage_kinematics, started[0])
        return (stage_rate, _advance(weighted_sum, stage_rate, weight), started), None

    first = jnp.arange(len(_ALL_STAGES)) == 0
    next_state, (held, out), _ = _four_stages(stage, state, dt, nothing, (first,))
    return next_state, held, out


def simulate_free_floating(
    robot: Robot, state: PlantState, joint_torques: jax.Array, dt
) -> tuple[PlantState, PlantState]:
    """Integrate the free-floating system (no force on the satellite) with the joint
    torques ``joint_torques`` (N, 7) N m, each held over one step of ``dt`` s.

    Returns:
        ``(final_state, trajectory)``, ``trajectory`` a [`PlantState`][spacegrasp_jax.integrator.PlantState] of stacked
        states (N + 1 leading entries, the initial state first).
    """

    def step(current, u):
        Q = jnp.concatenate([jnp.zeros(6, dtype=u.dtype), u])
        new = rk4_step(lambda s: free_floating_derivative(robot, s, Q), current, dt)
        return new, new

    final, path = jax.lax.scan(step, state, joint_torques)
    trajectory = jax.tree.map(lambda first, rest: jnp.concatenate([first[None], rest]), state, path)
    return final, trajectory
