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
from spacegrasp_jax.model import body_inertials, inertia_from_table, make_robot

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "paper_robot.toml"


def robot_fields(robot: sg.Robot) -> dict:
    return {field.name: np.asarray(getattr(robot, field.name)) for field in dataclasses.fields(robot)}


def test_paper_robot_matches_the_paper(robot):
    """Spot checks against Tables 1-3 and section 4, typed from the paper."""
    assert float(robot.satellite_mass) == 500.0
    np.testing.assert_array_equal(robot.satellite_inertia, np.diag([79.0, 79.0, 117.0]))
    np.testing.assert_array_equal(robot.mount_position, [0.2, 0.2, 0.2])
    np.testing.assert_array_equal(robot.dh_lambda, [0.4, -0.35, -0.3, -0.35, -0.3, 0.3, 0.25])
    np.testing.assert_array_equal(robot.dh_length, [0, 0, 0.6, 0.35, 0, 0, 0])
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


def with_field(name, value) -> dict:
    fields = paper_fields()
    fields[name] = value
    return fields


BAD_FIELDS = [
    ("missing", lambda f: {k: v for k, v in f.items() if k != "ee_mass"}, r"missing robot field\(s\): ee_mass"),
    ("unknown", lambda f: {**f, "gripper_mass": 1.0}, r"unknown robot field\(s\): gripper_mass"),
    ("wrong length", lambda f: {**f, "link_mass": f["link_mass"][:6]}, r"link_mass: expected shape \(7,\), got \(6,\)"),
    ("wrong shape", lambda f: {**f, "link_com": f["link_com"].T}, r"link_com: expected shape \(7, 3\), got \(3, 7\)"),
    ("not numbers", lambda f: {**f, "dh_alpha": ["a"] * 7}, r"dh_alpha: expected numbers"),
    ("nan", lambda f: {**f, "dh_lambda": np.r_[np.nan, f["dh_lambda"][1:]]}, r"dh_lambda: must be finite"),
    ("inf", lambda f: {**f, "mount_position": [0.2, np.inf, 0.2]}, r"mount_position: must be finite"),
    ("zero mass", lambda f: {**f, "satellite_mass": 0.0}, r"satellite_mass: masses must be positive"),
    (
        "zero rate limit",
        lambda f: {**f, "joint_rate_limit": [1.0] * 6 + [0.0]},
        r"joint_rate_limit: limits must be positive",
    ),
    ("short torque limits", lambda f: {**f, "joint_torque_limit": [10.0] * 6}, r"joint_torque_limit: expected shape"),
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
        r"arm.link_mass: expected shape \(7,\), got \(2,\)",
    ),
    ("nan", "mass = 500.0", "mass = nan", r"satellite.mass: must be finite"),
    ("negative mass", "mass = 7.0", "mass = -7.0", r"end_effector.mass: masses must be positive"),
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
