"""Tunable parameters: the logarithms of the gain diagonals, with a mask that freezes any
subset. ``exp`` keeps every tuned gain positive; frozen entries keep their base value and get
a zero gradient."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from spacegrasp_jax.control.gains import GAIN_SHAPES, Gains

#: Gain groups tuned for each controller (39 numbers for the admittance law).
GROUPS = {
    "admittance": ("Md", "Bd", "Kd", "kp", "ki", "kd"),
    "cartesian": ("K_lin", "K_eul", "kp", "ki", "kd"),
}


def make_mask(base: Gains, controller: str, frozen: tuple[str, ...] = ()) -> dict[str, jax.Array]:
    """Boolean arrays, True where an entry is tuned: the controller's groups minus the
    ``frozen`` groups, and never an entry whose base value is 0 (it has no logarithm)."""
    unknown = sorted(set(frozen) - set(GAIN_SHAPES))
    if unknown:
        raise ValueError(f"--freeze: unknown gain group(s) {', '.join(unknown)}; expected {', '.join(GAIN_SHAPES)}")
    return {
        name: jnp.asarray(getattr(base, name)) > 0.0 if name not in frozen else jnp.zeros(GAIN_SHAPES[name], dtype=bool)
        for name in GROUPS[controller]
    }


def initial_params(base: Gains, controller: str) -> dict[str, jax.Array]:
    """``log`` of the tuned groups' gains (a zero stands in where the base gain is 0)."""
    return {
        name: jnp.log(jnp.where(jnp.asarray(getattr(base, name)) > 0.0, getattr(base, name), 1.0))
        for name in GROUPS[controller]
    }


def gains_from_params(params: dict[str, jax.Array], base: Gains, mask: dict[str, jax.Array]) -> Gains:
    """The gains that ``params`` (log values) stand for; masked-out entries keep ``base``."""
    values = {name: getattr(base, name) for name in GAIN_SHAPES}
    for name, log_value in params.items():
        values[name] = jnp.where(mask[name], jnp.exp(log_value), values[name])
    return Gains(**values)
