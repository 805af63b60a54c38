"""The failure-probability estimators measured on problems whose probability is known.

    python -m spacegrasp_jax.benchmarks.reliability --out notebooks/data/reliability \\
        [--repeats 20] [--budgets 1000,2000,5000] [--methods form_is,subset,cross_entropy,montecarlo]

Known problems (``PROBLEMS``): a linear limit state in 20 standard normal dimensions at 1e-3,
1e-5 and 1e-7 (``Phi(-beta)`` exactly), one with two failure regions in 10 dimensions at 1e-5,
and the reliability problems RP28 (1.45e-7, 2 dimensions), RP77 (2.69e-7, 3, a jump), RP107
(2.87e-7, 10), RP111 (8.04e-7, 2, four failure regions) and RP25 (4.15e-5, 2) of Rozsas and
Slobbe's repository (Repository and black-box reliability challenge 2019), each at its exact
probability (quadrature; ``PUBLISHED`` gives the published ones). Each method runs
``repeats`` times (seeds 0, 1, ...) at each budget
(rollouts, a gradient counted ``reliability.GRADIENT_COST``). Appends a row a run to
``known.jsonl`` as it goes (a run already there is not run again), then writes
``known.json``: per problem, method and budget, the share of repeats within a factor of 2 of
the truth, the share whose 95% interval covers it, the repeats' own coefficient of variation
(their standard deviation over the truth) against the one the estimator reports, and the
mean rollouts and wall time; and, per problem and method, the rollouts to a coefficient of
variation of 0.3 (interpolated in log-log between the budgets; ``None`` if no budget reaches it).

On a capture (``--capture TRUTH``): the estimators against a brute-force truth, the campaign in
the folder ``TRUTH`` (``spacegrasp montecarlo`` of ``CAPTURE``'s gains, loop and envelope, run
first; about 171/p captures give the truth within 15% at 95%). Each method runs ``repeats``
times (estimator and noise seed ``CAPTURE_SEED + r``) at one budget (``--budgets``' first),
each repeat journaled under ``runs/`` (an interrupted repeat resumes), a row a repeat in
``capture.jsonl``; ``capture.json`` gives each method's coverage of the truth's failure rate,
its repeats' coefficient of variation about it, rollouts and wall time, beside a campaign's at
the same mean rollouts (binomial, at the truth's rate) and the truth's own captures in
consecutive blocks of the budget. A truth folder needs the campaign's ``campaign.json`` and
either its ``samples.npz`` or the ``outcomes.npz`` that ``--outcomes TRUTH`` writes from it
(the per-sample verdicts, a few hundred kB: what the repository keeps).

    spacegrasp montecarlo --n 30000 --controller admittance --baseline flight_schedule \\
        --realism flight --seed 7501 --range lar_position_m=0.0065 \\
        --range lar_estimate_position_m=0.0026 --range lar_angle_rad=0.013 \\
        --range lar_estimate_angle_rad=0.0065 --out results/truth
    python -m spacegrasp_jax.benchmarks.reliability --capture results/truth \\
        --out notebooks/data/reliability/capture --budgets 2800 --methods subset,form_is,cross_entropy
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
from scipy import stats

from spacegrasp_jax.analysis import reliability
from spacegrasp_jax.analysis.reliability import LimitState, Settings
from spacegrasp_jax.benchmarks.dynamics import machine

#: The coefficient of variation the rollouts are counted to.
TARGET_CV = 0.3


def linear(dimension: int, probability: float) -> LimitState:
    """``g(z) = beta - a.z``, ``|a| = 1``: failure probability ``Phi(-beta)`` exactly."""
    beta = -stats.norm.ppf(probability)
    a = np.ones(dimension) / math.sqrt(dimension)
    return LimitState(
        dimension,
        values=lambda z, first: {"g": beta - z @ a},
        value_and_gradient=lambda z: {"g": beta - z @ a, "gradient": -a},
    )


def two_regions(dimension: int, probability: float) -> LimitState:
    """``g(z) = beta - |z_0|``: two failure regions of ``probability / 2`` each."""
    beta = -stats.norm.ppf(probability / 2.0)
    return LimitState(
        dimension,
        values=lambda z, first: {"g": beta - np.abs(z[:, 0])},
        value_and_gradient=lambda z: {
            "g": beta - abs(z[0]),
            "gradient": np.r_[-np.sign(z[0]), np.zeros(dimension - 1)],
        },
    )


def _affine_normal(mean: np.ndarray, sigma: np.ndarray):
    """The map from standard normals to independent normals of ``mean`` and ``sigma``."""
    return lambda z: mean + sigma * z


def rp28() -> LimitState:
    """RP28: ``x1 x2 - 146.14 < 0`` with ``x1 ~ N(78064, 11710)``, ``x2 ~ N(0.0104, 0.00156)``
    independent (published probability 1.45e-7: Rozsas and Slobbe, Repository and black-box
    reliability challenge 2019)."""
    mean, sigma = np.array([78064.0, 0.0104]), np.array([11710.0, 0.00156])
    physical = _affine_normal(mean, sigma)

    def values(z, first):
        x = physical(np.asarray(z))
        return {"g": x[:, 0] * x[:, 1] - 146.14}

    def value_and_gradient(z):
        x = physical(np.asarray(z))
        return {"g": x[0] * x[1] - 146.14, "gradient": np.array([x[1], x[0]]) * sigma}

    return LimitState(2, values, value_and_gradient)


def rp107() -> LimitState:
    """RP107: ``5 sqrt(10) - sum(x) < 0`` in 10 standard normals (published 2.92e-7;
    ``Phi(-5) = 2.87e-7`` exactly)."""
    beta = 5.0 * math.sqrt(10.0)
    return LimitState(
        10,
        values=lambda z, first: {"g": beta - np.sum(z, axis=1)},
        value_and_gradient=lambda z: {"g": beta - float(np.sum(z)), "gradient": -np.ones(10)},
    )


def rp111() -> LimitState:
    """RP111: ``12.5 - |x1 x2| < 0`` in 2 standard normals, four failure regions (published
    7.65e-7)."""

    def value_and_gradient(z):
        product = z[0] * z[1]
        return {"g": 12.5 - abs(product), "gradient": -np.sign(product) * np.array([z[1], z[0]])}

    return LimitState(
        2,
        values=lambda z, first: {"g": 12.5 - np.abs(z[:, 0] * z[:, 1])},
        value_and_gradient=value_and_gradient,
    )


def rp25() -> LimitState:
    """RP25: ``max(x1^2 - 8 x2 + 16, -16 x1 + x2 + 32) < 0`` in 2 standard normals (published
    4.15e-5)."""

    def branches(z):
        return z[..., 0] ** 2 - 8.0 * z[..., 1] + 16.0, -16.0 * z[..., 0] + z[..., 1] + 32.0

    def value_and_gradient(z):
        first, second = branches(np.asarray(z))
        gradient = np.array([2.0 * z[0], -8.0]) if first >= second else np.array([-16.0, 1.0])
        return {"g": float(max(first, second)), "gradient": gradient}

    return LimitState(
        2,
        values=lambda z, first: {"g": np.maximum(*branches(np.asarray(z)))},
        value_and_gradient=value_and_gradient,
    )


def rp77() -> LimitState:
    """RP77: ``x1 - x2 - x3`` where ``x3 <= 5``, else ``x3 - x2``, below 0, with ``x1 ~ N(10,
    0.5)``, ``x2 ~ N(0, 1)``, ``x3 ~ N(4, 1)`` independent (published 2.87e-7): a limit state
    with a jump where the branches meet."""
    mean, sigma = np.array([10.0, 0.0, 4.0]), np.array([0.5, 1.0, 1.0])
    physical = _affine_normal(mean, sigma)

    def g(x):
        return np.where(x[..., 2] <= 5.0, x[..., 0] - x[..., 1] - x[..., 2], x[..., 2] - x[..., 1])

    def value_and_gradient(z):
        x = physical(np.asarray(z))
        gradient = np.array([1.0, -1.0, -1.0]) if x[2] <= 5.0 else np.array([0.0, -1.0, 1.0])
        return {"g": float(g(x)), "gradient": gradient * sigma}

    return LimitState(3, lambda z, first: {"g": g(physical(np.asarray(z)))}, value_and_gradient)


def _normal_integral(integrand, low: float, high: float, points=()) -> float:
    """``int integrand(x) phi(x) dx`` over ``[low, high]`` by adaptive quadrature."""
    from scipy import integrate

    value, _ = integrate.quad(
        lambda x: integrand(x) * stats.norm.pdf(x), low, high, points=points, limit=500, epsabs=0.0
    )
    return value


def rp28_probability() -> float:
    """RP28's probability by quadrature over ``x1``: ``P(x2 < 146.14 / x1)`` where ``x1 > 0``,
    ``P(x2 > 146.14 / x1)`` where ``x1 < 0``."""
    mean, sigma = (78064.0, 0.0104), (11710.0, 0.00156)

    def failing(u):
        x1 = mean[0] + sigma[0] * u
        standard = (146.14 / x1 - mean[1]) / sigma[1]
        return stats.norm.cdf(standard) if x1 > 0 else stats.norm.sf(standard)

    return _normal_integral(failing, -12.0, 12.0, points=(-mean[0] / sigma[0], -5.0, 0.0))


def rp111_probability() -> float:
    """RP111's probability: ``P(|z1 z2| > 12.5) = 2 int_0^inf 2 Phi(-12.5 / z1) phi(z1) dz1``."""
    return 2.0 * _normal_integral(lambda u: 2.0 * stats.norm.cdf(-12.5 / u), 1e-9, 12.0, points=(3.5,))


