"""The closed loop: contact -> sensor -> controller -> joint PID -> RK4, as one ``lax.scan``.

Each step of length ``dt`` (modelling notes):
1. the controller reads the state and the F/T sensor once (eqs 18-19), computes the desired
   joint rates (admittance eqs 9-17 or Cartesian eqs 21-22) and the PID joint torques;
2. the torques are held over the step (zero-order hold) while RK4 integrates the plant, the
   contact force of eq 20 being evaluated at every RK4 stage from that stage's state.

``rollout`` is pure: jit, vmap (over scenarios, robots or gains) and grad apply to it.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax import spatial, stages
from spacegrasp_jax.contact import (
    contact_force_exact,
    contact_force_smooth,
    rotate_wrench,
    sensor_wrench,
    wrench_at_ee,
)
from spacegrasp_jax.control.gains import Gains
from spacegrasp_jax.control.law import ControlInputs, ControllerState
from spacegrasp_jax.control.registry import as_controller
from spacegrasp_jax.dynamics import (
    dynamic_jacobian_from_parts,
    forward_dynamics_from_frames,
    frames_at_base,
    mass_matrix_parts_from_frames,
    solve_base,
)
from spacegrasp_jax.integrator import PlantState, rk4_step, state_rate
from spacegrasp_jax.kinematics import Frames, point_jacobian_blocks
from spacegrasp_jax.model import Robot, n_joints
from spacegrasp_jax.realism import Realism, Stage, ideal
from spacegrasp_jax.scenario import Scenario
from spacegrasp_jax.target import lar_frame, lar_velocity, target_momentum, target_rate
from spacegrasp_jax.trajectory import desired_state


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SimState:
    """The scan carry: the plant and the controller's memory."""

    plant: PlantState
    controller: ControllerState


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Log:
    """Time series of a rollout, one row per step (N rows, at t = 0, dt, ..., (N-1) dt),
    each taken at the start of the step together with the torque applied over it.

    Attributes:
        t: (N,) s.
        pose_ee: (N, 6) EE pose in LAR, ``[p (m); roll, pitch, yaw (rad)]``.
        pose_des: (N, 6) desired EE pose in LAR.
        twist_ee: (N, 6) EE twist in LAR ``[v (m/s); w (rad/s)]`` (true, base motion included).
        contact_force: (N, 3) N, force of the contact on the EE, LAR axes.
        momentum: (N, 6) ``[P (N s); L about the inertial origin (N m s)]``, inertial frame.
        V_base: (N, 6) satellite ``[v_s (m/s); w_s (rad/s)]``, inertial frame.
        u: (N, J) N m, joint torques (J: the arm's number of joints, the paper's 7).
        fts_force: (N, 3) N, F/T sensor force, sensor (frame J, the last) axes.
        fts_torque: (N, 3) N m, F/T sensor torque about the sensor point, sensor axes.
        V_ref: (N, 6) reference twist in LAR (admittance; zeros for the other laws).
        qd_des: (N, J) rad/s, desired joint rates (with a delay: those the PID applies;
            zeros for a law that commands torques).
        q: (N, J) rad. qd: (N, J) rad/s.
        fts_force_measured, fts_torque_measured: (N, 3) N, N m, the F/T sensor's reading
            the controller used (noise, bias, low-pass; held over the control period),
            sensor axes; ``None`` in the ideal loop, where it is ``fts_force``/``fts_torque``.
        q_measured, qd_measured: (N, J) rad, rad/s, the joint sensors' readings at the
            latest servo tick (the PID's; at the start of a control period also the
            controller's); ``None`` in the ideal loop.
        qd_des_computed: (N, J) rad/s, the desired joint rates the law computed in this
            control period (they reach the PID ``delay_periods`` later); ``None`` in the
            ideal loop, where they are ``qd_des``.
        target_position: (N, 3) m, the free-floating target's CoM, inertial frame.
        target_quat: (N, 4) its attitude ``[w, x, y, z]``, body (LAR axes) to inertial.
        target_velocity: (N, 3) m/s, its CoM's velocity, inertial frame.
        target_angular_velocity: (N, 3) rad/s, its angular velocity, body (LAR) axes.
        momentum_total: (N, 6) ``[P (N s); L (N m s)]``, the chaser's plus the target's
            momentum about the inertial origin. The target's fields are ``None`` for the
            paper's stationary target.
    """

    t: jax.Array
    pose_ee: jax.Array
    pose_des: jax.Array
    twist_ee: jax.Array
    contact_force: jax.Array
    momentum: jax.Array
    V_base: jax.Array
    u: jax.Array
    fts_force: jax.Array
    fts_torque: jax.Array
    V_ref: jax.Array
    qd_des: jax.Array
    q: jax.Array
    qd: jax.Array
    fts_force_measured: jax.Array | None = None
    fts_torque_measured: jax.Array | None = None
    q_measured: jax.Array | None = None
    qd_measured: jax.Array | None = None
    qd_des_computed: jax.Array | None = None
    target_position: jax.Array | None = None
    target_quat: jax.Array | None = None
    target_velocity: jax.Array | None = None
    target_angular_velocity: jax.Array | None = None
    momentum_total: jax.Array | None = None


