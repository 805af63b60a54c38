"""Seeded perturbations of the robot and the scenario, for robust tuning and Monte-Carlo
campaigns.

Sample ``i`` of a campaign depends only on ``(seed, i)`` (``jax.random.fold_in``), so a
batch gives the same samples whatever its size, chunking or device count. Every draw is
uniform, ``U`` meaning a fresh uniform number in [-1, 1]:

* ``q_init_rad``: each initial joint angle moves by ``U * q_init_rad``;
* ``lar_position_m``: the LAR origin moves by ``U * lar_position_m`` along each LAR axis;
* ``lar_angle_rad``: the LAR frame turns by a rotation vector (LAR axes) with components
  ``U * lar_angle_rad``;
* ``stiffness_factor``: the contact stiffness is scaled by ``stiffness_factor ** U``;
* ``base_speed_mps``, ``base_rate_radps``: each component of the satellite's initial linear
  (m/s) and angular (rad/s) velocity, inertial frame, is ``U * value`` (nominal: at rest);
* ``joint_rate_radps``: each initial joint rate is ``U * value`` (nominal: at rest);
* ``radius_fraction``: the contact sphere radius is scaled by ``1 + U * value``;
* ``satellite_mass_fraction``: the satellite mass is scaled by ``1 + U * value``;
* ``satellite_inertia_fraction``: the satellite inertia ``I`` becomes ``D I D`` with
  ``D = diag(sqrt(1 + U_k * value))`` (satellite axes), which scales each principal moment of
  a diagonal ``I`` independently and keeps any ``I`` symmetric positive definite.

* ``lar_estimate_position_m``, ``lar_estimate_angle_rad``: the LAR pose the controller
  believes is off the true one by ``U * value`` along each LAR axis and a rotation vector
  with components ``U * value`` (a flight-like loop's target estimate error,
  [`spacegrasp_jax.loop.realism`][spacegrasp_jax.loop.realism]; the perturbed LAR pose above is the true one).
* ``approach_offset_m``: the approach's timing. The LAR (with the contact sphere and a target)
  starts ``d = U * value`` farther along its approach axis (the LAR z axis: farther from the
  arm for ``d > 0``), and the approach is planned from where the end-effector is: the desired
  trajectory starts ``d`` farther back in LAR coordinates and its move lasts ``D + d`` over
  ``D`` times as long (``D``: the nominal move's length along z), so that the minimum-jerk
  profile keeps its speeds and first contact comes later (``d > 0``) or earlier. The horizon
  is unchanged. On the paper's approach (95 mm in 10 s, contact at about 4.3 s) 12 mm is
  about 1 s.

A flight-like loop's sensors and actuators (their stage is switched on where drawn;
[`spacegrasp_jax.loop.realism`][spacegrasp_jax.loop.realism]) draw, each group from a stream of its own:

* ``ft_force_bias_N``, ``ft_torque_bias_Nm``: the F/T sensor's bias moves by ``U * value``
  along each sensor axis (on top of the realism's);
* ``ft_force_noise_std_N``, ``ft_torque_noise_std_Nm``: its white noise's standard deviation
  on each axis grows by ``L * value``, one level ``L = (1 + U) / 2`` in [0, 1] for the sensor;
* ``actuator_torque_loss_fraction``: one joint, drawn uniformly, has its torque limit scaled
  by ``1 - L * value`` (``L`` in [0, 1] as above): a weak or degraded motor. It scales the
  realism's limits, so it needs one whose actuators saturate (``flight``).

A free-floating target (the scenario's ``target``) is moved with its LAR frame (the target's
pose is what ``lar_position_m`` and ``lar_angle_rad`` perturb) and draws, from a stream of its
own (the other samples stay as they are):

* ``target_mass_fraction``: the target's mass is scaled by ``1 + U * value``;
* ``target_inertia_fraction``: its inertia ``I`` becomes ``D I D``, ``D = diag(sqrt(1 + U_k
  * value))`` in LAR axes;
* ``target_speed_mps``, ``target_rate_radps``: each component of its initial velocity and
  angular velocity (LAR axes) moves by ``U * value`` (drift and tumble);
* ``target_mass_log_range``: its mass and its inertia both scale by ``exp(U * value)``
  (log-uniform; a body of the same shape and another density: "proportionate inertia");
* ``target_com_offset_m``: its CoM moves from ``com_in_lar`` to a point drawn uniformly in
  the ball of this radius around it (LAR coordinates).

The ``free_target`` envelope (``FREE_TARGET_RANGES``, about the nominal target of
``configs/free_target_envelope.toml``, 632 kg at rest with its CoM 0.25 m behind the ring)
spans targets of 200 to 2,000 kg, drifting up to 5 mm/s and tumbling up to 1 deg/s, their
CoM up to 0.5 m from the LAR origin.

Without a target these draws change nothing.

The LAR frame moves independently of ``q_init``: a perturbed sample starts with the EE off
its desired start, as a real approach would. Whether the controller is told about the model
perturbations (the satellite mass and inertia) is the campaign's choice
([`spacegrasp_jax.jobs.montecarlo`][spacegrasp_jax.jobs.montecarlo]): by default it believes the nominal robot.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import jax
import jax.numpy as jnp

from spacegrasp_jax.core import spatial
from spacegrasp_jax.core.inputs import is_real, read_document, short
from spacegrasp_jax.core.model import N_JOINTS, Robot
from spacegrasp_jax.core.target import fixed_target_state, initial_target_state
from spacegrasp_jax.core.trajectory import Trajectory
from spacegrasp_jax.envelope.scenario import Scenario


class PerturbationError(ValueError):
    """Invalid perturbation ranges; the message names the offending field."""


#: The half-widths that are fractions of a positive quantity: each must stay below 1.
FRACTIONS = (
    "radius_fraction",
    "satellite_mass_fraction",
    "satellite_inertia_fraction",
    "target_mass_fraction",
    "target_inertia_fraction",
    "actuator_torque_loss_fraction",
)


@jax.tree_util.register_pytree_node_class
@dataclasses.dataclass(frozen=True)
class PerturbationRanges:
    """Half-widths of the uniform perturbations (module docstring). The defaults are the
    Monte-Carlo campaign's (documentation, Monte-Carlo campaigns); all zeros give the
    nominal scenario.

    A pytree: the half-widths are its leaves, so a compiled campaign takes them as
    arguments and other ranges reuse the program. What shapes the program is whether the
    satellite is perturbed (``perturbs_robot``) and whether target estimate errors are drawn
    (``draws_estimate_errors``); they are worked out from the numbers when the ranges are
    made and travel as the pytree's static part.
    """

    q_init_rad: float = 0.02
    lar_position_m: float = 0.005
    lar_angle_rad: float = 0.01
    stiffness_factor: float = 2.0
    base_speed_mps: float = 0.001
    base_rate_radps: float = 0.001
    joint_rate_radps: float = 0.005
    radius_fraction: float = 0.1
    satellite_mass_fraction: float = 0.1
    satellite_inertia_fraction: float = 0.1
    lar_estimate_position_m: float = 0.002
    lar_estimate_angle_rad: float = 0.005
    target_mass_fraction: float = 0.1
    target_inertia_fraction: float = 0.1
    target_speed_mps: float = 0.001
    target_rate_radps: float = 0.005
    target_mass_log_range: float = 0.0
    target_com_offset_m: float = 0.0
    approach_offset_m: float = 0.0
    ft_force_bias_N: float = 0.0
    ft_torque_bias_Nm: float = 0.0
    ft_force_noise_std_N: float = 0.0
    ft_torque_noise_std_Nm: float = 0.0
    actuator_torque_loss_fraction: float = 0.0

    def __post_init__(self):
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if not is_real(value):
                raise PerturbationError(f"{field.name}: must be a finite number, got {short(value)}")
            if value < 0.0:
                raise PerturbationError(f"{field.name}: must be non-negative, got {value}")
        if self.stiffness_factor < 1.0:
            raise PerturbationError(
                f"stiffness_factor: must be >= 1 (1 leaves the stiffness unchanged), got {self.stiffness_factor}"
            )
        for name in FRACTIONS:
            if getattr(self, name) >= 1.0:
                raise PerturbationError(
                    f"{name}: must be below 1 (the quantity must stay positive), got {getattr(self, name)}"
                )

    def tree_flatten(self):
        values = tuple(getattr(self, field.name) for field in dataclasses.fields(self))
        return values, (
            self.perturbs_robot,
            self.draws_estimate_errors,
            self.draws_sensor_errors,
            self.draws_actuator_loss,
        )

    @classmethod
    def tree_unflatten(cls, flags, values):
        ranges = object.__new__(cls)  # placeholders inside a program: checked when first made
        for field, value in zip(dataclasses.fields(cls), values):
            object.__setattr__(ranges, field.name, value)
        object.__setattr__(ranges, "_flags", flags)
        return ranges

    @classmethod
    def nominal(cls) -> PerturbationRanges:
        """No perturbation at all."""
        return cls(**{field.name: 0.0 for field in dataclasses.fields(cls)} | {"stiffness_factor": 1.0})

    @property
    def perturbs_robot(self) -> bool:
        """Whether the satellite's mass or inertia varies between samples."""
        if "_flags" in vars(self):
            return self._flags[0]
        return self.satellite_mass_fraction > 0.0 or self.satellite_inertia_fraction > 0.0

    @property
    def draws_estimate_errors(self) -> bool:
        """Whether each sample draws an error of the LAR pose the controller believes."""
        if "_flags" in vars(self):
            return self._flags[1]
        return self.lar_estimate_position_m > 0.0 or self.lar_estimate_angle_rad > 0.0

    def scaled(self, factor: float, fields=None) -> PerturbationRanges:
        """The envelope ``factor`` times as wide (in ``fields`` only, names of half-widths;
        ``None``: every one): each half-width times ``factor``, the contact stiffness's factor
        raised to the power ``factor`` (it is drawn in its logarithm, ``stiffness_factor ** U``).
        Raises PerturbationError, naming the field, where a fraction would reach 1 (a mass,
        inertia, radius or torque limit would reach zero)."""
        if not (is_real(factor) and factor >= 0.0):
            raise PerturbationError(f"scale: must be a finite number of 0 or more, got {short(factor)}")
        names = [field.name for field in dataclasses.fields(self)] if fields is None else list(fields)
        values = {}
        for name in names:
            value = getattr(self, name)
            values[name] = value**factor if name == "stiffness_factor" else factor * value
            if name in FRACTIONS and values[name] >= 1.0:
                raise PerturbationError(
                    f"{name}: {value:g} times {factor:g} reaches {values[name]:g}; a fraction must "
                    "stay below 1 (the quantity must stay positive)"
                )
        return dataclasses.replace(self, **values)

    @property
    def draws_sensor_errors(self) -> bool:
        """Whether each sample draws its F/T sensor's bias or noise level."""
        if "_flags" in vars(self):
            return self._flags[2]
        return any(
            getattr(self, name) > 0.0
            for name in ("ft_force_bias_N", "ft_torque_bias_Nm", "ft_force_noise_std_N", "ft_torque_noise_std_Nm")
        )

    @property
    def draws_actuator_loss(self) -> bool:
        """Whether each sample draws an actuator at reduced torque."""
        if "_flags" in vars(self):
            return self._flags[3]
        return self.actuator_torque_loss_fraction > 0.0

    def to_dict(self) -> dict[str, float]:
        return dataclasses.asdict(self)

    @classmethod
    def from_mapping(cls, document: dict, base: PerturbationRanges | None = None) -> PerturbationRanges:
        """``base`` (default: the campaign defaults) with the values in ``document``
        replaced; unknown keys are rejected."""
        known = {field.name for field in dataclasses.fields(cls)}
        for key in document:
            if key not in known:
                raise PerturbationError(f"unknown perturbation range {key!r}; known: {', '.join(sorted(known))}")
        return dataclasses.replace(base if base is not None else cls(), **document)


