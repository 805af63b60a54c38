"""Real arms from URDF (a Franka Panda, 7 joints, and a UR5, 6 joints, as example-robot-data
ships them, and the paper's arm written as URDF) against Pinocchio reading the same files.

Pinocchio builds each system its own way: the arm's URDF as a fixed-base model (the gripper's
finger joints locked at zero), appended to a free-flyer satellite body at the mount, the
free-flyer's frame moved to the whole base body's CoM (our base frame). Compared on 20 random
states each: the frames, the end-effector pose, the mass matrix, the bias forces, forward
dynamics and the Dynamic Jacobian, to 1e-9 relative."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import numpy as np
import pinocchio as pin
import pinocchio_reference as ref
import pytest
from random_states import make_random_states

import spacegrasp_jax as sg
from spacegrasp_jax.core.urdf import robot_from_urdf, robot_to_urdf
from spacegrasp_jax.loop.simulate import RunSpec

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
RTOL = 1e-9
N_STATES = 20


@dataclasses.dataclass(frozen=True)
class Arm:
    mounting: str  # the mounting TOML in configs/
    urdf: str  # the URDF it mounts, in configs/
    tip: str
    locked: tuple[str, ...]  # joints Pinocchio locks at zero (they ride with the last link)
    mass: float  # the moving links' mass (not the base link's), kg: the URDF's <mass> values summed by hand
    joints: int


ARMS = {
    "panda": Arm(
        "panda_on_satellite.toml",
        "arms/panda.urdf",
        "panda_hand_tcp",
        ("panda_finger_joint1", "panda_finger_joint2"),
        16.822132,
        7,
    ),
    "ur5": Arm("ur5_on_satellite.toml", "arms/ur5_robot.urdf", "tool0", (), 16.9939, 6),
}


def pinocchio_system(arm: Arm, satellite_mass, satellite_inertia, mount_position, mount_rpy):
    """``(model, tip frame id)``: Pinocchio's free-floating system of ``arm`` on the satellite,
    its free-flyer frame at the base body's CoM with the satellite's axes."""
    fixed = pin.buildModelFromUrdf(str(CONFIGS / arm.urdf))
    if arm.locked:
        fixed = pin.buildReducedModel(fixed, [fixed.getJointId(name) for name in arm.locked], pin.neutral(fixed))

    def build(com):
        model = pin.Model()
        base = model.addJoint(0, pin.JointModelFreeFlyer(), pin.SE3.Identity(), "satellite")
        model.appendBodyToJoint(base, pin.Inertia(satellite_mass, -com, satellite_inertia), pin.SE3.Identity())
        body = model.addFrame(pin.Frame("satellite_body", base, 0, pin.SE3.Identity(), pin.FrameType.BODY))
        mount = pin.SE3(pin.rpy.rpyToMatrix(*mount_rpy), np.asarray(mount_position) - com)
        model = pin.appendModel(model, fixed, body, mount)
        model.gravity = pin.Motion.Zero()
        return model

    com = build(np.zeros(3)).inertias[1].lever  # the satellite with the arm's base link
    model = build(com)
    assert np.linalg.norm(model.inertias[1].lever) < 1e-15
    return model, model.getFrameId(arm.tip)


def paper_as_urdf():
    """The paper's arm, written as URDF and read back; Pinocchio reads the same text."""
    text = robot_to_urdf(sg.paper_robot())
    model = pin.buildModelFromXML(text, pin.JointModelFreeFlyer())
    model.gravity = pin.Motion.Zero()
    return robot_from_urdf(text), model, model.getFrameId("ee")


@pytest.fixture(scope="module", params=["panda", "ur5", "paper"])
def system(request):
    """``(robot, Pinocchio model, its data, tip frame id)`` of each arm."""
    if request.param == "paper":
        robot, model, tip = paper_as_urdf()
    else:
        arm = ARMS[request.param]
        robot = sg.load_robot(CONFIGS / arm.mounting)
        model, tip = pinocchio_system(arm, 500.0, np.diag([79.0, 79.0, 117.0]), [0.2, 0.2, 0.2], [0.0, 0.0, 0.0])
    return robot, model, model.createData(), tip


