"""When a capture succeeds: one set of criteria for campaigns, runs, margins, worst cases and
the tuning objective.

A capture succeeds when it neither diverged nor ran away, no joint left its range, and at the
end of the run

* the EE is within ``position_tolerance_m`` of the LAR's grasp pose and within
  ``orientation_tolerance_rad`` of its attitude;
* no joint's torque ever exceeded ``torque_threshold_Nm`` (an unstable capture reaches
  1e4-1e5 N m without turning non-finite);
* a free-floating target moves at most at ``target_speed_limit_mps`` (pushed away faster, it
  drifts out of reach before the grasp closes);
* where rate limits are criteria (``joint_rate_limits_radps``), no joint turned faster than its
  limit.

The words for torques mean one thing each, here and everywhere in the package:

* a joint's **torque limit** (N m, one a joint): what its motor can give,
  ``Robot.joint_torque_limit``; the flight-like loop's actuators saturate at them
  (``actuators.torque_limit_Nm``);
* **saturation**: the actuators clamping a command at its torque limit (``actuators.saturation``);
* the **torque threshold** (N m, one number): the success criterion above, which tells an
  unstable capture from a stable one, 100 N m by default;
* the **torque cap** (N m, one number): a tuning run's budget, ``TuneConfig.torque_cap_Nm``; the
  capture objective's **torque constraint** of joint ``i`` is
  ``min(torque_fraction * limit_i, cap)``;
* the **torque guard** (N m): the gradient tuner rejects a step whose peak torque exceeds it.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import numpy as np

from spacegrasp_jax.core import joint_limits

#: The names older run records and summaries gave the criteria, and today's.
_OLDER_NAMES = {
    "final_position_m": "position_tolerance_m",
    "final_orientation_rad": "orientation_tolerance_rad",
    "torque_limit_Nm": "torque_threshold_Nm",
    "target_speed_mps": "target_speed_limit_mps",
    "joint_rate_radps": "joint_rate_limits_radps",
}


def _known_now(value) -> bool:
    """A number known now, not a placeholder JAX put in while rebuilding the pytree."""
    return isinstance(value, (int, float, np.ndarray, np.generic)) or (
        isinstance(value, jax.Array) and not isinstance(value, jax.core.Tracer)
    )


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class CaptureCriteria:
    """The criteria of a capture's success (module docstring); the defaults are the campaigns'.

    A pytree: the thresholds are leaves (a compiled objective takes them as values), the rate
    limits static.

    Attributes:
        position_tolerance_m: m, the final EE position error's largest norm, LAR frame.
        orientation_tolerance_rad: rad, the final attitude error's largest angle.
        torque_threshold_Nm: N m, the largest peak |u_i| on any joint of a capture counted as
            stable (``None``: none).
        target_speed_limit_mps: m/s, a free-floating target's largest final speed (a fixed
            target's is zero).
        joint_rate_limits_radps: (N,) rad/s, each joint's rate limit as a criterion (``None``,
            the default: rates are no criterion, only a runaway, ten times the robot's
            ``joint_rate_limit``, fails).

    Raises:
        ValueError: a threshold that is not a positive finite number, naming it.
    """

    position_tolerance_m: float = 0.005
    orientation_tolerance_rad: float = math.radians(1.0)
    torque_threshold_Nm: float | None = 100.0
    target_speed_limit_mps: float = 0.005
    joint_rate_limits_radps: tuple[float, ...] | None = dataclasses.field(default=None, metadata=dict(static=True))

    def __post_init__(self):
        for name in ("position_tolerance_m", "orientation_tolerance_rad", "target_speed_limit_mps"):
            value = getattr(self, name)
            if not _known_now(value):
                return
            if isinstance(value, bool) or not (np.ndim(value) == 0 and math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name}: must be positive and finite, got {value!r}")
        threshold = self.torque_threshold_Nm
        if threshold is not None and _known_now(threshold):
            if isinstance(threshold, bool) or not (
                np.ndim(threshold) == 0 and math.isfinite(threshold) and threshold > 0
            ):
                raise ValueError(f"torque_threshold_Nm: must be positive and finite, or None, got {threshold!r}")
        try:
            object.__setattr__(
                self, "joint_rate_limits_radps", joint_limits.rate_criterion(self.joint_rate_limits_radps)
            )
        except ValueError as error:
            raise ValueError(f"joint_rate_limits_radps: {error}") from None

    def to_dict(self) -> dict:
        """The criteria as a run's files record them: the field names, plain numbers."""
        rates = self.joint_rate_limits_radps
        return {
            "position_tolerance_m": float(self.position_tolerance_m),
            "orientation_tolerance_rad": float(self.orientation_tolerance_rad),
            "torque_threshold_Nm": None if self.torque_threshold_Nm is None else float(self.torque_threshold_Nm),
            "target_speed_limit_mps": float(self.target_speed_limit_mps),
            "joint_rate_limits_radps": None if rates is None else list(rates),
        }

    @classmethod
    def from_dict(cls, document: dict) -> CaptureCriteria:
        """The criteria a record or a summary holds: today's names (``to_dict()``) or those of
        older versions (``final_position_m``, ``torque_limit_Nm``, ...); a criterion it does
        not name keeps its default.

        Raises:
            ValueError: a name that is no criterion, or a bad value, naming it.
        """
        fields = {}
        for name, value in document.items():
            name = _OLDER_NAMES.get(name, name)
            if name not in {field.name for field in dataclasses.fields(cls)}:
                raise ValueError(f"capture criteria: no criterion named {name!r}")
            fields[name] = tuple(value) if isinstance(value, list) else value
        return cls(**fields)


__all__ = ["CaptureCriteria"]
