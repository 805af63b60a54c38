"""Gradient health over the envelope: is the tuning objective's gradient at a set of gains
one a descent method can trust on every scenario it will meet?

For the nominal scenario and N perturbed ones (the Monte-Carlo campaigns' samples 1..N, with
their satellites, noise keys and target estimates under a realism), [`envelope_gradients()`][tuning.gradients.envelope_gradients]
computes the objective's gradient with respect to the log-gains (the tuning parameters,
[`spacegrasp_jax.tuning.parameters`][tuning.parameters]), batched and sharded like a campaign, over several
horizons at once (the objective of the log cut at each horizon). [`report()`][tuning.gradients.report] condenses
them into what ``spacegrasp gradients`` writes in ``gradients.json``:

* per gain group and entry: mean, median, spread (standard deviation and interquartile
  range) and *sign agreement*, the fraction of samples whose gradient entry has the nominal
  gradient's sign;
* the samples whose gradient or loss is not finite (indices, perturbations);
* the samples whose gradient norm exceeds ``outlier_factor`` times the nominal's
  (indices, norms, cosine with the nominal gradient, perturbations), and the distribution of
  the norm ratio and of the cosine;
* central differences against the gradient on a few samples (directional derivatives along
  random directions);
* the median and largest gradient norm at each horizon: a norm that grows exponentially with
  the horizon is the mark of a chaotic, untrustworthy gradient.

Every number is per unit relative change of a gain (log-gains): an entry of 0.5 means a 1%
larger gain raises the loss by about 0.005.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from spacegrasp_jax.core.model import Robot
from spacegrasp_jax.envelope.perturbations import PerturbationRanges
from spacegrasp_jax.envelope.scenario import Scenario
from spacegrasp_jax.jobs import batching, compilation
from spacegrasp_jax.jobs.experiment import loop_options
from spacegrasp_jax.jobs.montecarlo import sample_loops
from spacegrasp_jax.loop.control.gains import Gains
from spacegrasp_jax.loop.realism import ideal
from spacegrasp_jax.loop.simulate import RunSpec, closed_loop
from spacegrasp_jax.tuning.objective import Objective, objective_parts, objective_spec
from spacegrasp_jax.tuning.parameters import gains_from_params, initial_params, make_mask
from spacegrasp_jax.tuning.tune import block_steps

#: Horizons, as fractions of the scenario's duration, at which the gradient is taken.
HORIZONS = (0.125, 0.25, 0.5, 1.0)


@dataclasses.dataclass(frozen=True)
class EnvelopeGradients:
    """The gradients of one evaluation ([`envelope_gradients()`][tuning.gradients.envelope_gradients]).

    Attributes:
        horizons_s: (H,) s, the horizons; the last is the whole scenario.
        losses: (N + 1, H) the objective at each horizon; row 0 is the nominal scenario.
        gradients: group -> (N + 1, H, size) d loss / d log-gain.
        perturbations: field -> (N, ...) the perturbed samples' drawn numbers.
        sample_indices: (N,) the campaign indices of the perturbed samples (1..N).
    """

    horizons_s: np.ndarray
    losses: np.ndarray
    gradients: dict[str, np.ndarray]
    perturbations: dict[str, np.ndarray]
    sample_indices: np.ndarray


def _nominal_first(robot: Robot, scenario: Scenario, seed: int, n: int, ranges, realism):
    """The loops of the nominal scenario (row 0) and of samples 1..n, one batch."""
    perturbed = sample_loops(robot, scenario, seed, np.arange(1, n + 1), ranges, realism)
    nominal = jax.tree.map(lambda leaf: jnp.asarray(leaf)[None], (robot, scenario))
    realisms, keys = perturbed.realisms, perturbed.keys
    if realisms is not None:  # the nominal sample: the loop's own estimate errors, key of the seed
        base = realism if realism is not None else ideal()
        first = jax.tree.map(lambda leaf: leaf[:1], realisms)
        first = dataclasses.replace(
            first,
            lar_position_error_m=jnp.asarray(base.lar_position_error_m)[None],
            lar_angle_error_rad=jnp.asarray(base.lar_angle_error_rad)[None],
        )
        realisms = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), first, realisms)
        keys = jnp.concatenate([jax.random.PRNGKey(seed)[None], keys])
    robots, scenarios = jax.tree.map(
        lambda a, b: jnp.concatenate([a, b]), nominal, (perturbed.robots, perturbed.scenarios)
    )
    return (robots, scenarios, realisms, keys), perturbed.model_robot, perturbed.perturbations


def horizon_steps(n_steps: int, horizons=HORIZONS) -> tuple[int, ...]:
    """The log rows (at least one) that each horizon fraction of ``n_steps`` keeps."""
    return tuple(max(1, round(fraction * n_steps)) for fraction in horizons)


def _horizon_losses(params, base, mask, objective, spec, key, *, steps):
    """(H,) the objective of the run ``spec`` at the log-gains ``params`` (over ``base``),
    its log cut at each of ``steps`` rows."""
    gains = gains_from_params(params, base, mask)
    _, log = closed_loop(spec, gains, key)
    return jnp.stack(
        [
            objective_parts(jax.tree.map(lambda x: x[:rows], log), objective, free_target=spec.scenario.free_target)[
                "loss"
            ]
            for rows in steps
        ]
    )


def _item_gradients(spec, base, mask, objective, item, *, steps):
    """``(losses (H,), gradients group -> (H, size))`` of one item ``(params, robot, scenario,
    realism, key)``, the nominal run ``spec`` with the item's plant, scenario and realism:
    the horizon losses (``_horizon_losses()``) and their gradients: one forward pass, and
    one reverse pass vmapped over the horizons (a cotangent each)."""
    params, robot, scenario, realism, key = item
    sample = dataclasses.replace(spec, robot=robot, scenario=scenario, realism=realism)
    losses, pullback = jax.vjp(lambda p: _horizon_losses(p, base, mask, objective, sample, key, steps=steps), params)
    (gradients,) = jax.vmap(pullback)(jnp.eye(len(steps), dtype=losses.dtype))
    return losses, gradients


def _block(spec, base, mask, objective, batch, *, steps):
    """One device's share of items, one after another (the tape of one at a time)."""
    return compilation.map_one_at_a_time(
        lambda one: _item_gradients(spec, base, mask, objective, one, steps=steps), batch
    )


