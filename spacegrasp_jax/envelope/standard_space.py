"""The envelope's perturbations as independent standard normal variables.

Reliability methods (FORM, importance sampling, subset simulation) work in a standard space:
``d`` independent standard normal coordinates ``z``, the failure domain a region of it. A
campaign draws each perturbation as a uniform number ``U`` in [-1, 1]
([`perturbations.draw_units()`][spacegrasp_jax.envelope.perturbations.draw_units]), independent of every
other, so each ``U`` is one coordinate through the probit transform,

    U = 2 Phi(z) - 1 = erf(z / sqrt(2)),        z = sqrt(2) erfinv(U),

which maps a standard normal ``z`` to a uniform ``U`` exactly. Two draws are not one uniform
number a coordinate:

* the target's CoM offset is uniform in the unit ball: three coordinates ``z`` (3,) map to
  ``x = z / |z| * F(|z|^2) ** (1/3)``, ``F`` the chi-squared CDF of 3 degrees of freedom. As
  ``|z|^2`` is chi-squared, ``F(|z|^2)`` is uniform in [0, 1] and independent of the
  direction ``z / |z|``, which is uniform on the sphere; a radius ``F ** (1/3)`` is then that
  of a point uniform in the ball. The map is one to one, smooth but at ``z = 0``.
* the F/T sensor's noise level is one draw for both axes' standard deviations: one
  coordinate.

Only the draws that the envelope's half-widths make do something are coordinates (a field of
half-width 0, a target's draws without a free-floating target, the weakened joint without a
torque loss); the others hold their nominal unit, 0, which gives the same capture as any
other value would. The coordinates' names (``names``) say which perturbation each is:
``dp_lar_estimate[0]``, ``com_offset[2]``, ...
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax.envelope.perturbations import Perturbation, PerturbationRanges, draw_units

#: The half-width(s) that make each field of a ``Perturbation`` a draw (a field listed with
#: several names: one per block of its components, in order).
_HALF_WIDTHS = {
    "dq_init": ("q_init_rad",),
    "dp_lar": ("lar_position_m",),
    "dr_lar": ("lar_angle_rad",),
    "stiffness_scale": ("stiffness_factor",),
    "V_base_init": ("base_speed_mps", "base_rate_radps"),
    "qd_init": ("joint_rate_radps",),
    "radius_scale": ("radius_fraction",),
    "satellite_mass_scale": ("satellite_mass_fraction",),
    "satellite_inertia_scale": ("satellite_inertia_fraction",),
    "dp_lar_estimate": ("lar_estimate_position_m",),
    "dr_lar_estimate": ("lar_estimate_angle_rad",),
    "target_mass_scale": ("target_mass_fraction",),
    "target_inertia_scale": ("target_inertia_fraction",),
    "target_velocity": ("target_speed_mps",),
    "target_angular_velocity": ("target_rate_radps",),
    "target_mass_log_scale": ("target_mass_log_range",),
    "target_com_offset": ("target_com_offset_m",),
    "approach_offset": ("approach_offset_m",),
    "ft_force_bias": ("ft_force_bias_N",),
    "ft_torque_bias": ("ft_torque_bias_Nm",),
    "ft_force_noise_std": ("ft_force_noise_std_N", "ft_torque_noise_std_Nm"),
    "actuator_joint": ("actuator_torque_loss_fraction",),
    "actuator_torque_scale": ("actuator_torque_loss_fraction",),
}

#: Fields that follow another's coordinate: the sensor's one noise level.
_SHARED = {"ft_torque_noise_std": "ft_force_noise_std"}

#: The target's fields: draws only with a free-floating target.
_TARGET_FIELDS = frozenset(name for name in _HALF_WIDTHS if name.startswith("target_"))

#: The field drawn uniformly in the unit ball.
_BALL = "target_com_offset"

#: How far inside (-1, 1) a unit is taken before its inverse probit: a campaign's uniform draw
#: can be -1 exactly, whose coordinate would be infinite (|z| <= 8.2 this way).
_UNIT_EDGE = 1.0 - 2.0**-52


def _active(ranges: PerturbationRanges, name: str) -> bool:
    value = getattr(ranges, name)
    return value != 1.0 if name == "stiffness_factor" else value != 0.0


@dataclasses.dataclass(frozen=True)
class StandardSpace:
    """The coordinates ``z`` of an envelope (module docstring).

    Attributes:
        ranges: the envelope's half-widths.
        free_target: whether the scenario's target floats free (its draws count).
        n_joints: the arm's N.
        fields: ``(field, component indices)`` of the coordinates, in order; ``target_com_offset``,
            when drawn, is three coordinates mapped together.
        names: (d,) a name per coordinate, ``field[component]`` (``field`` for a scalar field).
    """

    ranges: PerturbationRanges
    free_target: bool
    n_joints: int
    fields: tuple[tuple[str, tuple[int, ...]], ...]
    names: tuple[str, ...]

    @classmethod
    def of(cls, ranges: PerturbationRanges, *, free_target: bool, n_joints: int) -> StandardSpace:
        """The standard space of the envelope ``ranges`` for an arm of ``n_joints`` joints."""
        sizes = {name: math.prod(value.shape) for name, value in vars(_unit_like(n_joints)).items()}
        fields, names = [], []
        for field, half_widths in _HALF_WIDTHS.items():
            if field in _TARGET_FIELDS and not free_target:
                continue
            size = sizes[field]
            if field == "ft_force_noise_std":  # one level for both axes: either half-width draws it
                components = (0,) if any(_active(ranges, name) for name in half_widths) else ()
            elif len(half_widths) == 1:
                components = tuple(range(size)) if _active(ranges, half_widths[0]) else ()
            else:  # blocks of equal size, one half-width each
                block = size // len(half_widths)
                components = tuple(
                    i
                    for k, name in enumerate(half_widths)
                    if _active(ranges, name)
                    for i in range(k * block, (k + 1) * block)
                )
            if not components:
                continue
            fields.append((field, components))
            names += [field if size == 1 else f"{field}[{i}]" for i in components]
        return cls(ranges, free_target, n_joints, tuple(fields), tuple(names))

    @property
    def dimension(self) -> int:
        """d, the number of coordinates."""
        return len(self.names)

    def to_units(self, z) -> Perturbation:
        """The units (a ``Perturbation`` of [-1, 1] numbers, ``draw_units()``'s) of one point
        ``z`` (d,) of the standard space; every other field at 0. Differentiable in ``z``
        (JAX; ``jax.vmap`` it over points)."""
        z = jnp.asarray(z)
        units = {name: jnp.zeros(value.shape, z.dtype) for name, value in vars(_unit_like(self.n_joints)).items()}
        start = 0
        for field, components in self.fields:
            coordinates = z[start : start + len(components)]
            start += len(components)
            value = (
                _ball_from_normal(coordinates)
                if field == _BALL
                else jax.scipy.special.erf(coordinates / math.sqrt(2.0))
            )
            shaped = units[field].reshape(-1).at[jnp.asarray(components)].set(value).reshape(units[field].shape)
            units[field] = shaped
        for follower, leader in _SHARED.items():
            units[follower] = units[leader]
        return Perturbation(**units)

    def from_units(self, units: Perturbation) -> np.ndarray:
        """(n, d) the coordinates of units with a leading axis n (NumPy; ``to_units()``'s
        inverse on the fields that are coordinates; a unit of exactly +-1 is taken 2^-52
        inside the box)."""
        import scipy.special  # imported on first use, as the command line's start does not need it

        columns = []
        for field, components in self.fields:
            value = np.asarray(getattr(units, field), dtype=np.float64)
            n = value.shape[0]
            flat = value.reshape(n, -1)[:, list(components)]
            if field == _BALL:
                columns.append(_normal_from_ball(flat))
            else:
                columns.append(math.sqrt(2.0) * scipy.special.erfinv(np.clip(flat, -_UNIT_EDGE, _UNIT_EDGE)))
        if not columns:
            return np.zeros((len(np.asarray(units.dq_init)), 0))
        return np.concatenate(columns, axis=1)

    def describe(self) -> dict:
        """The space as a record: its dimension and the coordinates' names."""
        return {"dimension": self.dimension, "coordinates": list(self.names), "free_target": self.free_target}


def _unit_like(n_joints: int) -> Perturbation:
    return jax.eval_shape(lambda: draw_units(jax.random.PRNGKey(0), jnp.float64, n_joints))


def _ball_from_normal(z):
    """(3,) the point of the unit ball of the standard normal ``z`` (3,) (module docstring)."""
    squared = jnp.sum(z * z)
    safe = jnp.where(squared > 0.0, squared, 1.0)
    radius = jax.scipy.special.gammainc(1.5, 0.5 * safe) ** (1.0 / 3.0)
    return jnp.where(squared > 0.0, z * radius / jnp.sqrt(safe), 0.0 * z)


def _normal_from_ball(x: np.ndarray) -> np.ndarray:
    """(n, 3) the standard normal coordinates of points ``x`` (n, 3) of the unit ball (NumPy)."""
    import scipy.special

    radius = np.linalg.norm(x, axis=1)
    cube = np.clip(radius**3, 0.0, _UNIT_EDGE)
    length = np.sqrt(2.0 * scipy.special.gammaincinv(1.5, cube))
    with np.errstate(invalid="ignore", divide="ignore"):
        direction = np.where(radius[:, None] > 0.0, x / radius[:, None], 0.0)
    return direction * length[:, None]


__all__ = ["StandardSpace"]
