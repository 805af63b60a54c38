"""The robot as URDF text, for the tools that read it (Pinocchio, Drake, MuJoCo, ROS).

The generated URDF describes the same rigid-body system as [`Robot`][spacegrasp_jax.model.Robot]
(a floating base is the reader's choice: a URDF has no free joint, so load it with one, e.g.
Pinocchio's ``buildModelFromXML(text, JointModelFreeFlyer())``). No gravity is written (a
URDF has none) and no geometry (visual only).

* link ``satellite`` is the satellite body, its frame at the satellite CoM.
* joint ``joint<i>`` turns link ``link<i>`` about the ``z`` axis of frame ``i-1``: the frame
  of link ``i`` is frame ``i-1`` turned by ``q_i`` (URDF places a joint's axis through its
  child link's origin), so joint ``i+1`` sits in it at ``Rz(joint_offset_i) F_i`` (for the
  paper's arm, Table 1 at ``q = 0``) and joint 1 at the mount.
* each link's ``<inertial>`` keeps the robot's numbers as they are (Tables 2 and 3 for the
  paper's arm): its frame has frame ``i``'s axes, at the CoM.
* the joints are ``continuous`` where the robot has no position limits (the paper gives
  none), else ``revolute`` with ``lower`` and ``upper``; the motors' torque and rate limits
  are ``effort`` (N m) and ``velocity`` (rad/s).
* link ``ee`` is the end-effector frame (frame N moved by ``ee_offset``), fixed to link N,
  with the EE body's inertial (none if it has no mass); readers that merge fixed joints add
  it to link N, as
  [`body_inertials()`][spacegrasp_jax.model.body_inertials] does.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from spacegrasp_jax.kinematics import joint_transforms
from spacegrasp_jax.model import Robot


def _number(value) -> str:
    """The shortest text that reads back as the same float64 (``-0.0`` written ``0.0``)."""
    return repr(float(value) + 0.0)


def _numbers(values) -> str:
    return " ".join(_number(v) for v in np.ravel(values))


def _rpy(R: np.ndarray) -> np.ndarray:
    """URDF's roll, pitch, yaw of a rotation matrix: ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""
    return np.array(
        [np.arctan2(R[2, 1], R[2, 2]), np.arctan2(-R[2, 0], np.hypot(R[2, 1], R[2, 2])), np.arctan2(R[1, 0], R[0, 0])]
    )


def _origin(p, R) -> str:
    return f'<origin xyz="{_numbers(p)}" rpy="{_numbers(_rpy(R))}"/>'


def _inertial(mass: float, com, R, inertia) -> list[str]:
    """An ``<inertial>``: CoM ``com`` and axes ``R`` in the link frame, ``inertia`` about the
    CoM in those axes."""
    inertia = np.asarray(inertia, dtype=float)
    return [
        "    <inertial>",
        f"      {_origin(com, R)}",
        f'      <mass value="{_number(mass)}"/>',
        f'      <inertia ixx="{_number(inertia[0, 0])}" ixy="{_number(inertia[0, 1])}" ixz="{_number(inertia[0, 2])}" '
        f'iyy="{_number(inertia[1, 1])}" iyz="{_number(inertia[1, 2])}" izz="{_number(inertia[2, 2])}"/>',
        "    </inertial>",
    ]


def robot_to_urdf(robot: Robot, name: str = "spacegrasp") -> str:
    """URDF text of ``robot`` (unbatched; module docstring). Each number is written as the
    shortest text that reads back as the robot's float64 value."""
    as_array = {f.name: np.asarray(getattr(robot, f.name), dtype=float) for f in dataclasses.fields(robot)}
    if as_array["link_mass"].ndim != 1:
        raise ValueError(f"robot_to_urdf: one robot, not a batch (link_mass has shape {as_array['link_mass'].shape})")
    n = as_array["link_mass"].shape[0]
    # The chain at q = 0: frame i in the frame of link i (frame i-1 turned by q_i).
    R_rel, p_rel = (np.asarray(x, dtype=float) for x in joint_transforms(robot, np.zeros(n)))
    lines = ['<?xml version="1.0"?>', f'<robot name="{name}">', '  <link name="satellite">']
    lines += _inertial(as_array["satellite_mass"], np.zeros(3), np.eye(3), as_array["satellite_inertia"])
    lines.append("  </link>")
    parent, placement = "satellite", (as_array["mount_position"], as_array["mount_rotation"])
    for i in range(n):
        link = f"link{i + 1}"
        lower, upper = as_array["joint_position_limit"][i]
        bounded = np.isfinite(lower) and np.isfinite(upper)
        position_limit = f' lower="{_number(lower)}" upper="{_number(upper)}"' if bounded else ""
        lines += [
            f'  <joint name="joint{i + 1}" type="{"revolute" if bounded else "continuous"}">',
            f'    <parent link="{parent}"/>',
            f'    <child link="{link}"/>',
            f"    {_origin(*placement)}",
            '    <axis xyz="0 0 1"/>',
            f'    <limit effort="{_number(as_array["joint_torque_limit"][i])}"{position_limit} '
            f'velocity="{_number(as_array["joint_rate_limit"][i])}"/>',
            "  </joint>",
        ]
        p, R = p_rel[i], R_rel[i]
        # Table 2's CoM starts at frame i-1's origin (this link's) and is written in frame
        # i's axes; Table 3's inertia too.
        lines += [
            f'  <link name="{link}">',
            *_inertial(as_array["link_mass"][i], R @ as_array["link_com"][i], R, as_array["link_inertia"][i]),
            "  </link>",
        ]
        parent, placement = link, (p, R)
    p7, R7 = placement
    ee_offset = as_array["ee_offset"]
    ee_body = _inertial(as_array["ee_mass"], as_array["ee_com"] - ee_offset, np.eye(3), as_array["ee_inertia"])
    lines += [
        '  <joint name="ee_joint" type="fixed">',
        f'    <parent link="{parent}"/>',
        '    <child link="ee"/>',
        f"    {_origin(p7 + R7 @ ee_offset, R7)}",
        "  </joint>",
        '  <link name="ee">',
        *(ee_body if as_array["ee_mass"] > 0.0 else []),
        "  </link>",
        "</robot>",
        "",
    ]
    return "\n".join(lines)


__all__ = ["robot_to_urdf"]