def envelope_gradients(
    spec: RunSpec,
    gains: Gains,
    objective: Objective,
    *,
    n: int,
    seed: int = 0,
    ranges: PerturbationRanges | None = None,
    horizons=HORIZONS,
    chunk: int = 8,
    progress=None,
) -> tuple[EnvelopeGradients, callable]:
    """The objective's gradient at ``gains`` on the nominal run ``spec`` and on the campaign
    samples 1..n of ``seed`` (``ranges``: the campaigns' default envelope), at each horizon.
    ``spec`` gives the robot, the scenario (its smooth contact law: gradients need it), the
    controller (a law's name or a law object with its settings,
    ``control.Admittance(pinv_damping=0.01)``), the realism and any added stages; the
    controller believes the nominal robot, as in a campaign, and the loop keeps its whole
    log, checkpointed.

    Raises:
        ValueError: ``spec`` has a ``model_robot`` (this analysis decides it, as a
            campaign).

    Returns:
        ``(gradients, evaluate)``: the [`EnvelopeGradients`][tuning.gradients.EnvelopeGradients], and ``evaluate(params,
        rows)``, the same program on items ``rows`` at per-item log-gains ``params``
        (group -> (len(rows), size)), returning ``(losses (len(rows), H), gradients)``
        (for central differences without another compile).
    """
    if spec.model_robot is not None:
        raise ValueError("envelope_gradients: the spec's model_robot must be None (each sample's is decided here)")
    robot, scenario, law, realism = spec.robot, spec.scenario, spec.controller, spec.realism
    ranges = PerturbationRanges() if ranges is None else ranges
    mask = make_mask(gains, law.law)  # the law object: a law of your own's groups too
    params = initial_params(gains, law.law)
    items, model_robot, perturbations = _nominal_first(robot, scenario, seed, n, ranges, realism)
    steps = horizon_steps(scenario.n_steps, horizons)
    segment = 1 if items[2] is not None else block_steps(scenario.n_steps)
    block = functools.partial(_block, steps=steps)
    options = loop_options(checkpoint=True)
    nominal = dataclasses.replace(
        objective_spec(robot, scenario, law, segment, realism, model_robot, options), stages=spec.stages
    )
    replicated = (nominal, gains, mask, objective)

    def evaluate(item_params, rows):
        batched = (item_params, *batching.take(items, np.asarray(rows)))
        return batching.map_in_chunks(
            "envelope-gradients",
            block,
            replicated,
            batched,
            chunk=chunk,
            progress=progress,
            label="gradients",
        )

    rows = np.arange(n + 1)
    repeated = jax.tree.map(lambda p: np.repeat(np.asarray(p)[None], n + 1, axis=0), params)
    losses, gradients = evaluate(repeated, rows)
    result = EnvelopeGradients(
        horizons_s=np.asarray(steps) * scenario.dt,
        losses=np.asarray(losses),
        gradients={name: np.asarray(value) for name, value in gradients.items()},
        perturbations={
            field.name: np.asarray(getattr(perturbations, field.name)) for field in dataclasses.fields(perturbations)
        },
        sample_indices=rows[1:],
    )
    return result, evaluate


