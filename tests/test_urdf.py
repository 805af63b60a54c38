"""The robot written as URDF (``spacegrasp_jax.core.urdf``) read by Pinocchio's own URDF parser:
the same rigid-body system as the model ``tests/pinocchio_reference.py`` builds from the
paper's tables, and the robot's numbers read back from the XML. (``tests/test_dynamics.py``
and ``tests/test_kinematics.py`` check ours against both Pinocchio models.)"""

from __future__ import annotations

import xml.etree.ElementTree as ElementTree

import numpy as np
import pinocchio as pin
import pinocchio_reference as ref
import pytest

from spacegrasp_jax import cli
from spacegrasp_jax.core.urdf import robot_to_urdf

RTOL = 1e-12


def relative_error(actual, expected) -> float:
    actual, expected = np.asarray(actual), np.asarray(expected)
    return float(np.max(np.abs(actual - expected)) / np.max(np.abs(expected)))


def test_pinocchio_reads_the_urdf_as_the_tables_robot(robot, random_states):
    """At 20 random states: every joint frame, the EE frame, the mass matrix, the bias forces,
    forward dynamics under random torques, the centroidal momentum matrix and the EE's frame
    Jacobian (what the Dynamic Jacobian is made of) equal the reference model's to 1e-12."""
    reference, reference_ee = ref.build_model()
    reference_data = reference.createData()
    model = pin.buildModelFromXML(robot_to_urdf(robot), pin.JointModelFreeFlyer())
    model.gravity = pin.Motion.Zero()  # a URDF gives none; Pinocchio's default is the Earth's
    data = model.createData()
    assert (model.nq, model.nv) == (21, 13)
    assert [model.names[i] for i in range(2, model.njoints)] == [f"joint{i}" for i in range(1, 8)]
    ee = model.getFrameId("ee")
    rng = np.random.default_rng(11)
    for state in random_states:
        q_ref = ref.configuration(state.p_base, state.R_base, state.q)
        q_urdf = ref.configuration(state.p_base, state.R_base, state.q, model)
        v = ref.velocity_map(state.R_base) @ np.concatenate([state.V_base, state.qd])
        tau = np.concatenate([np.zeros(6), rng.normal(scale=20.0, size=7)])
        pairs = {}
        for name, (m, d, q, frame) in {
            "urdf": (model, data, q_urdf, ee),
            "tables": (reference, reference_data, q_ref, reference_ee),
        }.items():
            pin.framesForwardKinematics(m, d, q)
            pin.computeJointJacobians(m, d, q)
            M = pin.crba(m, d, q)
            pairs[name] = {
                "joint frames": np.stack([d.oMi[j].homogeneous for j in range(1, m.njoints)]),
                "ee frame": d.oMf[frame].homogeneous,
                "mass matrix": np.triu(M) + np.triu(M, 1).T,
                "bias": pin.nonLinearEffects(m, d, q, v),
                "forward dynamics": pin.aba(m, d, q, v, tau),
                "centroidal momentum matrix": pin.ccrba(m, d, q, v),
                "ee Jacobian": pin.getFrameJacobian(m, d, frame, pin.LOCAL_WORLD_ALIGNED),
            }
        for quantity, expected in pairs["tables"].items():
            assert relative_error(pairs["urdf"][quantity], expected) <= RTOL, quantity


def test_the_urdf_holds_the_robots_numbers(robot):
    """Read back with the standard library's XML parser: the masses, the limits, the joints'
    chain and types, every number written with enough digits to give the float64 back."""
    root = ElementTree.fromstring(robot_to_urdf(robot))
    links = {link.get("name"): link for link in root.iter("link")}
    joints = root.findall("joint")
    assert list(links) == ["satellite", *(f"link{i}" for i in range(1, 8)), "ee"]
    chain = [(j.find("parent").get("link"), j.find("child").get("link")) for j in joints]
    assert chain == list(zip(list(links)[:-1], list(links)[1:]))
    assert [j.get("type") for j in joints] == ["continuous"] * 7 + ["fixed"]

    def mass(name):
        return float(links[name].find("inertial/mass").get("value"))

    assert mass("satellite") == float(robot.satellite_mass) and mass("ee") == float(robot.ee_mass)
    assert [mass(f"link{i}") for i in range(1, 8)] == np.asarray(robot.link_mass).tolist()
    limits = [j.find("limit") for j in joints[:7]]
    assert [float(limit.get("effort")) for limit in limits] == np.asarray(robot.joint_torque_limit).tolist()
    assert [float(limit.get("velocity")) for limit in limits] == np.asarray(robot.joint_rate_limit).tolist()
    mount = [float(x) for x in joints[0].find("origin").get("xyz").split()]
    assert mount == np.asarray(robot.mount_position).tolist()


def test_info_writes_the_urdf_and_never_overwrites_a_file(robot, tmp_path, capsys):
    out = tmp_path / "arm.urdf"
    assert cli.main(["info", "--urdf", str(out)]) == 0
    assert out.read_text() == robot_to_urdf(robot)
    assert f"URDF written to {out}" in capsys.readouterr().out
    out.write_text("mine\n")
    assert cli.main(["info", "--urdf", str(out)]) == 2
    assert f"--urdf: {out} exists" in capsys.readouterr().err
    assert out.read_text() == "mine\n"


def test_a_batched_robot_is_refused(robot):
    import jax

    batched = jax.tree.map(lambda x: np.stack([x, x]), robot)
    with pytest.raises(ValueError, match="one robot, not a batch"):
        robot_to_urdf(batched)
