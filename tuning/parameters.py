"""Tunable parameters: the logarithms of the gain diagonals and of the pseudoinverse's
damping, with a mask that freezes any subset. ``exp`` keeps every tuned gain positive; frozen
entries keep their base value and get a zero gradient. For a gain schedule
([`GainSchedule`][spacegrasp_jax.loop.control.schedule.GainSchedule]) the parameters are the
log-gains at every knot of every group: a group of K knots has K times its entries.

A damping of 0 (the paper's exact pseudoinverse) has no logarithm: a tuned damping starts at
``DAMPING_START``, small enough to change nothing measurable away from a singularity
(it adds ``1e-6`` to ``J J^T``, whose eigenvalues along the paper's motion are 0.01 to 1)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from spacegrasp_jax.loop.control.gains import GAIN_SHAPES, GAINS_USED, Gains
from spacegrasp_jax.loop.control.registry import gains_used
from spacegrasp_jax.loop.control.schedule import GainSchedule

#: Gain groups tuned for each controller: every group it uses (40 numbers for the admittance law).
GROUPS = GAINS_USED

#: Where a tuned ``pinv_damping`` starts when the base gains' is 0.
DAMPING_START = 1e-3


def group_values(gains: Gains | GainSchedule, name: str) -> jax.Array:
    """Group ``name``'s gains: (n,) of a gain set, (K, n) at a schedule's K knots."""
    return gains.values[name] if isinstance(gains, GainSchedule) else getattr(gains, name)


def make_mask(base: Gains | GainSchedule, controller, frozen: tuple[str, ...] = ()) -> dict[str, jax.Array]:
    """Boolean arrays, True where an entry is tuned: the controller's groups (``controller``: a
    law's name or a law object, [`gains_used()`][spacegrasp_jax.loop.control.registry.gains_used])
    minus the ``frozen`` groups, and never a gain whose base value is 0 (it has no logarithm;
    the damping starts at ``DAMPING_START`` instead)."""
    unknown = sorted(set(frozen) - set(GAIN_SHAPES))
    if unknown:
        raise ValueError(f"--freeze: unknown gain group(s) {', '.join(unknown)}; expected {', '.join(GAIN_SHAPES)}")
    return {
        name: jnp.zeros(jnp.shape(group_values(base, name)), dtype=bool)
        if name in frozen
        else jnp.ones(jnp.shape(group_values(base, name)), dtype=bool)
        if name == "pinv_damping"
        else jnp.asarray(group_values(base, name)) > 0.0
        for name in gains_used(controller)
    }


def initial_params(base: Gains | GainSchedule, controller) -> dict[str, jax.Array]:
    """``log`` of the tuned groups' gains (``controller``: a law's name or a law object; a zero
    stands in where the base gain is 0, and ``DAMPING_START`` where the base damping is)."""

    def start(name):
        value = jnp.asarray(group_values(base, name))
        fill = DAMPING_START if name == "pinv_damping" else 1.0
        return jnp.log(jnp.where(value > 0.0, value, fill))

    return {name: start(name) for name in gains_used(controller)}


def gains_from_params(
    params: dict[str, jax.Array], base: Gains | GainSchedule, mask: dict[str, jax.Array]
) -> Gains | GainSchedule:
    """The gains (or the schedule, for a schedule ``base``) that ``params`` (log values)
    stand for; masked-out entries keep ``base``. ``base`` may be any dataclass gain set that
    holds the tuned groups as fields (a law of your own's)."""
    tuned = {
        name: jnp.where(mask[name], jnp.exp(log_value), group_values(base, name)) for name, log_value in params.items()
    }
    if isinstance(base, GainSchedule):
        return dataclasses.replace(base, values=base.values | tuned)
    return dataclasses.replace(base, **tuned)