def _flat(gradients: dict, horizon: int = -1) -> np.ndarray:
    """(N + 1, P) every sample's gradient at one horizon, the groups in order."""
    return np.concatenate([value[:, horizon, :] for value in gradients.values()], axis=1)


def finite_rows(result: EnvelopeGradients) -> np.ndarray:
    """(N + 1,) bool: the rows (0: nominal) whose losses and gradients are all finite."""
    gradients = np.concatenate([value.reshape(value.shape[0], -1) for value in result.gradients.values()], axis=1)
    return np.all(np.isfinite(gradients), axis=1) & np.all(np.isfinite(result.losses), axis=1)


def _perturbation(result: EnvelopeGradients, sample: int) -> dict:
    return {name: np.asarray(value[sample - 1]).tolist() for name, value in result.perturbations.items()}


def central_differences(result: EnvelopeGradients, evaluate, gains: Gains, controller, *, samples, step=1e-4, seed=0):
    """The gradient's directional derivative against ``(loss(+h) - loss(-h)) / 2h`` on the
    items ``samples`` (0: nominal), each along a random unit direction of the tuned
    log-gains (``controller``'s groups: a law's name or a law object), at the whole horizon.
    Returns one dict per sample."""
    if not len(samples):
        return []
    params = initial_params(gains, controller)
    mask = make_mask(gains, controller)
    flat, unravel = ravel_pytree(params)
    tuned = np.asarray(ravel_pytree(mask)[0], dtype=float)
    rng = np.random.default_rng(seed)
    directions = []
    for _ in samples:
        direction = rng.standard_normal(flat.shape[0]) * tuned
        directions.append(direction / np.linalg.norm(direction))
    points = [np.asarray(flat) + sign * step * d for d in directions for sign in (1.0, -1.0)]
    stacked = jax.tree.map(lambda *leaves: np.stack(leaves), *[unravel(jnp.asarray(p)) for p in points])
    losses, _ = evaluate(stacked, np.repeat(np.asarray(samples), 2))
    checks = []
    gradient = _flat(result.gradients)
    for k, (sample, direction) in enumerate(zip(samples, directions, strict=True)):
        difference = (losses[2 * k, -1] - losses[2 * k + 1, -1]) / (2.0 * step)
        analytic = float(gradient[sample] @ direction)
        scale = max(abs(analytic), abs(difference), 1e-300)
        checks.append(
            {
                "sample": int(sample),
                "gradient_slope": analytic,
                "finite_difference_slope": float(difference),
                "relative_error": abs(analytic - difference) / scale,
                "step": step,
            }
        )
    return checks


