"""How much of the tuner's gradient a truncated backpropagation would keep.

    python -m spacegrasp_jax.benchmarks.truncation [--gains flight,paper] [--cuts 8.5,12.75]
        [--n 32] [--out results/benchmarks]

Backpropagating only through the last part of a capture, from a cut time ``t0`` on, would
skip the recomputation and the adjoints of the part before it: about 1 + 2.5 (T - t0) / T
forward rollouts a gradient instead of 3.5 (an estimate from the parts that
``benchmarks.gradient_parts`` measures: the forward pass 1, recomputation and adjoints 2.5;
no truncated gradient is implemented). What it would lose is measured here, on the shipped
flight gains' tuning problem (``benchmarks.estimators``: the flight-like loop, the capture
objective with a torque budget of 4 N m, the smooth contact law, the campaigns' envelope).

The gains are written as a time schedule of two knots, ``t0 - 0.01`` and ``t0`` s, both
holding the same gains: the loop runs exactly as with the constant gains, and the gradient
with respect to the second knot's log-gains is the truncated gradient (the gains' effect from
``t0`` on, the state at ``t0`` held), the sum over both knots the full one
(``tuning.gradients.envelope_gradients``, samples 1..n of seed 0). Reported for each gain set
and cut, over the 39 law and PID log-gains: each sample's cosine between the truncated and
the full gradient and their norms' ratio (median and quartile), and the cosine between the
truncated and the full batch estimates of the n samples under each of the tuner's
aggregates (``tuning.estimators.aggregate``). Writes ``truncation.json``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import spacegrasp_jax as sg
from spacegrasp_jax.benchmarks.dynamics import machine
from spacegrasp_jax.benchmarks.estimators import _problem
from spacegrasp_jax.loop.control.schedule import schedule_of
from spacegrasp_jax.tuning import estimators
from spacegrasp_jax.tuning.gradients import envelope_gradients
from spacegrasp_jax.tuning.parameters import make_mask


def _cosine(a: np.ndarray, b: np.ndarray) -> float:
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


def truncation_row(gains_name: str, cut_s: float, n: int) -> dict:
    """One gain set and cut: the module docstring's figures."""
    spec, gains, objective, ranges = _problem(gains_name)
    duration_s = spec.scenario.n_steps * spec.scenario.dt
    # The law's and the servo's tuned groups (39 log-gains for the paper's arm); the
    # pseudoinverse's damping, zero in the paper's gains, has no log.
    groups = [name for name in make_mask(gains, "admittance") if name != "pinv_damping"]
    schedule = schedule_of(gains, "time", [cut_s - 0.01, cut_s], groups)
    started = time.perf_counter()
    result, _ = envelope_gradients(spec, schedule, objective, n=n, seed=0, ranges=ranges, horizons=(1.0,))
    wall_s = time.perf_counter() - started
    knots = {name: np.asarray(result.gradients[name])[1:, -1] for name in groups}  # (n, 2 knots, size)
    before = np.concatenate([knots[name][:, 0] for name in groups], axis=1)
    truncated = np.concatenate([knots[name][:, 1] for name in groups], axis=1)
    full = before + truncated
    finite = np.all(np.isfinite(full), axis=1)
    truncated, full = truncated[finite], full[finite]
    cosines = [_cosine(t, f) for t, f in zip(truncated, full)]
    ratios = np.linalg.norm(truncated, axis=1) / np.linalg.norm(full, axis=1)
    return {
        "gains": gains_name,
        "cut_s": cut_s,
        "samples": int(finite.sum()),
        "sample_cosine": {"median": float(np.median(cosines)), "q25": float(np.percentile(cosines, 25))},
        "norm_ratio": {"median": float(np.median(ratios)), "q25": float(np.percentile(ratios, 25))},
        "batch_cosine": {
            method: _cosine(estimators.aggregate(truncated, method), estimators.aggregate(full, method))
            for method in ("mean", "clip", "median_of_means")
        },
        "estimated_rollouts_per_truncated_gradient": 1.0 + 2.5 * (duration_s - cut_s) / duration_s,
        "wall_s": wall_s,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gains", default="flight,paper")
    parser.add_argument("--cuts", default="8.5,12.75")
    parser.add_argument("--n", type=int, default=32)
    parser.add_argument("--out", default="results/benchmarks")
    args = parser.parse_args(argv)
    gain_sets = args.gains.split(",")
    for name in gain_sets:
        if name not in ("paper", "flight") and not Path(name).is_file():
            parser.error(f"--gains: expected paper, flight or a gains file, got {name!r}")
    try:
        cuts = [float(cut) for cut in args.cuts.split(",")]
    except ValueError:
        parser.error(f"--cuts: expected times in s separated by commas, got {args.cuts!r}")
    if not all(0.01 < cut < 17.0 for cut in cuts):
        parser.error(f"--cuts: each must lie inside the 17 s capture, got {args.cuts!r}")
    if args.n < 2:
        parser.error(f"--n: at least 2 captures, got {args.n}")
    sg.configure()
    rows = []
    for gains_name in gain_sets:
        for cut in cuts:
            rows.append(truncation_row(gains_name, cut, args.n))
            print(json.dumps(rows[-1]), flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "truncation.json").write_text(json.dumps({"machine": machine(), "rows": rows}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