def rp25_probability() -> float:
    """RP25's probability: both branches negative, ``(z1^2 + 16) / 8 < z2 < 16 z1 - 32``."""
    between = lambda u: max(0.0, stats.norm.cdf(16.0 * u - 32.0) - stats.norm.cdf((u * u + 16.0) / 8.0))  # noqa: E731
    return _normal_integral(between, 2.0, 12.0, points=(3.0, 4.0))


def rp77_probability() -> float:
    """RP77's probability over ``u3 = x3 - 4``: ``P(x1 - x2 < x3) = Phi((x3 - 10) / sqrt(1.25))``
    where ``x3 <= 5``, ``P(x2 > x3) = Phi(-x3)`` beyond."""
    below = _normal_integral(lambda u: stats.norm.cdf((u + 4.0 - 10.0) / math.sqrt(1.25)), -12.0, 1.0)
    beyond = _normal_integral(lambda u: stats.norm.cdf(-(u + 4.0)), 1.0, 12.0)
    return below + beyond


#: The probabilities the repository publishes (Rozsas and Slobbe, Repository and black-box
#: reliability challenge 2019). RP77's, RP107's and RP111's are sampled to three digits: the
#: exact values (quadrature, ``Phi(-5)``) are 6.2% below, 1.8% below and 5.0% above, and the
#: estimators are measured against those.
PUBLISHED = {
    "RP28": 1.4532945550025393e-07,
    "RP77": 2.87e-07,
    "RP107": 2.92e-07,
    "RP111": 7.65e-07,
    "RP25": 4.148566293759747e-05,
}