#: The free-floating targets a capture of the mission may meet, about the nominal target of
#: ``configs/free_target_envelope.toml`` (632 kg at rest, CoM 0.25 m behind the ring): 200 to
#: 2,000 kg log-uniformly with the inertia in proportion, drifting up to 5 mm/s and tumbling
#: up to 1 deg/s (each component up to 1/sqrt(3) of those, so the vectors stay within them),
#: the CoM up to 0.5 m from the LAR origin; the rest the campaigns' envelope.
FREE_TARGET_RANGES = PerturbationRanges(
    target_mass_fraction=0.0,
    target_inertia_fraction=0.0,
    target_mass_log_range=0.5 * math.log(10.0),
    target_speed_mps=0.005 / math.sqrt(3.0),
    target_rate_radps=math.radians(1.0) / math.sqrt(3.0),
    target_com_offset_m=0.25,
)


#: The free-target envelope with the drift and tumble of a defunct satellite met in flight:
#: up to 2 cm/s and 3 deg/s (Envisat spun at 2.7 deg/s in 2013: Kucharski et al., IEEE TGRS
#: 2014), each component up to 1/sqrt(3) of those; the rest as ``FREE_TARGET_RANGES``.
FREE_TARGET_FAST_RANGES = dataclasses.replace(
    FREE_TARGET_RANGES, target_speed_mps=0.02 / math.sqrt(3.0), target_rate_radps=math.radians(3.0) / math.sqrt(3.0)
)