def relative_error(actual, expected) -> float:
    actual, expected = np.asarray(actual), np.asarray(expected)
    return float(np.max(np.abs(actual - expected)) / np.max(np.abs(expected)))


def states(robot):
    return make_random_states(seed=20261203, count=N_STATES, n_joints=sg.core.model.n_joints(robot))


def test_the_mounting_files_read_the_arms_as_their_urdfs_give_them():
    for name, arm in ARMS.items():
        robot = sg.load_robot(CONFIGS / arm.mounting)
        assert sg.core.model.n_joints(robot) == arm.joints, name
        mass, _, _ = sg.core.model.body_inertials(robot)
        np.testing.assert_allclose(float(np.sum(mass)), arm.mass, rtol=1e-12, err_msg=name)


def test_frames_and_the_tip_pose_match_pinocchio(system):
    robot, model, data, tip = system
    fk = jax.jit(sg.forward_kinematics)
    for s in states(robot):
        qp = ref.configuration(s.p_base, s.R_base, s.q, model)
        pin.forwardKinematics(model, data, qp)
        pin.updateFramePlacements(model, data)
        pin.computeJointJacobians(model, data, qp)
        frames = fk(robot, s.p_base, s.R_base, s.q)
        np.testing.assert_allclose(frames.p_ee, data.oMf[tip].translation, rtol=0, atol=1e-12)
        np.testing.assert_allclose(frames.R_ee, data.oMf[tip].rotation, rtol=0, atol=1e-12)
        for joint in range(len(s.q)):  # Pinocchio's joint joint + 2 (after the universe and the free flyer)
            placement = data.oMi[joint + 2]
            axis = pin.getJointJacobian(model, data, joint + 2, pin.WORLD)[3:, 6 + joint]
            np.testing.assert_allclose(frames.joint_axis[joint], axis, rtol=0, atol=1e-12)
            # Our frame j-1's origin is a point on the joint's axis: Pinocchio's joint origin is another.
            offset = frames.joint_origin[joint] - placement.translation
            np.testing.assert_allclose(np.cross(offset, axis), 0.0, rtol=0, atol=1e-12)


def test_mass_matrix_bias_and_forward_dynamics_match_pinocchio(system):
    robot, model, data, _ = system
    mass_matrix, bias, forward = (jax.jit(f) for f in (sg.mass_matrix, sg.bias_forces, sg.forward_dynamics))
    rng = np.random.default_rng(3)
    for s in states(robot):
        T = ref.velocity_map(s.R_base, len(s.q))
        qp = ref.configuration(s.p_base, s.R_base, s.q, model)
        v_pin = T @ np.concatenate([s.V_base, s.qd])
        M_pin = pin.crba(model, data, qp)
        M_pin = np.triu(M_pin) + np.triu(M_pin, 1).T
        assert relative_error(mass_matrix(robot, s.R_base, s.q), T.T @ M_pin @ T) <= RTOL
        c = ref.frame_acceleration_offset(s.R_base, s.V_base, len(s.q))
        expected_bias = T.T @ (M_pin @ c + pin.nonLinearEffects(model, data, qp, v_pin))
        assert relative_error(bias(robot, s.R_base, s.q, s.V_base, s.qd), expected_bias) <= RTOL
        Q = np.concatenate([rng.normal(scale=5.0, size=6), rng.normal(scale=2.0, size=len(s.q))])
        a_pin = pin.aba(model, data, qp, v_pin, T @ Q)
        expected = T.T @ (a_pin - c)
        assert relative_error(forward(robot, s.R_base, s.q, s.V_base, s.qd, Q), expected) <= RTOL


