"""The closed loop: contact -> sensors -> controller -> joint PID -> RK4, as one ``lax.scan``.

Each control period (in the paper's loop, each step of length ``dt``; modelling notes):
1. the sensors read the state (the realism's stages: noise, bias, low-pass, the LAR
   estimate, the controller's own model; all off in the paper's loop), the controller
   computes its command (admittance eqs 9-17, Cartesian eqs 21-22: desired joint rates; or
   a torque law's torques) and the command enters the delay line;
2. at each servo tick the joint PID turns the rate error into torques (saturation and
   anti-windup with the actuators' stage), held over the tick's plant steps (zero-order
   hold) while RK4 integrates the plant, the contact force of eq 20 being evaluated at every
   RK4 stage from that stage's state.

[`closed_loop()`][spacegrasp_jax.loop.simulate.closed_loop] is the one scan driver; what it keeps of each step's log row is its
observer's choice ([`FullLog`][spacegrasp_jax.loop.simulate.FullLog] for [`rollout()`][spacegrasp_jax.loop.simulate.rollout], metrics folded in the scan for a campaign).
Everything is pure: jit, vmap (over scenarios, robots or gains) and grad apply.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from collections.abc import Callable
from typing import Any, Protocol

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax.core import spatial
from spacegrasp_jax.core.contact import (
    contact_force_exact,
    contact_force_smooth,
    rotate_wrench,
    sensor_wrench,
    wrench_at_ee,
)
from spacegrasp_jax.core.dynamics import (
    dynamic_jacobian_from_parts,
    forward_dynamics_from_frames,
    frames_at_base,
    mass_matrix_parts_from_frames,
    solve_base,
)
from spacegrasp_jax.core.integrator import (
    PlantState,
    rk4_step,
    state_rate,
)
from spacegrasp_jax.core.kinematics import Frames, point_jacobian_blocks
from spacegrasp_jax.core.model import Robot, n_joints
from spacegrasp_jax.core.tangents import with_derivative_of
from spacegrasp_jax.core.target import lar_frame, lar_velocity, target_momentum, target_rate
from spacegrasp_jax.core.trajectory import desired_state
from spacegrasp_jax.envelope.scenario import Scenario
from spacegrasp_jax.loop import stages
from spacegrasp_jax.loop.control.gains import Gains
from spacegrasp_jax.loop.control.law import ControlInputs, ControllerState
from spacegrasp_jax.loop.control.registry import as_controller
from spacegrasp_jax.loop.control.schedule import GainChoice, GainSchedule, contact_phase, scheduling_variable
from spacegrasp_jax.loop.realism import Realism, Stage, ideal


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
        target_position: (N, 3) m, the target's CoM (a fixed target's: the LAR origin),
            inertial frame.
        target_quat: (N, 4) its attitude ``[w, x, y, z]``, body (LAR axes) to inertial.
        target_velocity: (N, 3) m/s, its CoM's velocity, inertial frame (zero for the
            paper's fixed target).
        target_angular_velocity: (N, 3) rad/s, its angular velocity, body (LAR) axes.
        momentum_total: (N, 6) ``[P (N s); L (N m s)]``, the chaser's plus the target's
            momentum about the inertial origin (a fixed target's is not counted: the
            chaser's).
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
    target_position: jax.Array
    target_quat: jax.Array
    target_velocity: jax.Array
    target_angular_velocity: jax.Array
    momentum_total: jax.Array
    fts_force_measured: jax.Array | None = None
    fts_torque_measured: jax.Array | None = None
    q_measured: jax.Array | None = None
    qd_measured: jax.Array | None = None
    qd_des_computed: jax.Array | None = None


def lar_pose(scenario: Scenario, plant: PlantState) -> tuple[jax.Array, jax.Array]:
    """``(p_lar (3,) m, R_lar (3, 3))``, the LAR frame at ``plant`` (inertial): the
    scenario's, exactly, for the paper's fixed target; carried by the target's state for a
    free one."""
    if not plant.target.free:
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
        frames: [`Frames`][spacegrasp_jax.core.kinematics.Frames] with the satellite CoM at the
            origin ([`frames_at_base()`][spacegrasp_jax.core.dynamics.frames_at_base]).
        base: ``(m, h, I_O)``, the mass matrix's satellite block
            ``M_base = [[m 1, -h x], [h x, I_O]]`` ([`mass_matrix_parts_from_frames()`][spacegrasp_jax.core.dynamics.mass_matrix_parts_from_frames]).
        M_coupling, M_joints: (6, N), (N, N) blocks of the mass matrix.
        base_per_joint: (6, N) ``M_base^-1 M_coupling``: minus the satellite velocity per
            unit joint rate at zero momentum (eq 6).
        J_joints: (6, N) joint block ``J_m`` of the EE point Jacobian, inertial frame. Its
            satellite block ``J_s = [[1, -r x], [0, 1]]`` needs only ``r = frames.p_ee``,
            the EE point from the satellite CoM, and is applied as cross products.
        contact_force_lar: (3,) N, force of the contact sphere on the EE, LAR axes.
        p_lar, R_lar: (3,) m, (3, 3), the LAR frame at this state, inertial ([`lar_pose()`][spacegrasp_jax.loop.simulate.lar_pose]).
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
    """State rate under joint torques ``u`` (N,) N m and the contact force, given
    ``kinematics = plant_kinematics(robot, scenario, state)``."""
    k = kinematics
    force = spatial.matvec(k.R_lar, k.contact_force_lar)
    # The contact force acts at the EE point: generalised force J_point^T [f; 0].
    Q = jnp.concatenate(
        [force, spatial.cross(k.frames.p_ee, force), spatial.matvec(jnp.split(k.J_joints, 2)[0].T, force) + u]
    )
    mass_blocks = (k.base, k.M_coupling, k.M_joints, k.base_per_joint)
    xdd = forward_dynamics_from_frames(robot, k.frames, state.V_base, state.qd, Q, mass_blocks)
    if not state.target.free:
        return state_rate(state, xdd, state.target.at_rest())
    # Equal and opposite on the target, at the same point.
    return state_rate(state, xdd, target_rate(scenario.target, state.target, -force, state.p_base + k.frames.p_ee))


def plant_derivative(robot: Robot, scenario: Scenario, state: PlantState, u: jax.Array) -> PlantState:
    """State rate under joint torques ``u`` (N,) N m and the contact force at this state."""
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


@dataclasses.dataclass(frozen=True)
class Observation:
    """The true state as an ideal controller sees it ([`observe()`][spacegrasp_jax.loop.simulate.observe]).

    Attributes:
        inputs: what the law reads ([`ControlInputs`][spacegrasp_jax.loop.control.law.ControlInputs]).
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


