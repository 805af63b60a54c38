"""Confidence intervals and paired tests against hand-worked cases and their textbook formulas."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import comb
from scipy.stats import beta

from spacegrasp_jax.envelope import statistics

Z95 = 1.959963984540054  # the standard normal's 97.5th percentile


def wilson(k: int, n: int) -> tuple[float, float]:
    """The Wilson score interval written out (Wilson 1927)."""
    p = k / n
    centre = (p + Z95**2 / (2 * n)) / (1 + Z95**2 / n)
    half = Z95 / (1 + Z95**2 / n) * math.sqrt(p * (1 - p) / n + Z95**2 / (4 * n * n))
    return centre - half, centre + half


@pytest.mark.parametrize("k, n", [(172, 256), (0, 50), (50, 50), (7, 10), (905, 1000)])
def test_success_interval_is_wilsons(k, n):
    interval = statistics.success_interval(k, n)
    low, high = wilson(k, n)
    assert interval["rate"] == k / n
    assert interval["low"] == pytest.approx(low, abs=1e-12)
    assert interval["high"] == pytest.approx(high, abs=1e-12)
    assert interval["low"] <= k / n <= interval["high"]


def test_success_interval_at_1000_samples_is_about_two_points_either_side():
    interval = statistics.success_interval(900, 1000)  # 1.96 sqrt(0.9 * 0.1 / 1000) = 0.0186
    assert 0.017 < (interval["high"] - interval["low"]) / 2 < 0.020


def test_success_interval_refuses_impossible_counts():
    with pytest.raises(ValueError, match="successes"):
        statistics.success_interval(11, 10)
    assert math.isnan(statistics.success_interval(0, 0)["low"])


def test_mcnemar_exact_by_hand():
    # 1 sample only the reference captures, 8 only the candidate, 20 both, 3 neither.
    reference = np.array([True] * 1 + [False] * 8 + [True] * 20 + [False] * 3)
    candidate = np.array([False] * 1 + [True] * 8 + [True] * 20 + [False] * 3)
    result = statistics.compare_success(reference, candidate)
    # Two-sided exact binomial with 9 discordant pairs, 1 in the smaller tail:
    # 2 * (C(9,0) + C(9,1)) / 2^9.
    assert result["p_value"] == pytest.approx(2 * (comb(9, 0) + comb(9, 1)) / 2**9, rel=1e-12)
    assert (result["only_reference"], result["only_candidate"], result["both"], result["neither"]) == (1, 8, 20, 3)
    assert result["rate_difference"] == pytest.approx(7 / 32)
    # The Clopper-Pearson bounds of 8 of 9, mapped onto the difference.
    low, high = beta.ppf(0.025, 8, 2), beta.ppf(0.975, 9, 1)
    assert result["rate_difference_low"] == pytest.approx(9 / 32 * (2 * low - 1), rel=1e-9)
    assert result["rate_difference_high"] == pytest.approx(9 / 32 * (2 * high - 1), rel=1e-9)


def test_mcnemar_without_discordant_samples():
    flags = np.array([True, False, True])
    result = statistics.compare_success(flags, flags)
    assert result["p_value"] == 1.0 and result["rate_difference"] == 0.0


def test_mcnemar_is_symmetric():
    rng = np.random.default_rng(3)
    a, b = rng.random(200) < 0.6, rng.random(200) < 0.7
    forward, backward = statistics.compare_success(a, b), statistics.compare_success(b, a)
    assert forward["p_value"] == pytest.approx(backward["p_value"])
    assert forward["rate_difference"] == pytest.approx(-backward["rate_difference"])


def test_compare_metric_by_hand():
    reference = np.array([1.0, 2.0, 3.0, 4.0, 5.0, np.nan])
    candidate = reference - np.array([1.0, 2.0, 3.0, 4.0, 5.0, 0.0])  # lower on every finite pair
    result = statistics.compare_metric(reference, candidate)
    assert result["samples"] == 5
    assert (result["candidate_lower"], result["reference_lower"]) == (5, 0)
    assert result["median_difference"] == -3.0
    # The exact signed-rank null: all 5 signs alike has probability 2 / 2^5 (two-sided).
    assert result["p_value"] == pytest.approx(2 / 2**5)
    assert result["low"] <= -3.0 <= result["high"]


def test_compare_metric_interval_covers_a_known_shift():
    rng = np.random.default_rng(11)
    reference = rng.normal(10.0, 1.0, 400)
    candidate = reference + 0.5 + rng.normal(0.0, 0.1, 400)
    result = statistics.compare_metric(reference, candidate)
    assert result["low"] < 0.5 < result["high"] and result["high"] - result["low"] < 0.05
    assert result["p_value"] < 1e-10


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 8, 13])
def test_the_interquartile_mean_is_scipys_trimmed_mean(n):
    from scipy import stats

    values = np.random.default_rng(n).normal(size=n)
    assert statistics.interquartile_mean(values) == pytest.approx(stats.trim_mean(values, 0.25), rel=1e-14)


def test_the_interval_across_runs_is_the_bootstrap_distributions_quantiles():
    """Four runs: every resample of 4 with replacement is one of 4^4 = 256 equally likely
    draws, so the bootstrap distribution of the IQM is known exactly; the interval's ends are
    its 2.5% and 97.5% quantiles, to the resampling's precision."""
    import itertools

    values = np.array([0.02, 0.05, -0.01, 0.09])
    exact = np.sort(
        [statistics.interquartile_mean(values[list(draw)]) for draw in itertools.product(range(4), repeat=4)]
    )
    result = statistics.across_runs(values, resamples=200_000)
    assert result["iqm"] == pytest.approx(0.035) and result["runs"] == 4  # (0.02 + 0.05) / 2
    # the 2.5% quantile of 256 equally likely values lies between the 6th and the 7th
    assert exact[5] - 1e-12 <= result["low"] <= exact[6] + 1e-12
    assert exact[-7] - 1e-12 <= result["high"] <= exact[-6] + 1e-12
    assert statistics.across_runs([0.1] * 5)["low"] == statistics.across_runs([0.1] * 5)["high"] == pytest.approx(0.1)
