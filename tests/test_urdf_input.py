"""Reading URDF: a minimal valid arm read as written by hand, and every malformed or
unsupported URDF refused in one line naming the file and the element (exit 2 on the command
line, before anything compiles)."""

from __future__ import annotations

import re

import numpy as np
import pytest

import spacegrasp_jax as sg
from spacegrasp_jax import cli
from spacegrasp_jax.core.urdf import Mounting, URDFError, robot_from_urdf

INERTIAL = '<inertial><origin xyz="0 0 0.05"/><mass value="{mass}"/><inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.005"/></inertial>'


def arm_urdf(joints: int = 6) -> str:
    """A serial arm: a 10 kg base, ``joints`` revolute joints 0.3 m apart alternating about z
    and y (one continuous), a fixed tool frame."""
    lines = ['<?xml version="1.0"?>', '<robot name="arm">', f'  <link name="base">{INERTIAL.format(mass=10.0)}</link>']
    parent = "base"
    for i in range(1, joints + 1):
        kind = "continuous" if i == 1 else "revolute"
        axis = "0 0 1" if i % 2 else "0 1 0"
        limit = (
            '<limit effort="20" velocity="1.5"/>'
            if kind == "continuous"
            else '<limit effort="20" lower="-2" upper="2" velocity="1.5"/>'
        )
        lines += [
            f'  <joint name="j{i}" type="{kind}"><parent link="{parent}"/><child link="l{i}"/>'
            f'<origin xyz="0 0 0.3" rpy="0 0 0"/><axis xyz="{axis}"/>{limit}</joint>',
            f'  <link name="l{i}">{INERTIAL.format(mass=2.0)}</link>',
        ]
        parent = f"l{i}"
    lines += [
        f'  <joint name="tool_joint" type="fixed"><parent link="{parent}"/><child link="tool"/><origin xyz="0 0 0.1" rpy="0 0 1.5707963267948966"/></joint>',
        '  <link name="tool"/>',
        "</robot>",
    ]
    return "\n".join(lines)


def test_a_hand_written_arm_is_read_as_written():
    """Ten kilograms of base, six 2 kg links 0.3 m apart: at q = 0 the tool sits 6 x 0.3 + 0.1 m
    above the base origin, turned a quarter about z; the limits are the <limit> tags'."""
    robot = robot_from_urdf(arm_urdf())
    assert sg.core.model.n_joints(robot) == 6
    assert float(robot.satellite_mass) == 10.0
    np.testing.assert_allclose(robot.link_mass, 2.0)
    np.testing.assert_allclose(robot.joint_torque_limit, 20.0)
    np.testing.assert_allclose(robot.joint_rate_limit, 1.5)
    np.testing.assert_array_equal(robot.joint_position_limit[0], [-np.inf, np.inf])  # continuous
    np.testing.assert_array_equal(robot.joint_position_limit[1:], [[-2.0, 2.0]] * 5)
    # The base body's CoM is the base frame: 0.05 m above the base link's origin.
    p_ee, R_ee = sg.ee_pose(robot, np.zeros(3), np.eye(3), np.zeros(6))
    np.testing.assert_allclose(p_ee, [0.0, 0.0, 1.9 - 0.05], rtol=0, atol=1e-14)
    np.testing.assert_allclose(R_ee, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], rtol=0, atol=1e-15)
    # Joint 2 turns about y: at q_2 = pi/2 the tool, 1.3 m beyond it, swings onto +x.
    q = np.array([0.0, np.pi / 2, 0.0, 0.0, 0.0, 0.0])
    p_ee, _ = sg.ee_pose(robot, np.zeros(3), np.eye(3), q)
    np.testing.assert_allclose(p_ee, [1.3, 0.0, 0.6 - 0.05], rtol=0, atol=1e-14)


def replace(old: str, new: str, count: int = 1):
    def change(text: str) -> str:
        assert old in text, old
        return text.replace(old, new, count)

    return change