def report(result: EnvelopeGradients, *, outlier_factor: float = 100.0, listed: int = 20) -> dict:
    """The content of ``gradients.json`` (module docstring); non-finite numbers are NaN
    (``null`` in the file). ``listed``: at most this many outliers and non-finite samples
    are listed with their perturbations (the counts are complete)."""
    full = _flat(result.gradients)  # (N + 1, P), whole horizon
    finite = finite_rows(result)
    nominal = full[0]
    nominal_norm = float(np.linalg.norm(nominal)) if finite[0] else math.nan
    norms = np.linalg.norm(np.where(finite[:, None], full, 0.0), axis=1)
    norms[~finite] = np.nan
    with np.errstate(invalid="ignore", divide="ignore"):
        cosines = full @ nominal / (norms * nominal_norm)
        ratios = norms / nominal_norm
    perturbed = np.arange(1, full.shape[0])
    good = perturbed[finite[1:]]

    groups = {}
    for name, value in result.gradients.items():
        entries = value[:, -1, :]
        kept = entries[1:][finite[1:]]
        with np.errstate(invalid="ignore"):
            same_sign = np.sign(kept) == np.sign(entries[0])[None]
        quartiles = np.percentile(kept, [25, 75], axis=0) if len(kept) else np.full((2, entries.shape[1]), np.nan)
        groups[name] = {
            "nominal": entries[0],
            "mean": kept.mean(axis=0) if len(kept) else np.full(entries.shape[1], np.nan),
            "median": np.median(kept, axis=0) if len(kept) else np.full(entries.shape[1], np.nan),
            "std": kept.std(axis=0) if len(kept) else np.full(entries.shape[1], np.nan),
            "iqr": quartiles[1] - quartiles[0],
            "sign_agreement": same_sign.mean(axis=0) if len(kept) else np.full(entries.shape[1], np.nan),
            "norm_median": float(np.median(np.linalg.norm(kept, axis=1))) if len(kept) else math.nan,
        }

    def described(samples, limit):
        return [
            {
                "sample": int(i),
                "loss": float(result.losses[i, -1]),
                "norm": float(norms[i]),
                "norm_over_nominal": float(ratios[i]),
                "cosine_with_nominal": float(cosines[i]),
                "perturbation": _perturbation(result, int(i)),
            }
            for i in samples[:limit]
        ]

    bad = perturbed[~finite[1:]]
    outliers = good[ratios[good] > outlier_factor]
    outliers = outliers[np.argsort(-ratios[outliers])]
    horizon_norms = []
    for h, horizon in enumerate(result.horizons_s):
        at = np.linalg.norm(_flat(result.gradients, h), axis=1)
        kept = at[finite]
        horizon_norms.append(
            {
                "horizon_s": float(horizon),
                "nominal_norm": float(at[0]),
                "median_norm": float(np.median(kept)) if len(kept) else math.nan,
                "p95_norm": float(np.percentile(kept, 95)) if len(kept) else math.nan,
                "largest_norm": float(np.max(kept)) if len(kept) else math.nan,
            }
        )
    growth = [row["median_norm"] for row in horizon_norms]
    return {
        "samples": int(len(perturbed)),
        "horizons_s": result.horizons_s,
        "nominal": {"loss": float(result.losses[0, -1]), "gradient_norm": nominal_norm, "finite": bool(finite[0])},
        "nonfinite": {"count": int(len(bad)), "samples": described(bad, listed)},
        "groups": groups,
        "norm_over_nominal": {
            "median": float(np.median(ratios[good])) if len(good) else math.nan,
            "p95": float(np.percentile(ratios[good], 95)) if len(good) else math.nan,
            "largest": float(np.max(ratios[good])) if len(good) else math.nan,
        },
        "cosine_with_nominal": {
            "median": float(np.median(cosines[good])) if len(good) else math.nan,
            "p05": float(np.percentile(cosines[good], 5)) if len(good) else math.nan,
            "fraction_negative": float(np.mean(cosines[good] < 0.0)) if len(good) else math.nan,
        },
        "outliers": {
            "factor": outlier_factor,
            "count": int(len(outliers)),
            "fraction": float(len(outliers) / max(1, len(good))),
            "median_loss": float(np.median(result.losses[outliers, -1])) if len(outliers) else math.nan,
            "median_loss_of_the_others": float(np.median(result.losses[np.setdiff1d(good, outliers), -1]))
            if len(good) > len(outliers)
            else math.nan,
            "samples": described(outliers, listed),
        },
        "per_sample": {
            "loss": result.losses[1:, -1],
            "norm_over_nominal": ratios[1:],
            "cosine_with_nominal": cosines[1:],
        },
        "horizon_growth": {
            "norms": horizon_norms,
            "median_norm_ratio_last_to_first": growth[-1] / growth[0] if growth[0] else math.nan,
        },
    }


__all__ = [
    "HORIZONS",
    "EnvelopeGradients",
    "central_differences",
    "envelope_gradients",
    "finite_rows",
    "horizon_steps",
    "report",
]
