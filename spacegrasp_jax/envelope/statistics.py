"""What a success rate or a difference between two gain sets is worth: confidence intervals
and paired tests, on the host (NumPy and ``scipy.stats``).

* [`success_interval()`][spacegrasp_jax.envelope.statistics.success_interval] - a success rate with its 95% Wilson score interval.
* [`compare_success()`][spacegrasp_jax.envelope.statistics.compare_success] - two gain sets on the same samples: the exact McNemar test on
  the discordant pairs (samples one set captures and the other does not).
* [`compare_metric()`][spacegrasp_jax.envelope.statistics.compare_metric] - two gain sets' values of one metric on the same samples: the
  median of the paired differences with a bootstrap 95% interval, the Wilcoxon signed-rank
  p-value, and the counts of samples each set wins.
* [`interquartile_mean()`][spacegrasp_jax.envelope.statistics.interquartile_mean] and
  [`across_runs()`][spacegrasp_jax.envelope.statistics.across_runs] - a statistic over a few
  runs of a method (training seeds): the interquartile mean with a bootstrap 95% interval
  over the runs, as Agarwal et al. (NeurIPS 2021, "Deep reinforcement learning at the edge of
  the statistical precipice") report few-run results.

Every function returns plain floats and ints (``summary.json`` takes them as they are).
"""

from __future__ import annotations

import numpy as np

#: The confidence level of every interval the project reports.
CONFIDENCE = 0.95

#: Resamples of the paired bootstrap, and its fixed seed (a report is reproducible).
BOOTSTRAP_RESAMPLES = 4000
BOOTSTRAP_SEED = 0


def _stats():
    """``scipy.stats``, imported on first use: importing it takes most of a second, which
    every command would otherwise pay at start-up."""
    from scipy import stats

    return stats


def success_interval(successes: int, samples: int) -> dict:
    """``{"rate", "low", "high", "successes", "samples"}``: the success rate and its 95%
    Wilson score interval (``scipy.stats.binomtest(...).proportion_ci(method="wilson")``).
    Wilson's interval keeps its coverage near 0% and 100%, where the normal approximation
    collapses to a point. ``samples == 0`` gives NaN bounds."""
    successes, samples = int(successes), int(samples)
    if not 0 <= successes <= samples:
        raise ValueError(f"successes: need 0 <= successes <= samples, got {successes} of {samples}")
    if samples == 0:
        return {"rate": float("nan"), "low": float("nan"), "high": float("nan"), "successes": 0, "samples": 0}
    interval = _stats().binomtest(successes, samples).proportion_ci(confidence_level=CONFIDENCE, method="wilson")
    return {
        "rate": successes / samples,
        "low": float(interval.low),
        "high": float(interval.high),
        "successes": successes,
        "samples": samples,
    }


def format_interval(interval: dict) -> str:
    """``"67.2% [61.2, 72.7]"``: a [`success_interval()`][spacegrasp_jax.envelope.statistics.success_interval] as a console cell."""
    if interval["samples"] == 0:
        return "-"
    return f"{interval['rate']:.1%} [{100 * interval['low']:.1f}, {100 * interval['high']:.1f}]"


def compare_success(reference, candidate) -> dict:
    """The exact McNemar test of two success flags on the same samples.

    Args:
        reference, candidate: (n,) bool, each sample's success under the two gain sets.

    Returns:
        ``only_reference`` and ``only_candidate`` (the discordant counts: samples only one
        set captures), ``both`` and ``neither``; ``rate_difference`` (candidate - reference)
        with a 95% interval conditional on the discordant count (the Clopper-Pearson
        interval of the discordant split, times discordant / n); and ``p_value``: the
        two-sided exact binomial test that a discordant sample is equally likely to favour
        either set (1.0 when no sample is discordant).
    """
    reference = np.asarray(reference, dtype=bool)
    candidate = np.asarray(candidate, dtype=bool)
    if reference.shape != candidate.shape or reference.ndim != 1:
        raise ValueError(f"need two (n,) flags of the same samples, got {reference.shape} and {candidate.shape}")
    n = reference.size
    only_reference = int(np.sum(reference & ~candidate))
    only_candidate = int(np.sum(candidate & ~reference))
    discordant = only_reference + only_candidate
    if discordant:
        test = _stats().binomtest(only_candidate, discordant, 0.5)
        p_value = float(test.pvalue)
        share = test.proportion_ci(confidence_level=CONFIDENCE, method="exact")
        # difference = (only_candidate - only_reference) / n = discordant / n * (2 share - 1)
        low = discordant / n * (2.0 * share.low - 1.0)
        high = discordant / n * (2.0 * share.high - 1.0)
    else:
        p_value, low, high = 1.0, 0.0, 0.0
    return {
        "samples": n,
        "both": int(np.sum(reference & candidate)),
        "neither": int(np.sum(~reference & ~candidate)),
        "only_reference": only_reference,
        "only_candidate": only_candidate,
        "rate_difference": (only_candidate - only_reference) / n if n else float("nan"),
        "rate_difference_low": float(low),
        "rate_difference_high": float(high),
        "p_value": p_value,
        "test": "exact McNemar (two-sided binomial test on the discordant samples)",
    }