#: name -> a function giving ``(limit state, exact probability)``.
PROBLEMS = {
    "linear 20-D 1e-3": lambda: (linear(20, 1e-3), 1e-3),
    "linear 20-D 1e-5": lambda: (linear(20, 1e-5), 1e-5),
    "linear 20-D 1e-7": lambda: (linear(20, 1e-7), 1e-7),
    "two regions 10-D 1e-5": lambda: (two_regions(10, 1e-5), 1e-5),
    "RP28": lambda: (rp28(), rp28_probability()),
    "RP77": lambda: (rp77(), rp77_probability()),
    "RP107": lambda: (rp107(), float(stats.norm.cdf(-5.0))),
    "RP111": lambda: (rp111(), rp111_probability()),
    "RP25": lambda: (rp25(), rp25_probability()),
}


def run_known(out: Path, repeats: int, budgets: list[int], methods: list[str]) -> dict:
    """The rows of ``known.jsonl`` (run where missing) and the summary of ``known.json``."""
    out.mkdir(parents=True, exist_ok=True)
    rows_path = out / "known.jsonl"
    rows = [json.loads(line) for line in rows_path.read_text().splitlines()] if rows_path.exists() else []
    done = {(r["problem"], r["method"], r["budget"], r["seed"]) for r in rows}
    with rows_path.open("a") as stream:
        for name, build in PROBLEMS.items():
            state, truth = build()
            for row in rows:
                if row["problem"] == name:
                    row["truth"] = truth  # the problem's exact probability, whenever its run was
            for method in methods:
                for budget in budgets:
                    for seed in range(repeats):
                        if (name, method, budget, seed) in done:
                            continue
                        started = time.perf_counter()
                        result = reliability.estimate(
                            state,
                            Settings(method=method, budget=budget, seed=seed, smallest_probability=1e-8),
                        )
                        row = {
                            "problem": name,
                            "truth": truth,
                            "method": method,
                            "budget": budget,
                            "seed": seed,
                            "probability": result.probability,
                            "low": result.low,
                            "high": result.high,
                            "cv": result.coefficient_of_variation,
                            "rollouts": result.rollouts,
                            "complete": result.complete,
                            "wall_s": time.perf_counter() - started,
                        }
                        stream.write(json.dumps(row) + "\n")
                        stream.flush()
                        rows.append(row)
                print(f"{name}: {method} done", flush=True)
    summary = summarise(rows)
    document = {"machine": machine(), "repeats": repeats, "budgets": budgets, "summary": summary}
    (out / "known.json").write_text(json.dumps(document, indent=1) + "\n")
    return document