def test_dynamic_jacobian_matches_pinocchio(system):
    robot, model, data, tip = system
    dynamic_jacobian = jax.jit(sg.dynamic_jacobian)
    for s in states(robot):
        T = ref.velocity_map(s.R_base, len(s.q))
        qp = ref.configuration(s.p_base, s.R_base, s.q, model)
        J_tip = pin.computeFrameJacobian(model, data, qp, tip, pin.LOCAL_WORLD_ALIGNED) @ T
        A = pin.computeCentroidalMap(model, data, qp) @ T  # momentum about the CoM, world axes
        expected = J_tip[:, 6:] - J_tip[:, :6] @ np.linalg.solve(A[:, :6], A[:, 6:])
        assert relative_error(dynamic_jacobian(robot, s.R_base, s.q), expected) <= RTOL


def test_the_papers_arm_from_its_urdf_is_the_arm_of_its_tables():
    """The paper's robot (Tables 1-3, DH) and the robot read back from the URDF written from it:
    the same satellite, bodies, frames, end-effector and dynamics to 1e-12 (the URDF's frame 7 is
    the end-effector's, the EE body merged into link 7, the joint offsets folded into the frames)."""
    tables = sg.paper_robot()
    urdf = robot_from_urdf(robot_to_urdf(tables))
    for field in (
        "satellite_mass",
        "satellite_inertia",
        "mount_position",
        "mount_rotation",
        "joint_rate_limit",
        "joint_torque_limit",
    ):
        np.testing.assert_allclose(getattr(urdf, field), getattr(tables, field), rtol=0, atol=1e-12, err_msg=field)
    np.testing.assert_allclose(
        sg.core.model.body_inertials(urdf)[0], sg.core.model.body_inertials(tables)[0], rtol=1e-12
    )
    for s in make_random_states(seed=5, count=N_STATES):
        for name in ("mass_matrix", "dynamic_jacobian"):
            f = getattr(sg, name)
            assert relative_error(f(urdf, s.R_base, s.q), f(tables, s.R_base, s.q)) <= 1e-12, name
        a, b = (
            sg.forward_kinematics(urdf, s.p_base, s.R_base, s.q),
            sg.forward_kinematics(tables, s.p_base, s.R_base, s.q),
        )
        for field in ("joint_origin", "joint_axis", "p_ee", "R_ee"):
            np.testing.assert_allclose(getattr(a, field), getattr(b, field), rtol=0, atol=1e-12, err_msg=field)
        expected = sg.bias_forces(tables, s.R_base, s.q, s.V_base, s.qd)
        assert relative_error(sg.bias_forces(urdf, s.R_base, s.q, s.V_base, s.qd), expected) <= 1e-12


@pytest.mark.slow
@pytest.mark.parametrize("name", ["panda", "ur5"])
def test_the_shipped_scenario_and_gains_capture_with_each_arm(name):
    """The 17 s approach of configs/<arm>_scenario.toml with each shipped gains file in the
    loop it was tuned in (configs/<arm>_ideal_gains.json in the paper's loop,
    configs/<arm>_flight_gains.json under the flight preset): within the campaigns' capture
    tolerances (5 mm, 1 degree) and the arm's motors' limits."""
    import jax

    from spacegrasp_jax.envelope.scenario import load_scenario
    from spacegrasp_jax.jobs import experiment
    from spacegrasp_jax.loop.control import load_gains
    from spacegrasp_jax.loop.realism import flight

    arm = ARMS[name]
    robot = sg.load_robot(CONFIGS / arm.mounting)
    scenario = load_scenario(robot, CONFIGS / f"{name}_scenario.toml")
    for loop, realism in (("ideal", None), ("flight", flight(robot))):
        gains = load_gains(CONFIGS / f"{name}_{loop}_gains.json", "admittance", n_joints=arm.joints)
        spec = RunSpec(robot, scenario, "admittance", realism=realism)
        summary = experiment.run(spec, gains, key=None if realism is None else jax.random.PRNGKey(0)).summary
        assert summary["final_position_error_m"] <= 0.005, loop
        assert np.degrees(summary["final_orientation_error_rad"]) <= 1.0, loop
        assert summary["max_contact_force_N"] > 0.0, loop  # it did touch the ring
        assert np.all(np.asarray(summary["max_abs_torque_Nm"]) <= np.asarray(robot.joint_torque_limit)), loop
