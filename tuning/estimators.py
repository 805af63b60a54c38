"""Estimators of the envelope objective's gradient from a batch of samples, with variance
control: what turns the per-sample gradients of a capture (and forward rollouts at perturbed
gains) into the step a tuner takes.

The quantity estimated is the gradient of ``E_s[L(theta, s)]``, the capture objective
averaged over the envelope's scenarios ``s``, with respect to the log-gains ``theta``
(P numbers). Two kinds of sample estimate it:

* **first order**: a sample's reverse-mode gradient ``g_s = dL(theta, s)/dtheta``, one
  rollout and its adjoint (about 3.5 forward rollouts). Through near-discontinuous contact
  and chaotic captures its distribution is heavy-tailed: one sample's gradient can be 60
  times the median norm and steer a batch mean (documentation, Tuning the gains).
* **zeroth order**: an antithetic pair of forward rollouts of the same sample at
  ``theta +- sigma eps`` (``eps`` standard normal), giving
  ``(L(theta + sigma eps, s) - L(theta - sigma eps, s)) / (2 sigma) * eps``, an unbiased
  estimate of the gradient of the Gaussian-smoothed objective ``E_eps[L(theta + sigma eps)]``.
  Bounded where the loss is bounded, but its variance grows with P.

The batch estimators ([`aggregate()`][tuning.estimators.aggregate]):

* ``mean``: the plain mean of the first-order samples;
* ``clip``: each sample clipped to ``clip_factor`` times the batch's median norm, then
  the mean (a chaotic sample counts, but no more than a few typical ones);
* ``trimmed``: per coordinate, the mean of the samples left after the ``trim`` fraction at
  each end is dropped;
* ``median_of_means``: the batch split into ``groups`` groups in order, per coordinate
  the median of the groups' means.

[`alpha_mix()`][tuning.estimators.alpha_mix] combines a first-order and a zeroth-order
estimate by their measured variances (Suh et al., ICML 2022, the alpha-order estimator), and
trusts the first-order one only as far as the two agree within their noise.
[`guided_directions()`][tuning.estimators.guided_directions] draws the perturbations of a
search distribution stretched along first-order gradients (Maheswaranathan et al., ICML
2019, Guided ES), and [`guided_estimate()`][tuning.estimators.guided_estimate] turns their
antithetic rollouts into a gradient.

Every function is a pure function of arrays (NumPy or JAX), shapes given in each docstring;
a non-finite sample must be dropped by the caller.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

#: The batch estimators of [`aggregate()`][tuning.estimators.aggregate].
AGGREGATES = ("mean", "clip", "trimmed", "median_of_means")

#: ``clip``: a sample's gradient is clipped to this many times the batch's median norm.
CLIP_FACTOR = 3.0
#: ``trimmed``: the fraction of samples dropped at each end, per coordinate.
TRIM = 0.1
#: ``median_of_means``: groups the batch is split into.
GROUPS = 4


def aggregate(
    samples, method: str, *, clip_factor: float = CLIP_FACTOR, trim: float = TRIM, groups: int = GROUPS
) -> np.ndarray:
    """(P,) the batch estimate from ``samples`` (S, P), the per-sample gradients, by
    ``method`` (``AGGREGATES``, module docstring).

    Raises:
        ValueError: an unknown method, no samples, or settings out of range.
    """
    samples = np.asarray(samples, dtype=float)
    if method not in AGGREGATES:
        raise ValueError(f"aggregate: expected one of {', '.join(AGGREGATES)}, got {method!r}")
    if samples.ndim != 2 or samples.shape[0] < 1:
        raise ValueError(f"aggregate: expected samples of shape (S, P) with S >= 1, got {samples.shape}")
    count = samples.shape[0]
    if method == "mean":
        return samples.mean(axis=0)
    if method == "clip":
        return (samples * clip_scales(samples, clip_factor)[:, None]).mean(axis=0)
    if method == "trimmed":
        if not 0.0 <= trim < 0.5:
            raise ValueError(f"trim: must be in [0, 0.5), got {trim}")
        cut = int(math.floor(trim * count))
        ordered = np.sort(samples, axis=0)
        return ordered[cut : count - cut].mean(axis=0)
    if not 1 <= groups <= count:
        raise ValueError(f"groups: must be from 1 to the {count} samples, got {groups}")
    means = np.stack([part.mean(axis=0) for part in np.array_split(samples, groups)])
    return np.median(means, axis=0)


def clip_scales(samples, clip_factor: float = CLIP_FACTOR) -> np.ndarray:
    """(S,) the factor each sample of ``samples`` (S, P) is scaled by under ``clip``: 1, or
    ``clip_factor * median norm / norm`` for a sample above that norm."""
    norms = np.linalg.norm(np.asarray(samples, dtype=float), axis=1)
    ceiling = clip_factor * np.median(norms)
    return np.where(norms > ceiling, ceiling / np.where(norms > 0.0, norms, 1.0), 1.0)


def zeroth_order_samples(losses_plus, losses_minus, directions, sigma: float) -> np.ndarray:
    """(M, P) one zeroth-order sample per antithetic pair: ``(L+ - L-) / (2 sigma) * eps``,
    from the losses (M,) at ``theta + sigma eps`` and ``theta - sigma eps`` and the
    standard-normal ``directions`` eps (M, P). Their mean estimates the gradient of the
    objective smoothed by a Gaussian of standard deviation ``sigma`` (log-gain units)."""
    difference = (np.asarray(losses_plus, dtype=float) - np.asarray(losses_minus, dtype=float)) / (2.0 * sigma)
    return difference[:, None] * np.asarray(directions, dtype=float)


def variance_of_mean(samples) -> float:
    """The variance of the mean of ``samples`` (S, P), summed over the P coordinates (the
    trace of its covariance): ``sum_j var_j / S``, with the unbiased sample variance."""
    samples = np.asarray(samples, dtype=float)
    if samples.shape[0] < 2:
        return math.inf
    return float(np.sum(np.var(samples, axis=0, ddof=1)) / samples.shape[0])


@dataclasses.dataclass(frozen=True)
class Mix:
    """An alpha-order estimate ([`alpha_mix()`][tuning.estimators.alpha_mix]).

    Attributes:
        gradient: (P,) ``alpha * first + (1 - alpha) * zeroth``.
        alpha: the first-order estimate's weight, in [0, 1].
        first_variance, zeroth_variance: the variances of the two estimates (trace of
            their covariances).
        disagreement: ``|first - zeroth|``, and ``noise``, the norm that the two
            estimates' own variances explain (``z * sqrt(first + zeroth variance)``).
    """

    gradient: np.ndarray
    alpha: float
    first_variance: float
    zeroth_variance: float
    disagreement: float
    noise: float


def alpha_mix(first_order, zeroth_order, *, first: str = "clip", z: float = 2.0) -> Mix:
    """The alpha-order mix of the first-order samples ``first_order`` (S, P), aggregated by
    ``first`` ([`aggregate()`][tuning.estimators.aggregate]), and the zeroth-order samples
    ``zeroth_order`` (M, P) ([`zeroth_order_samples()`][tuning.estimators.zeroth_order_samples]).

    ``alpha = var_zeroth / (var_first + var_zeroth)`` minimises the mix's variance when both
    estimate the same gradient (the first-order variance is measured on the samples as
    ``first`` weighs them: clipped for ``clip``). Where the estimates differ by more than
    their noise explains (``|first - zeroth| > z sqrt(var_first + var_zeroth)``), the
    first-order one is biased (a stiff or chaotic capture) and alpha shrinks until the bias it
    can bring, ``alpha |first - zeroth|``, is within that noise (Suh et al., ICML 2022)."""
    first_order = np.asarray(first_order, dtype=float)
    zeroth_order = np.asarray(zeroth_order, dtype=float)
    if len(first_order) < 2 or len(zeroth_order) < 2:
        raise ValueError("alpha_mix: needs at least 2 samples of each kind, to measure their variances")
    weighed = first_order * clip_scales(first_order)[:, None] if first == "clip" else first_order
    first_estimate = aggregate(first_order, first)
    zeroth_estimate = zeroth_order.mean(axis=0)
    var_first, var_zeroth = variance_of_mean(weighed), variance_of_mean(zeroth_order)
    total = var_first + var_zeroth
    alpha = var_zeroth / total if total > 0.0 else 0.5
    disagreement = float(np.linalg.norm(first_estimate - zeroth_estimate))
    noise = z * math.sqrt(total)
    if alpha * disagreement > noise:
        alpha = noise / disagreement
    return Mix(
        gradient=alpha * first_estimate + (1.0 - alpha) * zeroth_estimate,
        alpha=float(alpha),
        first_variance=var_first,
        zeroth_variance=var_zeroth,
        disagreement=disagreement,
        noise=noise,
    )


def guided_directions(rng: np.random.Generator, guides, count: int, *, share: float = 0.5) -> np.ndarray:
    """(count, P) perturbation directions of Guided ES: ``sqrt(share / P) z + sqrt((1 -
    share) / k) U w``, ``z`` (P,) and ``w`` (k,) standard normal, ``U`` (P, k) an
    orthonormal basis of the ``guides`` (k, P), the recent first-order gradients. Their
    covariance is ``share / P I + (1 - share) / k U U^T``, of trace 1: a search distribution
    stretched along the gradients' subspace (``share = 1``: isotropic)."""
    guides = np.atleast_2d(np.asarray(guides, dtype=float))
    if not 0.0 < share <= 1.0:
        raise ValueError(f"share: must be in (0, 1], got {share}")
    size = guides.shape[1]
    basis, _ = np.linalg.qr(guides.T)  # (P, k)
    k = basis.shape[1]
    isotropic = rng.standard_normal((count, size)) * math.sqrt(share / size)
    along = rng.standard_normal((count, k)) @ basis.T * math.sqrt((1.0 - share) / k)
    return isotropic + along


