"""Wall time of a whole tuning run, compile included, and the rollouts each method uses.

    python -m spacegrasp_jax.benchmarks.tuning [--out results/benchmarks] [--methods cmaes,gradient]

Runs ``spacegrasp tune`` as a user does, each run in its own process with no persistent
compilation cache (``--compile-cache none``: the compile a first run pays), under the flight
preset on the campaigns' envelope (``--realism flight --ranges montecarlo``), the capture
objective with a torque budget of 4 N m (``--torque-cap 4``), from the paper's gains,
``--holdout 0``:
* ``cmaes``: the shipped ``tuned_gains("flight")`` run, two calls: 40 generations of 8 on a
  batch of 32, then, from their gains, 26 generations of 8 on a batch of 64 with a step of
  0.1 (``--step-size 0.1``: refining);
* ``gradient``: ``--method gradient --steps 39 --batch 32`` (the gradient run of the
  documentation's method comparison, with the same torque budget).
Reports for each call the process's wall time, the first step's wall time less the median of
the others (about the compile), that median, and the rollouts used: per CMA-ES generation
``(population + 1) x batch`` forward rollouts (the candidates and the mean, and the last
mean once more), per gradient step ``batch`` gradients of one capture (each costs a few
forward rollouts: ``benchmarks.gradient``), and the totals per method. Writes ``tuning.json``.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

METHODS = ("cmaes", "gradient")


#: The calls of each method: (name, steps, batch, extra options).
CALLS = {
    "cmaes": [
        ("cmaes_explore", 40, 32, ["--population", "8"]),
        ("cmaes_refine", 26, 64, ["--population", "8", "--step-size", "0.1"]),
    ],
    "gradient": [("gradient", 39, 32, [])],
}


def run_call(
    method: str, name: str, steps: int, batch: int, extra: list, start_gains: Path | None, folder: Path
) -> dict:
    """One ``spacegrasp tune`` call: its wall time and per-step figures."""
    out = folder / name
    command = [
        sys.executable,
        "-m",
        "spacegrasp_jax.cli",
        "tune",
        "--out",
        str(out),
        "--method",
        method,
        "--realism",
        "flight",
        "--ranges",
        "montecarlo",
        "--objective",
        "capture",
        "--torque-cap",
        "4",
        "--batch",
        str(batch),
        "--steps",
        str(steps),
        "--holdout",
        "0",
        "--compile-cache",
        "none",
        *extra,
    ]
    if start_gains is not None:
        command += ["--gains", str(start_gains)]
    start = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall_s = time.perf_counter() - start
    with open(out / "history.csv", newline="") as file:
        rows = list(csv.DictReader(file))
    step_walls = [float(row["wall_s"]) for row in rows if row["wall_s"] not in ("", "nan")]
    first, later = step_walls[0], step_walls[1:]
    per_step = statistics.median(later) if later else float("nan")
    if method == "cmaes":
        population = int(extra[extra.index("--population") + 1])
        rollouts = steps * (population + 1) * batch + batch  # + the last mean on its own
        unit = "forward rollouts"
    else:
        rollouts = steps * batch
        unit = "gradients of one capture"
    return {
        "command": " ".join(["spacegrasp", *command[3:]]).replace(str(folder), "DIR"),
        "steps": steps,
        "wall_s": wall_s,
        "wall_min": wall_s / 60.0,
        "first_step_s": first,
        "compile_s_estimate": first - per_step,
        "step_s_median": per_step,
        "rollouts": rollouts,
        "rollouts_unit": unit,
        "final_loss": float(rows[-1]["loss"]),
        "gains": json.loads((out / "gains.json").read_text()),
    }


def shipped_difference(gains: dict) -> float:
    """The largest relative difference between ``gains`` (a gains.json document) and the
    shipped ``tuned_gains("flight")``: 0 when the run reproduces them."""
    import spacegrasp_jax
    from spacegrasp_jax.control.gains import TUNED_GAINS_FILES

    data = Path(spacegrasp_jax.__file__).resolve().parent / "data"
    shipped = json.loads((data / TUNED_GAINS_FILES["flight"]).read_text())
    differences = []
    for name, value in shipped.items():
        value = np.asarray(value, dtype=float)
        differences.append(float(np.max(np.abs(np.asarray(gains[name], dtype=float) - value) / np.abs(value))))
    return max(differences)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="results/benchmarks")
    parser.add_argument("--methods", default=",".join(METHODS), help=f"comma-separated subset of {', '.join(METHODS)}")
    args = parser.parse_args(argv)
    methods = [method for method in args.methods.split(",") if method]
    unknown = set(methods) - set(METHODS)
    if unknown:
        parser.error(f"unknown method(s): {', '.join(sorted(unknown))}")
    results = {"machine": f"{os.cpu_count()} cpu(s)", "methods": {}}
    with tempfile.TemporaryDirectory() as folder:
        for method in methods:
            calls, start_gains = [], None
            for name, steps, batch, extra in CALLS[method]:
                result = run_call(method, name, steps, batch, extra, start_gains, Path(folder))
                start_gains = Path(folder) / name / "gains.json"
                calls.append(result)
                print(
                    f"{name:14s} {result['wall_min']:6.1f} min wall ({result['steps']} steps, about "
                    f"{result['compile_s_estimate']:.0f} s compiling, {result['step_s_median']:.1f} s a step) | "
                    f"{result['rollouts']} {result['rollouts_unit']} | final loss {result['final_loss']:.4f}",
                    flush=True,
                )
            total = {
                "wall_min": sum(call["wall_min"] for call in calls),
                "rollouts": sum(call["rollouts"] for call in calls),
                "rollouts_unit": calls[0]["rollouts_unit"],
            }
            if method == "cmaes":  # the shipped flight recipe: does it give the shipped gains?
                total["largest_relative_difference_from_shipped_gains"] = shipped_difference(calls[-1]["gains"])
            results["methods"][method] = {"calls": calls, "total": total}
            print(
                f"{method:14s} {total['wall_min']:6.1f} min wall in all | {total['rollouts']} {total['rollouts_unit']}"
            )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "tuning.json").write_text(json.dumps(results, indent=1) + "\n")
    print(f"wrote {out / 'tuning.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