#: The campaigns' envelope twice as wide in the LAR's pose and in the controller's estimate
#: of it: the LAR within 10 mm and 0.02 rad per axis, the estimate off by up to 4 mm and
#: 0.01 rad per axis more (on top of a flight-like loop's fixed bias); the rest the campaigns'.
LAR_WIDE_RANGES = PerturbationRanges(
    lar_position_m=0.01, lar_angle_rad=0.02, lar_estimate_position_m=0.004, lar_estimate_angle_rad=0.01
)


def load_ranges(path: str | Path, base: PerturbationRanges | None = None) -> PerturbationRanges:
    """Ranges from a TOML file whose keys are the field names (all optional, the others
    ``base``'s, by default the campaign defaults; a ``[perturbations]`` table is also
    accepted). Raises [`PerturbationError`][spacegrasp_jax.envelope.perturbations.PerturbationError]."""
    path = Path(path)
    document = read_document(path, PerturbationError, "toml")
    if set(document) == {"perturbations"} and isinstance(document["perturbations"], dict):
        document = document["perturbations"]
    try:
        return PerturbationRanges.from_mapping(document, base=base)
    except PerturbationError as error:
        raise PerturbationError(f"{path}: {error}") from None


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Perturbation:
    """The numbers drawn for one sample (module docstring for their meaning).

    Attributes:
        dq_init: (N,) rad. dp_lar: (3,) m, LAR axes. dr_lar: (3,) rad, rotation vector, LAR axes.
        stiffness_scale: (). V_base_init: (6,) ``[m/s, rad/s]`` inertial frame.
        qd_init: (N,) rad/s. radius_scale: (). satellite_mass_scale: ().
        satellite_inertia_scale: (3,) the diagonal of ``D^2``.
        dp_lar_estimate: (3,) m, LAR axes, and dr_lar_estimate: (3,) rad, rotation vector in
            LAR axes: the error of the LAR pose the controller believes.
        target_mass_scale: (). target_inertia_scale: (3,) the diagonal of ``D^2``, LAR axes.
        target_velocity: (3,) m/s and target_angular_velocity: (3,) rad/s, LAR axes: added
            to the target's initial motion.
        target_mass_log_scale: (), the log of the factor on the target's mass and inertia.
        target_com_offset: (3,) m, LAR axes, the target CoM's displacement.
        approach_offset: () m, how much farther along the approach axis the LAR starts.
        ft_force_bias: (3,) N and ft_torque_bias: (3,) N m, sensor axes: added to the F/T
            sensor's bias. ft_force_noise_std: () N and ft_torque_noise_std: () N m: added
            to its noise's standard deviation on every axis.
        actuator_joint: () in [-1, 1], the weakened joint's unit: joint
            ``floor((1 + u) / 2 * N)`` ([`weakened_joint()`][spacegrasp_jax.envelope.perturbations.weakened_joint]).
        actuator_torque_scale: () the factor on that joint's torque limit.
    """

    dq_init: jax.Array
    dp_lar: jax.Array
    dr_lar: jax.Array
    stiffness_scale: jax.Array
    V_base_init: jax.Array
    qd_init: jax.Array
    radius_scale: jax.Array
    satellite_mass_scale: jax.Array
    satellite_inertia_scale: jax.Array
    dp_lar_estimate: jax.Array
    dr_lar_estimate: jax.Array
    target_mass_scale: jax.Array
    target_inertia_scale: jax.Array
    target_velocity: jax.Array
    target_angular_velocity: jax.Array
    target_mass_log_scale: jax.Array
    target_com_offset: jax.Array
    approach_offset: jax.Array
    ft_force_bias: jax.Array
    ft_torque_bias: jax.Array
    ft_force_noise_std: jax.Array
    ft_torque_noise_std: jax.Array
    actuator_joint: jax.Array
    actuator_torque_scale: jax.Array