#: (case, how the valid arm is broken, the mounting, what the message must say).
MALFORMED = [
    ("not XML", replace("</robot>", ""), Mounting(), r"not valid XML"),
    (
        "not a robot",
        lambda t: t.replace('<robot name="arm">', "<model>").replace("</robot>", "</model>"),
        Mounting(),
        r"the root element is <model>, not <robot>",
    ),
    (
        "a link twice",
        replace('<link name="tool"/>', '<link name="tool"/><link name="tool"/>'),
        Mounting(),
        r"link 'tool' is defined twice",
    ),
    (
        "a joint twice",
        replace(
            "</robot>",
            '<joint name="j3" type="fixed"><parent link="tool"/><child link="extra"/></joint><link name="extra"/></robot>',
        ),
        Mounting(),
        r"joint 'j3' is defined twice",
    ),
    (
        "missing parent link",
        replace('<parent link="l2"/>', '<parent link="l9"/>'),
        Mounting(),
        r"joint 'j3': link 'l9' is not defined",
    ),
    ("no child element", replace('<child link="l4"/>', ""), Mounting(), r"joint 'j4': no <child link=...>"),
    (
        "closed loop",
        replace("</robot>", '<joint name="loop" type="fixed"><parent link="l6"/><child link="l2"/></joint></robot>'),
        Mounting(),
        r"link 'l2' is the child of two joints \('j2' and 'loop'\): a closed loop",
    ),
    (
        "two roots",
        replace("</robot>", '<link name="stray"/></robot>'),
        Mounting(tip_link="tool"),
        r"several root links \(base, stray\): name the base link",
    ),
    ("unknown base link", lambda t: t, Mounting(base_link="hull"), r"base link 'hull' is not a link"),
    (
        "tip not below the base",
        lambda t: t,
        Mounting(base_link="l3", tip_link="l1"),
        r"tip link 'l1' does not hang below base link 'l3'",
    ),
    (
        "branching chain",
        replace(
            "</robot>",
            '<joint name="side" type="revolute"><parent link="l2"/><child link="side_link"/><axis xyz="0 0 1"/><limit effort="1" lower="-1" upper="1" velocity="1"/></joint><link name="side_link"/></robot>',
        ),
        Mounting(tip_link="tool"),
        r"joint 'side' \(revolute\) branches off the chain at link 'l2'",
    ),
    (
        "prismatic on the chain",
        replace('name="j3" type="revolute"', 'name="j3" type="prismatic"'),
        Mounting(),
        r"joint 'j3': type prismatic on the chain",
    ),
    (
        "unknown joint type",
        replace('name="j3" type="revolute"', 'name="j3" type="ball"'),
        Mounting(),
        r"joint 'j3': unknown type='ball'",
    ),
    ("no limit", replace('<limit effort="20" velocity="1.5"/>', ""), Mounting(), r"joint 'j1' <limit>: no effort="),
    (
        "no velocity limit",
        replace('<limit effort="20" velocity="1.5"/>', '<limit effort="20"/>'),
        Mounting(),
        r"joint 'j1' <limit>: no velocity=",
    ),
    (
        "revolute without a range",
        replace('<limit effort="20" lower="-2" upper="2" velocity="1.5"/>', '<limit effort="20" velocity="1.5"/>'),
        Mounting(),
        r"joint 'j2' <limit>: a revolute joint needs lower= and upper=",
    ),
    (
        "empty range",
        replace('lower="-2" upper="2"', 'lower="2" upper="-2"'),
        Mounting(),
        r"joint 'j2' <limit>: lower=2.0 is not below upper=-2.0",
    ),
    (
        "missing inertial",
        replace(f'<link name="l6">{INERTIAL.format(mass=2.0)}</link>', '<link name="l6"/>'),
        Mounting(),
        r"link 'l6': no <inertial> with mass .* joint 'j6' would move a massless body",
    ),
    (
        "negative mass",
        replace('<mass value="2.0"/>', '<mass value="-2.0"/>'),
        Mounting(),
        r"link 'l1' <inertial> <mass>: value=-2.0 is negative",
    ),
    ("no mass", replace('<mass value="2.0"/>', ""), Mounting(), r"link 'l1' <inertial> <mass>: no value="),
    (
        "bad origin",
        replace('<origin xyz="0 0 0.3" rpy="0 0 0"/>', '<origin xyz="0 0.3" rpy="0 0 0"/>'),
        Mounting(),
        r"joint 'j1' <origin>: xyz='0 0.3' is not 3 finite number\(s\)",
    ),
    (
        "NaN in an origin",
        replace('<origin xyz="0 0 0.3" rpy="0 0 0"/>', '<origin xyz="0 0 nan" rpy="0 0 0"/>'),
        Mounting(),
        r"joint 'j1' <origin>: xyz='0 0 nan' is not 3 finite",
    ),
    (
        "zero axis",
        replace('<axis xyz="0 1 0"/>', '<axis xyz="0 0 0"/>'),
        Mounting(),
        r"joint 'j2' <axis>: xyz='0 0 0' is not a direction",
    ),
    (
        "inertia not positive",
        replace('ixx="0.01" ixy="0"', 'ixx="-0.5" ixy="0"'),
        Mounting(),
        r"link 'base' <inertial> <inertia>: not positive semi-definite",
    ),
    (
        "too few joints",
        lambda t: t,
        Mounting(tip_link="l4"),
        r"the chain from 'base' to 'l4' has 4 revolute joint\(s\).*at least 6",
    ),
]


@pytest.mark.parametrize("case, change, mounting, message", MALFORMED, ids=[case[0] for case in MALFORMED])
def test_a_malformed_urdf_is_refused_naming_the_element(case, change, mounting, message):
    with pytest.raises(URDFError, match=message) as error:
        robot_from_urdf(change(arm_urdf()), mounting, source="arm.urdf")
    assert str(error.value).startswith("arm.urdf: ") and "\n" not in str(error.value)