def summarise(rows: list[dict]) -> dict:
    """Per problem, method and budget: the repeats' accuracy and the intervals' coverage; per
    problem and method, the rollouts to a coefficient of variation of ``TARGET_CV``."""
    summary: dict = {}
    for row in rows:
        cell = summary.setdefault(row["problem"], {}).setdefault(row["method"], {}).setdefault(str(row["budget"]), [])
        cell.append(row)
    table: dict = {}
    for problem, methods in summary.items():
        for method, budgets in methods.items():
            entry = {}
            for budget, cell in budgets.items():
                truth = cell[0]["truth"]
                estimates = np.array([np.nan if r["probability"] is None else r["probability"] for r in cell], float)
                found = np.isfinite(estimates)
                ratio = estimates / truth
                entry[budget] = {
                    "repeats": len(cell),
                    "within_2x": int(np.sum(found & (ratio > 0.5) & (ratio < 2.0))),
                    "covered": int(sum(r["low"] is not None and r["low"] <= truth <= r["high"] for r in cell)),
                    "no_estimate": int(np.sum(~found)),
                    "median_ratio": float(np.nanmedian(ratio)) if found.any() else None,
                    "empirical_cv": float(np.sqrt(np.nanmean((ratio - 1.0) ** 2))) if found.any() else None,
                    "reported_cv": float(np.nanmean([np.nan if r["cv"] is None else r["cv"] for r in cell])),
                    "rollouts": float(np.mean([r["rollouts"] for r in cell])),
                    "wall_s": float(np.mean([r["wall_s"] for r in cell])),
                }
            entry["rollouts_to_cv_0.3"] = rollouts_to(entry, TARGET_CV)
            table.setdefault(problem, {})[method] = entry
    return table


def rollouts_to(entry: dict, target: float) -> float | None:
    """The rollouts at which the repeats' coefficient of variation (their root mean square
    relative error) falls to ``target``, interpolated in log-log between budgets."""
    points = sorted(
        (cell["rollouts"], cell["empirical_cv"])
        for cell in entry.values()
        if isinstance(cell, dict) and cell["empirical_cv"] is not None and cell["no_estimate"] == 0
    )
    for (n0, c0), (n1, c1) in zip(points, points[1:], strict=False):
        if c0 > target >= c1 and c0 > 0 and c1 > 0:
            slope = (math.log(c1) - math.log(c0)) / (math.log(n1) - math.log(n0))
            return float(math.exp(math.log(n0) + (math.log(target) - math.log(c0)) / slope))
    if points and points[0][1] <= target:
        return float(points[0][0])  # reached at the smallest budget: at most that
    return None


#: The capture the estimators are measured on: the shipped flight schedule, flight-like loop,
#: the campaigns' envelope with the LAR's pose and its estimate 1.3 times as wide (a failure
#: probability near 6e-3).
CAPTURE = {
    "gains": "flight_schedule",
    "controller": "admittance",
    "realism": "flight",
    "ranges": {
        "lar_position_m": 0.0065,
        "lar_estimate_position_m": 0.0026,
        "lar_angle_rad": 0.013,
        "lar_estimate_angle_rad": 0.0065,
    },
}

