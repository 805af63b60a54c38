"""The capture scenario: initial state, LAR frame, desired trajectory and contact sphere.

``duration``, ``dt`` and ``contact_law`` are static (they fix the scan length and the code
path); everything else is an array leaf, so a batch of scenarios vmaps and model
perturbations are differentiable.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax.core.inputs import numbers, read_document
from spacegrasp_jax.core.integrator import PlantState, plant_state
from spacegrasp_jax.core.kinematics import ee_pose
from spacegrasp_jax.core.model import N_JOINTS, PAPER_Q_INIT, Robot, n_joints
from spacegrasp_jax.core.precision import require_float64
from spacegrasp_jax.core.target import (
    TargetBody,
    TargetState,
    fixed_target_body,
    fixed_target_state,
    initial_target_state,
)
from spacegrasp_jax.core.trajectory import Trajectory

CONTACT_LAWS = ("exact", "smooth")


class ScenarioError(ValueError):
    """Invalid scenario; the message names the offending field."""


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Scenario:
    """One capture: the initial state, the LAR, the desired trajectory, the contact sphere and the target.

    Attributes:
        initial: the system's state at t = 0.
        p_lar: (3,) m, origin of the LAR frame in the inertial frame (at t = 0 for a free-floating target).
        R_lar: (3, 3) LAR to inertial rotation.
        trajectory: desired EE pose in LAR.
        sphere_centre: (3,) m, contact sphere centre in LAR.
        sphere_radius: () m.
        contact_stiffness: () N m^2 (``k`` of eq 20).
        contact_sharpness: () 1/m, sharpness of the smooth contact law.
        target: the target's mass properties
            ([`TargetBody`][spacegrasp_jax.core.target.TargetBody]; its state is ``initial.target``,
            whose ``free`` flag says whether it floats): the paper's fixed target
            ([`fixed_target_body()`][spacegrasp_jax.core.target.fixed_target_body]) or a
            free-floating one, for which ``p_lar`` and ``R_lar`` are the LAR pose at t = 0.
        duration: s, simulated time (static).
        dt: s, integration and control period (static).
        contact_law: ``"exact"`` (eq 20) or ``"smooth"`` (static).
    """

    initial: PlantState
    p_lar: jax.Array
    R_lar: jax.Array
    trajectory: Trajectory
    sphere_centre: jax.Array
    sphere_radius: jax.Array
    contact_stiffness: jax.Array
    contact_sharpness: jax.Array
    target: TargetBody
    duration: float = dataclasses.field(default=17.0, metadata=dict(static=True))
    dt: float = dataclasses.field(default=1e-3, metadata=dict(static=True))
    contact_law: str = dataclasses.field(default="exact", metadata=dict(static=True))

    @property
    def n_steps(self) -> int:
        """Number of control and integration steps, ``duration / dt``."""
        return int(round(self.duration / self.dt))

    @property
    def free_target(self) -> bool:
        """Whether the target floats free (``False``: the paper's fixed target); static."""
        return self.initial.target.free


def paper_scenario(
    robot: Robot,
    *,
    q_init=None,
    duration: float = 17.0,
    dt: float = 1e-3,
    lar_offset: float = 0.08,
    start_pose=(0.0, 0.0, -0.08, 0.0, 0.0, 0.0),
    end_pose=(0.0, 0.0, 0.015, 0.0, 0.0, 0.0),
    move_duration: float = 10.0,
    sphere_centre=(0.0, 0.0, -0.015),
    sphere_radius: float = 0.03,
    contact_stiffness: float = 0.1,
    contact_sharpness: float = 1e4,
    contact_law: str = "exact",
    target: dict | None = None,
) -> Scenario:
    """The paper's grasping scenario (section 4; modelling notes), every number overridable.

    The satellite starts at the origin with identity attitude and the system at rest at
    ``q_init`` (N,) rad (``PAPER_Q_INIT`` by default, for an arm of the paper's 7 joints;
    required for any other). The LAR frame has the orientation of the initial EE frame and its origin
    ``lar_offset`` (m) along the initial EE z axis. The desired EE pose goes from
    ``start_pose`` to ``end_pose`` (LAR, ``[m, m, m, rad, rad, rad]``) over ``move_duration``
    (s), then is held. The contact sphere (eq 20) is centred at ``sphere_centre`` (LAR).

    ``target``: ``None`` for the paper's stationary target, or the free-floating target's
    keys (``TARGET_KEYS``): ``mass`` (kg) and ``inertia`` ((3, 3) or its (3,) diagonal,
    kg m^2, about the target's CoM in LAR axes) required; ``com_in_lar`` (3,) m, the CoM in
    LAR coordinates; ``velocity`` (3,) m/s and ``angular_velocity`` (3,) rad/s, the CoM's
    velocity and the angular velocity at t = 0 in LAR axes (default zero).

    Raises:
        ScenarioError: a value is out of range or not finite; the message names it.
    """
    require_float64("a Scenario")
    n = n_joints(robot)
    if q_init is None:
        if n != N_JOINTS:
            raise ScenarioError(f"q_init: required for an arm of {n} joints (the default is the paper's 7-joint arm's)")
        q_init = PAPER_Q_INIT
    _check_scenario_numbers(
        n,
        q_init=q_init,
        duration=duration,
        dt=dt,
        lar_offset=lar_offset,
        start_pose=start_pose,
        end_pose=end_pose,
        move_duration=move_duration,
        sphere_centre=sphere_centre,
        sphere_radius=sphere_radius,
        contact_stiffness=contact_stiffness,
        contact_sharpness=contact_sharpness,
        contact_law=contact_law,
    )
    free_target = None if target is None else _check_target(target)
    motion = None
    if free_target is not None:
        motion = {key: jnp.asarray(free_target[key], dtype=jnp.float64) for key in TARGET_KEYS}
    initial, p_lar, R_lar, body = _initial_geometry(robot, jnp.asarray(q_init, dtype=jnp.float64), lar_offset, motion)
    return Scenario(
        initial=initial,
        p_lar=p_lar,
        R_lar=R_lar,
        trajectory=Trajectory(
            start_pose=jnp.asarray(start_pose, dtype=jnp.float64),
            end_pose=jnp.asarray(end_pose, dtype=jnp.float64),
            duration=jnp.asarray(move_duration, dtype=jnp.float64),
        ),
        sphere_centre=jnp.asarray(sphere_centre, dtype=jnp.float64),
        sphere_radius=jnp.asarray(sphere_radius, dtype=jnp.float64),
        contact_stiffness=jnp.asarray(contact_stiffness, dtype=jnp.float64),
        contact_sharpness=jnp.asarray(contact_sharpness, dtype=jnp.float64),
        target=body,
        duration=float(duration),
        dt=float(dt),
        contact_law=contact_law,
    )


@functools.partial(jax.jit, compiler_options={"xla_backend_optimization_level": 0})
def _initial_geometry(robot: Robot, q, lar_offset, free_target: dict | None):
    """``(initial state, p_lar (3,) m, R_lar (3, 3), target body)`` of a scenario starting at
    rest at ``q`` (N,) rad, its LAR ``lar_offset`` (m) along the initial EE z axis;
    ``free_target``: the free-floating target's ``TARGET_KEYS`` as arrays, or ``None``.

    One compiled program, instead of some eighty single operations. At LLVM's -O0 nothing
    fuses a multiply with an add, so its numbers are those of the operation-by-operation
    evaluation, bit for bit (``tests/test_scenario.py``), which the reproduction's log
    depends on to its last digits.
    """
    p_base, R_base = jnp.zeros(3), jnp.eye(3)
    p_ee, R_ee = ee_pose(robot, p_base, R_base, q)
    p_lar, R_lar = p_ee + lar_offset * R_ee[:, 2], R_ee
    if free_target is None:
        body, target_state = fixed_target_body(), fixed_target_state(p_lar, R_lar)
    else:
        body = TargetBody(
            mass=free_target["mass"], inertia=free_target["inertia"], com_in_lar=free_target["com_in_lar"]
        )
        motion = (free_target["velocity"], free_target["angular_velocity"])
        target_state = initial_target_state(body, p_lar, R_lar, *motion)
    initial = plant_state(p_base, R_base, q, jnp.zeros(6), jnp.zeros(q.shape[0]), target_state)
    return initial, p_lar, R_lar, body


_SHAPES = {
    "q_init": ("N",),
    "duration": (),
    "dt": (),
    "lar_offset": (),
    "start_pose": (6,),
    "end_pose": (6,),
    "move_duration": (),
    "sphere_centre": (3,),
    "sphere_radius": (),
    "contact_stiffness": (),
    "contact_sharpness": (),
}
_POSITIVE = {"duration", "dt", "move_duration", "sphere_radius", "contact_sharpness"}
#: The integration steps a scenario may have (the 17 s scenario has 17,000 at dt = 1 ms).
MAX_STEPS = 10_000_000
#: The integration periods a scenario may have, s: RK4 on this plant is meaningless outside.
DT_LIMITS_S = (1e-6, 0.1)


def _check_scenario_numbers(n: int, **values) -> None:
    """Check the scenario's numbers for an arm of ``n`` joints (``"N"`` in ``_SHAPES``)."""
    law = values.pop("contact_law")
    if not isinstance(law, str) or law not in CONTACT_LAWS:
        raise ScenarioError(f"contact_law: expected one of {CONTACT_LAWS}, got {law!r}")
    for name, shape in _SHAPES.items():
        value = numbers(values[name], name, ScenarioError)
        shape = tuple(n if size == "N" else size for size in shape)
        if value.shape != shape:
            joints = f" (one angle per joint of this {n}-joint arm)" if name == "q_init" else ""
            raise ScenarioError(f"{name}: expected shape {shape}{joints}, got {value.shape}")
        if name in _POSITIVE and value <= 0.0:
            raise ScenarioError(f"{name}: must be positive, got {float(value)}")
        values[name] = value
    low, high = DT_LIMITS_S
    if not low <= values["dt"] <= high:
        raise ScenarioError(f"dt: must be in [{low:g}, {high:g}] s, got {float(values['dt']):g}")
    if values["duration"] / values["dt"] > MAX_STEPS:
        raise ScenarioError(
            f"duration: {float(values['duration']):g} s at dt = {float(values['dt']):g} s is more than "
            f"{MAX_STEPS:,} steps (the log of one run would not fit in memory)"
        )
    if values["contact_stiffness"] < 0.0:
        raise ScenarioError(f"contact_stiffness: must be non-negative, got {values['contact_stiffness']}")
    steps = values["duration"] / values["dt"]
    if abs(steps - round(steps)) > 1e-6 * steps:
        raise ScenarioError(f"duration: {values['duration']} s is not a whole number of steps dt = {values['dt']} s")
    pitches = [values["start_pose"][4], values["end_pose"][4]]
    if any(abs(pitch) >= math.pi / 2 - 1e-3 for pitch in pitches):
        raise ScenarioError("start_pose/end_pose: pitch must stay away from +-pi/2 (ZYX Euler singularity)")


#: The keys of a free-floating target (``[target]`` in a scenario file) -> (shape, default);
#: ``None``: required.
TARGET_KEYS = {
    "mass": ((), None),
    "inertia": ((3, 3), None),
    "com_in_lar": ((3,), 0.0),
    "velocity": ((3,), 0.0),
    "angular_velocity": ((3,), 0.0),
}
#: Bounds of a target's numbers: beyond them a value is a mistake, not a target.
TARGET_LIMITS = {"mass": 1e12, "com_in_lar": 100.0, "velocity": 10.0, "angular_velocity": 10.0}


def _check_target(target) -> dict:
    """The free-floating target's keys (``TARGET_KEYS``) checked, as float64 arrays."""
    if not isinstance(target, dict):
        raise ScenarioError(f"target: expected a table of {', '.join(TARGET_KEYS)}, got {type(target).__name__}")
    for key in target:
        if key not in TARGET_KEYS:
            raise ScenarioError(f"unknown scenario key target.{key}; expected {', '.join(TARGET_KEYS)}")
    values = {}
    for key, (shape, default) in TARGET_KEYS.items():
        if key not in target and default is None:
            raise ScenarioError(f"target.{key}: required for a free-floating target")
        value = numbers(target.get(key, default), f"target.{key}", ScenarioError)
        if key == "inertia" and value.shape == (3,):
            value = np.diag(value)
        if value.ndim == 0 and shape:
            value = np.full(shape, float(value))
        if value.shape != shape:
            raise ScenarioError(f"target.{key}: expected shape {shape}, got {value.shape}")
        if key in TARGET_LIMITS and np.linalg.norm(value) > TARGET_LIMITS[key]:
            raise ScenarioError(f"target.{key}: {value.tolist()} is beyond {TARGET_LIMITS[key]:g} in magnitude")
        values[key] = value
    if values["mass"] <= 0.0:
        raise ScenarioError(f"target.mass: must be positive, got {float(values['mass'])}")
    inertia = values["inertia"]
    if not np.allclose(inertia, inertia.T, rtol=1e-9, atol=1e-12 * np.abs(inertia).max()):
        raise ScenarioError(f"target.inertia: must be symmetric, got {inertia.tolist()}")
    moments = np.linalg.eigvalsh(inertia)
    if moments[0] <= 0.0:
        raise ScenarioError(f"target.inertia: must be positive definite, principal moments {moments.tolist()}")
    if moments[2] > (moments[0] + moments[1]) * (1 + 1e-9):
        raise ScenarioError(
            f"target.inertia: principal moments {moments.tolist()} break the triangle inequality (no rigid body has them)"
        )
    return values


# File keys -> paper_scenario keyword arguments.
_FILE_KEYS = {
    ("duration",): "duration",
    ("dt",): "dt",
    ("q_init",): "q_init",
    ("lar", "offset"): "lar_offset",
    ("trajectory", "start"): "start_pose",
    ("trajectory", "end"): "end_pose",
    ("trajectory", "duration"): "move_duration",
    ("contact", "law"): "contact_law",
    ("contact", "centre"): "sphere_centre",
    ("contact", "radius"): "sphere_radius",
    ("contact", "stiffness"): "contact_stiffness",
    ("contact", "sharpness"): "contact_sharpness",
}


def scenario_from_mapping(robot: Robot, document: dict) -> Scenario:
    """The paper scenario with the values given in ``document`` replaced; every key is
    optional (documentation, File formats) and unknown keys are rejected."""
    kwargs = {}
    for key, value in document.items():
        if key == "target":
            if value is None:  # JSON's null: a mistake, not the paper's fixed target (no key at all)
                raise ScenarioError(
                    f"target: expected a table of {', '.join(TARGET_KEYS)}, got null "
                    "(leave the key out for the paper's fixed target)"
                )
            kwargs["target"] = value
        elif isinstance(value, dict):
            for sub_key, sub_value in value.items():
                if (key, sub_key) not in _FILE_KEYS:
                    raise ScenarioError(f"unknown scenario key {key}.{sub_key}")
                kwargs[_FILE_KEYS[(key, sub_key)]] = sub_value
        elif (key,) in _FILE_KEYS:
            kwargs[_FILE_KEYS[(key,)]] = value
        elif key in {table for table, *rest in _FILE_KEYS if rest}:
            raise ScenarioError(f"{key}: expected a table of settings, got {value!r}")
        else:
            raise ScenarioError(f"unknown scenario key {key}")
    return paper_scenario(robot, **kwargs)


def scenario_to_dict(scenario: Scenario) -> dict:
    """The scenario's numbers as plain JSON (initial state, LAR pose, trajectory, contact,
    target). A fixed target is written ``null`` (its body and state follow from the LAR pose),
    a free one as its numbers."""
    leaves = dataclasses.asdict(scenario)  # nested dataclasses become dicts of arrays
    if scenario.free_target:
        del leaves["initial"]["target"]["free"]
    else:
        leaves["target"] = leaves["initial"]["target"] = None

    def plain(value):
        if isinstance(value, dict):
            return {key: plain(item) for key, item in value.items()}
        if value is None or isinstance(value, (str, float, int)):
            return value
        return np.asarray(value).tolist()

    return plain(leaves)


def scenario_from_dict(document: dict) -> Scenario:
    """The scenario that [`scenario_to_dict()`][spacegrasp_jax.envelope.scenario.scenario_to_dict]
    wrote, leaf for leaf (float64 arrays): what a run folder's ``config.json`` or a
    campaign's ``campaign.json`` records is run again exactly."""
    require_float64("a Scenario")
    arrays = lambda cls, fields: cls(**{name: jnp.asarray(value, dtype=jnp.float64) for name, value in fields.items()})
    initial = dict(document["initial"])
    target_state = initial.pop("target")
    p_lar = jnp.asarray(document["p_lar"], dtype=jnp.float64)
    R_lar = jnp.asarray(document["R_lar"], dtype=jnp.float64)
    if document["target"] is None:
        body, target_state = fixed_target_body(), fixed_target_state(p_lar, R_lar)
    else:
        body, target_state = arrays(TargetBody, document["target"]), arrays(TargetState, target_state)
    initial = PlantState(
        **{name: jnp.asarray(value, dtype=jnp.float64) for name, value in initial.items()}, target=target_state
    )
    return Scenario(
        initial=initial,
        p_lar=p_lar,
        R_lar=R_lar,
        trajectory=arrays(Trajectory, document["trajectory"]),
        sphere_centre=jnp.asarray(document["sphere_centre"], dtype=jnp.float64),
        sphere_radius=jnp.asarray(document["sphere_radius"], dtype=jnp.float64),
        contact_stiffness=jnp.asarray(document["contact_stiffness"], dtype=jnp.float64),
        contact_sharpness=jnp.asarray(document["contact_sharpness"], dtype=jnp.float64),
        target=body,
        duration=float(document["duration"]),
        dt=float(document["dt"]),
        contact_law=str(document["contact_law"]),
    )


def load_scenario(robot: Robot, path: str | Path) -> Scenario:
    """Read a scenario (TOML or JSON, by extension) as [`scenario_from_mapping()`][spacegrasp_jax.envelope.scenario.scenario_from_mapping].

    Raises:
        ScenarioError: unreadable file, unknown key or invalid value; names the file.
    """
    path = Path(path)
    document = read_document(path, ScenarioError)
    try:
        return scenario_from_mapping(robot, document)
    except ScenarioError as error:
        raise ScenarioError(f"{path}: {error}") from None