@pytest.mark.parametrize("case, change, mounting, message", MALFORMED[:18], ids=[case[0] for case in MALFORMED[:18]])
def test_the_command_line_refuses_a_malformed_urdf_with_exit_2(tmp_path, capsys, case, change, mounting, message):
    path = tmp_path / "arm.urdf"
    path.write_text(change(arm_urdf()))
    arguments = ["info", "--robot", str(path)]
    if mounting != Mounting():
        mount = tmp_path / "mount.toml"
        keys = [f'{key} = "{getattr(mounting, key)}"' for key in ("base_link", "tip_link") if getattr(mounting, key)]
        mount.write_text('[urdf]\nfile = "arm.urdf"\n' + "\n".join(keys) + "\n")
        arguments = ["info", "--robot", str(mount)]
    assert cli.main(arguments) == 2
    err = capsys.readouterr().err
    assert re.search(message, err), err
    assert str(path) in err


MOUNTING_ERRORS = [
    ("no file", "[urdf]\n", r"urdf.file: missing"),
    ("missing file", '[urdf]\nfile = "nowhere.urdf"\n', r"nowhere.urdf: no such file"),
    ("unknown key", '[urdf]\nfile = "arm.urdf"\ncolour = "red"\n', r"unknown key urdf.colour"),
    ("unknown table", '[urdf]\nfile = "arm.urdf"\n[gripper]\nmass = 1.0\n', r"unknown key 'gripper'"),
    (
        "mass without inertia",
        '[urdf]\nfile = "arm.urdf"\n[satellite]\nmass = 500.0\n',
        r"satellite.mass and satellite.inertia: give both",
    ),
    (
        "bad inertia",
        '[urdf]\nfile = "arm.urdf"\n[satellite]\nmass = 500.0\ninertia = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 5.0]]\n',
        r"satellite.inertia: principal moments",
    ),
    (
        "short mount",
        '[urdf]\nfile = "arm.urdf"\n[satellite]\nmount_position = [0.2, 0.2]\n',
        r"satellite.mount_position: expected shape \(3,\)",
    ),
    (
        "limits of the wrong length",
        '[urdf]\nfile = "arm.urdf"\n[limits]\njoint_torque = [5.0, 5.0]\n',
        r"limits.joint_torque: expected 6 positive numbers",
    ),
]


@pytest.mark.parametrize("case, text, message", MOUNTING_ERRORS, ids=[case[0] for case in MOUNTING_ERRORS])
def test_a_bad_mounting_file_is_refused_naming_the_key(tmp_path, case, text, message):
    (tmp_path / "arm.urdf").write_text(arm_urdf())
    mount = tmp_path / "mount.toml"
    mount.write_text(text)
    with pytest.raises(sg.RobotConfigError, match=message):
        sg.load_robot(mount)


def test_a_mounting_puts_the_arm_on_the_satellite(tmp_path):
    """500 kg at the origin and the arm's 10 kg base 1 m along x: the base frame moves to the
    pair's CoM (10/510 m along x), the mount with it; rpy turns the arm; [limits] replace the
    URDF's."""
    (tmp_path / "arm.urdf").write_text(arm_urdf())
    mount = tmp_path / "mount.toml"
    mount.write_text(
        '[urdf]\nfile = "arm.urdf"\n[satellite]\nmass = 500.0\ninertia = [[80.0, 0.0, 0.0], [0.0, 80.0, 0.0], [0.0, 0.0, 100.0]]\n'
        "mount_position = [1.0, 0.0, 0.0]\nmount_rpy = [0.0, 1.5707963267948966, 0.0]\n[limits]\njoint_torque = [7.0, 7.0, 7.0, 7.0, 7.0, 7.0]\n"
    )
    robot = sg.load_robot(mount)
    com = np.array([1.0 + 0.05, 0.0, 0.0]) * 10.0 / 510.0  # the base link's CoM is 0.05 m along its z: +x here
    assert float(robot.satellite_mass) == 510.0
    np.testing.assert_allclose(robot.joint_torque_limit, 7.0)
    p_ee, _ = sg.ee_pose(robot, np.zeros(3), np.eye(3), np.zeros(6))
    np.testing.assert_allclose(p_ee, np.array([1.0 + 1.9, 0.0, 0.0]) - com, rtol=0, atol=1e-14)
    # The inertia about the pair's CoM: the parallel axes add m d^2 about y and z.
    d = np.array([1.05, 0.0, 0.0])
    shift = lambda m, r: m * (r @ r * np.eye(3) - np.outer(r, r))  # noqa: E731
    base = np.array([[0.005, 0, 0], [0, 0.01, 0], [0, 0, 0.01]])  # the base link's tensor turned by pitch pi/2
    expected = np.diag([80.0, 80.0, 100.0]) + shift(500.0, -com) + base + shift(10.0, d - com)
    np.testing.assert_allclose(robot.satellite_inertia, expected, rtol=1e-12, atol=1e-15)