def lar_pose(scenario: Scenario, plant: PlantState) -> tuple[jax.Array, jax.Array]:
    """``(p_lar (3,) m, R_lar (3, 3))``, the LAR frame at ``plant`` (inertial): the
    scenario's for a stationary target, carried by the target's state for a free one."""
    if scenario.target is None:
        return scenario.p_lar, scenario.R_lar
    return lar_frame(scenario.target, plant.target)


def contact_force_lar(scenario: Scenario, p_ee: jax.Array, p_lar=None, R_lar=None) -> jax.Array:
    """Force (3,) N of the contact sphere on the EE point ``p_ee`` (3,) m (inertial), in LAR
    axes, by the scenario's contact law; the LAR frame at ``p_lar``, ``R_lar`` (default the
    scenario's)."""
    p_lar = scenario.p_lar if p_lar is None else p_lar
    R_lar = scenario.R_lar if R_lar is None else R_lar
    p_from_centre = spatial.matvec(R_lar.T, p_ee - p_lar) - scenario.sphere_centre
    if scenario.contact_law == "exact":
        return contact_force_exact(p_from_centre, scenario.sphere_radius, scenario.contact_stiffness)
    return contact_force_smooth(
        p_from_centre, scenario.sphere_radius, scenario.contact_stiffness, scenario.contact_sharpness
    )


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PlantKinematics:
    """What both the controller and the plant's rate need at one state, computed once.

    Matrices are kept as blocks (satellite, joints), none larger than 64 numbers: XLA's CPU
    runtime then runs the step's kernels in sequence instead of as a task graph where loops
    run kernel by kernel (documentation, Performance).

    Attributes:
        frames: [`Frames`][spacegrasp_jax.kinematics.Frames] with the satellite CoM at the
            origin ([`frames_at_base()`][spacegrasp_jax.dynamics.frames_at_base]).
        base: ``(m, h, I_O)``, the mass matrix's satellite block
            ``M_base = [[m 1, -h x], [h x, I_O]]`` ([`mass_matrix_parts_from_frames()`][spacegrasp_jax.dynamics.mass_matrix_parts_from_frames]).
        M_coupling, M_joints: (6, N), (N, N) blocks of the mass matrix.
        base_per_joint: (6, N) ``M_base^-1 M_coupling``: minus the satellite velocity per
            unit joint rate at zero momentum (eq 6).
        J_joints: (6, 7) joint block ``J_m`` of the EE point Jacobian, inertial frame. Its
            satellite block ``J_s = [[1, -r x], [0, 1]]`` needs only ``r = frames.p_ee``,
            the EE point from the satellite CoM, and is applied as cross products.
        contact_force_lar: (3,) N, force of the contact sphere on the EE, LAR axes.
        p_lar, R_lar: (3,) m, (3, 3), the LAR frame at this state, inertial ([`lar_pose()`][spacegrasp_jax.simulate.lar_pose]).
    """

    frames: Frames
    base: tuple
    M_coupling: jax.Array
    M_joints: jax.Array
    base_per_joint: jax.Array
    J_joints: jax.Array
    contact_force_lar: jax.Array
    p_lar: jax.Array
    R_lar: jax.Array


def plant_kinematics(robot: Robot, scenario: Scenario, state: PlantState, with_contact: bool = True) -> PlantKinematics:
    """One kinematics pass, the mass matrix, the EE Jacobian and (``with_contact``, else
    zeros) the contact force at ``state``."""
    frames = frames_at_base(robot, state.R_base, state.q)  # satellite CoM at the origin
    m, h, I_O, M_coupling, M_joints = mass_matrix_parts_from_frames(robot, frames)
    _, J_joints = point_jacobian_blocks(frames, jnp.zeros(3, dtype=state.q.dtype), frames.p_ee, n_joints(robot))
    p_lar, R_lar = lar_pose(scenario, state)
    force = (
        contact_force_lar(scenario, state.p_base + frames.p_ee, p_lar, R_lar)
        if with_contact
        else jnp.zeros(3, dtype=state.q.dtype)
    )
    return PlantKinematics(
        frames=frames,
        base=(m, h, I_O),
        M_coupling=M_coupling,
        M_joints=M_joints,
        base_per_joint=solve_base(m, h, I_O, M_coupling),
        J_joints=J_joints,
        contact_force_lar=force,
        p_lar=p_lar,
        R_lar=R_lar,
    )