#: The fields of a [`Perturbation`][spacegrasp_jax.envelope.perturbations.Perturbation] added
#: after others: a stored perturbation without one reads it as its nominal unit, 0.
LATER_FIELDS = (
    "approach_offset",
    "ft_force_bias",
    "ft_torque_bias",
    "ft_force_noise_std",
    "ft_torque_noise_std",
    "actuator_joint",
    "actuator_torque_scale",
)


def draw(key: jax.Array, ranges: PerturbationRanges, dtype=jnp.float64, n_joints: int = N_JOINTS) -> Perturbation:
    """The perturbation of one sample, drawn with ``key``: ``from_units(draw_units(key), ranges)``."""
    return from_units(draw_units(key, dtype, n_joints), ranges)


def draw_units(key: jax.Array, dtype=jnp.float64, n_joints: int = N_JOINTS) -> Perturbation:
    """The uniform numbers ``U`` of one sample (module docstring), drawn with ``key``, as a
    [`Perturbation`][spacegrasp_jax.envelope.perturbations.Perturbation] of units: every field in [-1, 1]
    (``target_com_offset`` in the unit ball), the ``satellite_inertia_scale``-like fields
    holding their ``U`` (``from_units()`` scales them). ``n_joints``: the arm's N (the paper's 7).

    Each group of draws has a stream of its own, so a group added later leaves the samples of
    the others as they were: ``split(key, 4)`` the initial joint angles, the LAR pose and the
    stiffness; ``fold_in(key, 1)`` the initial velocities, the sphere radius and the
    satellite's mass and inertia; ``fold_in(key, 2)`` the target estimate's error;
    ``fold_in(key, 3)`` the target's mass, inertia and motion; ``fold_in(key, 4)`` the free
    target envelope's mass scale and CoM offset; ``fold_in(key, 5)`` the approach's timing;
    ``fold_in(key, 6)`` the F/T sensor's bias and noise level; ``fold_in(key, 7)`` the
    weakened actuator."""

    def uniform(k, shape):
        return jax.random.uniform(k, shape, dtype, -1.0, 1.0)

    k_q, k_p, k_r, k_k = jax.random.split(key, 4)
    k_v, k_w, k_qd, k_radius, k_mass, k_inertia = jax.random.split(jax.random.fold_in(key, 1), 6)
    k_estimate_p, k_estimate_r = jax.random.split(jax.random.fold_in(key, 2), 2)
    k_target_m, k_target_i, k_target_v, k_target_w = jax.random.split(jax.random.fold_in(key, 3), 4)
    k_target_log_m, k_target_com = jax.random.split(jax.random.fold_in(key, 4), 2)
    k_approach = jax.random.fold_in(key, 5)
    k_force_bias, k_torque_bias, k_noise = jax.random.split(jax.random.fold_in(key, 6), 3)
    k_joint, k_loss = jax.random.split(jax.random.fold_in(key, 7), 2)
    return Perturbation(
        dq_init=uniform(k_q, (n_joints,)),
        dp_lar=uniform(k_p, (3,)),
        dr_lar=uniform(k_r, (3,)),
        stiffness_scale=uniform(k_k, ()),
        V_base_init=jnp.concatenate([uniform(k_v, (3,)), uniform(k_w, (3,))]),
        qd_init=uniform(k_qd, (n_joints,)),
        radius_scale=uniform(k_radius, ()),
        satellite_mass_scale=uniform(k_mass, ()),
        satellite_inertia_scale=uniform(k_inertia, (3,)),
        dp_lar_estimate=uniform(k_estimate_p, (3,)),
        dr_lar_estimate=uniform(k_estimate_r, (3,)),
        target_mass_scale=uniform(k_target_m, ()),
        target_inertia_scale=uniform(k_target_i, (3,)),
        target_velocity=uniform(k_target_v, (3,)),
        target_angular_velocity=uniform(k_target_w, (3,)),
        target_mass_log_scale=uniform(k_target_log_m, ()),
        target_com_offset=_in_unit_ball(k_target_com, dtype),
        approach_offset=uniform(k_approach, ()),
        ft_force_bias=uniform(k_force_bias, (3,)),
        ft_torque_bias=uniform(k_torque_bias, (3,)),
        ft_force_noise_std=uniform(k_noise, ()),
        ft_torque_noise_std=uniform(k_noise, ()),  # one noise level for the sensor
        actuator_joint=uniform(k_joint, ()),
        actuator_torque_scale=uniform(k_loss, ()),
    )


