"""The robot: a serial arm of N revolute joints on a free-floating satellite, as a static pytree.

Frames and conventions (the modelling notes of the documentation)
------------------------------------------------
* Satellite (base) frame: origin at the satellite CoM.
* Frame 0 sits at ``mount_position`` with axes ``mount_rotation`` (satellite frame; the
  paper's: parallel to the satellite's). Joint ``i`` (1..N) turns about the z axis of frame
  ``i-1``, and ``T_{i-1,i} = Rz(q_i + joint_offset_i) F_i``: frame ``i`` is placed in frame
  ``i-1`` turned by ``q_i`` by the fixed transform ``F_i = (frame_rotation_i,
  frame_position_i)``. The paper's standard DH table is one such chain,
  ``F_i = Tz(dh_lambda_i) Tx(dh_length_i) Rx(dh_alpha_i)``
  ([`make_robot()`][spacegrasp_jax.core.model.make_robot] converts it); a URDF's joint origins and
  axes are another ([`spacegrasp_jax.core.urdf`][spacegrasp_jax.core.urdf]).
* ``link_com[i]`` (Table 2) is the vector from the origin of frame ``i-1`` to the CoM of
  link ``i``, expressed in frame ``i`` axes.
* ``link_inertia[i]`` (Table 3) is the inertia tensor about the link CoM in frame ``i``
  axes; the products are the off-diagonal tensor elements as printed (``I[0, 2] = Ixz``).
* The end-effector (EE) frame is frame N followed by a translation ``ee_offset``. The EE
  body is rigidly fixed to link N; ``ee_com`` is its CoM from the origin of frame N, in
  frame N axes, and ``ee_inertia`` its inertia about that CoM in frame N axes. A robot may
  have no EE body of its own (``ee_mass`` 0 and a zero ``ee_inertia``: a URDF's tool is
  part of link N).

Every leaf is a float64 array, so a batch of robots (e.g. perturbed satellite mass in a
Monte-Carlo campaign) is simply a ``Robot`` with a leading batch axis under ``jax.vmap``.
Build robots with [`make_robot()`][spacegrasp_jax.core.model.make_robot], [`paper_robot()`][spacegrasp_jax.core.model.paper_robot] or [`load_robot()`][spacegrasp_jax.core.robot_files.load_robot], which
validate their input; the dataclass constructor itself does not (it must accept tracers).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax.core import spatial
from spacegrasp_jax.core.inputs import numbers
from spacegrasp_jax.core.precision import require_float64

#: The paper's arm has 7 joints; a robot's own number is [`n_joints()`][spacegrasp_jax.core.model.n_joints].
N_JOINTS = 7
#: The fewest joints an arm may have: both laws command a 6-DoF EE twist.
MIN_JOINTS = 6

#: The paper's initial joint angles q_init [rad] (section 4).
PAPER_Q_INIT = (2.196, -2.386, -2.011, 2.595, 2.558, 0.756, 0.949)


class RobotConfigError(ValueError):
    """A robot description is invalid; the message names the offending field."""


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Robot:
    """Mass, inertia and geometry of the satellite-manipulator system (SI units).

    Attributes:
        satellite_mass: () kg.
        satellite_inertia: (3, 3) kg m^2 about the satellite CoM, satellite axes.
        mount_position: (3,) m, origin of frame 0 in the satellite frame.
        mount_rotation: (3, 3) axes of frame 0 in the satellite frame (frame 0 to
            satellite; the identity by default, as in the paper).
        joint_offset: (N,) rad, added to q_i to give the angle of ``Rz`` (DH's theta_i).
        frame_rotation: (N, 3, 3) axes of frame i in frame i-1 turned by q_i (the DH table's
            ``Rx(alpha_i)``).
        frame_position: (N, 3) m, origin of frame i in frame i-1 turned by q_i (the DH
            table's ``(L_i, 0, lambda_i)``).
        link_mass: (N,) kg.
        link_com: (N, 3) m, from the origin of frame i-1 to the CoM of link i, frame i axes.
        link_inertia: (N, 3, 3) kg m^2 about the CoM of link i, frame i axes.
        ee_offset: (3,) m, origin of the EE frame in frame N (axes parallel to frame N).
        ee_mass: () kg, the EE body rigidly fixed to link N (0: none).
        ee_com: (3,) m, EE body CoM from the origin of frame N, frame N axes.
        ee_inertia: (3, 3) kg m^2 about the EE body CoM, frame N axes.
        joint_position_limit: (N, 2) rad, the lowest and highest angle of each joint
            (``-inf, inf`` by default: the paper gives none). Not a constraint of the
            dynamics: a capture that starts outside it is refused, and a run says when it
            first left it ([`spacegrasp_jax.core.joint_limits`][spacegrasp_jax.core.joint_limits]).
        joint_rate_limit: (N,) rad/s, the fastest each joint can turn (the paper gives none:
            ``PAPER_JOINT_RATE_LIMIT`` by default). Not a constraint of the dynamics: a
            run whose rates go far beyond it is a runaway ([`spacegrasp_jax.jobs.anatomy`][spacegrasp_jax.jobs.anatomy]).
        joint_torque_limit: (N,) N m, the largest torque each joint's motor gives
            (``PAPER_JOINT_TORQUE_LIMIT`` by default); the flight-like loop's actuators
            saturate at their own ``torque_limit_Nm``.
    """

    satellite_mass: jax.Array
    satellite_inertia: jax.Array
    mount_position: jax.Array
    mount_rotation: jax.Array
    joint_offset: jax.Array
    frame_rotation: jax.Array
    frame_position: jax.Array
    link_mass: jax.Array
    link_com: jax.Array
    link_inertia: jax.Array
    ee_offset: jax.Array
    ee_mass: jax.Array
    ee_com: jax.Array
    ee_inertia: jax.Array
    joint_position_limit: jax.Array
    joint_rate_limit: jax.Array
    joint_torque_limit: jax.Array


def n_joints(robot: Robot) -> int:
    """The number of joints N of ``robot`` (of every robot in a batch)."""
    return robot.link_mass.shape[-1]


#: Joint rate limits of the paper's arm (rad/s; the paper gives none): 1 rad/s, about one and
#: a half times the fastest joint of the paper's two runs (0.68 rad/s, joint 1 under the
#: Cartesian law, in the first second).
PAPER_JOINT_RATE_LIMIT = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0)
#: Joint torque limits of the paper's arm (N m; the paper gives none): the ``flight``
#: realism preset's actuators, four to ten times Table 5's peaks.
PAPER_JOINT_TORQUE_LIMIT = (10.0, 10.0, 10.0, 5.0, 5.0, 2.0, 2.0)

# Field -> (shape, kind, key in the TOML file); "N" is the number of joints. Kinds select
# the validation rules.
_FIELDS: dict[str, tuple[tuple, str, str]] = {
    "satellite_mass": ((), "mass", "satellite.mass"),
    "satellite_inertia": ((3, 3), "inertia", "satellite.inertia"),
    "mount_position": ((3,), "real", "satellite.mount_position"),
    "mount_rotation": ((3, 3), "rotation", "satellite.mount_rotation"),
    "joint_offset": (("N",), "real", "arm.joint_offset"),
    "frame_rotation": (("N", 3, 3), "rotation", "arm.frame_rotation"),
    "frame_position": (("N", 3), "real", "arm.frame_position"),
    "link_mass": (("N",), "mass", "arm.link_mass"),
    "link_com": (("N", 3), "real", "arm.link_com"),
    "link_inertia": (("N", 3, 3), "inertia", "arm.link_inertia"),
    "ee_offset": ((3,), "real", "end_effector.offset"),
    "ee_mass": ((), "mass or none", "end_effector.mass"),
    "ee_com": ((3,), "real", "end_effector.com"),
    "ee_inertia": ((3, 3), "inertia or none", "end_effector.inertia"),
    "joint_position_limit": (("N", 2), "range", "limits.joint_position"),
    "joint_rate_limit": (("N",), "limit", "limits.joint_rate"),
    "joint_torque_limit": (("N",), "limit", "limits.joint_torque"),
}

#: The standard DH table, an input converted once to ``frame_rotation`` and ``frame_position``.
_DH_FIELDS: dict[str, tuple[tuple, str, str]] = {
    "dh_lambda": (("N",), "real", "arm.dh_lambda"),
    "dh_length": (("N",), "real", "arm.dh_length"),
    "dh_alpha": (("N",), "real", "arm.dh_alpha"),
}

#: Fields a robot description may leave out, and the values they then take (``N``: the
#: number of joints). The paper's limits apply to a 7-joint arm only.
_DEFAULTS = {
    "mount_rotation": lambda n: np.eye(3),
    "joint_offset": lambda n: np.zeros(n),
    "joint_position_limit": lambda n: np.tile([-np.inf, np.inf], (n, 1)),
    "joint_rate_limit": lambda n: PAPER_JOINT_RATE_LIMIT if n == N_JOINTS else None,
    "joint_torque_limit": lambda n: PAPER_JOINT_TORQUE_LIMIT if n == N_JOINTS else None,
}

# Relative tolerance of the inertia checks (symmetry, positive definiteness, triangle).
_INERTIA_RTOL = 1e-9
# How far from orthonormal a rotation matrix may be (numbers read from text).
_ROTATION_ATOL = 1e-9


def check_inertia(name: str, tensor: np.ndarray) -> None:
    """Raise ``RobotConfigError`` naming ``name`` unless ``tensor`` (3, 3) kg m^2 is a rigid body's
    inertia: symmetric, positive definite, its principal moments obeying the triangle inequality."""
    scale = np.max(np.abs(tensor))
    if not np.allclose(tensor, tensor.T, rtol=0.0, atol=_INERTIA_RTOL * scale):
        raise RobotConfigError(f"{name}: inertia tensor is not symmetric: {tensor.tolist()}")
    principal = np.linalg.eigvalsh(tensor)
    if principal[0] <= _INERTIA_RTOL * scale:
        raise RobotConfigError(
            f"{name}: inertia tensor is not positive definite (principal moments {principal.tolist()} kg m^2)"
        )
    # A rigid body's principal moments satisfy I_a + I_b >= I_c for every permutation.
    if principal[0] + principal[1] < principal[2] * (1.0 - _INERTIA_RTOL):
        raise RobotConfigError(
            f"{name}: principal moments {principal.tolist()} kg m^2 break the triangle "
            "inequality I1 + I2 >= I3, so no rigid body has this inertia"
        )


def make_robot(**fields) -> Robot:
    """Validate the fields of [`Robot`][spacegrasp_jax.core.model.Robot] and build it with float64 leaves.

    The arm's geometry is given either as ``frame_rotation`` and ``frame_position`` or as
    the standard DH table ``dh_lambda``, ``dh_length`` and ``dh_alpha`` (N,) (m, m, rad),
    converted once: ``frame_rotation_i = Rx(dh_alpha_i)``, ``frame_position_i =
    (dh_length_i, 0, dh_lambda_i)``. ``mount_rotation`` (identity), ``joint_offset`` (zeros)
    and ``joint_position_limit`` (none) may be left out; the paper's joint rate and torque
    limits are the default of a 7-joint arm only.

    Raises:
        RobotConfigError: a field is missing or unknown, has the wrong shape, holds a
            non-finite number, a non-positive mass, a rotation that is not one, or an
            inertia tensor that is not symmetric positive definite or breaks the triangle
            inequality; the arm has fewer than ``MIN_JOINTS`` joints, or its fields
            disagree on how many. The message names the field.
    """
    return Robot(**_validated(fields, label=lambda field: field))


@jax.jit
def _rotation_about_x(angle: np.ndarray) -> jax.Array:
    """``Rx(angle)`` (..., 3, 3) with exact zeros and ones, computed as the closed loop computes
    its own cosines (so that a DH robot's frames come out as the DH formula's, bit for bit).
    One compiled program rather than eight single operations, each compiled apart."""
    angle = jnp.asarray(angle)
    c, s = jnp.cos(angle), jnp.sin(angle)
    zero, one = jnp.zeros_like(c), jnp.ones_like(c)
    return jnp.stack([jnp.stack([one, zero, zero], -1), jnp.stack([zero, c, -s], -1), jnp.stack([zero, s, c], -1)], -2)


def _from_dh_table(fields: dict, label) -> dict:
    """``fields`` with a DH table replaced by the general chain's ``frame_rotation`` and ``frame_position``."""
    given = [field for field in _DH_FIELDS if field in fields]
    if not given:
        return fields
    missing = [label(field) for field in _DH_FIELDS if field not in fields]
    if missing:
        raise RobotConfigError(f"missing robot field(s): {', '.join(missing)} (a DH table needs all three)")
    both = [label(field) for field in ("frame_rotation", "frame_position") if field in fields]
    if both:
        raise RobotConfigError(f"{', '.join(both)}: give the arm as a DH table or as frames, not both")
    table = {}
    for field in _DH_FIELDS:
        value = numbers(fields[field], label(field), RobotConfigError)
        if value.ndim != 1:
            raise RobotConfigError(f"{label(field)}: expected one number per joint, got shape {value.shape}")
        table[field] = value
    lengths = {value.shape[0] for value in table.values()}
    if len(lengths) != 1:
        raise RobotConfigError(
            "the DH table's columns differ in length: "
            + ", ".join(f"{label(field)} has {value.shape[0]}" for field, value in table.items())
        )
    rest = {field: value for field, value in fields.items() if field not in _DH_FIELDS}
    zero = np.zeros_like(table["dh_length"])
    return rest | {
        "frame_rotation": np.asarray(_rotation_about_x(table["dh_alpha"])),
        "frame_position": np.stack([table["dh_length"], zero, table["dh_lambda"]], axis=-1),
    }


def _joint_count(fields: dict, label) -> int:
    """N, from ``link_mass``; every field sized by the joints must agree (checked in ``_validated``)."""
    if "link_mass" not in fields:
        raise RobotConfigError(f"missing robot field(s): {label('link_mass')}")
    link_mass = numbers(fields["link_mass"], label("link_mass"), RobotConfigError)
    if link_mass.ndim != 1:
        raise RobotConfigError(f"{label('link_mass')}: expected one mass per joint, got shape {link_mass.shape}")
    n = link_mass.shape[0]
    if n < MIN_JOINTS:
        raise RobotConfigError(
            f"{label('link_mass')}: an arm of {n} joint(s); both laws command a 6-DoF end-effector "
            f"twist, so an arm needs at least {MIN_JOINTS} joints"
        )
    return n


def _validated(fields: dict, label) -> dict[str, jax.Array]:
    require_float64("a Robot")
    unknown = sorted(set(fields) - set(_FIELDS) - set(_DH_FIELDS))
    if unknown:
        raise RobotConfigError(f"unknown robot field(s): {', '.join(map(label, unknown))}")
    fields = _from_dh_table(fields, label)
    n = _joint_count(fields, label)
    lengths = {}
    for field, (shape, _, _) in _FIELDS.items():
        if shape[:1] == ("N",) and field in fields:
            value = numbers(fields[field], label(field), RobotConfigError, allow_infinite=True)
            lengths[label(field)] = value.shape[0] if value.ndim else 0
    if set(lengths.values()) != {n}:
        raise RobotConfigError(
            "the arm's fields disagree on its number of joints: "
            + ", ".join(f"{name} has {length}" for name, length in lengths.items())
        )
    defaults = {field: default(n) for field, default in _DEFAULTS.items()}
    fields = {field: value for field, value in defaults.items() if value is not None} | fields
    missing = [field for field in _FIELDS if field not in fields]
    if missing:
        needed = [label(field) for field in missing]
        paper_only = {"joint_rate_limit", "joint_torque_limit"} & set(missing)
        reason = f" (the default limits are the paper's 7-joint arm's; this arm has {n} joints)" if paper_only else ""
        raise RobotConfigError(f"missing robot field(s): {', '.join(needed)}{reason}")
    arrays = {}
    for field, (shape, kind, _) in _FIELDS.items():
        name = label(field)
        value = numbers(fields[field], name, RobotConfigError, allow_infinite=kind == "range")
        shape = tuple(n if size == "N" else size for size in shape)
        if value.shape != shape:
            joints = f" ({n} joints)" if "N" in _FIELDS[field][0] else ""
            raise RobotConfigError(f"{name}: expected shape {shape}{joints}, got {value.shape}")
        if kind == "mass" and np.any(value <= 0.0):
            raise RobotConfigError(f"{name}: masses must be positive, got {value.tolist()}")
        if kind == "mass or none" and np.any(value < 0.0):
            raise RobotConfigError(f"{name}: a mass must be positive or 0 (none), got {value.tolist()}")
        if kind == "limit" and np.any(value <= 0.0):
            raise RobotConfigError(f"{name}: limits must be positive, got {value.tolist()}")
        if kind == "range" and (np.any(np.isnan(value)) or np.any(value[:, 0] >= value[:, 1])):
            raise RobotConfigError(f"{name}: each joint's [lower, upper] must have lower < upper, got {value.tolist()}")
        if kind == "rotation":
            for index, matrix in enumerate(value.reshape(-1, 3, 3)):
                _check_rotation(f"{name}[{index}]" if value.ndim == 3 else name, matrix)
        if kind == "inertia" or (kind == "inertia or none" and np.any(value != 0.0)):
            for index, tensor in enumerate(value.reshape(-1, 3, 3)):
                where = f"{name}[{index}]" if value.ndim == 3 else name
                check_inertia(where, tensor)
        arrays[field] = jnp.asarray(value)
    if (float(arrays["ee_mass"]) == 0.0) != bool(np.all(np.asarray(arrays["ee_inertia"]) == 0.0)):
        raise RobotConfigError(
            f"{label('ee_mass')}, {label('ee_inertia')}: an EE body without mass has no inertia, and one with mass has one"
        )
    return arrays


def _check_rotation(name: str, matrix: np.ndarray) -> None:
    if not np.allclose(matrix.T @ matrix, np.eye(3), rtol=0.0, atol=_ROTATION_ATOL) or np.linalg.det(matrix) <= 0.0:
        raise RobotConfigError(f"{name}: not a rotation matrix (orthonormal, determinant +1): {matrix.tolist()}")


def paper_robot() -> Robot:
    """The manipulator of the paper: Tables 1-3 and section 4."""
    half_pi = math.pi / 2
    link_inertia_table = np.array(  # Ixx, Iyy, Izz, Ixy, Ixz, Iyz (Table 3)
        [
            [0.2, 0.15, 0.1, 0.0, 0.0, 0.0],
            [0.2, 0.12, 0.12, 0.0, 0.0, 0.0],
            [0.3, 1.0, 1.0, 0.0, 0.2, 0.0],
            [0.08, 0.45, 0.4, 0.0, 0.1, 0.0],
            [0.6, 0.55, 0.35, 0.0, 0.0, 0.0],
            [0.75, 0.4, 0.7, 0.0, 0.0, 0.0],
            [0.3, 0.3, 0.3, 0.0, 0.0, 0.0],
        ]
    )
    return make_robot(
        satellite_mass=500.0,
        satellite_inertia=np.diag([79.0, 79.0, 117.0]),
        mount_position=[0.2, 0.2, 0.2],
        dh_lambda=[0.4, -0.35, -0.3, -0.35, -0.3, 0.3, 0.25],
        dh_length=[0.0, 0.0, 0.6, 0.35, 0.0, 0.0, 0.0],
        dh_alpha=[half_pi, half_pi, 0.0, 0.0, -half_pi, half_pi, 0.0],
        joint_offset=[half_pi, half_pi, 0.0, 0.0, 0.0, half_pi, 0.0],
        link_mass=[15.0, 13.0, 18.0, 10.0, 8.5, 10.5, 5.0],
        link_com=[
            [0.0, 0.3, 0.0],
            [0.0, -0.25, 0.0],
            [0.3, 0.0, -0.2],
            [0.25, 0.0, -0.35],
            [0.0, 0.2, 0.0],
            [0.0, 0.25, 0.0],
            [0.0, 0.0, 0.1],
        ],
        link_inertia=np.stack([inertia_from_table(row) for row in link_inertia_table]),
        ee_offset=[0.0, 0.0, 0.175],
        ee_mass=7.0,
        ee_com=[0.0, 0.0, 0.1],
        ee_inertia=inertia_from_table([0.09, 0.05, 0.12, 0.0, 0.0, 0.0]),
    )


def inertia_from_table(row) -> np.ndarray:
    """Inertia tensor (3, 3) from a Table 3 row ``[Ixx, Iyy, Izz, Ixy, Ixz, Iyz]``."""
    ixx, iyy, izz, ixy, ixz, iyz = row
    return np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]], dtype=np.float64)


