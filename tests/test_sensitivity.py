"""Sobol indices against the Ishigami function's analytic ones (Ishigami and Homma 1990;
the indices as in Saltelli et al., Global Sensitivity Analysis: The Primer, 2008)."""

from __future__ import annotations

import numpy as np
import pytest

from spacegrasp_jax.analysis import sensitivity


def ishigami(points: np.ndarray, a: float = 7.0, b: float = 0.1) -> np.ndarray:
    x = np.pi * (2.0 * points - 1.0)  # [0, 1] -> [-pi, pi]
    return np.sin(x[:, 0]) + a * np.sin(x[:, 1]) ** 2 + b * x[:, 2] ** 4 * np.sin(x[:, 0])


def ishigami_indices(a: float = 7.0, b: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """The analytic first-order and total indices of x1, x2, x3."""
    v1 = 0.5 * (1 + b * np.pi**4 / 5) ** 2
    v2 = a**2 / 8
    v13 = b**2 * np.pi**8 * (1 / 18 - 1 / 50)
    variance = v1 + v2 + v13
    return np.array([v1, v2, 0.0]) / variance, np.array([v1 + v13, v2, v13]) / variance


def test_the_indices_of_the_ishigami_function_are_its_analytic_ones():
    first, total = ishigami_indices()
    np.testing.assert_allclose(first, [0.3139, 0.4424, 0.0], atol=1e-4)  # the textbook's values
    result = sensitivity.analyse(ishigami, [[0], [1], [2]], count=2**13, seed=1)
    np.testing.assert_allclose(result["first"], first, atol=0.02)
    np.testing.assert_allclose(result["total"], total, atol=0.02)
    assert np.all(result["first_low"] <= first + 0.01) and np.all(first - 0.01 <= result["first_high"])
    assert np.all(result["total_low"] <= total + 0.01) and np.all(total - 0.01 <= result["total_high"])
    assert result["evaluations"] == 2**13 * 5


def test_a_group_counts_its_inputs_together():
    # {x1, x3} against x2: the group's first-order index is 1 - ST2 and its total 1 - S2.
    first, total = ishigami_indices()
    result = sensitivity.analyse(ishigami, [[0, 2], [1]], count=2**12, seed=2)
    np.testing.assert_allclose(result["first"], [1 - total[1], first[1]], atol=0.03)
    np.testing.assert_allclose(result["total"], [1 - first[1], total[1]], atol=0.03)


def test_a_failure_indicator_attributes_its_failures():
    # One cause alone: x0 explains every failure (S0 = ST0 = 1), the others none.
    alone = sensitivity.analyse(lambda x: (x[:, 0] > 0.9).astype(float), [[0], [1], [2]], count=2**12, seed=3)
    np.testing.assert_allclose(alone["first"], [1.0, 0.0, 0.0], atol=0.05)
    assert alone["total"][0] == pytest.approx(1.0, abs=0.05) and np.all(alone["total"][1:] == 0.0)

    # Two causes, x0 > 0.9 or x1 x2 > 0.8: x3 never matters, x1 and x2 alike, each cause's
    # inputs interact with the other's (an OR), so totals exceed first-order indices.
    def fails(points):
        return ((points[:, 0] > 0.9) | (points[:, 1] * points[:, 2] > 0.8)).astype(float)

    both = sensitivity.analyse(fails, [[0], [1], [2], [3]], count=2**12, seed=3)
    assert both["total"][3] == 0.0 and abs(both["first"][3]) < 0.01
    np.testing.assert_allclose(both["total"][1], both["total"][2], atol=0.03)
    assert np.all(both["total"][:3] > both["first"][:3]) and both["total"][0] > both["total"][1] > 0.05


def test_bad_designs_are_refused():
    with pytest.raises(ValueError, match="must partition the columns"):
        sensitivity.saltelli_design([[0], [2]], 8, 0)
    with pytest.raises(ValueError, match="a power of two"):
        sensitivity.saltelli_design([[0], [1]], 12, 0)
    design = sensitivity.saltelli_design([[0], [1]], 8, 0)
    with pytest.raises(ValueError, match="need 32 outputs"):
        sensitivity.sobol_indices(design, np.zeros(31))