def plant_rate(
    robot: Robot, scenario: Scenario, state: PlantState, kinematics: PlantKinematics, u: jax.Array
) -> PlantState:
    """State rate under joint torques ``u`` (7,) N m and the contact force, given
    ``kinematics = plant_kinematics(robot, scenario, state)``."""
    k = kinematics
    force = spatial.matvec(k.R_lar, k.contact_force_lar)
    # The contact force acts at the EE point: generalised force J_point^T [f; 0].
    Q = jnp.concatenate(
        [force, spatial.cross(k.frames.p_ee, force), spatial.matvec(jnp.split(k.J_joints, 2)[0].T, force) + u]
    )
    mass_blocks = (k.base, k.M_coupling, k.M_joints, k.base_per_joint)
    xdd = forward_dynamics_from_frames(robot, k.frames, state.V_base, state.qd, Q, mass_blocks)
    if scenario.target is None:
        return state_rate(state, xdd)
    # Equal and opposite on the target, at the same point.
    return state_rate(state, xdd, target_rate(scenario.target, state.target, -force, state.p_base + k.frames.p_ee))


def plant_derivative(robot: Robot, scenario: Scenario, state: PlantState, u: jax.Array) -> PlantState:
    """State rate under joint torques ``u`` (7,) N m and the contact force at this state."""
    return plant_rate(robot, scenario, state, plant_kinematics(robot, scenario, state), u)


def momentum_at(kinematics: PlantKinematics, plant: PlantState) -> jax.Array:
    """``[P (N s); L about the inertial origin (N m s)]`` (6,), inertial frame."""
    # Rows 0-5 of M give [P; L about the satellite CoM]; move L to the inertial origin.
    m, h, I_O = kinematics.base
    v_s, w_s = jnp.split(plant.V_base, 2)
    P, L = jnp.split(spatial.matvec(kinematics.M_coupling, plant.qd), 2)
    P = P + m * v_s - spatial.cross(h, w_s)
    L = L + spatial.cross(h, v_s) + spatial.matvec(I_O, w_s)
    return jnp.concatenate([P, L + spatial.cross(plant.p_base, P)])


def initial_state(scenario: Scenario, controller="admittance") -> SimState:
    """The scan's initial carry: the scenario's plant state, the law's initial state
    (``V_ref(0) = 0`` for the admittance law), the joint servo at rest."""
    dtype = scenario.initial.q.dtype
    controller_state = as_controller(controller).init(scenario.initial.q.shape[-1], dtype)
    return SimState(plant=scenario.initial, controller=controller_state)


def control_step(
    robot: Robot,
    scenario: Scenario,
    gains: Gains,
    controller,
    state: SimState,
    t,
    kinematics: PlantKinematics | None = None,
):
    """One controller update at time ``t``: returns ``(u (7,), new ControllerState, log row)``.

    ``controller``: a law's name, a law object or a controller
    ([`as_controller()`][spacegrasp_jax.control.registry.as_controller]). ``kinematics``:
    [`plant_kinematics()`][spacegrasp_jax.simulate.plant_kinematics] of ``state.plant`` if the caller has it."""
    control = as_controller(controller)
    plant = state.plant
    if kinematics is None:
        kinematics = plant_kinematics(robot, scenario, plant)
    observed = observe(robot, scenario, plant, kinematics, t)
    command, law_state = control.law.update(gains, observed.inputs, state.controller.law, scenario.dt)
    u, servo_state = control.torque(gains, command, plant.qd, state.controller.pid, t, scenario.dt)
    logged = control.logged(command, state.controller.law)
    row = log_row(plant, kinematics, t, observed, scenario.target, u=u, **logged)
    return u, ControllerState(law=law_state, pid=servo_state), row


@dataclasses.dataclass(frozen=True)
class Observation:
    """The true state as an ideal controller sees it ([`observe()`][spacegrasp_jax.simulate.observe]).

    Attributes:
        inputs: what the law reads ([`ControlInputs`][spacegrasp_jax.control.law.ControlInputs]).
        pose, twist: (6,) the EE pose and twist in LAR (the log's ``pose_ee``, ``twist_ee``).
        force_fts, torque_fts: (3,) N, N m, the ideal F/T sensor's reading, sensor axes.
    """

    inputs: ControlInputs
    pose: jax.Array
    twist: jax.Array
    force_fts: jax.Array
    torque_fts: jax.Array


def observe(robot: Robot, scenario: Scenario, plant: PlantState, kinematics: PlantKinematics, t) -> Observation:
    """The true state at time ``t`` (s) through perfect sensors, given ``kinematics`` of ``plant``."""
    force_fts, torque_fts = sensor_reading(robot, scenario, kinematics)
    inputs, (pose, twist) = controller_inputs(
        robot,
        scenario.trajectory,
        plant.p_base,
        plant.V_base,
        plant.q,
        plant.qd,
        kinematics,
        kinematics.p_lar,
        kinematics.R_lar,
        force_fts,
        torque_fts,
        t,
        lar_motion=target_motion(scenario, plant),
    )
    return Observation(inputs, pose, twist, force_fts, torque_fts)