def robot_to_toml(robot: Robot, comment: str = "", *, rate_limits_stated: bool = True) -> str:
    """``robot`` as a robot TOML of its frames (``arm.frame_rotation``, ``arm.frame_position``)
    that [`load_robot()`][spacegrasp_jax.core.robot_files.load_robot] reads back bit for bit: every field,
    each float written with the 17 digits that name it (``inf`` for an open joint range).
    ``comment``: lines put at the top, each after ``#``. A run folder keeps its robot so.
    ``rate_limits_stated=False`` leaves ``limits.joint_rate`` out (a comment line says it)
    where they are the paper's assumed limits, which the file then takes by default: like the
    file it came from, it does not make them success criteria
    ([`rate_limits_stated()`][spacegrasp_jax.core.robot_files.rate_limits_stated]). Other limits are
    always written.
    """
    default = _DEFAULTS["joint_rate_limit"](n_joints(robot))
    omit_rates = (
        not rate_limits_stated
        and default is not None
        and np.array_equal(np.asarray(robot.joint_rate_limit), np.asarray(default))
    )

    def value(array) -> str:
        array = np.asarray(array, dtype=np.float64)
        if array.ndim == 0:
            number = float(array)
            return repr(number) if np.isfinite(number) else ("inf" if number > 0 else "-inf")
        return "[" + ", ".join(value(item) for item in array) + "]"

    tables: dict[str, list[str]] = {}
    for field, (_, _, key) in _FIELDS.items():
        section, name = key.split(".")
        entry = f"{name} = {value(getattr(robot, field))}"
        if field == "joint_rate_limit" and omit_rates:
            entry = f"# {entry}: assumed (the default), not a success criterion"
        tables.setdefault(section, []).append(entry)
    lines = [f"# {line}" if line else "#" for line in comment.splitlines()]
    for section, entries in tables.items():
        lines += ["", f"[{section}]", *entries]
    return "\n".join(lines).lstrip("\n") + "\n"