#: The seed of repeat 0 (repeat r: CAPTURE_SEED + r); the truth's campaign has its own seed.
CAPTURE_SEED = 1000

#: What a truth's ``outcomes.npz`` keeps of its campaign's ``samples.npz``: per sample, in
#: sample order, the verdict, its position and orientation parts and the metrics they judge.
OUTCOME_FIELDS = (
    "success",
    "failed_position",
    "failed_orientation",
    "final_position_error_m",
    "final_orientation_error_rad",
    "largest_peak_torque_Nm",
)


def write_outcomes(truth: Path) -> Path:
    """``truth/outcomes.npz`` from the campaign's ``samples.npz`` (one variant): its
    ``OUTCOME_FIELDS`` and the variant's ``label``, a few hundred kB where the samples are
    tens of MB, all that ``truth_success()`` and the documentation read."""
    from spacegrasp_jax.jobs import campaign

    _, by_variant = campaign.load_samples(truth / "samples.npz")
    if len(by_variant) != 1:
        raise SystemExit(f"{truth}: a truth is a campaign of one variant, this one has {sorted(by_variant)}")
    ((label, metrics),) = by_variant.items()
    path = truth / "outcomes.npz"
    np.savez_compressed(path, label=np.array(label), **{name: metrics[name] for name in OUTCOME_FIELDS})
    return path


def truth_success(truth: Path) -> np.ndarray:
    """(n,) bool, sample by sample, whether the truth's campaign captured: from its
    ``samples.npz`` where the folder has it, else from the ``outcomes.npz`` that
    ``write_outcomes()`` keeps of it."""
    from spacegrasp_jax.jobs import campaign

    if (truth / "samples.npz").exists():
        _, by_variant = campaign.load_samples(truth / "samples.npz")
        return np.concatenate([np.asarray(v["success"], dtype=bool) for v in by_variant.values()])
    if (truth / "outcomes.npz").exists():
        with np.load(truth / "outcomes.npz") as outcomes:
            return np.asarray(outcomes["success"], dtype=bool)
    raise SystemExit(f"--capture {truth}: neither samples.npz nor outcomes.npz there")