def target_motion(scenario: Scenario, plant: PlantState):
    """``(v_lar (3,) m/s, w (3,) rad/s)``, the LAR origin's velocity and the target's
    angular velocity (inertial), or ``None`` for a stationary target."""
    return None if scenario.target is None else lar_velocity(scenario.target, plant.target)


def log_row(plant: PlantState, kinematics: PlantKinematics, t, observed: Observation, target=None, **controller) -> Log:
    """One row of the [`Log`][spacegrasp_jax.simulate.Log]: the plant's true state at ``t`` (s) and ``controller``'s
    fields (``u``, ``V_ref``, ``qd_des`` and, in the flight-like loop, its readings);
    ``target``: the scenario's [`TargetBody`][spacegrasp_jax.target.TargetBody] (``None``: a
    stationary target)."""
    momentum = momentum_at(kinematics, plant)
    target_fields = {}
    if target is not None:
        state = plant.target
        target_fields = dict(
            target_position=state.p,
            target_quat=state.quat,
            target_velocity=state.v,
            target_angular_velocity=state.w,
            momentum_total=momentum + target_momentum(target, state),
        )
    return Log(
        t=t,
        pose_ee=observed.pose,
        pose_des=observed.inputs.pose_des,
        twist_ee=observed.twist,
        contact_force=kinematics.contact_force_lar,
        momentum=momentum,
        V_base=plant.V_base,
        fts_force=observed.force_fts,
        fts_torque=observed.torque_fts,
        q=plant.q,
        qd=plant.qd,
        **target_fields,
        **controller,
    )


def sensor_reading(robot: Robot, scenario: Scenario, kinematics: PlantKinematics) -> tuple[jax.Array, jax.Array]:
    """The ideal F/T sensor between link 7 and the EE: the contact's force (3,) N and its
    torque about the sensor point (3,) N m, in sensor (frame 7) axes (eqs 18-19)."""
    R_fts = kinematics.frames.R_ee  # frame 7's rotation
    force = spatial.matvec(R_fts.T, spatial.matvec(kinematics.R_lar, kinematics.contact_force_lar))
    return sensor_wrench(force, robot.ee_offset)


def controller_inputs(
    robot, trajectory, p_base, V_base, q, qd, kinematics, p_lar, R_lar, force_fts, torque_fts, t, lar_motion=None
):
    """What the law reads ([`ControlInputs`][spacegrasp_jax.control.law.ControlInputs]), and the EE
    pose and twist in LAR, from a view of the state: the satellite's position ``p_base`` (3,)
    m and twist ``V_base`` (6,), the joint angles ``q`` (N,) rad and rates ``qd`` (N,) rad/s
    it measured, ``kinematics`` of the robot the controller believes at ``q``, the LAR frame it believes
    (``p_lar`` (3,) m, ``R_lar`` (3, 3), inertial), and the F/T reading ``force_fts``,
    ``torque_fts`` (3,) in sensor axes, at time ``t`` (s). ``lar_motion``: ``(v_lar, w)``
    (3,) m/s, rad/s, inertial, the LAR origin's velocity and the target's angular velocity
    ([`target_motion()`][spacegrasp_jax.simulate.target_motion]), or ``None`` for a stationary target; the twist is then relative
    to the moving frame, ``[d p_rel/dt; R_lar^T (w_ee - w)]``."""
    frames = kinematics.frames
    p_ee = p_base + frames.p_ee
    R_lar_ee = spatial.matmul(R_lar.T, frames.R_ee)
    p_rel = spatial.matvec(R_lar.T, p_ee - p_lar)
    pose = jnp.concatenate([p_rel, spatial.euler_zyx(R_lar_ee)])
    r_ee = frames.p_ee  # EE point from the satellite CoM
    v_s, w_s = jnp.split(V_base, 2)
    twist_inertial = jnp.concatenate([v_s + spatial.cross(w_s, r_ee), w_s]) + spatial.matvec(kinematics.J_joints, qd)
    # Both 3-vectors of a twist (wrench, Jacobian) rotate at once as a (2, 3) array.
    twist = spatial.matvec(R_lar.T, twist_inertial.reshape(2, 3)).reshape(6)
    frame_twist = None
    if lar_motion is not None:
        # The LAR frame's own twist at the EE point, LAR axes: the EE's inertial twist is
        # the relative one plus this (d p_rel/dt = R^T (v_ee - v_lar) - (R^T w) x p_rel).
        v_lar, w = (spatial.matvec(R_lar.T, x) for x in lar_motion)
        frame_twist = jnp.concatenate([v_lar + spatial.cross(w, p_rel), w])
        twist = twist - frame_twist

    R_fts = frames.R_ee  # frame 7's rotation
    wrench_ee = wrench_at_ee(force_fts, torque_fts, robot.ee_offset)
    wrench_lar = rotate_wrench(spatial.matmul(R_lar.T, R_fts), wrench_ee)

    pose_des, twist_des, twist_rate_des = desired_state(trajectory, t)
    J_dyn = dynamic_jacobian_from_parts(kinematics.base_per_joint, kinematics.J_joints, r_ee)  # eq 8
    J_dyn_ee = spatial.matmul(frames.R_ee.T, J_dyn.reshape(2, 3, -1)).reshape(J_dyn.shape)
    inputs = ControlInputs(
        pose, twist, wrench_lar, pose_des, twist_des, twist_rate_des, J_dyn_ee, R_lar_ee, q, qd, frame_twist
    )
    return inputs, (pose, twist)


