"""The tuning loss's gradient against central differences, gain group by gain group (a module
of its own, so that tests can import it: ``conftest`` is not importable by name)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def check_each_group(loss, params: dict, gradient: dict, groups, seed: int) -> None:
    """Along a random direction of each group of ``groups`` in log-gain space, the slope of
    ``gradient`` equals the central difference of ``loss`` (``params -> (value, aux)``) to 1e-4."""
    value_only = jax.jit(lambda p: loss(p)[0])
    rng = np.random.default_rng(seed)
    for group in groups:
        # The damping (from 1e-3) adds lambda^2 = 1e-6 to J J^T: its effect on the loss is
        # 1e-4 of a gain's, so its difference needs a larger step to rise above the rollout's
        # rounding (the loss is smooth in it; truncation stays far below the tolerance).
        h = 1e-3 if group == "pinv_damping" else 1e-5
        direction = jnp.asarray(rng.normal(size=params[group].shape))
        plus = value_only({**params, group: params[group] + h * direction})
        minus = value_only({**params, group: params[group] - h * direction})
        numeric = float(plus - minus) / (2 * h)
        analytic = float(jnp.vdot(gradient[group], direction))
        assert abs(analytic - numeric) <= 1e-4 * abs(numeric) + 1e-9, (group, analytic, numeric)
