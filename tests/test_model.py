"""The Robot pytree: the paper's numbers, the TOML loader, and every validation error."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import spacegrasp_jax as sg
from spacegrasp_jax.core.model import body_inertials, inertia_from_table, make_robot

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "paper_robot.toml"


def robot_fields(robot: sg.Robot) -> dict:
    return {field.name: np.asarray(getattr(robot, field.name)) for field in dataclasses.fields(robot)}


def test_paper_robot_matches_the_paper(robot):
    """Spot checks against Tables 1-3 and section 4, typed from the paper."""
    assert float(robot.satellite_mass) == 500.0
    np.testing.assert_array_equal(robot.satellite_inertia, np.diag([79.0, 79.0, 117.0]))
    np.testing.assert_array_equal(robot.mount_position, [0.2, 0.2, 0.2])
    # Table 1 as the chain's fixed transforms: (L_i, 0, lambda_i) and Rx(alpha_i).
    np.testing.assert_array_equal(robot.frame_position[:, 2], [0.4, -0.35, -0.3, -0.35, -0.3, 0.3, 0.25])
    np.testing.assert_array_equal(robot.frame_position[:, 0], [0, 0, 0.6, 0.35, 0, 0, 0])
    np.testing.assert_array_equal(robot.frame_position[:, 1], 0.0)
    alpha = np.pi / 2 * np.array([1, 1, 0, 0, -1, 1, 0])
    for rotation, a in zip(np.asarray(robot.frame_rotation), alpha):
        c, s = np.cos(a), np.sin(a)
        np.testing.assert_allclose(rotation, [[1, 0, 0], [0, c, -s], [0, s, c]], rtol=0, atol=1e-16)
    np.testing.assert_array_equal(robot.mount_rotation, np.eye(3))
    np.testing.assert_array_equal(robot.joint_position_limit, np.tile([-np.inf, np.inf], (7, 1)))
    np.testing.assert_allclose(robot.joint_offset, np.pi / 2 * np.array([1, 1, 0, 0, 0, 1, 0]), rtol=0, atol=0)
    np.testing.assert_array_equal(robot.link_mass, [15, 13, 18, 10, 8.5, 10.5, 5])
    assert float(robot.link_inertia[2, 0, 2]) == 0.2 and float(robot.link_inertia[3, 2, 0]) == 0.1
    assert float(robot.ee_mass) == 7.0
    np.testing.assert_array_equal(robot.ee_offset, [0, 0, 0.175])
    assert all(leaf.dtype == jnp.float64 for leaf in jax.tree.leaves(robot))


def test_toml_config_gives_the_paper_robot(robot):
    loaded = sg.load_robot(CONFIG)
    for name, value in robot_fields(robot).items():
        np.testing.assert_array_equal(robot_fields(loaded)[name], value, err_msg=name)


def test_body_inertials_merge_link7_and_ee(robot):
    mass, com, inertia = body_inertials(robot)
    assert float(mass[-1]) == 12.0  # link 7 (5 kg) + EE (7 kg)
    # Link 7's CoM is 0.1 m past frame 6's origin, i.e. 0.15 m before frame 7's origin;
    # the EE's is 0.1 m past frame 7's origin: combined (5 * -0.15 + 7 * 0.1) / 12.
    np.testing.assert_allclose(com[-1], [0, 0, (5 * -0.15 + 7 * 0.1) / 12], atol=1e-15)
    # Parallel axes for the two z-offset bodies: Ixx gains sum m d^2.
    d7, de = -0.15 - com[-1, 2], 0.1 - com[-1, 2]
    np.testing.assert_allclose(inertia[-1, 0, 0], 0.3 + 0.09 + 5 * d7**2 + 7 * de**2, rtol=1e-14)
    np.testing.assert_allclose(inertia[-1, 2, 2], 0.3 + 0.12, rtol=1e-14)
    # The modelling notes' reading, by hand: link 3 (L = 0.6, lambda = -0.3) has its CoM halfway
    # along its 0.6 m length, at (0.3 - 0.6, 0, -0.2 + 0.3) from frame 3's origin.
    np.testing.assert_allclose(com[2], [-0.3, 0.0, -0.2 - (-0.3)], atol=1e-15)


def test_robot_is_a_pytree_that_vmaps(robot):
    """A batch of robots with perturbed satellite masses is a Robot with a batch axis."""
    masses = jnp.array([400.0, 500.0, 600.0])
    batch = jax.tree.map(lambda leaf: jnp.broadcast_to(leaf, (3,) + leaf.shape), robot)
    batch = dataclasses.replace(batch, satellite_mass=masses)
    q = jnp.asarray(sg.PAPER_Q_INIT)
    M = jax.vmap(sg.mass_matrix, in_axes=(0, None, None))(batch, jnp.eye(3), q)
    np.testing.assert_allclose(M[:, 0, 0], masses + 87.0, rtol=1e-14)


# ---- validation ---------------------------------------------------------------------------


def paper_fields() -> dict:
    return robot_fields(sg.paper_robot())


def paper_dh_fields() -> dict:
    """The paper's robot with its arm as Table 1's DH columns, as ``configs/paper_robot.toml`` gives it."""
    fields = {k: v for k, v in paper_fields().items() if k not in ("frame_rotation", "frame_position")}
    half_pi = np.pi / 2
    return fields | {
        "dh_lambda": np.array([0.4, -0.35, -0.3, -0.35, -0.3, 0.3, 0.25]),
        "dh_length": np.array([0.0, 0.0, 0.6, 0.35, 0.0, 0.0, 0.0]),
        "dh_alpha": np.array([half_pi, half_pi, 0.0, 0.0, -half_pi, half_pi, 0.0]),
    }


def with_field(name, value) -> dict:
    fields = paper_fields()
    fields[name] = value
    return fields


BAD_FIELDS = [
    ("missing", lambda f: {k: v for k, v in f.items() if k != "ee_mass"}, r"missing robot field\(s\): ee_mass"),
    ("unknown", lambda f: {**f, "gripper_mass": 1.0}, r"unknown robot field\(s\): gripper_mass"),
    (
        "wrong length",
        lambda f: {**f, "link_mass": f["link_mass"][:6]},
        r"disagree on its number of joints: joint_offset has 7, frame_rotation has 7, frame_position has 7, "
        r"link_mass has 6",
    ),
    (
        "wrong shape",
        lambda f: {**f, "link_com": f["link_com"][:, :2]},
        r"link_com: expected shape \(7, 3\) \(7 joints\), got \(7, 2\)",
    ),
    ("not numbers", lambda f: {**paper_dh_fields(), "dh_alpha": ["a"] * 7}, r"dh_alpha: expected numbers"),
    ("nan", lambda f: {**paper_dh_fields(), "dh_lambda": [np.nan] + [0.0] * 6}, r"dh_lambda: must be finite"),
    (
        "DH and frames",
        lambda f: {**f, "dh_lambda": [0.0] * 7, "dh_length": [0.0] * 7, "dh_alpha": [0.0] * 7},
        r"frame_rotation, frame_position: give the arm as a DH table or as frames, not both",
    ),
    (
        "half a DH table",
        lambda f: {k: v for k, v in paper_dh_fields().items() if k != "dh_alpha"},
        r"missing robot field\(s\): dh_alpha \(a DH table needs all three\)",
    ),
    (
        "DH columns of different lengths",
        lambda f: {**paper_dh_fields(), "dh_length": [0.0] * 6},
        r"the DH table's columns differ in length: dh_lambda has 7, dh_length has 6, dh_alpha has 7",
    ),
    (
        "too few joints",
        lambda f: {**f, "link_mass": [1.0] * 5},
        r"link_mass: an arm of 5 joint\(s\).*at least 6 joints",
    ),
    (
        "not a rotation",
        lambda f: {**f, "mount_rotation": np.diag([1.0, 1.0, -1.0])},
        r"mount_rotation: not a rotation matrix",
    ),
    (
        "skewed frame",
        lambda f: {
            **f,
            "frame_rotation": np.concatenate([f["frame_rotation"][:2], 1.1 * np.eye(3)[None], f["frame_rotation"][3:]]),
        },
        r"frame_rotation\[2\]: not a rotation matrix",
    ),
    (
        "empty position range",
        lambda f: {**f, "joint_position_limit": [[-1.0, 1.0]] * 6 + [[1.0, 1.0]]},
        r"joint_position_limit: each joint's \[lower, upper\] must have lower < upper",
    ),
    (
        "massless EE with inertia",
        lambda f: {**f, "ee_mass": 0.0},
        r"ee_mass, ee_inertia: an EE body without mass has no inertia",
    ),
    ("inf", lambda f: {**f, "mount_position": [0.2, np.inf, 0.2]}, r"mount_position: must be finite"),
    ("zero mass", lambda f: {**f, "satellite_mass": 0.0}, r"satellite_mass: masses must be positive"),
    (
        "zero rate limit",
        lambda f: {**f, "joint_rate_limit": [1.0] * 6 + [0.0]},
        r"joint_rate_limit: limits must be positive",
    ),
    ("short torque limits", lambda f: {**f, "joint_torque_limit": [10.0] * 6}, r"joint_torque_limit has 6"),
    (
        "negative mass",
        lambda f: {**f, "link_mass": np.r_[f["link_mass"][:3], -1.0, f["link_mass"][4:]]},
        r"link_mass: masses must be positive",
    ),
    (
        "asymmetric",
        lambda f: {**f, "ee_inertia": f["ee_inertia"] + np.triu(np.ones((3, 3)), 1) * 0.01},
        r"ee_inertia: inertia tensor is not symmetric",
    ),
    (
        "not positive definite",
        lambda f: {**f, "satellite_inertia": np.diag([79.0, -1.0, 117.0])},
        r"satellite_inertia: inertia tensor is not positive definite",
    ),
    (
        "triangle inequality",
        lambda f: {
            **f,
            "link_inertia": np.concatenate(
                [f["link_inertia"][:4], np.diag([0.1, 0.1, 0.5])[None], f["link_inertia"][5:]]
            ),
        },
        r"link_inertia\[4\]: principal moments .* break the triangle inequality",
    ),
]


@pytest.mark.parametrize("case, change, message", BAD_FIELDS, ids=[case[0] for case in BAD_FIELDS])
def test_make_robot_rejects_bad_fields(case, change, message):
    with pytest.raises(sg.RobotConfigError, match=message):
        make_robot(**change(paper_fields()))


def test_the_dh_table_and_the_frames_it_converts_to_give_the_same_robot():
    """Table 1 as DH columns and as the general chain's frames: the same robot, bit for bit."""
    from_table, from_frames = make_robot(**paper_dh_fields()), make_robot(**paper_fields())
    for name, value in robot_fields(from_frames).items():
        np.testing.assert_array_equal(robot_fields(from_table)[name], value, err_msg=name)