def closed_loop_step(robot: Robot, scenario: Scenario, gains: Gains, controller, checkpoint: bool = False):
    """The scan body ``step(state: SimState, k) -> (next SimState, Log row)`` for step
    number ``k`` (a float, t = k dt): one controller update, then one RK4 step of the plant
    under the held torques. Arguments as [`rollout()`][spacegrasp_jax.simulate.rollout].

    ``checkpoint``: put the controller update and RK4's first stage under
    ``jax.checkpoint`` (RK4's later stages always are, one by one: ``integrator.rk4_step``).
    A reverse-mode gradient then keeps, per step, the state and the rates RK4's stages
    start from, and recomputes each part just before differentiating it."""
    control = as_controller(controller)

    def control_and_first_rate(state: SimState, t):
        # The controller reads the state RK4's first stage starts from: share the kinematics.
        kinematics = plant_kinematics(robot, scenario, state.plant)
        u, controller_state, row = control_step(robot, scenario, gains, control, state, t, kinematics=kinematics)
        return u, controller_state, row, plant_rate(robot, scenario, state.plant, kinematics, u)

    if checkpoint:
        # Inside a scan no CSE can undo the checkpoint; without the optimisation barriers of
        # the default prevent_cse=True, XLA fuses more (integrator.rk4_step).
        control_and_first_rate = jax.checkpoint(control_and_first_rate, prevent_cse=False)

    def step(state: SimState, k):
        u, controller_state, row, k1 = control_and_first_rate(state, k * scenario.dt)
        plant = rk4_step(lambda s: plant_derivative(robot, scenario, s, u), state.plant, scenario.dt, rate_at_start=k1)
        return SimState(plant=plant, controller=controller_state), row

    return step


def largest_divisor(n: int, at_most: int) -> int:
    """The largest divisor of ``n`` that is at most ``at_most`` (1 if none larger)."""
    return max(d for d in range(1, at_most + 1) if n % d == 0)


#: Steps per inner scan of [`rollout()`][spacegrasp_jax.simulate.rollout]: the largest log field (7 numbers) times 8 is 56,
#: under the 64 numbers (512 bytes) up to which XLA's CPU runtime runs a loop in sequence.
LOG_BLOCK = 8