def from_units(units: Perturbation, ranges: PerturbationRanges) -> Perturbation:
    """The perturbation whose uniform numbers are ``units`` (``draw_units()``'s; any point of
    the box [-1, 1], ``target_com_offset`` of the unit ball), with the half-widths ``ranges``.
    Differentiable in ``units``: the worst-case search ascends through it."""
    u = units
    dtype = jnp.result_type(u.dq_init)
    return Perturbation(
        dq_init=ranges.q_init_rad * u.dq_init,
        dp_lar=ranges.lar_position_m * u.dp_lar,
        dr_lar=ranges.lar_angle_rad * u.dr_lar,
        stiffness_scale=jnp.asarray(ranges.stiffness_factor, dtype) ** u.stiffness_scale,
        V_base_init=jnp.concatenate(
            [ranges.base_speed_mps * u.V_base_init[:3], ranges.base_rate_radps * u.V_base_init[3:]]
        ),
        qd_init=ranges.joint_rate_radps * u.qd_init,
        radius_scale=1.0 + ranges.radius_fraction * u.radius_scale,
        satellite_mass_scale=1.0 + ranges.satellite_mass_fraction * u.satellite_mass_scale,
        satellite_inertia_scale=1.0 + ranges.satellite_inertia_fraction * u.satellite_inertia_scale,
        dp_lar_estimate=ranges.lar_estimate_position_m * u.dp_lar_estimate,
        dr_lar_estimate=ranges.lar_estimate_angle_rad * u.dr_lar_estimate,
        target_mass_scale=1.0 + ranges.target_mass_fraction * u.target_mass_scale,
        target_inertia_scale=1.0 + ranges.target_inertia_fraction * u.target_inertia_scale,
        target_velocity=ranges.target_speed_mps * u.target_velocity,
        target_angular_velocity=ranges.target_rate_radps * u.target_angular_velocity,
        target_mass_log_scale=ranges.target_mass_log_range * u.target_mass_log_scale,
        target_com_offset=ranges.target_com_offset_m * u.target_com_offset,
        approach_offset=ranges.approach_offset_m * u.approach_offset,
        ft_force_bias=ranges.ft_force_bias_N * u.ft_force_bias,
        ft_torque_bias=ranges.ft_torque_bias_Nm * u.ft_torque_bias,
        ft_force_noise_std=ranges.ft_force_noise_std_N * 0.5 * (1.0 + u.ft_force_noise_std),
        ft_torque_noise_std=ranges.ft_torque_noise_std_Nm * 0.5 * (1.0 + u.ft_torque_noise_std),
        actuator_joint=u.actuator_joint,
        actuator_torque_scale=1.0 - ranges.actuator_torque_loss_fraction * 0.5 * (1.0 + u.actuator_torque_scale),
    )


