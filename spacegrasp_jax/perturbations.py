"""Seeded perturbations of a scenario, for robust tuning and Monte-Carlo campaigns.

Sample ``i`` of a campaign depends only on ``(seed, i)`` (``jax.random.fold_in``), so a
batch gives the same samples whatever its size or chunking. Every perturbation is uniform:

* ``q_init_rad``: each initial joint angle moves by up to +- this much;
* ``lar_position_m``: the LAR origin moves by up to +- this much along each LAR axis;
* ``lar_angle_rad``: the LAR frame turns by a rotation vector whose components are up to +-
  this much (LAR axes);
* ``stiffness_factor``: the contact stiffness is scaled by ``factor^U(-1, 1)``.

The LAR frame is moved independently of ``q_init``: a perturbed sample starts with the EE off
its desired start, as a real approach would.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from spacegrasp_jax import spatial
from spacegrasp_jax.scenario import Scenario


@dataclasses.dataclass(frozen=True)
class PerturbationRanges:
    """Half-widths of the uniform perturbations (module docstring); zeros give the nominal."""

    q_init_rad: float = 0.01
    lar_position_m: float = 0.003
    lar_angle_rad: float = 0.005
    stiffness_factor: float = 2.0

    def __post_init__(self):
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if not (isinstance(value, (int, float)) and value == value and abs(value) != float("inf")):
                raise ValueError(f"{field.name}: must be a finite number, got {value!r}")
            if value < 0.0:
                raise ValueError(f"{field.name}: must be non-negative, got {value}")
        if self.stiffness_factor < 1.0:
            raise ValueError(f"stiffness_factor: must be >= 1 (1 leaves the stiffness unchanged), got {self.stiffness_factor}")


def perturb(scenario: Scenario, key: jax.Array, ranges: PerturbationRanges) -> Scenario:
    """One perturbed copy of ``scenario`` drawn with ``key``."""
    k_q, k_p, k_r, k_k = jax.random.split(key, 4)
    dtype = scenario.initial.q.dtype
    dq = ranges.q_init_rad * jax.random.uniform(k_q, (7,), dtype, -1.0, 1.0)
    dp = ranges.lar_position_m * jax.random.uniform(k_p, (3,), dtype, -1.0, 1.0)
    dr = ranges.lar_angle_rad * jax.random.uniform(k_r, (3,), dtype, -1.0, 1.0)
    stiffness_exponent = jax.random.uniform(k_k, (), dtype, -1.0, 1.0)
    return dataclasses.replace(
        scenario,
        initial=dataclasses.replace(scenario.initial, q=scenario.initial.q + dq),
        p_lar=scenario.p_lar + scenario.R_lar @ dp,
        R_lar=scenario.R_lar @ spatial.rotation_exp(dr),
        contact_stiffness=scenario.contact_stiffness * ranges.stiffness_factor**stiffness_exponent,
    )


def sample_scenarios(scenario: Scenario, seed: int, indices, ranges: PerturbationRanges) -> Scenario:
    """A batch of perturbed scenarios (leading axis over ``indices``), sample ``i`` drawn
    with ``fold_in(PRNGKey(seed), i)``."""
    base_key = jax.random.PRNGKey(seed)
    keys = jax.vmap(lambda i: jax.random.fold_in(base_key, i))(jnp.asarray(indices, dtype=jnp.uint32))
    return jax.vmap(lambda key: perturb(scenario, key, ranges))(keys)