def target_motion(scenario: Scenario, plant: PlantState) -> tuple[jax.Array, jax.Array] | None:
    """``(v_lar (3,) m/s, w (3,) rad/s)``, the LAR origin's velocity and the target's
    angular velocity (inertial); ``None`` for the paper's fixed target, decided by its
    static flag: a frame at rest, whose zero motion the loop does no arithmetic on."""
    return lar_velocity(scenario.target, plant.target) if plant.target.free else None


def log_row(plant: PlantState, kinematics: PlantKinematics, t, observed: Observation, target, **controller) -> Log:
    """One row of the [`Log`][spacegrasp_jax.loop.simulate.Log]: the plant's true state at ``t`` (s) and ``controller``'s
    fields (``u``, ``V_ref``, ``qd_des`` and, in the flight-like loop, its readings);
    ``target``: the scenario's [`TargetBody`][spacegrasp_jax.core.target.TargetBody]."""
    momentum = momentum_at(kinematics, plant)
    state = plant.target
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
        target_position=state.p,
        target_quat=state.quat,
        target_velocity=state.v,
        target_angular_velocity=state.w,
        momentum_total=momentum + target_momentum(target, state),
        **controller,
    )


def sensor_reading(robot: Robot, scenario: Scenario, kinematics: PlantKinematics) -> tuple[jax.Array, jax.Array]:
    """The ideal F/T sensor between the last link (N) and the EE: the contact's force (3,) N
    and its torque about the sensor point (3,) N m, in sensor (frame N) axes (eqs 18-19)."""
    R_fts = kinematics.frames.R_ee  # frame N's rotation
    force = spatial.matvec(R_fts.T, spatial.matvec(kinematics.R_lar, kinematics.contact_force_lar))
    return sensor_wrench(force, robot.ee_offset)


def controller_inputs(
    robot, trajectory, p_base, V_base, q, qd, kinematics, p_lar, R_lar, force_fts, torque_fts, t, lar_motion
):
    """What the law reads ([`ControlInputs`][spacegrasp_jax.loop.control.law.ControlInputs]), and the EE
    pose and twist in LAR, from a view of the state: the satellite's position ``p_base`` (3,)
    m and twist ``V_base`` (6,), the joint angles ``q`` (N,) rad and rates ``qd`` (N,) rad/s
    it measured, ``kinematics`` of the robot the controller believes at ``q``, the LAR frame it believes
    (``p_lar`` (3,) m, ``R_lar`` (3, 3), inertial), and the F/T reading ``force_fts``,
    ``torque_fts`` (3,) in sensor axes, at time ``t`` (s). ``lar_motion``: ``(v_lar, w)``
    (3,) m/s, rad/s, inertial, the LAR origin's velocity and the target's angular velocity
    ([`target_motion()`][spacegrasp_jax.loop.simulate.target_motion]); the twist is relative to the LAR frame,
    ``[d p_rel/dt; R_lar^T (w_ee - w)]``. ``None``: the frame is at rest (the paper's fixed
    target), and the laws read a zero ``frame_twist``: adding computed zeros would change
    nothing but how XLA fuses the paper's loop, and so the last bits of its results."""
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
    # The LAR frame's own twist at the EE point, LAR axes: the EE's inertial twist is the
    # relative one plus this (d p_rel/dt = R^T (v_ee - v_lar) - (R^T w) x p_rel).
    if lar_motion is None:
        frame_twist = jnp.zeros(6, twist.dtype)
    else:
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


# ---- the closed loop -----------------------------------------------------------------------


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class LoopState:
    """The closed loop's carry.

    Attributes:
        plant: the true state. controller: the law's and the joint servo's memory.
        stages: each stage's memory, in the order of the loop's chain
            ([`loop_stages()`][spacegrasp_jax.loop.simulate.loop_stages]); ``()`` in the paper's loop.
    """

    plant: PlantState
    controller: ControllerState
    stages: tuple = ()