def test_an_arm_of_six_joints_without_an_ee_body():
    """The paper's first six links, the seventh and the EE merged into nothing: N = 6, an
    empty EE body, limits of its own (the paper's default limits are the 7-joint arm's)."""
    f = paper_fields()
    six = {
        k: (
            v[:6]
            if k
            in (
                "joint_offset",
                "frame_rotation",
                "frame_position",
                "link_mass",
                "link_com",
                "link_inertia",
                "joint_position_limit",
            )
            else v
        )
        for k, v in f.items()
    }
    six |= {"ee_mass": 0.0, "ee_inertia": np.zeros((3, 3)), "joint_rate_limit": [1.0] * 6}
    with pytest.raises(sg.RobotConfigError, match=r"joint_torque_limit \(the default limits are the paper's 7-joint"):
        make_robot(**{k: v for k, v in six.items() if k != "joint_torque_limit"})
    robot = make_robot(**(six | {"joint_torque_limit": [5.0] * 6}))
    mass, _, _ = body_inertials(robot)
    np.testing.assert_array_equal(mass, [15.0, 13.0, 18.0, 10.0, 8.5, 10.5])
    assert sg.mass_matrix(robot, jnp.eye(3), jnp.zeros(6)).shape == (12, 12)


def test_config_error_is_a_value_error():
    assert issubclass(sg.RobotConfigError, ValueError)