def rollout(
    robot: Robot,
    scenario: Scenario,
    gains: Gains,
    controller,
    checkpoint_segment: int | None = None,
    realism: Realism | None = None,
    key: jax.Array | None = None,
    model_robot: Robot | None = None,
) -> tuple[SimState | FlightState, Log]:
    """Simulate the closed loop over ``scenario.duration`` with one ``jax.lax.scan``.

    Args:
        robot, scenario, gains: pytrees (any leaf may carry a vmap batch axis).
        controller: static: a law's name (``"admittance"``, eqs 9-17; ``"cartesian"``, eqs
            21-22; any of ``control.CONTROLLERS``), a law object (``control.Admittance()``)
            or a ``control.Controller``
            ([`as_controller()`][spacegrasp_jax.control.registry.as_controller]); a law
            object carries its settings (``control.Admittance(pinv_damping=0.01)``: damped
            least squares; a name: the paper's exact pseudoinverse).
        checkpoint_segment: the number of steps per inner scan (static; must divide
            ``n_steps``; ``None``: ``LOG_BLOCK`` or the largest divisor below it). In the
            paper's loop each step's parts are always under ``jax.checkpoint``
            ([`closed_loop_step()`][spacegrasp_jax.simulate.closed_loop_step]), which changes nothing in a forward
            rollout (the same log, bit for bit) and makes a reverse-mode gradient's tape
            hold, per step, the state and the rates RK4's stages start from instead of
            every intermediate (the measured cost: documentation, Performance). A stage's rate is at most 7
            numbers a field, so the three of one step are (3, 7) and inner scans of 2
            steps hold no array over 64 numbers, which matters where XLA runs loops
            kernel by kernel (with loops compiled whole the length does not).
        realism: ``None`` or an ideal [`Realism`][spacegrasp_jax.realism.Realism]: the paper's
            loop. Otherwise the flight-like loop of [`flight_rollout()`][spacegrasp_jax.simulate.flight_rollout] (static fields
            fix the program; a ``checkpoint_segment``, which must divide the steps there
            too, checkpoints each control period).
        key: the ``jax.random`` key of the sensors' noise (flight-like loop with noise).
        model_robot: the robot the controller believes, if not ``robot`` (the flight-like
            loop; [`flight_rollout()`][spacegrasp_jax.simulate.flight_rollout]).

    Returns:
        ``(final_state, log)``: the state after ``scenario.n_steps`` steps (a
        [`SimState`][spacegrasp_jax.simulate.SimState] in the paper's loop, a
        [`FlightState`][spacegrasp_jax.simulate.FlightState] in the flight-like loop) and the
        [`Log`][spacegrasp_jax.simulate.Log]. A diverging rollout carries non-finite values from the first bad
        step on; [`first_nonfinite_time()`][spacegrasp_jax.simulate.first_nonfinite_time] finds it (``experiment.run`` reports it).
    """
    n_steps = scenario.n_steps
    if checkpoint_segment is not None and (checkpoint_segment < 1 or n_steps % checkpoint_segment):
        raise ValueError(f"checkpoint_segment: {checkpoint_segment} must be a positive divisor of the {n_steps} steps")
    if (realism is not None and not realism.is_ideal(scenario.dt)) or model_robot is not None:
        realism = ideal() if realism is None else realism
        if key is None:
            if Stage.SENSORS in realism.stages:
                raise ValueError("key: a realism with noisy sensors needs a jax.random key")
            key = jax.random.PRNGKey(0)  # drawn from by no stage
        return flight_rollout(
            robot,
            scenario,
            gains,
            controller,
            realism,
            key,
            model_robot=model_robot,
            checkpoint=checkpoint_segment is not None,
        )
    step = closed_loop_step(robot, scenario, gains, controller, checkpoint=True)
    block = largest_divisor(n_steps, LOG_BLOCK) if checkpoint_segment is None else checkpoint_segment
    # Blocks of a few steps, each an inner scan whose buffers (log rows, saved states) stay
    # within 64 numbers a field. Where XLA runs loops kernel by kernel, it then runs that
    # inner loop's kernels in sequence, where a loop that writes into the whole log runs as
    # a task graph; compiled whole (spacegrasp_jax.compilation), the inner loop is one
    # kernel.
    steps = jnp.arange(n_steps, dtype=scenario.initial.q.dtype).reshape(-1, block)
    final, rows = jax.lax.scan(lambda s, ks: jax.lax.scan(step, s, ks), initial_state(scenario, controller), steps)
    return final, jax.tree.map(lambda x: x.reshape((n_steps,) + x.shape[2:]), rows)


# ---- the flight-like loop (spacegrasp_jax.realism) -----------------------------------------


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class FlightState:
    """The flight-like loop's carry.

    Attributes:
        plant: the true state. controller: the law's and the joint servo's memory.
        wrench_reading: (6,) the low-passed F/T reading ``[f (N); n (N m)]``, sensor axes.
        commands_in_flight: (delay_periods, N), the law's commands computed but not yet
            applied, oldest first (desired joint rates, rad/s, or a torque law's N m).
        rates_in_flight: with a [`ServoInputDelay`][spacegrasp_jax.simulate.ServoInputDelay], its line of joint-rate
            readings (``ServoInputDelay.init()``); ``None`` without.
    """

    plant: PlantState
    controller: ControllerState
    wrench_reading: jax.Array
    commands_in_flight: jax.Array
    rates_in_flight: tuple | None = None


@dataclasses.dataclass(frozen=True)
class ServoInputDelay:
    """A delay of whole servo ticks between the joint sensors and the joint PID: at tick j
    the PID reads the joint rates measured at tick ``j - ticks`` (zeros before the first).

    Attributes:
        capacity: the line's length (static); ``ticks`` must be below it.
        ticks: () int, the delay in servo ticks (a value: every delay below ``capacity``
            runs the same program).
    """

    capacity: int
    ticks: jax.Array

    def init(self, n_joints: int, dtype) -> tuple:
        """``(readings (capacity, n_joints) rad/s, head () int)``: the line, empty."""
        return jnp.zeros((self.capacity, n_joints), dtype), jnp.zeros((), jnp.int32)

    def push(self, line: tuple, reading: jax.Array) -> tuple[jax.Array, tuple]:
        """``(the reading the PID gets (7,), the line after)`` when ``reading`` (7,) is measured."""
        readings, head = line
        readings = readings.at[head].set(reading)
        return readings[(head - self.ticks) % self.capacity], (readings, (head + 1) % self.capacity)


