"""The robot: a 7-joint arm on a free-floating satellite, as a static pytree.

Frames and conventions (the modelling notes of the documentation)
------------------------------------------------
* Satellite (base) frame: origin at the satellite CoM.
* Frame 0 is the mounting point ``mount_position`` (satellite frame), axes parallel to
  the satellite's. Standard DH: ``T_{i-1,i} = Rz(q_i + joint_offset_i) Tz(dh_lambda_i)
  Tx(dh_length_i) Rx(dh_alpha_i)``; joint ``i`` turns about the z axis of frame ``i-1``.
* ``link_com[i]`` (Table 2) is the vector from the origin of frame ``i-1`` to the CoM of
  link ``i``, expressed in frame ``i`` axes.
* ``link_inertia[i]`` (Table 3) is the inertia tensor about the link CoM in frame ``i``
  axes; the products are the off-diagonal tensor elements as printed (``I[0, 2] = Ixz``).
* The end-effector (EE) frame is frame 7 followed by a translation ``ee_offset``. The EE
  body is rigidly fixed to link 7; ``ee_com`` is its CoM from the origin of frame 7, in
  frame 7 axes, and ``ee_inertia`` its inertia about that CoM in frame 7 axes.

Every leaf is a float64 array, so a batch of robots (e.g. perturbed satellite mass in a
Monte-Carlo campaign) is simply a ``Robot`` with a leading batch axis under ``jax.vmap``.
Build robots with [`make_robot()`][spacegrasp_jax.model.make_robot], [`paper_robot()`][spacegrasp_jax.model.paper_robot] or [`load_robot()`][spacegrasp_jax.model.load_robot], which
validate their input; the dataclass constructor itself does not (it must accept tracers).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax.compilation import require_float64
from spacegrasp_jax.inputs import numbers, parse_document, read_text

N_JOINTS = 7

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
        dh_lambda: (7,) m, DH offsets along z_{i-1} (Table 1, lambda_i).
        dh_length: (7,) m, DH lengths along x_i (Table 1, L_i).
        dh_alpha: (7,) rad, DH twists about x_i (Table 1, alpha_i).
        joint_offset: (7,) rad, added to q_i to give the DH angle theta_i.
        link_mass: (7,) kg.
        link_com: (7, 3) m, from the origin of frame i-1 to the CoM of link i, frame i axes.
        link_inertia: (7, 3, 3) kg m^2 about the CoM of link i, frame i axes.
        ee_offset: (3,) m, origin of the EE frame in frame 7 (axes parallel to frame 7).
        ee_mass: () kg, the EE body rigidly fixed to link 7.
        ee_com: (3,) m, EE body CoM from the origin of frame 7, frame 7 axes.
        ee_inertia: (3, 3) kg m^2 about the EE body CoM, frame 7 axes.
        joint_rate_limit: (7,) rad/s, the fastest each joint can turn (the paper gives none:
            ``PAPER_JOINT_RATE_LIMIT`` by default). Not a constraint of the dynamics: a
            run whose rates go far beyond it is a runaway ([`spacegrasp_jax.anatomy`][spacegrasp_jax.anatomy]).
        joint_torque_limit: (7,) N m, the largest torque each joint's motor gives
            (``PAPER_JOINT_TORQUE_LIMIT`` by default); the flight-like loop's actuators
            saturate at their own ``torque_limit_Nm``.
    """

    satellite_mass: jax.Array
    satellite_inertia: jax.Array
    mount_position: jax.Array
    dh_lambda: jax.Array
    dh_length: jax.Array
    dh_alpha: jax.Array
    joint_offset: jax.Array
    link_mass: jax.Array
    link_com: jax.Array
    link_inertia: jax.Array
    ee_offset: jax.Array
    ee_mass: jax.Array
    ee_com: jax.Array
    ee_inertia: jax.Array
    joint_rate_limit: jax.Array
    joint_torque_limit: jax.Array


#: Joint rate limits of the paper's arm (rad/s; the paper gives none): 1 rad/s, about one and
#: a half times the fastest joint of the paper's two runs (0.68 rad/s, joint 1 under the
#: Cartesian law, in the first second).
PAPER_JOINT_RATE_LIMIT = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0)
#: Joint torque limits of the paper's arm (N m; the paper gives none): the ``flight``
#: realism preset's actuators, four to ten times Table 5's peaks.
PAPER_JOINT_TORQUE_LIMIT = (10.0, 10.0, 10.0, 5.0, 5.0, 2.0, 2.0)

# Field -> (shape, kind, key in the TOML file). Kinds select the validation rules.
_FIELDS: dict[str, tuple[tuple[int, ...], str, str]] = {
    "satellite_mass": ((), "mass", "satellite.mass"),
    "satellite_inertia": ((3, 3), "inertia", "satellite.inertia"),
    "mount_position": ((3,), "real", "satellite.mount_position"),
    "dh_lambda": ((N_JOINTS,), "real", "arm.dh_lambda"),
    "dh_length": ((N_JOINTS,), "real", "arm.dh_length"),
    "dh_alpha": ((N_JOINTS,), "real", "arm.dh_alpha"),
    "joint_offset": ((N_JOINTS,), "real", "arm.joint_offset"),
    "link_mass": ((N_JOINTS,), "mass", "arm.link_mass"),
    "link_com": ((N_JOINTS, 3), "real", "arm.link_com"),
    "link_inertia": ((N_JOINTS, 3, 3), "inertia", "arm.link_inertia"),
    "ee_offset": ((3,), "real", "end_effector.offset"),
    "ee_mass": ((), "mass", "end_effector.mass"),
    "ee_com": ((3,), "real", "end_effector.com"),
    "ee_inertia": ((3, 3), "inertia", "end_effector.inertia"),
    "joint_rate_limit": ((N_JOINTS,), "limit", "limits.joint_rate"),
    "joint_torque_limit": ((N_JOINTS,), "limit", "limits.joint_torque"),
}

