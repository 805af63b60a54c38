"""Looking at the objective around a set of gains: which gains matter (the gradient per gain
group), and the loss along a line in parameter space checked against the gradient's slope.

Parameters are log-gains ([`spacegrasp_jax.tuning.parameters`][tuning.parameters]), so ``d loss / d param`` is the change of
the loss per unit *relative* change of a gain: a gradient entry of 0.5 means a 1% larger gain
raises the loss by about 0.005.
"""

from __future__ import annotations

import jax
import numpy as np


def _dot(a: dict, b: dict) -> float:
    return float(sum(np.vdot(np.asarray(a[name]), np.asarray(b[name])) for name in a))


def group_norms(gradient: dict) -> dict[str, float]:
    """Euclidean norm of the gradient of each gain group (``Md``, ``Bd``, ``kp``, ...)."""
    return {name: float(np.linalg.norm(np.asarray(value))) for name, value in gradient.items()}


def descent_direction(gradient: dict) -> dict[str, np.ndarray]:
    """``-gradient / |gradient|``: the unit direction of steepest descent in log-gain space."""
    norm = np.sqrt(_dot(gradient, gradient))
    if not np.isfinite(norm) or norm == 0.0:
        raise ValueError(f"descent_direction: the gradient norm is {norm}; no direction to follow")
    return {name: -np.asarray(value) / norm for name, value in gradient.items()}


def loss_slice(value_and_grad, params: dict, direction: dict, steps) -> dict[str, np.ndarray]:
    """The loss along the line ``params + s * direction`` and its exact slope there.

    Args:
        value_and_grad: ``params -> ((loss, aux), gradient)``, e.g. from [`spacegrasp_jax.tuning.tune.setup()`][tuning.tune.setup].
        params: the line's origin (log-gains). direction: same structure (e.g. [`descent_direction()`][tuning.analysis.descent_direction]).
        steps: (S,) values of ``s``.

    Returns:
        ``step`` (S,), ``loss`` (S,) and ``slope`` (S,): ``d loss / d s = gradient . direction``
        at each point, from the gradient (no finite differences).
    """
    steps = np.asarray(steps, dtype=float)
    losses, slopes = [], []
    for s in steps:
        point = jax.tree.map(lambda p, d: p + s * d, params, direction)
        (loss, _), gradient = value_and_grad(point)
        losses.append(float(loss))
        slopes.append(_dot(gradient, direction))
    return {"step": steps, "loss": np.array(losses), "slope": np.array(slopes)}


def slope_check(value_and_grad, params: dict, direction: dict, h: float = 1e-4) -> dict[str, float]:
    """The gradient's directional derivative at ``params`` against the central difference
    ``(loss(+h) - loss(-h)) / 2h`` along ``direction``.

    Returns:
        ``gradient_slope``, ``finite_difference_slope`` and their ``relative_error``.
    """
    probe = loss_slice(value_and_grad, params, direction, [-h, 0.0, h])
    finite_difference = (probe["loss"][2] - probe["loss"][0]) / (2.0 * h)
    analytic = probe["slope"][1]
    return {
        "gradient_slope": analytic,
        "finite_difference_slope": finite_difference,
        "relative_error": abs(analytic - finite_difference) / max(abs(analytic), 1e-300),
    }


__all__ = ["descent_direction", "group_norms", "loss_slice", "slope_check"]