@dataclasses.dataclass(frozen=True)
class LoopOptions:
    """How the loop is compiled and differentiated, never what it computes (beyond rounding).
    Static: a field of the program's key. The host fills it once
    ([`experiment.loop_options()`][spacegrasp_jax.jobs.experiment.loop_options]); nothing in the
    loop asks the process while it is traced.

    Attributes:
        checkpoint: put the parts of each control period under ``jax.checkpoint`` for
            reverse mode: the controller update, with the kinematics at the period's start;
            in a period of several plant steps, each step's start (its kinematics and log
            row); and each of RK4's stages, one by one
            ([`integrator.rk4_step()`][spacegrasp_jax.core.integrator.rk4_step]). The tape keeps,
            per plant step, the state, the kinematics at its start and the rates RK4's stages
            start from, and per period the controller's inputs (the sensors' noise is drawn
            outside the checkpoint, once). A forward run agrees with the unchecked loop's
            to rounding.
        reuse_start_kinematics: with ``checkpoint`` and a period of one step, RK4's first
            stage reads the kinematics the controller computed instead of computing them
            again. That puts them on the tape, in the inner scans of two steps: over 64
            numbers an array, which makes XLA's CPU runtime run those loops as a task graph
            where it runs them kernel by kernel (a gradient 35% slower than recomputing
            them). Where loops compile whole it runs as fast and compiles in 56-71% of the
            time (documentation, Performance): the host sets it where they do.
        gradient_from_s: truncated backpropagation (s; ``None``: the whole run). The loop
            runs in two scans: the control periods before the cut with the gains and the
            spec held (``jax.lax.stop_gradient``), then the rest. Reverse mode differentiates
            only the second: the gains' effect from the cut on, the state at the cut held,
            so it neither records nor recomputes the first. The cut is the first block
            boundary of the observer at or after ``gradient_from_s``
            ([`gradient_cut()`][spacegrasp_jax.loop.simulate.gradient_cut]). What the loop computes is
            unchanged (to rounding); its derivatives are those of the run after the cut.
    """

    checkpoint: bool = False
    reuse_start_kinematics: bool = False
    gradient_from_s: float | None = None

    def __post_init__(self):
        if self.gradient_from_s is not None and not (
            isinstance(self.gradient_from_s, int | float) and 0.0 <= self.gradient_from_s < float("inf")
        ):
            raise ValueError(f"gradient_from_s: must be a time >= 0 s, got {self.gradient_from_s!r}")


def loop_stages(spec: RunSpec) -> tuple:
    """The loop's chain of stages: the realism's
    ([`stages.realism_stages()`][spacegrasp_jax.loop.stages.realism_stages]), then ``spec.stages``."""
    realism = ideal() if spec.realism is None else spec.realism
    period = realism.steps_per_period(spec.scenario.dt) * spec.scenario.dt
    return stages.realism_stages(realism, period) + tuple(spec.stages)


def initial_state(spec: RunSpec) -> LoopState:
    """The initial carry of the loop of ``spec`` ([`RunSpec`][spacegrasp_jax.loop.simulate.RunSpec]): the scenario's plant state, the
    law's initial state (``V_ref(0) = 0`` for the admittance law), the joint servo at rest,
    each stage's initial memory (``init()``)."""
    initial = spec.scenario.initial
    dtype, n = initial.q.dtype, initial.q.shape[-1]
    joints = (jnp.zeros(n, dtype), jnp.zeros(n, dtype))
    values = dict(
        wrench=jnp.zeros(6, dtype),
        joints=joints,
        lar=(jnp.zeros(3, dtype), jnp.zeros((3, 3), dtype)),
        command=jnp.zeros(n, dtype),
        servo_joints=joints,
        torque=jnp.zeros(n, dtype),
    )
    return LoopState(
        plant=initial,
        controller=spec.controller.init(n, dtype),
        stages=stages.init_chain(loop_stages(spec), values),
    )


def loop_realism(realism: Realism | None, scenario: Scenario) -> Realism | None:
    """``realism``, or ``None`` where it runs the paper's loop for ``scenario`` (every stage
    off, a control period of one step): the hosts pass that on, so that one compiled program
    serves both."""
    return None if realism is None or realism.is_ideal(scenario.dt) else realism


@dataclasses.dataclass(frozen=True)
class LoopBody:
    """The closed loop as [`closed_loop()`][spacegrasp_jax.loop.simulate.closed_loop] runs it ([`loop_body()`][spacegrasp_jax.loop.simulate.loop_body]).

    Attributes:
        start: the initial [`LoopState`][spacegrasp_jax.loop.simulate.LoopState].
        period: ``period(state, k) -> (state, rows)``: control period number ``k`` (a
            float, ``t = k T``) and its plant steps' log rows, a [`Log`][spacegrasp_jax.loop.simulate.Log] with a leading
            axis of ``steps_per_period``.
        periods: the number of control periods in the scenario.
        steps_per_period: plant steps per control period (1: the paper's loop).
    """

    start: LoopState
    period: Callable[[LoopState, jax.Array], tuple[LoopState, Log]]
    periods: int
    steps_per_period: int


def _latched(gains) -> bool:
    """Whether the loop carries the contact latch for ``gains``: a schedule on
    ``contact_time``, or a ``GainChoice`` with one among its options."""
    if isinstance(gains, GainChoice):
        return gains.latched
    return isinstance(gains, GainSchedule) and gains.variable == "contact_time"


def _gains_at(gains: Gains | GainSchedule, t, pose: jax.Array, reading: jax.Array, contact_time) -> Gains:
    """A gain set's gains at the start of a period: ``t`` (s), the pose and F/T ``reading``
    the controller reads, ``contact_time`` (s) from the latch (``None`` without one)."""
    if not isinstance(gains, GainSchedule):
        return gains
    if gains.variable == "contact_time":
        return gains.at(contact_time)
    return gains.at(scheduling_variable(gains.variable, t, pose, reading))