def flight_rollout(
    robot: Robot,
    scenario: Scenario,
    gains: Gains,
    controller,
    realism: Realism,
    key: jax.Array,
    *,
    model_robot: Robot | None = None,
    checkpoint: bool = False,
) -> tuple[FlightState, Log]:
    """The closed loop with the realism model (module [`spacegrasp_jax.realism`][spacegrasp_jax.realism]), one
    ``jax.lax.scan`` over control periods, each an inner scan over the plant's steps.

    At the start of control period k (``t_k = k T``, ``T = realism.control_period``): the
    sensors read the true state (noise drawn from ``fold_in(key, k)``), the controller runs
    with its own model and LAR estimate, and its desired joint rates enter the delay line.
    The rates leaving it are held over the period; at each servo tick (``j S``, ``S =
    realism.servo_period``, by default ``T``: one tick a period) the PID reads the joint
    sensors (noise from the same key of the period) and turns the rate error into torques
    (anti-windup, saturation), held over the tick's plant steps (RK4 at ``scenario.dt``, the
    contact force at every stage). The log has one row per plant step, as [`rollout()`][spacegrasp_jax.simulate.rollout]'s.

    Args:
        robot, scenario, gains, controller: as [`rollout()`][spacegrasp_jax.simulate.rollout].
        realism: the realism settings (static fields fix the program).
        key: a ``jax.random`` key; same key, same rollout.
        model_robot: the robot the controller's model starts from (default ``robot``);
            its satellite mass and inertia are scaled by the realism's factors.
        checkpoint: put each control period under ``jax.checkpoint`` (reverse-mode
            gradients of long rollouts: the tape keeps one state per period).
    """
    start, one_period, periods = flight_loop(
        robot,
        scenario,
        gains,
        controller,
        realism,
        key,
        model_robot=model_robot,
        checkpoint=checkpoint,
    )
    final, rows = jax.lax.scan(one_period, start, jnp.arange(periods, dtype=scenario.initial.q.dtype))
    return final, jax.tree.map(lambda x: x.reshape((scenario.n_steps,) + x.shape[2:]), rows)