def project_units(units: Perturbation) -> Perturbation:
    """The nearest point of the units' domain: every field clipped to [-1, 1], the
    ``target_com_offset`` scaled back into the unit ball."""
    clipped = jax.tree.map(lambda x: jnp.clip(x, -1.0, 1.0), units)
    offset = units.target_com_offset
    norm = jnp.sqrt(jnp.sum(offset * offset))
    return dataclasses.replace(clipped, target_com_offset=offset / jnp.maximum(norm, 1.0))


def _in_unit_ball(key: jax.Array, dtype) -> jax.Array:
    """(3,) a point drawn uniformly in the unit ball."""
    k_direction, k_radius = jax.random.split(key)
    direction = jax.random.normal(k_direction, (3,), dtype)
    direction = direction / jnp.linalg.norm(direction)
    return direction * jax.random.uniform(k_radius, (), dtype) ** (1.0 / 3.0)


def apply_to_robot(robot: Robot, perturbation: Perturbation) -> Robot:
    """The robot with the satellite's mass and inertia perturbed."""
    D = jnp.sqrt(perturbation.satellite_inertia_scale)
    return dataclasses.replace(
        robot,
        satellite_mass=robot.satellite_mass * perturbation.satellite_mass_scale,
        satellite_inertia=D[:, None] * robot.satellite_inertia * D[None, :],
    )