#: Fields a robot description may leave out, and the values they then take.
_DEFAULTS = {"joint_rate_limit": PAPER_JOINT_RATE_LIMIT, "joint_torque_limit": PAPER_JOINT_TORQUE_LIMIT}

# Relative tolerance of the inertia checks (symmetry, positive definiteness, triangle).
_INERTIA_RTOL = 1e-9


def _check_inertia(name: str, tensor: np.ndarray) -> None:
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
    """Validate the fields of [`Robot`][spacegrasp_jax.model.Robot] and build it with float64 leaves.

    Raises:
        RobotConfigError: a field is missing or unknown, has the wrong shape, holds a
            non-finite number, a non-positive mass, or an inertia tensor that is not
            symmetric positive definite or breaks the triangle inequality. The message
            names the field.
    """
    return Robot(**_validated(fields, label=lambda field: field))


def _validated(fields: dict, label) -> dict[str, jax.Array]:
    require_float64("a Robot")
    unknown = sorted(set(fields) - set(_FIELDS))
    if unknown:
        raise RobotConfigError(f"unknown robot field(s): {', '.join(map(label, unknown))}")
    fields = _DEFAULTS | fields
    missing = [field for field in _FIELDS if field not in fields]
    if missing:
        raise RobotConfigError(f"missing robot field(s): {', '.join(map(label, missing))}")
    arrays = {}
    for field, (shape, kind, _) in _FIELDS.items():
        name = label(field)
        value = numbers(fields[field], name, RobotConfigError)
        if value.shape != shape:
            raise RobotConfigError(f"{name}: expected shape {shape}, got {value.shape}")
        if kind == "mass" and np.any(value <= 0.0):
            raise RobotConfigError(f"{name}: masses must be positive, got {value.tolist()}")
        if kind == "limit" and np.any(value <= 0.0):
            raise RobotConfigError(f"{name}: limits must be positive, got {value.tolist()}")
        if kind == "inertia":
            for index, tensor in enumerate(value.reshape(-1, 3, 3)):
                where = f"{name}[{index}]" if value.ndim == 3 else name
                _check_inertia(where, tensor)
        arrays[field] = jnp.asarray(value)
    return arrays


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


def load_robot(path: str | Path) -> Robot:
    """Read a robot from a TOML file (schema in the documentation's File formats and ``configs/paper_robot.toml``).

    The file has three tables, ``[satellite]``, ``[arm]`` and ``[end_effector]``, and an
    optional ``[limits]`` (``joint_rate`` in rad/s, ``joint_torque`` in N m); each key
    maps to one [`Robot`][spacegrasp_jax.model.Robot] field (``satellite.mass`` -> ``satellite_mass``,
    ``end_effector.offset`` -> ``ee_offset``, ``arm.link_com`` -> ``link_com``, ...).

    Raises:
        RobotConfigError: the file is not valid TOML, or a key is missing, unknown or
            invalid; the message names the file and the key (``arm.link_mass``).
    """
    path = Path(path)
    return robot_from_toml(read_text(path, RobotConfigError), source=str(path))


def robot_from_toml(text: str, source: str = "<robot TOML>") -> Robot:
    """[`load_robot()`][spacegrasp_jax.model.load_robot] on the text of a TOML file; errors name ``source``."""
    path = source
    document = parse_document(text, "toml", path, RobotConfigError)
    key_to_field = {key: field for field, (_, _, key) in _FIELDS.items()}
    fields = {}
    for section, table in document.items():
        if not isinstance(table, dict):
            raise RobotConfigError(f"{path}: unknown key {section!r} outside the tables")
        for key, value in table.items():
            dotted = f"{section}.{key}"
            if dotted not in key_to_field:
                raise RobotConfigError(f"{path}: unknown robot key {dotted}")
            fields[key_to_field[dotted]] = value
    field_to_key = {field: key for key, field in key_to_field.items()}
    try:
        return Robot(**_validated(fields, label=lambda field: field_to_key[field]))
    except RobotConfigError as error:
        raise RobotConfigError(f"{path}: {error}") from None


def body_inertials(robot: Robot) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Mass, CoM and inertia of the 7 moving bodies, the EE merged into link 7.

    Returns:
        mass: (7,) kg.
        com: (7, 3) m, CoM of body i from the origin of frame i, in frame i axes.
        inertia: (7, 3, 3) kg m^2 about the CoM of body i, frame i axes.
    """
    # Table 2 gives the CoM from the origin of frame i-1; the origin of frame i sits at
    # (L_i, lambda_i sin(alpha_i), lambda_i cos(alpha_i)) from it, in frame i axes.
    origin_offset = jnp.stack(
        [
            robot.dh_length,
            robot.dh_lambda * jnp.sin(robot.dh_alpha),
            robot.dh_lambda * jnp.cos(robot.dh_alpha),
        ],
        axis=-1,
    )
    com = robot.link_com - origin_offset
    mass = robot.link_mass

    # Link 7 and the EE body form one rigid body: combine by the parallel-axis theorem.
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