def edited_config(tmp_path, old: str, new: str) -> Path:
    text = CONFIG.read_text()
    assert old in text, old
    path = tmp_path / "robot.toml"
    path.write_text(text.replace(old, new, 1))
    return path


BAD_TOML = [
    ("missing key", "mass = 7.0", "", r"missing robot field\(s\): end_effector.mass"),
    ("unknown key", "[end_effector]", "[end_effector]\ncolour = 1.0", r"unknown robot key end_effector.colour"),
    ("unknown table", "[arm]", "[gripper]\nsize = 1.0\n[arm]", r"unknown robot key gripper.size"),
    (
        "wrong length",
        "link_mass = [15.0, 13.0, 18.0, 10.0, 8.5, 10.5, 5.0]",
        "link_mass = [15.0, 13.0]",
        r"arm.link_mass: an arm of 2 joint\(s\)",
    ),
    ("nan", "mass = 500.0", "mass = nan", r"satellite.mass: must be finite"),
    ("negative mass", "mass = 7.0", "mass = -7.0", r"end_effector.mass: a mass must be positive or 0"),
    (
        "DH column too short",
        "dh_length = [0.0, 0.0, 0.6, 0.35, 0.0, 0.0, 0.0]",
        "dh_length = [0.0, 0.0, 0.6]",
        r"the DH table's columns differ in length: arm.dh_lambda has 7, arm.dh_length has 3",
    ),
    (
        "not positive definite",
        "[[79.0, 0.0, 0.0], [0.0, 79.0, 0.0], [0.0, 0.0, 117.0]]",
        "[[79.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 117.0]]",
        r"satellite.inertia: inertia tensor is not positive definite",
    ),
    (
        "triangle",
        "[[0.09, 0.0, 0.0], [0.0, 0.05, 0.0], [0.0, 0.0, 0.12]]",
        "[[0.01, 0.0, 0.0], [0.0, 0.05, 0.0], [0.0, 0.0, 0.12]]",
        r"end_effector.inertia: principal moments",
    ),
    (
        "asymmetric",
        "[[0.3, 0.0, 0.2], [0.0, 1.0, 0.0], [0.2, 0.0, 1.0]]",
        "[[0.3, 0.0, 0.2], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]",
        r"arm.link_inertia\[2\]: inertia tensor is not symmetric",
    ),
    ("syntax", "mass = 500.0", "mass = = 500.0", r"not valid TOML"),
]


@pytest.mark.parametrize("case, old, new, message", BAD_TOML, ids=[case[0] for case in BAD_TOML])
def test_load_robot_rejects_bad_files_naming_the_key(tmp_path, case, old, new, message):
    path = edited_config(tmp_path, old, new)
    with pytest.raises(sg.RobotConfigError, match=message) as error:
        sg.load_robot(path)
    assert str(path) in str(error.value)


def test_load_robot_accepts_an_edited_valid_file(tmp_path):
    path = edited_config(tmp_path, "mass = 500.0", "mass = 750.0")
    assert float(sg.load_robot(path).satellite_mass) == 750.0


def test_inertia_from_table_layout():
    tensor = inertia_from_table([1.0, 2.0, 3.0, 0.1, 0.2, 0.3])
    np.testing.assert_array_equal(tensor, [[1.0, 0.1, 0.2], [0.1, 2.0, 0.3], [0.2, 0.3, 3.0]])
    assert re.search("Ixz", inertia_from_table.__doc__)