@dataclasses.dataclass(frozen=True)
class _Period:
    """What the parts of one control period share: the run's settings, decided once on the
    host from the spec (``loop_body()``)."""

    spec: RunSpec
    gains: Gains | GainSchedule
    key: jax.Array | None
    chain: tuple
    control: Any  # the controller with the realism's actuators
    own_model: bool  # the controller has a model of its own (``model``)
    model: Robot  # the robot the controller believes
    limit: jax.Array | None  # the actuators' saturation (N m), with the actuators' stage
    senses: bool  # the controller's view differs from the truth
    logs_readings: bool  # the log keeps the readings (the paper's loop: they would repeat the truth)
    noisy: bool
    n: int
    dtype: Any
    ticks: int  # servo ticks per control period
    per_period: int
    per_servo: int
    period: float
    servo_period: float

    def noise(self, k):
        """(6 + N ticks,) standard normals of period k: the wrench's, then each tick's rates."""
        size = 6 + self.n * self.ticks
        if not self.noisy:
            return jnp.zeros(size, self.dtype)  # read by no stage
        return jax.random.normal(jax.random.fold_in(self.key, k.astype(jnp.uint32)), (size,), self.dtype)

    def kinematics(self, plant: PlantState) -> PlantKinematics:
        return plant_kinematics(self.spec.robot, self.spec.scenario, plant)

    def rate(self, plant: PlantState, kinematics: PlantKinematics, u) -> PlantState:
        return plant_rate(self.spec.robot, self.spec.scenario, plant, kinematics, u)

    def observe(self, plant: PlantState, kinematics: PlantKinematics, t) -> Observation:
        return observe(self.spec.robot, self.spec.scenario, plant, kinematics, t)

    def sensed_inputs(self, memories: tuple, plant: PlantState, truth: PlantKinematics, t, noise):
        """What the controller reads through the stages of the wrench, the joints and the
        LAR and its own model: ``(inputs, the F/T reading (6,), the memories after)``."""
        robot, scenario = self.spec.robot, self.spec.scenario
        reading, memories = stages.run_chain(
            self.chain, memories, "wrench", jnp.concatenate(sensor_reading(robot, scenario, truth)), noise[:6]
        )
        (q, qd), memories = stages.run_chain(self.chain, memories, "joints", (plant.q, plant.qd), noise[6 : 6 + self.n])
        if self.own_model:
            view = plant_kinematics(self.model, scenario, dataclasses.replace(plant, q=q), with_contact=False)
        else:
            view = truth
        (p_lar, R_lar), memories = stages.run_chain(self.chain, memories, "lar", (truth.p_lar, truth.R_lar))
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
        return inputs, reading, memories

    def gains_now(self, t, inputs: ControlInputs, reading: jax.Array, phase: tuple) -> tuple[Gains, tuple]:
        """The period's gains and the schedule's contact latch after it: the gain set, or a
        schedule's at its variable as the controller reads it at ``t`` (s) from its
        ``inputs`` and F/T ``reading`` (6,) ([`control.schedule`][spacegrasp_jax.loop.control.schedule];
        ``contact_time`` from the latch ``phase``, [`contact_phase()`][spacegrasp_jax.loop.control.schedule.contact_phase])."""
        contact_time = None
        if _latched(self.gains):
            contact_time, phase = contact_phase(phase, t, reading)
        if not isinstance(self.gains, GainChoice):
            return _gains_at(self.gains, t, inputs.pose, reading, contact_time), phase
        options = [_gains_at(option, t, inputs.pose, reading, contact_time) for option in self.gains.options]
        chosen = jnp.asarray(self.gains.chosen, jnp.int32)
        return jax.tree.map(lambda *values: jax.lax.select_n(chosen, *values), *options), phase

    def control_update(self, state: LoopState, k, noise, truth: PlantKinematics, observed: Observation | None):
        """The controller's update at the start of period k: the stages' memories moved on,
        the law's next state, and what is held over the period (the command leaving the
        command's stages, the log's controller fields, the period's gains)."""
        memories = state.stages
        if self.senses:
            inputs, reading, memories = self.sensed_inputs(memories, state.plant, truth, k * self.period, noise)
        else:
            inputs, reading = observed.inputs, jnp.concatenate([observed.force_fts, observed.torque_fts])
        gains, phase = self.gains_now(k * self.period, inputs, reading, state.controller.phase)
        computed, law_state = self.control.command(gains, inputs, state.controller.law, self.period)
        command, memories = stages.run_chain(self.chain, memories, "command", computed)
        held = self.control.logged(command, state.controller.law)
        if self.logs_readings:
            held |= dict(
                qd_des_computed=self.control.desired_rates(computed),
                fts_force_measured=reading[:3],
                fts_torque_measured=reading[3:],
            )
        return memories, ControllerState(law_state, state.controller.pid, phase), command, held, gains

    def servo_update(self, plant: PlantState, pid_state, memories, j, command, held, gains, noise):
        """Servo tick j (a float) of the whole run: the joint sensors and the PID at the
        period's ``gains``; returns the torques' log fields (``u`` (N,) N m and the readings),
        the PID's state and the stages' memories."""
        tick = j.astype(jnp.int32) % self.ticks if self.noisy else 0
        tick_noise = jax.lax.dynamic_slice_in_dim(noise, 6 + self.n * tick, self.n)
        (q, qd), memories = stages.run_chain(self.chain, memories, "servo_joints", (plant.q, plant.qd), tick_noise)
        u, pid_state = self.control.torque(
            gains, command, qd, pid_state, j * self.servo_period, self.servo_period, self.limit
        )
        u, memories = stages.run_chain(self.chain, memories, "torque", u)
        fields = dict(held, u=u, q_measured=q, qd_measured=qd) if self.logs_readings else dict(held, u=u)
        return fields, pid_state, memories

    def row(self, plant: PlantState, kinematics: PlantKinematics, t, fields, observed=None) -> Log:
        observed = self.observe(plant, kinematics, t) if observed is None else observed
        return log_row(plant, kinematics, t, observed, self.spec.scenario.target, **fields)

    def control_at_start(self, state: LoopState, k, truth: PlantKinematics):
        """A one-step period's controller, servo and log row at its start: ``(u, (the state
        with the controller's and the stages' memory moved on, the row))``."""
        noise = self.noise(k)
        t = k * self.spec.scenario.dt
        observed = self.observe(state.plant, truth, t)
        memories, controller, command, held, gains = self.control_update(state, k, noise, truth, observed)
        fields, pid_state, memories = self.servo_update(
            state.plant, state.controller.pid, memories, k, command, held, gains, noise
        )
        row = self.row(state.plant, truth, t, fields, observed)
        controller = dataclasses.replace(controller, pid=pid_state)
        state = dataclasses.replace(state, controller=controller, stages=memories)
        return fields["u"], (state, row)

    def one_step(self, state: LoopState, k):
        """A period of one plant step: the controller at its start, then RK4."""
        dt = self.spec.scenario.dt
        if not self.spec.options.checkpoint:
            # The controller runs at RK4's first stage, on its kinematics: one copy of the
            # kinematics and the rate in the program.
            at_start = lambda truth: self.control_at_start(state, k, truth)
            plant, _, (state, row) = rk4_step(self.kinematics, self.rate, state.plant, dt, at_start=at_start)
            return dataclasses.replace(state, plant=plant), jax.tree.map(lambda x: x[None], row)

        # Inside a scan no CSE can undo the checkpoint; without the optimisation barriers of
        # the default prevent_cse=True, XLA fuses more (integrator.rk4_step).
        @functools.partial(jax.checkpoint, prevent_cse=False)
        def control(state: LoopState, k):
            truth = self.kinematics(state.plant)
            u, (state, row) = self.control_at_start(state, k, truth)
            return state, u, row, truth

        state, u, row, truth = control(state, k)
        reused = truth if self.spec.options.reuse_start_kinematics else None
        plant, _, _ = rk4_step(self.kinematics, self.rate, state.plant, dt, u, start_kinematics=reused, checkpoint=True)
        return dataclasses.replace(state, plant=plant), jax.tree.map(lambda x: x[None], row)

    def plant_step(self, plant: PlantState, step, fields):
        """Plant step ``step`` (a float) of a longer period with the servo's ``fields``: the
        step and its log row."""
        dt = self.spec.scenario.dt
        t, u = step * dt, fields["u"]
        if self.spec.options.checkpoint:
            # The step's start (its kinematics and log row) is checkpointed like the
            # controller: the tape keeps its inputs and the kinematics, not every intermediate.
            @functools.partial(jax.checkpoint, prevent_cse=False)
            def start_of_step(plant, t, fields):
                kinematics = self.kinematics(plant)
                return kinematics, self.row(plant, kinematics, t, fields)

            kinematics, row = start_of_step(plant, t, fields)
            next_plant, _, _ = rk4_step(
                self.kinematics, self.rate, plant, dt, u, start_kinematics=kinematics, checkpoint=True
            )
            return next_plant, row
        next_plant, _, kinematics = rk4_step(self.kinematics, self.rate, plant, dt, u)
        return next_plant, self.row(plant, kinematics, t, fields)

    def several_steps(self, state: LoopState, k):
        """A period of several plant steps: the controller at its start, then each servo
        tick's sensors and PID and its plant steps."""
        dtype = self.dtype
        noise = self.noise(k)

        def start_of_period(state, k, noise):
            truth = self.kinematics(state.plant)
            observed = None if self.senses else self.observe(state.plant, truth, k * self.period)
            return self.control_update(state, k, noise, truth, observed)

        if self.spec.options.checkpoint:  # the noise is drawn outside: once, not again in the backward pass
            start_of_period = jax.checkpoint(start_of_period, prevent_cse=False)
        memories, controller, command, held, gains = start_of_period(state, k, noise)
        if isinstance(self.gains, Gains):
            gains = self.gains  # the loop's own argument, not a checkpoint's output: no adjoint through it
        # The servo ticks carry the memories of the stages they run, no others.
        ticking = [i for i, stage in enumerate(self.chain) if stage.signal in stages.TICK_SIGNALS]

        def servo_tick(carry, j):
            plant, pid_state, carried = carry
            every = list(memories)
            for i, memory in zip(ticking, carried, strict=True):
                every[i] = memory
            fields, pid_state, every = self.servo_update(plant, pid_state, tuple(every), j, command, held, gains, noise)
            carried = tuple(every[i] for i in ticking)
            steps = j * self.per_servo + jnp.arange(self.per_servo, dtype=dtype)
            if self.per_servo == 1:
                plant, row = self.plant_step(plant, steps[0], fields)
                return (plant, pid_state, carried), jax.tree.map(lambda x: x[None], row)
            plant, rows = jax.lax.scan(lambda p, i: self.plant_step(p, i, fields), plant, steps)
            return (plant, pid_state, carried), rows

        carry = (state.plant, state.controller.pid, tuple(memories[i] for i in ticking))
        if self.ticks == 1:
            (plant, pid_state, carried), rows = servo_tick(carry, k)
        else:
            ticks = k * self.ticks + jnp.arange(self.ticks, dtype=dtype)
            (plant, pid_state, carried), rows = jax.lax.scan(servo_tick, carry, ticks)
            rows = jax.tree.map(lambda x: x.reshape((self.per_period,) + x.shape[2:]), rows)
        memories = list(memories)
        for i, memory in zip(ticking, carried, strict=True):
            memories[i] = memory
        memories = tuple(memories)
        return LoopState(plant, dataclasses.replace(controller, pid=pid_state), memories), rows


