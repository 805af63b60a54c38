"""Robots to and from URDF, the format Pinocchio, Drake, MuJoCo, SPART and ROS read.

Reading ([`robot_from_urdf()`][spacegrasp_jax.core.urdf.robot_from_urdf]): the serial chain of a URDF
from a base link to a tip link becomes a [`Robot`][spacegrasp_jax.core.model.Robot] with N revolute
joints; what is read and what is not is in its docstring and the documentation's "Your own
arm". The XML is read with the standard library's parser: the subset a rigid-body model needs
(links, joints, origins, axes, limits, inertials) is small, and a URDF package would bring
mesh libraries the model never uses.

Writing ([`robot_to_urdf()`][spacegrasp_jax.core.urdf.robot_to_urdf]): the generated URDF describes
the same rigid-body system as the ``Robot`` (a floating base is the reader's choice: a URDF has
no free joint, so load it with one, e.g. Pinocchio's ``buildModelFromXML(text,
JointModelFreeFlyer())``). No gravity is written (a URDF has none) and no geometry.

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
  it to link N, as [`body_inertials()`][spacegrasp_jax.core.model.body_inertials] does.

Reading a written URDF back gives the same robot to rounding (its EE body merged into link N,
its frames those of the joints).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from xml.etree import ElementTree

import jax.numpy as jnp
import numpy as np

from spacegrasp_jax.core.inputs import numbers, parse_document, read_text
from spacegrasp_jax.core.kinematics import joint_transforms
from spacegrasp_jax.core.model import (
    MIN_JOINTS,
    Robot,
    RobotConfigError,
    check_inertia,
    make_robot,
    n_joints,
    paper_robot,
)


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


# ---- reading ----------------------------------------------------------------------------------

_JOINT_TYPES = ("revolute", "continuous", "prismatic", "fixed", "floating", "planar")


class URDFError(RobotConfigError):
    """A URDF (or the TOML that mounts it) is malformed or describes what the model cannot
    hold; the one-line message names the file and the element."""


@dataclasses.dataclass(frozen=True)
class _Inertial:
    """A rigid body's mass (kg), CoM (3,) m and inertia about the CoM (3, 3) kg m^2, in some frame."""

    mass: float
    com: np.ndarray
    inertia: np.ndarray

    @staticmethod
    def zero() -> _Inertial:
        return _Inertial(0.0, np.zeros(3), np.zeros((3, 3)))

    def moved(self, p: np.ndarray, R: np.ndarray) -> _Inertial:
        """The same body seen from a frame in which this one sits at ``(p, R)``."""
        return _Inertial(self.mass, p + R @ self.com, R @ self.inertia @ R.T)

    def __add__(self, other: _Inertial) -> _Inertial:
        mass = self.mass + other.mass
        if mass == 0.0:
            return _Inertial.zero()
        com = (self.mass * self.com + other.mass * other.com) / mass

        def about_com(body: _Inertial) -> np.ndarray:
            d = body.com - com
            return body.inertia + body.mass * (d @ d * np.eye(3) - np.outer(d, d))

        return _Inertial(mass, com, about_com(self) + about_com(other))


@dataclasses.dataclass(frozen=True)
class _Joint:
    name: str
    kind: str
    parent: str
    child: str
    p: np.ndarray  # origin of the joint frame in the parent link's frame (m)
    R: np.ndarray  # axes of the joint frame in the parent link's frame
    axis: np.ndarray  # unit axis in the joint frame
    limit: dict[str, float]  # the <limit> attributes given, as numbers


