"""Variance-based global sensitivity: which perturbations a capture's outcome depends on.

Sobol indices of an output ``Y = f(X)`` of independent inputs ``X``, grouped: for a group
``G`` of inputs, the first-order index ``S_G = Var(E[Y | X_G]) / Var(Y)`` (the share of the
variance that ``X_G`` explains alone) and the total index ``ST_G = E[Var(Y | X_~G)] / Var(Y)``
(its share with all its interactions). With ``Y`` a capture's failure (0 or 1), ``ST_G`` is
the share of failures that the perturbations of group ``G`` take part in causing; a group
with ``ST_G`` near 0 can be left at any value of its range without changing the outcome.

The design is Saltelli's (Saltelli et al., Computer Physics Communications 181, 2010): two
independent matrices ``A`` and ``B`` of ``N`` points each (the two halves of a scrambled
Sobol sequence in ``2 d`` dimensions), and for each group ``i`` the matrix ``AB_i``: ``A``
with the columns of group ``i`` taken from ``B``; ``N (k + 2)`` evaluations for ``k`` groups.
Estimators: ``S_i = mean(f(B) (f(AB_i) - f(A))) / V`` (Saltelli 2010) and
``ST_i = mean((f(A) - f(AB_i))^2) / (2 V)`` (Jansen 1999), ``V`` the variance of ``f(A)``
and ``f(B)`` together; 95% intervals by a percentile bootstrap over the ``N`` rows.
The suite checks the estimators against the Ishigami function's analytic indices.

Inputs live in the unit cube [0, 1]^d here; a caller maps them to its own ranges.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable, Sequence

import numpy as np

#: Bootstrap resamples of the rows for the intervals, and their generator's seed.
BOOTSTRAP_RESAMPLES = 2000
BOOTSTRAP_SEED = 20261207


@dataclasses.dataclass(frozen=True)
class Design:
    """Saltelli's design for ``groups`` of the ``d`` inputs.

    Attributes:
        A, B: (N, d) the two base matrices, in [0, 1].
        AB: (k, N, d) ``AB[i]``: ``A`` with the columns of group ``i`` from ``B``.
        groups: k tuples of column indices, every column in exactly one.
    """

    A: np.ndarray
    B: np.ndarray
    AB: np.ndarray
    groups: tuple[tuple[int, ...], ...]

    @property
    def points(self) -> np.ndarray:
        """(N (k + 2), d) every point to evaluate: ``A``, ``B``, then each ``AB_i``."""
        return np.concatenate([self.A, self.B, *self.AB])


def saltelli_design(groups: Sequence[Sequence[int]], count: int, seed: int) -> Design:
    """The design of ``count`` base points (a power of two: the Sobol sequence's balance) for
    ``groups`` (lists of column indices that partition ``range(d)``), from a scrambled Sobol
    sequence of ``seed`` (``scipy.stats.qmc.Sobol``)."""
    from scipy.stats import qmc

    groups = tuple(tuple(int(c) for c in group) for group in groups)
    columns = sorted(c for group in groups for c in group)
    d = len(columns)
    if not groups or any(not group for group in groups) or columns != list(range(d)):
        raise ValueError(f"groups: must partition the columns 0..d-1 into non-empty groups, got {groups}")
    if count < 2 or count & (count - 1):
        raise ValueError(f"count: must be a power of two of at least 2, got {count}")
    sample = qmc.Sobol(2 * d, scramble=True, seed=seed).random(count)
    A, B = sample[:, :d], sample[:, d:]
    AB = np.repeat(A[None], len(groups), axis=0)
    for i, group in enumerate(groups):
        AB[i][:, group] = B[:, group]
    return Design(A, B, AB, groups)


def _indices(f_A, f_B, f_AB):
    variance = np.var(np.concatenate([f_A, f_B], axis=-1), axis=-1)
    first = np.mean(f_B[..., None, :] * (f_AB - f_A[..., None, :]), axis=-1) / variance[..., None]
    total = 0.5 * np.mean((f_A[..., None, :] - f_AB) ** 2, axis=-1) / variance[..., None]
    return first, total, variance


def sobol_indices(design: Design, values: np.ndarray, resamples: int = BOOTSTRAP_RESAMPLES) -> dict:
    """The groups' first-order and total indices from ``values`` (N (k + 2),), the output at
    ``design.points`` in order, with percentile bootstrap 95% intervals over the rows.

    Returns:
        ``first`` and ``total``: (k,) the estimates; ``first_low``, ``first_high``,
        ``total_low``, ``total_high``: (k,) their intervals; ``variance``: ``Var(Y)``
        (0: the output never changed, every index NaN); ``evaluations``: N (k + 2).
    """
    values = np.asarray(values, dtype=float)
    count, k = design.A.shape[0], len(design.groups)
    if values.shape != (count * (k + 2),):
        raise ValueError(f"values: need {count * (k + 2)} outputs (the design's points), got {values.shape}")
    f_A, f_B, f_AB = values[:count], values[count : 2 * count], values[2 * count :].reshape(k, count)
    result = {"evaluations": int(values.size)}
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    with np.errstate(divide="ignore", invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a constant output: NaN indices
        first, total, variance = _indices(f_A, f_B, f_AB)
        draws = []
        for _ in range(resamples):
            rows = rng.integers(0, count, size=count)
            draws.append(_indices(f_A[rows], f_B[rows], f_AB[:, rows])[:2])
        first_b, total_b = (np.array([draw[j] for draw in draws]) for j in (0, 1))
        result |= {"first": first, "total": total, "variance": float(variance)}
        for name, values_b in (("first", first_b), ("total", total_b)):
            result[f"{name}_low"], result[f"{name}_high"] = np.nanpercentile(values_b, [2.5, 97.5], axis=0)
    return result


def analyse(
    function: Callable[[np.ndarray], np.ndarray], groups: Sequence[Sequence[int]], count: int, seed: int
) -> dict:
    """[`sobol_indices()`][spacegrasp_jax.analysis.sensitivity.sobol_indices] of ``function``
    (points (M, d) in [0, 1]^d -> outputs (M,)) on the design of
    [`saltelli_design()`][spacegrasp_jax.analysis.sensitivity.saltelli_design]."""
    design = saltelli_design(groups, count, seed)
    return sobol_indices(design, np.asarray(function(design.points), dtype=float))


__all__ = ["Design", "analyse", "saltelli_design", "sobol_indices"]