def loop_body(spec: RunSpec, gains: Gains, key: jax.Array | None = None) -> LoopBody:
    """The closed loop's body: one control period, from the sensors to the plant's steps.

    At the start of control period k (``t_k = k T``, ``T = realism.control_period``, by
    default ``scenario.dt``): the sensors read the true state (noise drawn from
    ``fold_in(key, k)``), the controller runs with its own model and LAR estimate, and its
    command passes the command's stages (the delay line). The command leaving them is held
    over the period; at each servo tick (``j S``, ``S = realism.servo_period``, by default
    ``T``) the joint PID reads the joint sensors (noise from the same key of the period) and
    turns the rate error into torques (anti-windup, saturation), which pass the torque's
    stages and are held over the tick's plant steps (RK4 at ``scenario.dt``, the contact
    force at every stage). Each signal passes its stages of the loop's chain
    ([`loop_stages()`][spacegrasp_jax.loop.simulate.loop_stages]: the realism's, then
    ``spec.stages``; [`spacegrasp_jax.loop.stages`][spacegrasp_jax.loop.stages]); with none and a period
    of one plant step, this is the paper's loop (the modelling notes).

    How a plant step is written depends on ``spec.options``
    ([`LoopOptions`][spacegrasp_jax.loop.simulate.LoopOptions]). Without checkpointing (forward
    runs), RK4's four stages are one ``lax.scan`` and what reads the step's start (the
    controller and the log row of a one-step period, the log row of a longer period's step)
    runs at the first stage on its kinematics: one copy of the kinematics and the dynamics
    in the program, which then compiles in 55-70% of the time. With it (reverse mode), the
    controller (with the kinematics at the period's start), in a period of several steps
    each step's start (its kinematics and log row), and each of RK4's four stages are
    checkpointed apart, which keeps the tape and the backward pass small; no checkpoint
    spans a whole period. The two are the same operations in the same order and agree to
    rounding ([`integrator.rk4_step()`][spacegrasp_jax.core.integrator.rk4_step]).

    Args:
        spec: the run ([`RunSpec`][spacegrasp_jax.loop.simulate.RunSpec]: the plant, the
            controller, the realism, the controller's model, added stages and options; its
            observer is not the body's concern).
        gains: the gains, or a gain schedule ([`control.schedule`][spacegrasp_jax.loop.control.schedule]; any leaf may
            carry a vmap batch axis).
        key: a ``jax.random`` key, needed with noisy sensors (``Stage.SENSORS``); same key,
            same rollout.
    """
    robot, scenario, model_robot = spec.robot, spec.scenario, spec.model_robot
    realism = ideal() if spec.realism is None else spec.realism
    realism.check_timing(scenario.dt, scenario.n_steps)
    realism.check_joints(n_joints(robot))
    chain = loop_stages(spec)
    stages.check_chain(chain)
    per_period = realism.steps_per_period(scenario.dt)
    per_servo = realism.steps_per_servo(scenario.dt)
    noisy = Stage.SENSORS in realism.stages
    if noisy and key is None:
        raise ValueError("key: a realism with noisy sensors needs a jax.random key")
    own_model = bool(realism.stages & (Stage.SENSORS | Stage.MODEL)) or model_robot is not None
    model = stages.believed_robot(robot if model_robot is None else model_robot, realism) if own_model else robot
    period = _Period(
        spec=spec,
        gains=gains,
        key=key,
        chain=chain,
        control=spec.controller.with_actuators(realism.saturation, realism.anti_windup),
        own_model=own_model,
        model=model,
        limit=realism.torque_limit_Nm if Stage.ACTUATORS in realism.stages else None,
        senses=own_model or stages.acts_on(chain, "wrench", "joints", "lar"),
        logs_readings=not realism.is_ideal(scenario.dt) or model_robot is not None or bool(spec.stages),
        noisy=noisy,
        n=n_joints(robot),
        dtype=scenario.initial.q.dtype,
        ticks=per_period // per_servo,
        per_period=per_period,
        per_servo=per_servo,
        period=per_period * scenario.dt,
        servo_period=per_servo * scenario.dt,
    )
    one_period = period.one_step if per_period == 1 else period.several_steps
    start = initial_state(spec)
    if _latched(gains):  # the latch: not yet in contact
        zero = jnp.zeros((), scenario.initial.q.dtype)
        start = dataclasses.replace(start, controller=dataclasses.replace(start.controller, phase=(zero, zero)))
    return LoopBody(
        start=start,
        period=one_period,
        periods=scenario.n_steps // per_period,
        steps_per_period=per_period,
    )


