"""The gradient estimators' bias and variance on the capture objective, measured against
large-pool references.

    python -m spacegrasp_jax.benchmarks.estimators [--gains paper|flight|FILE] [--first 256] [--pairs 1024]
        [--guided 256] [--batch 32] [--draws 200] [--seed 0] [--out results/benchmarks]

At one gain set, on the flight-like loop and the Monte-Carlo campaigns' envelope (the
shipped flight gains' tuning problem: the capture objective with a torque budget of 4 N m,
the smooth contact law), three pools of samples are drawn, each sample a fresh capture of
the envelope:

* ``--first`` first-order samples: each capture's reverse-mode gradient with respect to the
  log-gains (``tuning.gradients.envelope_gradients``);
* ``--pairs`` zeroth-order samples: an antithetic pair of forward rollouts of one capture at
  ``theta +- sigma eps`` (``tuning.estimators.zeroth_order_samples``; ``--sigma``, log-gain
  units);
* ``--guided`` Guided ES pairs, their directions stretched along the first-order estimate
  of the estimation half (``tuning.estimators.guided_directions``).

Each pool is split in two halves: estimates are drawn from the first, references made from
the second, so no estimate is compared with itself. The references: the zeroth-order mean of
its half (the gradient of the Gaussian-smoothed objective, unbiased whatever the dynamics)
and the first-order clipped and plain means of theirs. For each estimator at a batch of
``--batch`` captures, ``--draws`` times two disjoint batches are drawn from the estimation
halves; reported per estimator: the median and quartiles of its cosine with each reference,
of its relative error against the zeroth-order reference, and of the cosine between its two
batches' estimates (split-half agreement); and its cost in forward rollouts (a gradient
about 3.5, a pair 2).

Writes ``estimators_<gains>.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

#: Forward rollouts a first-order sample costs (a checkpointed reverse-mode gradient of the
#: flight-like loop on 2 cores; documentation, Performance).
GRADIENT_COST = 3.5


def _problem(gains_name: str):
    """``(spec, gains, objective, ranges)``: the shipped flight gains' tuning problem at the
    gains ``gains_name`` (paper, flight or a gains file)."""
    import spacegrasp_jax as sg
    from spacegrasp_jax.envelope.perturbations import PerturbationRanges
    from spacegrasp_jax.envelope.scenario import paper_scenario
    from spacegrasp_jax.jobs import paper
    from spacegrasp_jax.loop.control import load_gains, paper_gains, tuned_gains
    from spacegrasp_jax.loop.realism import flight
    from spacegrasp_jax.loop.simulate import RunSpec
    from spacegrasp_jax.tuning.tune import TuneConfig, make_objective

    robot = sg.paper_robot()
    if gains_name == "paper":
        gains = paper_gains()
    elif gains_name == "flight":
        gains = tuned_gains("flight")
    else:
        gains = load_gains(gains_name, "admittance", 7)
    scenario = paper_scenario(robot, contact_law="smooth")
    config = TuneConfig(realism=flight().to_dict(), torque_cap_Nm=4.0, ranges=PerturbationRanges())
    objective = make_objective(robot, config, paper.MAX_ABS_TORQUE_NM["admittance"])
    return RunSpec(robot, scenario, "admittance", realism=flight()), gains, objective, config.ranges


def _quartiles(values) -> dict:
    values = np.asarray(values, dtype=float)
    values = values[np.isfinite(values)]
    if not len(values):
        return {"p25": math.nan, "median": math.nan, "p75": math.nan}
    p25, median, p75 = np.percentile(values, [25, 50, 75])
    return {"p25": float(p25), "median": float(median), "p75": float(p75)}


def compare_estimators(first, zeroth, guided, *, batch: int, draws: int, seed: int, sigma: float) -> dict:
    """The estimators' statistics from the pools (module docstring): ``first`` (S, P)
    first-order samples, ``zeroth`` (M, P) zeroth-order samples, ``guided`` a tuple
    ``(losses_plus (G,), losses_minus (G,), directions (G, P))`` or ``None``."""
    from spacegrasp_jax.tuning import estimators

    rng = np.random.default_rng(seed)
    first_estimation, first_reference = np.array_split(first, 2)
    zeroth_estimation, zeroth_reference = np.array_split(zeroth, 2)
    references = {
        "zeroth_order": zeroth_reference.mean(axis=0),
        "first_order_clip": estimators.aggregate(first_reference, "clip"),
        "first_order_mean": first_reference.mean(axis=0),
    }
    zeroth_noise = math.sqrt(estimators.variance_of_mean(zeroth_reference)) / np.linalg.norm(references["zeroth_order"])
    equal_cost = max(1, round(batch * GRADIENT_COST / 2))  # pairs costing what `batch` gradients cost

    def first_order(method):
        return lambda a, b: estimators.aggregate(a, method)

    def zeroth_of(count):
        return lambda a, b: b[:count].mean(axis=0)

    def mix(a, b):
        return estimators.alpha_mix(a, b[:batch]).gradient

    methods = {f"first_order_{method}": (first_order(method), batch, 0) for method in estimators.AGGREGATES}
    methods["zeroth_order"] = (zeroth_of(batch), 0, batch)
    methods["zeroth_order_equal_cost"] = (zeroth_of(equal_cost), 0, equal_cost)
    methods["alpha_mix"] = (mix, batch, batch)

    results, alphas = {}, []
    for name, (estimate, firsts, pairs) in methods.items():
        cosines = {key: [] for key in references}
        errors, halves = [], []
        for _ in range(draws):
            chosen_first = rng.permutation(len(first_estimation))[: 2 * firsts]
            chosen_zeroth = rng.permutation(len(zeroth_estimation))[: 2 * pairs]
            one, two = (
                estimate(
                    first_estimation[chosen_first[k * firsts : (k + 1) * firsts]],
                    zeroth_estimation[chosen_zeroth[k * pairs : (k + 1) * pairs]],
                )
                for k in (0, 1)
            )
            for key, reference in references.items():
                cosines[key].append(estimators.cosine(one, reference))
            errors.append(np.linalg.norm(one - references["zeroth_order"]) / np.linalg.norm(references["zeroth_order"]))
            halves.append(estimators.cosine(one, two))
            if name == "alpha_mix":
                alphas.append(
                    estimators.alpha_mix(
                        first_estimation[chosen_first[:firsts]], zeroth_estimation[chosen_zeroth[:pairs]]
                    ).alpha
                )
        results[name] = {
            "first_order_samples": firsts,
            "zeroth_order_pairs": pairs,
            "cost_rollouts": firsts * GRADIENT_COST + 2 * pairs,
            **{f"cosine_with_{key}": _quartiles(values) for key, values in cosines.items()},
            "relative_error_to_zeroth_order": _quartiles(errors),
            "split_half_cosine": _quartiles(halves),
        }
    results["alpha_mix"]["alpha"] = _quartiles(alphas)
    if guided is not None:
        plus, minus, directions = guided
        half = len(plus) // 2
        results["guided_es"] = {
            "pairs_in_pool": int(len(plus)),
            "cosine_with_zeroth_order": estimators.cosine(
                estimators.guided_estimate(plus, minus, directions, sigma), references["zeroth_order"]
            ),
            "split_half_cosine": estimators.cosine(
                estimators.guided_estimate(plus[:half], minus[:half], directions[:half], sigma),
                estimators.guided_estimate(plus[half:], minus[half:], directions[half:], sigma),
            ),
            "cost_rollouts": 2 * int(len(plus)),
        }
    agreement = {
        "first_order_mean_vs_zeroth_order": estimators.cosine(
            references["first_order_mean"], references["zeroth_order"]
        ),
        "first_order_clip_vs_zeroth_order": estimators.cosine(
            references["first_order_clip"], references["zeroth_order"]
        ),
        "zeroth_order_reference_relative_noise": float(zeroth_noise),
        "first_order_median_norm": float(np.median(np.linalg.norm(first, axis=1))),
        "first_order_largest_norm_over_median": float(
            np.max(np.linalg.norm(first, axis=1)) / np.median(np.linalg.norm(first, axis=1))
        ),
        "zeroth_order_reference_norm": float(np.linalg.norm(references["zeroth_order"])),
    }
    return {"references": agreement, "estimators": results}


def measure(gains_name: str, *, first: int, pairs: int, guided: int, sigma: float, seed: int, progress=sys.stderr):
    """The three pools at the gains ``gains_name`` (module docstring): ``(first (S, P),
    zeroth (M, P), guided tuple or None, timings)``, non-finite samples dropped."""
    import jax

    from spacegrasp_jax.jobs.montecarlo import sample_loops
    from spacegrasp_jax.tuning import cmaes, estimators
    from spacegrasp_jax.tuning.gradients import envelope_gradients
    from spacegrasp_jax.tuning.parameters import initial_params, make_mask

    spec, gains, objective, ranges = _problem(gains_name)
    mask = make_mask(gains, "admittance")
    params = initial_params(gains, "admittance")
    theta = cmaes.flatten(params, mask)
    timings = {}

    start = time.perf_counter()
    result, _ = envelope_gradients(spec, gains, objective, n=first, seed=seed, ranges=ranges, horizons=(1.0,))
    gradient = {name: np.asarray(value)[1:, -1, :] for name, value in result.gradients.items()}
    first_pool = np.concatenate([gradient[name][:, np.asarray(mask[name])] for name in params], axis=1)
    first_pool = first_pool[np.all(np.isfinite(first_pool), axis=1)]
    timings["first_order_s"] = time.perf_counter() - start
    print(f"{gains_name}: {len(first_pool)} first-order samples in {timings['first_order_s']:.0f} s", file=progress)

    rng = np.random.default_rng(seed + 1)
    samples = sample_loops(spec.robot, spec.scenario, seed + 1, range(pairs + guided), ranges, spec.realism)
    items = cmaes.make_item_evaluator(spec.robot, samples, "admittance", objective, chunk=min(64, 2 * (pairs + guided)))
    start_params = {name: np.asarray(value) for name, value in params.items()}

    def evaluate(vectors, rows):
        sets = [cmaes.gains_of(vector, start_params, gains, mask) for vector in vectors]
        return items(jax.tree.map(lambda *leaves: np.stack([np.asarray(leaf) for leaf in leaves]), *sets), rows)

    directions = rng.standard_normal((pairs, theta.size))
    estimation_guide = estimators.aggregate(np.array_split(first_pool, 2)[0], "clip")
    guided_directions = estimators.guided_directions(rng, estimation_guide[None], guided) if guided else None
    # zeroth-order pairs: eps standard normal, so the step sigma * eps; Guided ES: sigma * d, trace(C) = 1
    steps = np.concatenate([directions * sigma] + ([guided_directions * sigma] if guided else []))
    rows = np.arange(len(steps))
    start = time.perf_counter()
    losses = evaluate(np.concatenate([theta + steps, theta - steps]), np.concatenate([rows, rows]))["loss"]
    timings["forward_pairs_s"] = time.perf_counter() - start
    plus, minus = losses[: len(steps)], losses[len(steps) :]
    finite = np.isfinite(plus) & np.isfinite(minus)
    zeroth = estimators.zeroth_order_samples(plus[:pairs], minus[:pairs], directions, sigma)[finite[:pairs]]
    guided_pool = None
    if guided:
        keep = finite[pairs:]
        guided_pool = (plus[pairs:][keep], minus[pairs:][keep], guided_directions[keep])
    print(f"{gains_name}: {2 * len(steps)} forward rollouts in {timings['forward_pairs_s']:.0f} s", file=progress)
    timings["devices"] = jax.device_count()
    return first_pool, zeroth, guided_pool, timings


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m spacegrasp_jax.benchmarks.estimators", description=__doc__.split("\n\n")[0], allow_abbrev=False
    )
    parser.add_argument("--gains", default="paper", help="paper, flight (the shipped flight gains) or a gains file")
    parser.add_argument("--first", type=int, default=256, help="first-order samples (default 256)")
    parser.add_argument("--pairs", type=int, default=1024, help="zeroth-order antithetic pairs (default 1024)")
    parser.add_argument("--guided", type=int, default=256, help="Guided ES pairs (default 256; 0: none)")
    parser.add_argument("--sigma", type=float, default=0.05, help="smoothing, log-gain units (default 0.05)")
    parser.add_argument("--batch", type=int, default=32, help="captures a batch estimate uses (default 32)")
    parser.add_argument("--draws", type=int, default=200, help="pairs of batches drawn (default 200)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the envelope's samples (default 0)")
    parser.add_argument("--out", default="results/benchmarks", help="folder for the JSON (default results/benchmarks)")
    args = parser.parse_args(argv)
    for name in ("first", "pairs", "batch", "draws"):
        if getattr(args, name) < 4:
            parser.error(f"--{name}: must be at least 4, got {getattr(args, name)}")
    if args.guided < 0 or args.seed < 0:
        parser.error("--guided and --seed: must be non-negative")
    if 2 * args.batch > args.first // 2 or 2 * args.batch > args.pairs // 2:
        parser.error("--batch: two disjoint batches must fit in each pool's estimation half (--first/4, --pairs/4)")
    if args.gains not in ("paper", "flight") and not Path(args.gains).is_file():
        parser.error(f"--gains: {args.gains}: no such file; expected paper, flight or a gains file")
    if not (math.isfinite(args.sigma) and 0.0 < args.sigma <= 1.0):
        parser.error(f"--sigma: must be in (0, 1], got {args.sigma}")
    from spacegrasp_jax.jobs import batching
    from spacegrasp_jax.jobs.compilation import configure

    batching.use_all_cpu_cores()  # before anything touches a device: the pools shard over the cores
    configure()
    first, zeroth, guided, timings = measure(
        args.gains, first=args.first, pairs=args.pairs, guided=args.guided, sigma=args.sigma, seed=args.seed
    )
    document = compare_estimators(
        first, zeroth, guided, batch=args.batch, draws=args.draws, seed=args.seed, sigma=args.sigma
    )
    document["settings"] = {key: value for key, value in vars(args).items() if key != "out"}
    document["settings"] |= {"first_order_samples": int(len(first)), "zeroth_order_pairs": int(len(zeroth))}
    document["timings"] = timings
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    label = Path(args.gains).stem if args.gains not in ("paper", "flight") else args.gains
    path = out / f"estimators_{label}.json"
    path.write_text(json.dumps(document, indent=2) + "\n")
    print(f"wrote {path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