def guided_estimate(losses_plus, losses_minus, directions, sigma: float) -> np.ndarray:
    """(P,) the gradient estimate of antithetic pairs along Guided ES ``directions`` (M, P)
    of covariance ``C`` (trace 1, [`guided_directions()`][tuning.estimators.guided_directions]):
    ``mean((L+ - L-) / (2 sigma) * d) * P``, where ``L+-`` are the losses (M,) at
    ``theta +- sigma d``. With ``C = I / P`` (``share = 1``) it is
    [`zeroth_order_samples()`][tuning.estimators.zeroth_order_samples]'s mean up to the
    directions' scale; otherwise it estimates ``P C`` times the smoothed gradient, the
    gradient stretched along the guides' subspace (the Guided ES step)."""
    directions = np.asarray(directions, dtype=float)
    difference = (np.asarray(losses_plus, dtype=float) - np.asarray(losses_minus, dtype=float)) / (2.0 * sigma)
    return (difference[:, None] * directions).mean(axis=0) * directions.shape[1]


def cosine(a, b) -> float:
    """The cosine between two vectors (NaN if either is zero)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    scale = float(np.linalg.norm(a) * np.linalg.norm(b))
    return float(a @ b) / scale if scale > 0.0 else math.nan


__all__ = [
    "AGGREGATES",
    "CLIP_FACTOR",
    "GROUPS",
    "TRIM",
    "Mix",
    "aggregate",
    "alpha_mix",
    "clip_scales",
    "cosine",
    "guided_directions",
    "guided_estimate",
    "variance_of_mean",
    "zeroth_order_samples",
]