class Observer(Protocol):
    """What a [`closed_loop()`][spacegrasp_jax.loop.simulate.closed_loop] keeps of the rows it produces: the whole log
    ([`FullLog`][spacegrasp_jax.loop.simulate.FullLog]), metrics folded in the scan with every k-th row
    ([`FoldedMetrics`][spacegrasp_jax.jobs.montecarlo.FoldedMetrics]), or your own.

    The loop runs its control periods in blocks of ``periods_per_block(body)`` (an inner
    scan each; 1: no inner scan). Each period's rows (a [`Log`][spacegrasp_jax.loop.simulate.Log] with a leading axis of
    the period's steps) go through ``fold(memory, rows) -> (memory, output)``; a block's
    outputs, stacked, through ``keep(outputs)``; at the end ``finish(memory, kept, final,
    scenario, realism)`` gives the observer's result.
    """

    def periods_per_block(self, body: LoopBody) -> int: ...

    def init(self, robot: Robot, scenario: Scenario) -> Any: ...

    def fold(self, memory: Any, rows: Log) -> tuple[Any, Any]: ...

    def keep(self, outputs: Any) -> Any: ...

    def finish(self, memory: Any, kept: Any, final: LoopState, scenario: Scenario, realism: Realism | None) -> Any: ...


def largest_divisor(n: int, at_most: int) -> int:
    """The largest divisor of ``n`` that is at most ``at_most`` (1 if none larger)."""
    return max(d for d in range(1, at_most + 1) if n % d == 0)


#: Steps per inner scan of [`rollout()`][spacegrasp_jax.loop.simulate.rollout]: the largest log field (7 numbers) times 8 is 56,
#: under the 64 numbers (512 bytes) up to which XLA's CPU runtime runs a loop in sequence.
LOG_BLOCK = 8