def compare_metric(reference, candidate) -> dict:
    """Two gain sets' values of one metric on the same samples (lower is better: errors,
    torques), over the samples where both are finite.

    Returns:
        ``samples`` (pairs used), ``median_difference`` (candidate - reference) with its
        paired bootstrap 95% interval (percentile method, ``BOOTSTRAP_RESAMPLES``
        resamples of the pairs, seed ``BOOTSTRAP_SEED``), ``candidate_lower`` and
        ``reference_lower`` (samples each set wins; ties in neither), and ``p_value``: the
        two-sided Wilcoxon signed-rank test of the differences (1.0 when all are zero).
    """
    reference = np.asarray(reference, dtype=float)
    candidate = np.asarray(candidate, dtype=float)
    if reference.shape != candidate.shape or reference.ndim != 1:
        raise ValueError(f"need two (n,) arrays of the same samples, got {reference.shape} and {candidate.shape}")
    both = np.isfinite(reference) & np.isfinite(candidate)
    difference = candidate[both] - reference[both]
    n = int(difference.size)
    result = {
        "samples": n,
        "candidate_lower": int(np.sum(difference < 0.0)),
        "reference_lower": int(np.sum(difference > 0.0)),
        "test": "Wilcoxon signed-rank (two-sided); paired bootstrap interval of the median difference",
    }
    if n == 0:
        return result | {"median_difference": float("nan"), "low": float("nan"), "high": float("nan"), "p_value": 1.0}
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    resampled = difference[rng.integers(0, n, size=(BOOTSTRAP_RESAMPLES, n))]
    low, high = np.percentile(np.median(resampled, axis=1), [50 * (1 - CONFIDENCE), 50 * (1 + CONFIDENCE)])
    p_value = 1.0 if not np.any(difference) else float(_stats().wilcoxon(difference).pvalue)
    return result | {
        "median_difference": float(np.median(difference)),
        "low": float(low),
        "high": float(high),
        "p_value": p_value,
    }


def interquartile_mean(values) -> float:
    """The mean of the middle half of ``values`` (a quarter, rounded down, cut from each end
    of the sorted values: ``scipy.stats.trim_mean(values, 0.25)``); NaN for none."""
    values = np.sort(np.asarray(values, dtype=float).ravel())
    cut = int(0.25 * values.size)
    kept = values[cut : values.size - cut]
    return float(np.mean(kept)) if kept.size else float("nan")


def across_runs(values, resamples: int = BOOTSTRAP_RESAMPLES) -> dict:
    """A statistic of a few runs (one value a run, e.g. each training seed's held-out success,
    or each seed's difference between two methods): their interquartile mean with a
    percentile bootstrap 95% interval over the runs (runs drawn with replacement, the IQM of
    each resample), the runs' values and how many."""
    values = np.asarray(values, dtype=float).ravel()
    n = int(values.size)
    result = {"runs": n, "values": values.tolist(), "iqm": interquartile_mean(values)}
    result["test"] = "interquartile mean over runs; percentile bootstrap over runs"
    if n == 0:
        return result | {"low": float("nan"), "high": float("nan")}
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    resampled = np.sort(values[rng.integers(0, n, size=(resamples, n))], axis=1)
    cut = int(0.25 * n)
    means = resampled[:, cut : n - cut].mean(axis=1)
    low, high = np.percentile(means, [50 * (1 - CONFIDENCE), 50 * (1 + CONFIDENCE)])
    return result | {"low": float(low), "high": float(high)}


__all__ = [
    "BOOTSTRAP_RESAMPLES",
    "CONFIDENCE",
    "across_runs",
    "compare_metric",
    "compare_success",
    "format_interval",
    "interquartile_mean",
    "success_interval",
]