def rpy_to_rotation(rpy) -> np.ndarray:
    """URDF's ``rpy`` (3,) rad as a rotation matrix: ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    r, p, y = (float(angle) for angle in rpy)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def _aligning_z_with(axis: np.ndarray) -> np.ndarray:
    """A rotation ``A`` with ``A e_z = axis`` (a unit vector): the identity for ``e_z``, else
    the shortest turn (a half turn about x for ``-e_z``)."""
    z = np.array([0.0, 0.0, 1.0])
    cos = float(axis @ z)
    if cos > 1.0 - 1e-15:
        return np.eye(3)
    if cos < -1.0 + 1e-15:
        return np.diag([1.0, -1.0, -1.0])
    k = np.cross(z, axis)
    k = k / np.linalg.norm(k)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    sin = np.sqrt(max(0.0, 1.0 - cos * cos))
    return np.eye(3) + sin * K + (1.0 - cos) * K @ K


class _Reader:
    """Reads the elements of one URDF, each error naming the file and the element."""

    def __init__(self, source: str):
        self.source = source

    def fail(self, message: str):
        raise URDFError(f"{self.source}: {message}")

    def numbers(self, element, attribute: str, where: str, count: int, default=None) -> np.ndarray:
        text = element.get(attribute) if element is not None else None
        if text is None:
            if default is None:
                self.fail(f"{where}: no {attribute}=")
            return np.asarray(default, dtype=float)
        try:
            values = np.array([float(word) for word in text.split()])
        except ValueError:
            values = np.array([])
        if values.size != count or not np.all(np.isfinite(values)):
            self.fail(f"{where}: {attribute}={text!r} is not {count} finite number(s)")
        return values

    def origin(self, element, where: str) -> tuple[np.ndarray, np.ndarray]:
        origin = element.find("origin")
        where = f"{where} <origin>"
        p = self.numbers(origin, "xyz", where, 3, default=np.zeros(3))
        rpy = self.numbers(origin, "rpy", where, 3, default=np.zeros(3))
        return p, rpy_to_rotation(rpy)

    def inertial(self, link) -> _Inertial | None:
        element = link.find("inertial")
        if element is None:
            return None
        where = f"link {link.get('name')!r} <inertial>"
        p, R = self.origin(element, where)
        mass = float(self.numbers(element.find("mass"), "value", f"{where} <mass>", 1)[0])
        if mass < 0.0:
            self.fail(f"{where} <mass>: value={mass!r} is negative")
        tensor = element.find("inertia")
        if tensor is None:
            self.fail(f"{where}: no <inertia>")
        ixx, ixy, ixz, iyy, iyz, izz = (
            self.numbers(tensor, key, f"{where} <inertia>", 1)[0] for key in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
        )
        inertia = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
        scale = max(np.abs(inertia).max(), 1e-300)
        if np.linalg.eigvalsh(inertia)[0] < -1e-9 * scale:
            self.fail(
                f"{where} <inertia>: not positive semi-definite (principal moments {np.linalg.eigvalsh(inertia).tolist()})"
            )
        return _Inertial(mass, p, R @ inertia @ R.T)

    def joint(self, element) -> _Joint:
        name = element.get("name")
        where = f"joint {name!r}"
        kind = element.get("type")
        if kind not in _JOINT_TYPES:
            self.fail(f"{where}: unknown type={kind!r} (URDF's are {', '.join(_JOINT_TYPES)})")
        ends = {}
        for end in ("parent", "child"):
            found = element.find(end)
            if found is None or not found.get("link"):
                self.fail(f"{where}: no <{end} link=...>")
            ends[end] = found.get("link")
        p, R = self.origin(element, where)
        axis = self.numbers(element.find("axis"), "xyz", f"{where} <axis>", 3, default=[1.0, 0.0, 0.0])
        if kind in ("revolute", "continuous", "prismatic"):
            norm = np.linalg.norm(axis)
            if norm < 1e-12:
                self.fail(f"{where} <axis>: xyz={element.find('axis').get('xyz')!r} is not a direction")
            axis = axis / norm
        limit = {}
        found = element.find("limit")
        if found is not None:
            for key in ("effort", "velocity", "lower", "upper"):
                if found.get(key) is not None:
                    limit[key] = float(self.numbers(found, key, f"{where} <limit>", 1)[0])
        return _Joint(name, kind, ends["parent"], ends["child"], p, R, axis, limit)


def _parse(text: str, source: str):
    """``(links {name: element}, joints [_Joint])`` of URDF ``text``."""
    reader = _Reader(source)
    try:
        root = ElementTree.fromstring(text)
    except ElementTree.ParseError as error:
        reader.fail(f"not valid XML: {error}")
    if root.tag != "robot":
        reader.fail(f"not a URDF: the root element is <{root.tag}>, not <robot>")
    links = {}
    for link in root.findall("link"):
        name = link.get("name")
        if not name:
            reader.fail("a <link> without a name")
        if name in links:
            reader.fail(f"link {name!r} is defined twice")
        links[name] = link
    joints, joint_names, parent_joint = [], set(), {}
    for element in root.findall("joint"):
        joint = reader.joint(element)
        if joint.name in joint_names:
            reader.fail(f"joint {joint.name!r} is defined twice")
        joint_names.add(joint.name)
        for end in (joint.parent, joint.child):
            if end not in links:
                reader.fail(f"joint {joint.name!r}: link {end!r} is not defined")
        if joint.child in parent_joint:
            reader.fail(
                f"link {joint.child!r} is the child of two joints ({parent_joint[joint.child].name!r} and "
                f"{joint.name!r}): a closed loop, which a serial chain cannot have"
            )
        parent_joint[joint.child] = joint
        joints.append(joint)
    if not links:
        reader.fail("no <link>")
    return reader, links, joints, parent_joint


def _path_up(link: str, parent_joint: dict, reader: _Reader, stop: str | None = None) -> list[_Joint] | None:
    """The joints from ``link`` up to ``stop`` (or to its tree's root), nearest first; ``None``
    if ``stop`` is not above ``link``."""
    path, seen = [], {link}
    while link != stop and link in parent_joint:
        joint = parent_joint[link]
        path.append(joint)
        link = joint.parent
        if link in seen:
            reader.fail(f"link {link!r} is its own ancestor (joint {joint.name!r}): a closed loop")
        seen.add(link)
    if stop is not None and link != stop:
        return None
    return path


def _children(joints) -> dict[str, list[_Joint]]:
    children: dict[str, list[_Joint]] = {}
    for joint in joints:
        children.setdefault(joint.parent, []).append(joint)
    return children


@dataclasses.dataclass(frozen=True)
class Mounting:
    """Where and how a URDF arm sits on the satellite, and which of its links are the chain.

    Attributes:
        base_link: the link bolted to the satellite (``None``: the URDF's one root link).
        tip_link: the link whose frame is the end-effector frame (``None``: the one leaf link
            beyond the last revolute joint).
        satellite_mass: kg, the satellite body without the arm (``None``: the URDF's base
            link and what is fixed to it are the whole satellite body).
        satellite_inertia: (3, 3) kg m^2 about the satellite's CoM, satellite axes.
        mount_position: (3,) m, the base link's origin in the satellite frame (from its CoM).
        mount_rpy: (3,) rad, the base link's axes in the satellite frame, as URDF's ``rpy``.
    """

    base_link: str | None = None
    tip_link: str | None = None
    satellite_mass: float | None = None
    satellite_inertia: tuple | None = None
    mount_position: tuple = (0.0, 0.0, 0.0)
    mount_rpy: tuple = (0.0, 0.0, 0.0)


def robot_from_urdf(text: str, mounting: Mounting = Mounting(), source: str = "<URDF>") -> Robot:
    """The [`Robot`][spacegrasp_jax.core.model.Robot] of the serial chain of URDF ``text`` from
    ``mounting.base_link`` to ``mounting.tip_link`` (the documentation's "Your own arm" and
    modelling notes).

    * The chain's ``revolute`` and ``continuous`` joints are the arm's N joints; ``fixed``
      joints are merged into the body they hang from; a ``prismatic``, ``planar`` or
      ``floating`` joint on the chain is refused.
    * Frame ``i`` of the model is joint ``i+1``'s frame turned to put its axis on z; frame N
      is the tip link's frame, which is the EE frame (the EE body is empty: the tip's links
      are part of link N).
    * The base link and everything fixed to it join the satellite body (``Mounting``'s, if it
      has one), the base frame at the CoM of the two; links past the tip (a gripper's fingers) ride with link N at their
      joints' zero; any other branch with a moving joint is refused.
    * Joint limits come from ``<limit>``: ``effort`` (N m) and ``velocity`` (rad/s), required;
      ``lower`` and ``upper`` (rad) for ``revolute`` joints, none for ``continuous``.
    * Meshes, collision shapes, ``<dynamics>`` (damping, friction), transmissions and Gazebo
      tags are not read.

    Raises:
        URDFError: in one line naming ``source`` and the element.
    """
    reader, links, joints, parent_joint = _parse(text, source)
    children = _children(joints)
    base = mounting.base_link
    if base is None:
        roots = sorted(name for name in links if name not in parent_joint)
        if not roots:
            reader.fail("every link is a joint's child: a closed loop, which a serial chain cannot have")
        if len(roots) != 1:
            reader.fail(
                f"several root links ({', '.join(roots)}): name the base link (--base-link on the command line, "
                f"base_link in a mounting TOML)"
            )
        base = roots[0]
    elif base not in links:
        reader.fail(f"base link {base!r} is not a link of this URDF")
    for joint in joints:  # every link below the base has one path up to it: no loops
        _path_up(joint.child, parent_joint, reader)
    tip = mounting.tip_link
    if tip is None:
        below = _subtree(base, children)
        leaves = sorted(name for name in below if name not in children)
        if len(leaves) != 1:
            reader.fail(
                f"several leaf links below {base!r} ({', '.join(leaves)}): name the tip link (--tip-link on the "
                f"command line, tip_link in a mounting TOML)"
            )
        tip = leaves[0]
    elif tip not in links:
        reader.fail(f"tip link {tip!r} is not a link of this URDF")
    path = _path_up(tip, parent_joint, reader, stop=base)
    if path is None:
        reader.fail(f"tip link {tip!r} does not hang below base link {base!r}")
    path.reverse()  # base to tip
    for joint in path:
        if joint.kind not in ("revolute", "continuous", "fixed"):
            reader.fail(f"joint {joint.name!r}: type {joint.kind} on the chain (revolute, continuous and fixed only)")
    moving = [joint for joint in path if joint.kind != "fixed"]
    if len(moving) < MIN_JOINTS:
        reader.fail(
            f"the chain from {base!r} to {tip!r} has {len(moving)} revolute joint(s); both laws command a "
            f"6-DoF end-effector twist, so an arm needs at least {MIN_JOINTS}"
        )
    # Bodies: 0 (the base's) to N, each the links its joint moves and the next does not.
    starts = [base] + [joint.child for joint in moving]
    bodies = []
    for k, start in enumerate(starts):
        last = k == len(moving)
        bodies.append(_rigid_body(start, children, moving, last, links, reader))

    # Frames along the chain at q = 0, each link's frame in its body's start frame.
    def placement_in(body_start: str, link: str) -> tuple[np.ndarray, np.ndarray]:
        p, R = np.zeros(3), np.eye(3)
        for joint in reversed(_path_up(link, parent_joint, reader, stop=body_start)):
            p, R = p + R @ joint.p, R @ joint.R
        return p, R

    aligned = [_aligning_z_with(joint.axis) for joint in moving]
    joint_frames = []  # joint k's frame (before its motion) in body k-1's start frame
    for start, joint in zip(starts, moving):
        p, R = placement_in(start, joint.parent)
        joint_frames.append((p + R @ joint.p, R @ joint.R))
    tip_in_last = placement_in(starts[-1], tip)
    # Frame k (k < N) is joint k+1's frame turned by A_{k+1}; frame N is the tip's.
    frames = [(p, R @ A) for (p, R), A in zip(joint_frames[1:], aligned[1:])] + [tip_in_last]
    frame_rotation, frame_position, link_com, link_inertia, link_mass = [], [], [], [], []
    for k in range(len(moving)):
        A = aligned[k]
        p_next, R_next = frames[k]  # in body k's start frame (the joint's child link)
        F_R, F_p = A.T @ R_next, A.T @ p_next
        body = bodies[k + 1]
        if body.mass <= 0.0:
            link = starts[k + 1]
            reader.fail(
                f"link {link!r}: no <inertial> with mass on it or on what is fixed to it, so joint "
                f"{moving[k].name!r} would move a massless body"
            )
        to_frame = (A @ F_R).T  # body start frame -> frame k+1 axes
        frame_rotation.append(F_R)
        frame_position.append(F_p)
        link_mass.append(body.mass)
        link_com.append(to_frame @ body.com)
        link_inertia.append(to_frame @ body.inertia @ to_frame.T)
    # The satellite: the mounting's (if any) and the base's body, as one rigid body at its CoM.
    mount_p = np.asarray(mounting.mount_position, dtype=float)
    mount_R = rpy_to_rotation(mounting.mount_rpy)
    satellite = bodies[0].moved(mount_p, mount_R)
    if mounting.satellite_mass is not None:
        satellite = satellite + _Inertial(
            float(mounting.satellite_mass), np.zeros(3), np.asarray(mounting.satellite_inertia, dtype=float)
        )
    if satellite.mass <= 0.0:
        reader.fail(f"base link {base!r}: no mass on it or fixed to it, and no [satellite] to mount it on")
    p1, R1 = joint_frames[0]
    limits = _joint_limits(moving, reader)
    try:
        return make_robot(
            satellite_mass=satellite.mass,
            satellite_inertia=satellite.inertia,
            mount_position=mount_p + mount_R @ p1 - satellite.com,
            mount_rotation=mount_R @ R1 @ aligned[0],
            joint_offset=np.zeros(len(moving)),
            frame_rotation=np.array(frame_rotation),
            frame_position=np.array(frame_position),
            link_mass=np.array(link_mass),
            link_com=np.array(link_com),
            link_inertia=np.array(link_inertia),
            ee_offset=np.zeros(3),
            ee_mass=0.0,
            ee_com=np.zeros(3),
            ee_inertia=np.zeros((3, 3)),
            **limits,
        )
    except RobotConfigError as error:
        raise URDFError(f"{source}: {error}") from None


#: The keys of a mounting TOML (``load_robot()`` on a TOML with a ``[urdf]`` table).
_MOUNTING_KEYS = {
    "urdf": ("file", "base_link", "tip_link"),
    "satellite": ("mass", "inertia", "mount_position", "mount_rpy"),
    "limits": ("joint_rate", "joint_torque"),
}


def paper_mounting(base_link: str | None = None, tip_link: str | None = None) -> Mounting:
    """The paper's satellite for a URDF arm (``--mount paper``): Section 4's 500 kg body,
    its inertia, and the arm's base link at the paper's mount point, its axes the satellite's."""
    robot = paper_robot()
    return Mounting(
        base_link=base_link,
        tip_link=tip_link,
        satellite_mass=float(robot.satellite_mass),
        satellite_inertia=np.asarray(robot.satellite_inertia),
        mount_position=tuple(np.asarray(robot.mount_position).tolist()),
    )


def urdf_arm(
    text: str,
    source: str,
    *,
    mount: str | Path = "paper",
    base_link: str | None = None,
    tip_link: str | None = None,
) -> Robot:
    """The robot of the URDF arm ``text`` (read from the file ``source``), from ``base_link``
    to ``tip_link``, mounted by ``mount``: ``"paper"``
    ([`paper_mounting()`][spacegrasp_jax.core.urdf.paper_mounting]), ``"urdf"`` (the URDF is the whole
    servicer: its base link and what is fixed to it are the satellite body), or the path of a
    mounting file: a TOML with the ``[satellite]`` and optional ``[limits]`` tables of a
    mounting TOML ([`robot_from_mounting()`][spacegrasp_jax.core.urdf.robot_from_mounting]) and no
    ``[urdf]`` table (the arm is ``text``).

    Raises:
        URDFError: in one line naming the file (``source``, or the mounting file) and the
            element or key.
    """
    if mount == "paper":
        return robot_from_urdf(text, paper_mounting(base_link, tip_link), source=source)
    if mount == "urdf":
        return robot_from_urdf(text, Mounting(base_link=base_link, tip_link=tip_link), source=source)
    mount_path = Path(mount)
    document = parse_document(read_text(mount_path, URDFError), "toml", str(mount_path), URDFError)
    if "urdf" in document:
        raise URDFError(
            f"{mount_path}: [urdf]: a mounting file given with the arm holds the satellite only ([satellite], "
            f"[limits]); a file that names its URDF in [urdf] is a robot of its own (--robot {mount_path})"
        )
    if "satellite" not in document:
        raise URDFError(f"{mount_path}: [satellite]: missing (the satellite the arm is mounted on: mass, inertia, ...)")
    mounting = _mounting(document, str(mount_path), base_link, tip_link)
    robot = robot_from_urdf(text, mounting, source=source)
    return _with_limits(robot, document, str(mount_path))


def robot_from_mounting(document: dict, source: str) -> Robot:
    """The robot a mounting TOML describes (``document`` parsed from the file ``source``): a
    URDF arm (``[urdf]``: ``file``, relative to ``source``'s folder, and optional
    ``base_link`` and ``tip_link``) on a satellite (``[satellite]``: ``mass`` kg and
    ``inertia`` (3, 3) kg m^2 about its CoM, together or not at all; ``mount_position`` (3,) m
    and ``mount_rpy`` (3,) rad, the base link's pose in the satellite frame, zero by default),
    with optional motor limits of its own (``[limits]``: ``joint_rate`` rad/s and
    ``joint_torque`` N m, (N,), which replace the URDF's ``velocity`` and ``effort``).

    Raises:
        URDFError: a key is missing, unknown or invalid, or the URDF is (naming the file and
            the key or the element).
    """

    def fail(message: str):
        raise URDFError(f"{source}: {message}")

    arm = document["urdf"]
    if not isinstance(arm, dict):
        fail("urdf: expected a table ([urdf], with file, base_link and tip_link)")
    for key in ("file", "base_link", "tip_link"):
        if key in arm and (not isinstance(arm[key], str) or not arm[key]):
            fail(f"urdf.{key}: expected a name, got {arm[key]!r}")
    if "file" not in arm:
        fail("urdf.file: missing (the URDF file, relative to this one)")
    mounting = _mounting(document, source, arm.get("base_link"), arm.get("tip_link"))
    urdf_path = Path(source).parent / arm["file"]
    try:
        text = read_text(urdf_path, URDFError)
    except URDFError as error:  # name the key that held the path, and the file that held the key
        raise URDFError(f"{source}: urdf.file = {arm['file']!r}: {error}") from None
    robot = robot_from_urdf(text, mounting, source=str(urdf_path))
    return _with_limits(robot, document, source)


def _mounting(document: dict, source: str, base_link: str | None, tip_link: str | None) -> Mounting:
    """The ``Mounting`` of a mounting file's ``document`` (its tables checked)."""

    def fail(message: str):
        raise URDFError(f"{source}: {message}")

    for section, table in document.items():
        if section not in _MOUNTING_KEYS or not isinstance(table, dict):
            fail(f"unknown key {section!r} (a mounting file has {', '.join(f'[{name}]' for name in _MOUNTING_KEYS)})")
        for key in table:
            if key not in _MOUNTING_KEYS[section]:
                fail(f"unknown key {section}.{key}")
    satellite = document.get("satellite", {})
    if ("mass" in satellite) != ("inertia" in satellite):
        fail("satellite.mass and satellite.inertia: give both (the satellite body) or neither (the base link is)")
    numbers_of = {}
    for key, shape in (("mass", ()), ("inertia", (3, 3)), ("mount_position", (3,)), ("mount_rpy", (3,))):
        if key in satellite:
            value = numbers(satellite[key], f"satellite.{key}", URDFError)
            if value.shape != shape:
                fail(f"satellite.{key}: expected shape {shape}, got {value.shape}")
            numbers_of[key] = value
    mounting = Mounting(
        base_link=base_link,
        tip_link=tip_link,
        satellite_mass=float(numbers_of["mass"]) if "mass" in numbers_of else None,
        satellite_inertia=numbers_of.get("inertia"),
        mount_position=tuple(numbers_of.get("mount_position", np.zeros(3))),
        mount_rpy=tuple(numbers_of.get("mount_rpy", np.zeros(3))),
    )
    if mounting.satellite_mass is not None:
        try:
            check_inertia("satellite.inertia", numbers_of["inertia"])
        except RobotConfigError as error:
            fail(str(error))
        if mounting.satellite_mass <= 0.0:
            fail(f"satellite.mass: must be positive, got {mounting.satellite_mass!r}")
    return mounting


def _with_limits(robot: Robot, document: dict, source: str) -> Robot:
    """``robot`` with the motor limits of a mounting file's ``[limits]`` table."""

    def fail(message: str):
        raise URDFError(f"{source}: {message}")

    limits = document.get("limits", {})
    replaced = {}
    for key, field in (("joint_rate", "joint_rate_limit"), ("joint_torque", "joint_torque_limit")):
        if key in limits:
            value = numbers(limits[key], f"limits.{key}", URDFError)
            if value.shape != (n_joints(robot),) or np.any(value <= 0.0):
                fail(f"limits.{key}: expected {n_joints(robot)} positive numbers (one a joint), got {value.tolist()}")
            replaced[field] = jnp.asarray(value)
    return dataclasses.replace(robot, **replaced)


def _subtree(link: str, children: dict) -> list[str]:
    below, pending = [], [link]
    while pending:
        name = pending.pop()
        below.append(name)
        pending.extend(joint.child for joint in children.get(name, []))
    return below


def _rigid_body(start, children, moving, last, links, reader) -> _Inertial:
    """The inertial of the links rigidly attached to ``start`` (itself included), in its frame:
    those reached by ``fixed`` joints off the chain, and for the ``last`` body every link past
    it at its joints' zero."""
    total = _Inertial.zero()
    pending = [(start, np.zeros(3), np.eye(3))]
    moving_names = {joint.name for joint in moving}
    while pending:
        name, p, R = pending.pop()
        inertial = reader.inertial(links[name])
        if inertial is not None:
            total = total + inertial.moved(p, R)
        for joint in children.get(name, []):
            if joint.name in moving_names:
                continue  # the next body
            if joint.kind != "fixed" and not last:
                reader.fail(
                    f"joint {joint.name!r} ({joint.kind}) branches off the chain at link {name!r}: only a serial "
                    "chain can be read (links past the tip may move: they ride with the last link)"
                )
            pending.append((joint.child, p + R @ joint.p, R @ joint.R))
    return total


def _joint_limits(moving, reader) -> dict[str, np.ndarray]:
    effort, velocity, position = [], [], []
    for joint in moving:
        where = f"joint {joint.name!r} <limit>"
        for key in ("effort", "velocity"):
            if key not in joint.limit:
                reader.fail(
                    f"{where}: no {key}= (the motor's {'torque' if key == 'effort' else 'rate'} limit is needed)"
                )
            if joint.limit[key] <= 0.0:
                reader.fail(f"{where}: {key}={joint.limit[key]!r} must be positive")
        effort.append(joint.limit["effort"])
        velocity.append(joint.limit["velocity"])
        if joint.kind == "continuous":
            position.append((-np.inf, np.inf))
            continue
        if "lower" not in joint.limit or "upper" not in joint.limit:
            reader.fail(f"{where}: a revolute joint needs lower= and upper= (rad); a joint without them is continuous")
        if joint.limit["lower"] >= joint.limit["upper"]:
            reader.fail(f"{where}: lower={joint.limit['lower']!r} is not below upper={joint.limit['upper']!r}")
        position.append((joint.limit["lower"], joint.limit["upper"]))
    return {
        "joint_torque_limit": np.array(effort),
        "joint_rate_limit": np.array(velocity),
        "joint_position_limit": np.array(position),
    }


__all__ = ["Mounting", "URDFError", "robot_from_urdf", "robot_to_urdf", "rpy_to_rotation"]