@dataclasses.dataclass(frozen=True)
class FullLog:
    """The observer that keeps every row: the [`Log`][spacegrasp_jax.loop.simulate.Log] of the whole run.

    Attributes:
        block_steps: plant steps per inner scan at most (``None``: ``LOG_BLOCK``): the
            largest number of whole control periods that fits and divides the run's (at
            least one).
    """

    block_steps: int | None = None

    def periods_per_block(self, body: LoopBody) -> int:
        steps = LOG_BLOCK if self.block_steps is None else self.block_steps
        return largest_divisor(body.periods, max(1, steps // body.steps_per_period))

    def init(self, robot: Robot, scenario: Scenario) -> tuple:
        return ()

    def fold(self, memory: tuple, rows: Log) -> tuple[tuple, Log]:
        return memory, rows

    def keep(self, outputs: Log) -> Log:
        return _merge_leading_axes(outputs)

    def finish(self, memory, kept: Log, final, scenario: Scenario, realism) -> Log:
        return _merge_leading_axes(kept)


def _merge_leading_axes(rows: Log) -> Log:
    """Rows stacked as (A, B, ...) as (A B, ...)."""
    return jax.tree.map(lambda x: x.reshape((x.shape[0] * x.shape[1],) + x.shape[2:]), rows)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RunSpec:
    """One closed-loop run, all of it but the gains and the noise key: the plant, the
    controller, the loop's stages and what the loop keeps. [`closed_loop()`][spacegrasp_jax.loop.simulate.closed_loop] runs it,
    [`experiment.run()`][spacegrasp_jax.jobs.experiment.run] on the host.

    A pytree: the robot, the scenario, the realism's numbers, the controller's model and the
    added stages' numbers are its arrays (each may carry a vmap batch axis); the controller,
    the observer, the options and every static setting of its parts (the realism's stages and
    timing, the scenario's steps, the added stages' kinds and settings) are its structure. Two specs that differ only in numbers
    run one compiled program, and the host looks programs up by the spec's structure and its
    arrays' shapes ([`experiment.compiled_loop()`][spacegrasp_jax.jobs.experiment.compiled_loop]), never by a key written by hand.

    Attributes:
        robot: the plant's [`Robot`][spacegrasp_jax.core.model.Robot].
        scenario: the [`Scenario`][spacegrasp_jax.envelope.scenario.Scenario] (initial state, LAR or target, contact sphere, trajectory,
            ``dt``, duration).
        controller: static: a [`Controller`][spacegrasp_jax.loop.control.law.Controller]; a law's name (``"admittance"``, eqs 9-17;
            ``"cartesian"``, eqs 21-22; any of ``control.CONTROLLERS``: the paper's exact
            pseudoinverse) or a law object with its settings
            (``control.Admittance(pinv_damping=0.01)``) is made one
            ([`as_controller()`][spacegrasp_jax.loop.control.registry.as_controller]).
        realism: the realism settings ([`loop_body()`][spacegrasp_jax.loop.simulate.loop_body]; ``None``: the paper's loop).
        model_robot: the robot the controller's model starts from (``None``: ``robot``); its
            satellite mass and inertia are scaled by the realism's factors.
        stages: stages added to the realism's, each on its signal after the realism's own
            ([`spacegrasp_jax.loop.stages`][spacegrasp_jax.loop.stages]: a delay line, an actuator's
            lag, a sensor of your own); with any, the log keeps the readings.
        observer: static: what the loop keeps ([`Observer`][spacegrasp_jax.loop.simulate.Observer]; default
            [`FullLog`][spacegrasp_jax.loop.simulate.FullLog], the whole log).
        options: static: how the loop is compiled and differentiated
            ([`LoopOptions`][spacegrasp_jax.loop.simulate.LoopOptions]: checkpointing for reverse
            mode).
    """

    robot: Robot
    scenario: Scenario
    controller: Any = dataclasses.field(default="admittance", metadata=dict(static=True))
    realism: Realism | None = None
    model_robot: Robot | None = None
    stages: tuple = ()
    observer: Any = dataclasses.field(default=FullLog(), metadata=dict(static=True))
    options: LoopOptions = dataclasses.field(default=LoopOptions(), metadata=dict(static=True))

    def __post_init__(self):
        object.__setattr__(self, "controller", as_controller(self.controller))


def closed_loop(spec: RunSpec, gains: Gains, key: jax.Array | None = None) -> tuple[LoopState, Any]:
    """The closed loop of ``spec`` over its scenario's duration, one ``jax.lax.scan`` over
    control periods ([`loop_body()`][spacegrasp_jax.loop.simulate.loop_body]), with what ``spec.observer`` keeps of it.

    Args:
        spec: the run ([`RunSpec`][spacegrasp_jax.loop.simulate.RunSpec]).
        gains: the gains, or a gain schedule ([`control.schedule`][spacegrasp_jax.loop.control.schedule]; any leaf may
            carry a vmap batch axis).
        key: the ``jax.random`` key of the sensors' noise (needed with noisy sensors).

    Returns:
        ``(final, observed)``: the [`LoopState`][spacegrasp_jax.loop.simulate.LoopState] after the
        last step and the observer's result.
    """
    robot, scenario, observer = spec.robot, spec.scenario, spec.observer
    body = loop_body(spec, gains, key)
    block = observer.periods_per_block(body)
    if block < 1 or body.periods % block:
        raise ValueError(f"the observer's block of {block} periods does not divide the {body.periods} control periods")
    cut = gradient_cut(spec.options.gradient_from_s, body.steps_per_period * scenario.dt, block, body.periods)
    dtype = scenario.initial.q.dtype
    carry = (body.start, observer.init(robot, scenario), jnp.zeros((), dtype))
    if cut:
        held = loop_body(jax.lax.stop_gradient(spec), jax.lax.stop_gradient(gains), key)
        carry, kept_before = _scan_periods(held, observer, block, carry, cut)
        carry = jax.lax.stop_gradient(carry)
    start = carry[0]
    if spec.options.checkpoint:
        # The gains drive every part of the loop's state but a fixed target's: those parts
        # carry their derivative from the start, so reverse mode linearises the period once.
        start = with_derivative_of(start, gains)
        if not scenario.free_target:
            start = dataclasses.replace(start, plant=dataclasses.replace(start.plant, target=carry[0].plant.target))
    (final, memory, _), kept = _scan_periods(body, observer, block, (start, *carry[1:]), body.periods - cut)
    if cut:
        kept = jax.tree.map(lambda before, after: jnp.concatenate([before, after]), kept_before, kept)
    return final, observer.finish(memory, kept, final, scenario, spec.realism)


def gradient_cut(gradient_from_s: float | None, period_s: float, block: int, periods: int) -> int:
    """The control periods before a truncated backpropagation's cut
    ([`LoopOptions`][spacegrasp_jax.loop.simulate.LoopOptions]' ``gradient_from_s``): the first
    multiple of ``block`` periods of ``period_s`` seconds at or after ``gradient_from_s``; 0
    for ``None``. A cut at or past the run's ``periods`` is an error: nothing would be
    differentiated."""
    if gradient_from_s is None:
        return 0
    periods_before = int(np.ceil(round(gradient_from_s / period_s, 9)))
    cut = -(-periods_before // block) * block
    if cut >= periods:
        raise ValueError(
            f"gradient_from_s: {gradient_from_s:g} s is at or past the run's end ({periods * period_s:g} s): "
            "nothing would be differentiated"
        )
    return cut


def _scan_periods(body: LoopBody, observer, block: int, carry: tuple, periods: int):
    """``periods`` control periods of ``body`` from ``carry = (state, memory, k)``, in
    blocks of ``block``: ``(carry, kept)``."""

    # The period number rides in the carry rather than being scanned over: the loop then
    # reads no array longer than 64 numbers, and XLA's CPU runtime runs its body as a sequence.
    def period_and_fold(carry, _):
        state, memory, k = carry
        state, rows = body.period(state, k)
        memory, output = observer.fold(memory, rows)
        return (state, memory, k + 1), output

    if block == 1:
        return jax.lax.scan(period_and_fold, carry, None, length=periods)

    def run_block(carry, _):
        carry, outputs = jax.lax.scan(period_and_fold, carry, None, length=block)
        return carry, observer.keep(outputs)

    return jax.lax.scan(run_block, carry, None, length=periods // block)


def rollout(
    robot: Robot,
    scenario: Scenario,
    gains: Gains,
    controller,
    block_steps: int | None = None,
    realism: Realism | None = None,
    key: jax.Array | None = None,
    model_robot: Robot | None = None,
    options: LoopOptions | None = None,
    *,
    checkpoint_segment: int | None = None,
) -> tuple[LoopState, Log]:
    """Simulate the closed loop over ``scenario.duration`` and keep its whole log: in one
    call, [`closed_loop()`][spacegrasp_jax.loop.simulate.closed_loop] of ``RunSpec(robot, scenario, controller, realism=realism,
    model_robot=model_robot, observer=FullLog(block_steps), options=options)``
    ([`RunSpec`][spacegrasp_jax.loop.simulate.RunSpec]).

    Args:
        robot, scenario, gains: pytrees (any leaf may carry a vmap batch axis).
        controller: static: a law's name (``"admittance"``, eqs 9-17; ``"cartesian"``, eqs
            21-22; any of ``control.CONTROLLERS``), a law object (``control.Admittance()``)
            or a ``control.Controller``
            ([`as_controller()`][spacegrasp_jax.loop.control.registry.as_controller]); a law
            object carries its settings (``control.Admittance(pinv_damping=0.01)``: damped
            least squares; a name: the paper's exact pseudoinverse).
        block_steps: the log's block: steps per inner scan of the loop (static; must divide
            ``n_steps``; ``None``: ``LOG_BLOCK`` or the largest divisor below it; a loop
            whose control period spans several steps runs whole periods;
            [`FullLog`][spacegrasp_jax.loop.simulate.FullLog]'s ``block_steps``). Where XLA runs
            loops kernel by kernel, an inner scan whose arrays stay within 64 numbers runs
            as a sequence: a checkpointed step's three RK4 rates are (3, 7), so inner scans
            of 2 steps hold none larger (with loops compiled whole the length does not
            matter). How each control period is checkpointed is ``options``'.
        realism: the realism settings ([`loop_body()`][spacegrasp_jax.loop.simulate.loop_body]; ``None``: the paper's loop).
        key: the ``jax.random`` key of the sensors' noise (needed with noisy sensors).
        model_robot: the robot the controller believes, if not ``robot``.
        options: static: the loop's [`LoopOptions`][spacegrasp_jax.loop.simulate.LoopOptions]
            (``None``: ``LoopOptions(checkpoint=True)``;
            [`experiment.loop_options(checkpoint=True)`][spacegrasp_jax.jobs.experiment.loop_options]
            gives the one this process compiles best).
        checkpoint_segment: ``block_steps``' name before, with a ``DeprecationWarning``.

    Returns:
        ``(final_state, log)``: the [`LoopState`][spacegrasp_jax.loop.simulate.LoopState] after
        ``scenario.n_steps`` steps and the [`Log`][spacegrasp_jax.loop.simulate.Log]. A diverging rollout carries non-finite
        values from the first bad step on; [`first_nonfinite_time()`][spacegrasp_jax.loop.simulate.first_nonfinite_time] finds it (``experiment.run`` reports it).
    """
    if checkpoint_segment is not None:
        warnings.warn("rollout: checkpoint_segment is now block_steps", DeprecationWarning, stacklevel=2)
        block_steps = checkpoint_segment if block_steps is None else block_steps
    n_steps = scenario.n_steps
    if block_steps is not None and (block_steps < 1 or n_steps % block_steps):
        raise ValueError(f"block_steps: {block_steps} must be a positive divisor of the {n_steps} steps")
    spec = RunSpec(
        robot,
        scenario,
        controller,
        realism=realism,
        model_robot=model_robot,
        observer=FullLog(block_steps),
        options=LoopOptions(checkpoint=True) if options is None else options,
    )
    return closed_loop(spec, gains, key)


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
