"""The tuning objective, from a rollout log.

With ``e_p`` the final EE position error in LAR (m), ``e_o`` the final orientation error (rad),
``rms`` the RMS position tracking error over the run (m), ``|u_i(t)|`` the joint torques and
``|F(t)|`` the contact force:

    loss = w_position    * e_p / position_scale
         + w_orientation * e_o / orientation_scale
         + w_rms         * rms / rms_scale
         + w_torque      * smoothmax_{t, i} |u_i(t)| / torque_scale_i
         + w_contact     * smoothmax_t |F(t)| / contact_scale
         + w_target      * |v_target(T)| / target_speed_scale      (free-floating target only)

``smoothmax(x) = T log sum exp(x / T)`` over every sample (temperature ``T``) is a smooth upper
bound of the hard maximum, exceeding it by at most ``T log(count)``; the hard maximum and the
gap are always reported beside it. With ``torque_scale_i`` the peaks of the initial gains,
the torque term is the largest peak relative to where the tuning started: below 1 means every
joint's peak went down. ``|v_target(T)|`` is a free-floating target's final speed ("do not
push it away"); its weight is 0 by default.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from spacegrasp_jax import metrics


@dataclasses.dataclass(frozen=True)
class Weights:
    """Weights of the objective's parts (dimensionless; each part is scaled first)."""

    final_position: float = 1.0
    final_orientation: float = 0.1
    rms_tracking: float = 0.1
    peak_torque: float = 10.0
    contact_force: float = 0.0
    target_speed: float = 0.0

    @classmethod
    def parse(cls, text: str) -> Weights:
        """``"final_position=1,peak_torque=2"`` -> Weights; unknown names or negative or
        non-finite values raise ``ValueError`` naming them."""
        values = {}
        known = {field.name for field in dataclasses.fields(cls)}
        for item in filter(None, (part.strip() for part in text.split(","))):
            name, _, number = item.partition("=")
            if name not in known:
                raise ValueError(f"--weights: unknown weight {name!r}; expected {', '.join(sorted(known))}")
            try:
                value = float(number)
            except ValueError:
                raise ValueError(f"--weights: {name} needs a number, got {number!r}") from None
            if not value >= 0.0 or value == float("inf"):
                raise ValueError(f"--weights: {name} must be finite and non-negative, got {number}")
            values[name] = value
        return cls(**values)


@dataclasses.dataclass(frozen=True)
class Objective:
    """Weights, scales and temperature of the objective (module docstring).

    Attributes:
        torque_scale_Nm: (7,) per-joint torque scale; ``tuning`` sets it to the peaks of
            the initial gains on the nominal scenario.
    """

    weights: Weights
    torque_scale_Nm: tuple[float, ...]
    position_scale_m: float = 1e-3
    orientation_scale_rad: float = 1e-2
    rms_scale_m: float = 1e-2
    contact_scale_N: float = 10.0
    target_speed_scale_mps: float = 1e-3
    temperature: float = 0.02

    def __post_init__(self):
        if len(self.torque_scale_Nm) != 7 or min(self.torque_scale_Nm) <= 0.0:
            raise ValueError(f"torque_scale_Nm: need 7 positive numbers, got {self.torque_scale_Nm}")
        if not self.temperature > 0.0:
            raise ValueError(f"temperature: must be positive, got {self.temperature}")


def smooth_max(values: jax.Array, temperature: float) -> jax.Array:
    """``T log sum exp(values / T)`` over all entries: an upper bound of ``max(values)``."""
    return temperature * jax.nn.logsumexp(values.ravel() / temperature)


def objective_parts(log, objective: Objective) -> dict[str, jax.Array]:
    """Every part of the objective, unweighted, plus ``loss`` (the weighted sum); with a
    free-floating target, its final speed ``final_target_speed_mps`` too."""
    w = objective.weights
    torque_ratio = jnp.abs(log.u) / jnp.asarray(objective.torque_scale_Nm)
    contact = metrics.contact_force_norm(log)
    parts = {
        "final_position_m": metrics.final_position_error(log),
        "final_orientation_rad": metrics.final_orientation_error(log),
        "rms_tracking_m": metrics.rms_position_error(log),
        "peak_torque_smooth": smooth_max(torque_ratio, objective.temperature),
        "peak_torque_hard": jnp.max(torque_ratio),
        "peak_contact_smooth_N": smooth_max(contact, objective.temperature * objective.contact_scale_N),
        "peak_contact_hard_N": jnp.max(contact),
    }
    parts["peak_torque_gap"] = parts["peak_torque_smooth"] - parts["peak_torque_hard"]
    parts["loss"] = (
        w.final_position * parts["final_position_m"] / objective.position_scale_m
        + w.final_orientation * parts["final_orientation_rad"] / objective.orientation_scale_rad
        + w.rms_tracking * parts["rms_tracking_m"] / objective.rms_scale_m
        + w.peak_torque * parts["peak_torque_smooth"]
        + w.contact_force * parts["peak_contact_smooth_N"] / objective.contact_scale_N
    )
    if log.target_velocity is not None:
        parts["final_target_speed_mps"] = metrics.safe_norm(log.target_velocity[-1])
        parts["loss"] = (
            parts["loss"] + w.target_speed * parts["final_target_speed_mps"] / objective.target_speed_scale_mps
        )
    return parts