def run_capture(truth: Path, out: Path, repeats: int, budget: int, methods: list[str]) -> dict:
    """The rows of ``capture.jsonl`` (run where missing) and the summary of ``capture.json``;
    the campaign in ``truth`` must be ``CAPTURE``'s (its gains, loop and envelope)."""
    import dataclasses

    import spacegrasp_jax as sg
    from spacegrasp_jax.analysis import limit_state
    from spacegrasp_jax.jobs import campaign
    from spacegrasp_jax.loop.control.schedule import tuned_schedule

    sg.configure()  # float64 and loops compiled whole, as the command line
    record, config = campaign.campaign_record(truth)
    for name, value in CAPTURE["ranges"].items():
        if getattr(config.ranges, name) != value:
            raise SystemExit(f"--capture {truth}: its {name} is {getattr(config.ranges, name)}, the capture's {value}")
    captured = truth_success(truth)
    failures, n = int(np.sum(~captured)), len(captured)
    truth_p = failures / n
    truth_low, truth_high = reliability.binomial_interval(failures, n)
    block_p = np.mean(~captured[: n - n % budget].reshape(-1, budget), axis=1)

    robot, scenario = record.robot, record.scenario  # the truth's own
    gains = tuned_schedule(CAPTURE["gains"])
    out.mkdir(parents=True, exist_ok=True)
    rows_path = out / "capture.jsonl"
    rows = [json.loads(line) for line in rows_path.read_text().splitlines()] if rows_path.exists() else []
    done = {(r["method"], r["seed"]) for r in rows}
    with rows_path.open("a") as stream:
        for r in range(repeats):  # repeat by repeat, so that an interrupted run leaves every method even
            for method in methods:
                seed = CAPTURE_SEED + r
                if (method, seed) in done:
                    continue
                state = limit_state.limit_state(
                    robot,
                    scenario,
                    gains,
                    CAPTURE["controller"],
                    dataclasses.replace(config, seed=seed),
                    block=100,
                    gradient=method in reliability.GRADIENT_METHODS,
                )
                result = reliability.estimate(
                    state.limit_state,
                    Settings(method=method, budget=budget, seed=seed, smallest_probability=1e-4),
                    journal=out / "runs" / f"{method}_{seed}" / "journal",
                )
                row = {
                    "method": method,
                    "seed": seed,
                    "probability": result.probability,
                    "low": result.low,
                    "high": result.high,
                    "cv": result.coefficient_of_variation,
                    "rollouts": result.rollouts,
                    "gradients": result.gradients,
                    "wall_s": result.wall_s,
                    "compile_s": state.compile_s,
                }
                stream.write(json.dumps(row) + "\n")
                stream.flush()
                rows.append(row)
                print(f"{method} seed {seed}: {result.summary()}", flush=True)
    summary = {}
    for method in methods:
        cell = [r for r in rows if r["method"] == method]
        if not cell:
            continue
        estimates = np.array([np.nan if r["probability"] is None else r["probability"] for r in cell], float)
        summary[method] = {
            "repeats": len(cell),
            "covered": int(sum(r["low"] is not None and r["low"] <= truth_p <= r["high"] for r in cell)),
            "empirical_cv": float(np.sqrt(np.nanmean((estimates / truth_p - 1.0) ** 2))),
            "reported_cv": float(np.nanmean([np.nan if r["cv"] is None else r["cv"] for r in cell])),
            "rollouts": float(np.mean([r["rollouts"] for r in cell])),
            "wall_s": float(np.mean([r["wall_s"] for r in cell])),
        }
        # A campaign of the same rollouts: the binomial coefficient of variation at the truth.
        rollouts = summary[method]["rollouts"]
        summary[method]["campaign_cv_at_same_rollouts"] = float(math.sqrt((1.0 - truth_p) / (rollouts * truth_p)))
    summary["montecarlo, the truth's captures in blocks"] = {
        "repeats": int(len(block_p)),
        "empirical_cv": float(np.sqrt(np.mean((block_p / truth_p - 1.0) ** 2))),
        "rollouts": float(budget),
    }
    document = {
        "machine": machine(),
        "capture": CAPTURE,
        "truth": {"failures": failures, "n": n, "probability": truth_p, "low": truth_low, "high": truth_high},
        "budget": budget,
        "summary": summary,
    }
    (out / "capture.json").write_text(json.dumps(document, indent=1) + "\n")
    return document


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--budgets", default="1000,2000,5000")
    parser.add_argument("--methods", default=",".join(reliability.METHODS))
    parser.add_argument("--capture", metavar="TRUTH", help="measure on the capture against this campaign folder")
    parser.add_argument(
        "--outcomes",
        metavar="TRUTH",
        help="write TRUTH/outcomes.npz (what --capture reads of a truth) from its samples.npz, and stop",
    )
    args = parser.parse_args(argv)
    if args.outcomes:
        print(write_outcomes(Path(args.outcomes)))
        return
    budgets = [int(b) for b in args.budgets.split(",")]
    methods = args.methods.split(",")
    unknown = set(methods) - set(reliability.METHODS)
    if unknown:
        parser.error(f"--methods: unknown {', '.join(sorted(unknown))}; expected {', '.join(reliability.METHODS)}")
    if args.capture:
        from spacegrasp_jax.jobs.batching import use_all_cpu_cores

        use_all_cpu_cores()  # a device a core, as the command line: the captures shard over them
        document = run_capture(Path(args.capture), Path(args.out), args.repeats, budgets[0], methods)
        print(json.dumps(document["truth"]), json.dumps(document["summary"], indent=1))
        return
    import openturns as ot

    shown = ot.Log.Flags()
    ot.Log.Show(ot.Log.NONE)  # RP25's gradient falls back on finite differences, with a warning a step
    try:
        document = run_known(Path(args.out), args.repeats, budgets, methods)
    finally:
        ot.Log.Show(shown)
    for problem, methods_table in document["summary"].items():
        for method, entry in methods_table.items():
            last = entry[str(max(budgets))]
            print(
                f"{problem:24s} {method:14s} within 2x {last['within_2x']:2d}/{last['repeats']}, "
                f"covered {last['covered']:2d}/{last['repeats']}, c.o.v. {last['empirical_cv'] or float('nan'):.2f} "
                f"(reported {last['reported_cv']:.2f}), rollouts to c.o.v. 0.3: {entry['rollouts_to_cv_0.3']}"
            )


if __name__ == "__main__":
    main()