def apply_to_scenario(scenario: Scenario, perturbation: Perturbation) -> Scenario:
    """The scenario with its initial state, LAR pose, contact sphere and target perturbed (a
    fixed target moves with the LAR; only a free-floating one has mass properties and a
    velocity to perturb)."""
    p, initial = perturbation, scenario.initial
    approach = jnp.zeros(3, p.dp_lar.dtype).at[2].set(p.approach_offset)
    p_lar = scenario.p_lar + scenario.R_lar @ (p.dp_lar + approach)
    R_lar = scenario.R_lar @ spatial.rotation_exp(p.dr_lar)
    initial = dataclasses.replace(
        initial, q=initial.q + p.dq_init, V_base=initial.V_base + p.V_base_init, qd=initial.qd + p.qd_init
    )
    body = scenario.target
    if not scenario.free_target:
        initial = dataclasses.replace(initial, target=fixed_target_state(p_lar, R_lar))
    else:
        D = jnp.sqrt(p.target_inertia_scale)
        proportion = jnp.exp(p.target_mass_log_scale)
        body = dataclasses.replace(
            body,
            mass=body.mass * p.target_mass_scale * proportion,
            inertia=proportion * D[:, None] * body.inertia * D[None, :],
            com_in_lar=body.com_in_lar + p.target_com_offset,
        )
        velocity_lar = scenario.R_lar.T @ initial.target.v + p.target_velocity
        state = initial_target_state(body, p_lar, R_lar, velocity_lar, initial.target.w + p.target_angular_velocity)
        initial = dataclasses.replace(initial, target=state)
    return dataclasses.replace(
        scenario,
        initial=initial,
        p_lar=p_lar,
        R_lar=R_lar,
        trajectory=replanned(scenario.trajectory, p.approach_offset),
        sphere_radius=scenario.sphere_radius * p.radius_scale,
        contact_stiffness=scenario.contact_stiffness * p.stiffness_scale,
        target=body,
    )