def robot_from_tables(document: dict, source: str = "<robot TOML>") -> Robot:
    """The robot of a robot TOML's tables ``document`` (``[satellite]``, ``[arm]``,
    ``[end_effector]``, ``[limits]``, already parsed; the schema of
    [`load_robot()`][spacegrasp_jax.core.robot_files.load_robot]), validated; errors name ``source``
    and the key."""
    key_to_field = {key: field for field, (_, _, key) in (_FIELDS | _DH_FIELDS).items()}
    fields = {}
    for section, table in document.items():
        if not isinstance(table, dict):
            raise RobotConfigError(f"{source}: unknown key {section!r} outside the tables")
        for key, value in table.items():
            dotted = f"{section}.{key}"
            if dotted not in key_to_field:
                raise RobotConfigError(f"{source}: unknown robot key {dotted}")
            fields[key_to_field[dotted]] = value
    field_to_key = {field: key for key, field in key_to_field.items()}
    try:
        return Robot(**_validated(fields, label=lambda field: field_to_key[field]))
    except RobotConfigError as error:
        raise RobotConfigError(f"{source}: {error}") from None


def body_inertials(robot: Robot) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Mass, CoM and inertia of the N moving bodies, the EE merged into link N.

    Returns:
        mass: (N,) kg.
        com: (N, 3) m, CoM of body i from the origin of frame i, in frame i axes.
        inertia: (N, 3, 3) kg m^2 about the CoM of body i, frame i axes.
    """
    # Table 2 gives the CoM from the origin of frame i-1; the origin of frame i sits at
    # frame_rotation_i^T frame_position_i from it, in frame i axes (the DH table's
    # (L_i, lambda_i sin(alpha_i), lambda_i cos(alpha_i))).
    origin_offset = spatial.matvec(jnp.swapaxes(robot.frame_rotation, -1, -2), robot.frame_position)
    com = robot.link_com - origin_offset
    mass = robot.link_mass

    # Link N and the EE body form one rigid body: combine by the parallel-axis theorem.
    m7, me = mass[-1], robot.ee_mass
    m_total = m7 + me
    c7, ce = com[-1], robot.ee_com
    c_total = (m7 * c7 + me * ce) / m_total

    def shifted(inertia, m, c):
        d = c - c_total
        return inertia + m * (jnp.sum(d * d) * jnp.eye(3) - d[:, None] * d[None, :])

    inertia7 = shifted(robot.link_inertia[-1], m7, c7) + shifted(robot.ee_inertia, me, ce)
    return (
        mass.at[-1].set(m_total),
        com.at[-1].set(c_total),
        robot.link_inertia.at[-1].set(inertia7),
    )