def flight_loop(
    robot: Robot,
    scenario: Scenario,
    gains: Gains,
    controller,
    realism: Realism,
    key: jax.Array,
    *,
    model_robot: Robot | None = None,
    checkpoint: bool = False,
    servo_input_delay: ServoInputDelay | None = None,
):
    """The parts of [`flight_rollout()`][spacegrasp_jax.simulate.flight_rollout] (same arguments): ``(start, one_period,
    periods)``, the initial [`FlightState`][spacegrasp_jax.simulate.FlightState], the scan body ``one_period(state, k) ->
    (state, rows)`` of control period ``k`` (a float) with its plant steps' log rows (a
    [`Log`][spacegrasp_jax.simulate.Log] with a leading axis of the period's steps), and the number of periods.

    ``servo_input_delay``: a [`ServoInputDelay`][spacegrasp_jax.simulate.ServoInputDelay] between the joint sensors and the PID
    (``spacegrasp_jax.margins``); the log's ``qd_measured`` is then the delayed reading."""
    realism.check_timing(scenario.dt, scenario.n_steps)
    per_period = realism.steps_per_period(scenario.dt)
    per_servo = realism.steps_per_servo(scenario.dt)
    periods = scenario.n_steps // per_period
    ticks = per_period // per_servo  # servo ticks per control period
    period, servo_period = per_period * scenario.dt, per_servo * scenario.dt
    dtype = scenario.initial.q.dtype
    n = n_joints(robot)
    realism.check_joints(n)
    control = as_controller(controller).with_actuators(realism.saturation, realism.anti_windup)
    limit = realism.torque_limit_Nm if Stage.ACTUATORS in realism.stages else None
    own_model = bool(realism.stages & (Stage.SENSORS | Stage.MODEL)) or model_robot is not None
    model = stages.believed_robot(robot if model_robot is None else model_robot, realism) if own_model else robot
    smoothing = stages.low_pass_gain(realism, period)

    def period_noise(k):
        """(6 + N ticks,) standard normals of period k: the wrench's, then each tick's rates."""
        return jax.random.normal(jax.random.fold_in(key, k.astype(jnp.uint32)), (6 + n * ticks,), dtype)

    def control_period(state: FlightState, k, noise):
        plant, t = state.plant, k * period
        truth = plant_kinematics(robot, scenario, plant)
        reading = stages.wrench_reading(realism, *sensor_reading(robot, scenario, truth), noise)
        q, qd = stages.joint_reading(realism, plant.q, plant.qd, noise[6 : 6 + n])
        reading = stages.low_pass(realism, state.wrench_reading, reading, smoothing)
        view = (
            plant_kinematics(model, scenario, dataclasses.replace(plant, q=q), with_contact=False)
            if own_model
            else truth
        )
        p_lar, R_lar = stages.lar_estimate(realism, truth.p_lar, truth.R_lar)
        inputs, _ = controller_inputs(
            robot,
            scenario.trajectory,
            plant.p_base,
            plant.V_base,
            q,
            qd,
            view,
            p_lar,
            R_lar,
            reading[:3],
            reading[3:],
            t,
            lar_motion=target_motion(scenario, plant),
        )
        computed, law_state = control.law.update(gains, inputs, state.controller.law, period)
        command, in_flight = stages.delay_line(realism, state.commands_in_flight, computed)
        held = dict(
            control.logged(command, state.controller.law),
            command=command,
            qd_des_computed=control.desired_rates(computed),
            fts_force_measured=reading[:3],
            fts_torque_measured=reading[3:],
        )
        return dataclasses.replace(state, wrench_reading=reading, commands_in_flight=in_flight), law_state, held

    def plant_step(plant: PlantState, k, held):
        t = k * scenario.dt
        kinematics = plant_kinematics(robot, scenario, plant)
        logged = {name: value for name, value in held.items() if name != "command"}
        row = log_row(plant, kinematics, t, observe(robot, scenario, plant, kinematics, t), scenario.target, **logged)
        u = held["u"]
        k1 = plant_rate(robot, scenario, plant, kinematics, u)
        return rk4_step(lambda s: plant_derivative(robot, scenario, s, u), plant, scenario.dt, rate_at_start=k1), row

    def servo_tick(carry, j, held, noise):
        """Servo tick j (a float) of the whole run: the joint sensors, the PID, its plant steps."""
        plant, pid_state, line = carry
        tick_noise = jax.lax.dynamic_slice_in_dim(noise, 6 + n * (j.astype(jnp.int32) % ticks), n)
        q, qd = stages.joint_reading(realism, plant.q, plant.qd, tick_noise)
        if servo_input_delay is not None:
            qd, line = servo_input_delay.push(line, qd)
        u, pid_state = control.torque(gains, held["command"], qd, pid_state, j * servo_period, servo_period, limit)
        steps = j * per_servo + jnp.arange(per_servo, dtype=dtype)
        held = dict(held, u=u, q_measured=q, qd_measured=qd)
        if per_servo == 1:
            plant, row = plant_step(plant, steps[0], held)
            return (plant, pid_state, line), jax.tree.map(lambda x: x[None], row)
        plant, rows = jax.lax.scan(lambda p, i: plant_step(p, i, held), plant, steps)
        return (plant, pid_state, line), rows

    def one_period(state: FlightState, k):
        noise = period_noise(k)
        state, law_state, held = control_period(state, k, noise)
        carry = (state.plant, state.controller.pid, state.rates_in_flight)
        if ticks == 1:
            (plant, pid_state, line), rows = servo_tick(carry, k, held, noise)
        else:
            tick = lambda carry, j: servo_tick(carry, j, held, noise)
            (plant, pid_state, line), rows = jax.lax.scan(tick, carry, k * ticks + jnp.arange(ticks, dtype=dtype))
            rows = jax.tree.map(lambda x: x.reshape((per_period,) + x.shape[2:]), rows)
        controller_state = ControllerState(law_state, pid_state)
        return dataclasses.replace(state, plant=plant, controller=controller_state, rates_in_flight=line), rows

    if checkpoint:  # inside a scan no CSE can undo it (see closed_loop_step)
        one_period = jax.checkpoint(one_period, prevent_cse=False)
    start = FlightState(
        plant=scenario.initial,
        controller=control.init(n, dtype),
        wrench_reading=jnp.zeros(6, dtype),
        commands_in_flight=jnp.zeros((realism.delay_periods, n), dtype),
        rates_in_flight=None if servo_input_delay is None else servo_input_delay.init(n, dtype),
    )
    return start, one_period, periods


def first_nonfinite_step(log: Log) -> int | None:
    """Index of the first log row holding a non-finite value, or ``None`` (host side)."""
    bad = np.zeros(np.shape(log.t), dtype=bool)
    for name, series in vars(log).items():
        if name != "t" and series is not None:
            values = np.asarray(series)
            bad |= ~np.all(np.isfinite(values.reshape(values.shape[0], -1)), axis=1)
    return int(np.argmax(bad)) if bad.any() else None


def first_nonfinite_time(log: Log) -> float | None:
    """Time (s) of the first log row holding a non-finite value, or ``None`` (host side)."""
    step = first_nonfinite_step(log)
    return None if step is None else float(np.asarray(log.t)[step])