def replanned(trajectory: Trajectory, offset) -> Trajectory:
    """The approach planned from ``offset`` (m) farther back along the LAR z axis: the start
    pose that much farther back, the move's duration stretched with its length, so that the
    minimum-jerk profile keeps its speeds (module docstring). ``offset = 0`` gives
    ``trajectory`` exactly."""
    length = trajectory.end_pose[2] - trajectory.start_pose[2]
    stretch = jnp.where(length != 0.0, (length + offset) / jnp.where(length != 0.0, length, 1.0), 1.0)
    return dataclasses.replace(
        trajectory, start_pose=trajectory.start_pose.at[2].add(-offset), duration=trajectory.duration * stretch
    )


def check_for_scenario(ranges: PerturbationRanges, scenario: Scenario) -> None:
    """Raises PerturbationError where ``ranges`` cannot perturb ``scenario``: an approach
    offset needs a move along the LAR z axis longer than the offset's half-width."""
    if ranges.approach_offset_m > 0.0:
        length = float(scenario.trajectory.end_pose[2] - scenario.trajectory.start_pose[2])
        if not length > ranges.approach_offset_m:
            raise PerturbationError(
                f"approach_offset_m: {ranges.approach_offset_m:g} m needs an approach along the LAR z axis longer "
                f"than that; this scenario's moves {length:g} m"
            )


def weakened_joint(perturbation: Perturbation, n_joints: int) -> jax.Array:
    """(N,) the factor on each joint's torque limit: ``actuator_torque_scale`` at the drawn
    joint ``floor((1 + u) / 2 * N)`` (the last for ``u = 1``), 1 elsewhere."""
    index = jnp.clip(jnp.floor(0.5 * (1.0 + perturbation.actuator_joint) * n_joints), 0, n_joints - 1)
    return jnp.where(jnp.arange(n_joints) == index, perturbation.actuator_torque_scale, 1.0)


def sample_keys(seed: int, indices) -> jax.Array:
    """The keys ``fold_in(PRNGKey(seed), i)`` of the samples ``indices`` (n,)."""
    base_key = jax.random.PRNGKey(seed)
    return jax.vmap(lambda i: jax.random.fold_in(base_key, i))(jnp.asarray(indices, dtype=jnp.uint32))


def sample(
    robot: Robot, scenario: Scenario, seed: int, indices, ranges: PerturbationRanges
) -> tuple[Robot, Scenario, Perturbation]:
    """Samples ``indices`` of the campaign ``seed``: the perturbed robots and scenarios and
    the drawn perturbations, each with a leading batch axis."""
    perturbations = jax.vmap(lambda key: draw(key, ranges, scenario.initial.q.dtype, scenario.initial.q.shape[-1]))(
        sample_keys(seed, indices)
    )
    robots = jax.vmap(lambda p: apply_to_robot(robot, p))(perturbations)
    scenarios = jax.vmap(lambda p: apply_to_scenario(scenario, p))(perturbations)
    return robots, scenarios, perturbations


def sample_scenarios(scenario: Scenario, seed: int, indices, ranges: PerturbationRanges) -> Scenario:
    """The perturbed scenarios alone (leading axis over ``indices``), for ranges that leave
    the robot unchanged (tuning vmaps over scenarios with one robot)."""
    if ranges.perturbs_robot:
        raise PerturbationError(
            "these ranges perturb the satellite's mass or inertia: use sample(), which returns the robots too"
        )
    perturbations = jax.vmap(lambda key: draw(key, ranges, scenario.initial.q.dtype, scenario.initial.q.shape[-1]))(
        sample_keys(seed, indices)
    )
    return jax.vmap(lambda p: apply_to_scenario(scenario, p))(perturbations)
