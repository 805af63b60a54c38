"""Wall time of a whole tuning run, compile included, and the rollouts each method uses.

    python -m spacegrasp_jax.benchmarks.tuning [--out results/benchmarks] [--methods cmaes,gradient]
    python -m spacegrasp_jax.benchmarks.tuning --races notebooks/data [--out results/benchmarks]

Runs ``spacegrasp tune`` as a user does, each run in its own process with no persistent
compilation cache (``--compile-cache none``: the compile a first run pays), under the flight
preset on the campaigns' envelope (``--realism flight --ranges montecarlo``), the capture
objective with a torque budget of 4 N m (``--torque-cap 4``), from the paper's gains,
``--holdout 0``:
* ``cmaes``: the run of the CMA-ES flight gains shipped until 2026-12-07, two calls: 40 generations of 8 on a
  batch of 32, then, from their gains, 26 generations of 8 on a batch of 64 with a step of
  0.1 (``--step-size 0.1``: refining);
* ``gradient``: ``--method gradient --steps 39 --batch 32`` (the gradient run of the
  documentation's method comparison, with the same torque budget).
Reports for each call the process's wall time, the first step's wall time less the median of
the others (about the compile), that median, and the rollouts used: per CMA-ES generation
``(population + 1) x batch`` forward rollouts (the candidates and the mean, and the last
mean once more), per gradient step ``batch`` gradients of one capture (each costs a few
forward rollouts: ``benchmarks.gradient``), and the totals per method. Writes ``tuning.json``.

With ``--races DIR`` it runs nothing: it reports every finished race under ``DIR``
(``benchmarks.race``, a folder holding ``race.json``) per problem (constant gains or a
schedule), training seed, method and wall-time mark: the held-out success with its 95%
interval, the steps (CMA-ES: generations), forward rollouts or gradients of one capture used
by the mark, the compile (the first step's wall time less the median of the others), and the
gradient method's margin over CMA-ES at the same mark (exact McNemar on the same held-out
captures). A race over seeds (``benchmarks.race_seeds``) gives one row per run and mark,
its McNemar test against the race's reference method on the same seed, and a second table:
per method and mark, the interquartile mean of the seeds' held-out success and of their
paired differences to the reference, each with its bootstrap interval over the seeds.
Writes ``races.json`` and prints the tables.
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
    first, *later = step_walls(out / "history.csv")
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


#: The CMA-ES flight gains shipped as ``tuned_gains("flight")`` until 2026-12-07 (since then the
#: gradient recipe's, documentation: Tuning the gains), which the ``cmaes`` recipe gives.
CMAES_FLIGHT_GAINS = (
    Path(__file__).resolve().parents[1]
    / "notebooks/data/race_seeds_constant/confirm_7312071/flight_gains_shipped_until_20261207.json"
)


def cmaes_gains_difference(gains: dict) -> float:
    """The largest relative difference between ``gains`` (a gains.json document) and the CMA-ES
    flight gains shipped until 2026-12-07 (``CMAES_FLIGHT_GAINS``): 0 when the run reproduces them."""
    shipped = json.loads(CMAES_FLIGHT_GAINS.read_text())
    differences = []
    for name, value in shipped.items():
        value = np.asarray(value, dtype=float)
        differences.append(float(np.max(np.abs(np.asarray(gains[name], dtype=float) - value) / np.abs(value))))
    return max(differences)


def step_walls(history: Path) -> list[float]:
    """A run's wall time of each step that records one (s), from its ``history.csv``."""
    with open(history, newline="") as file:
        return [float(row["wall_s"]) for row in csv.DictReader(file) if row["wall_s"] not in ("", "nan")]


def compile_estimate(history: Path, snapshots: dict | None = None) -> float:
    """A run's compile, about (s): its first row's wall time less what the row evaluated at
    the pace of the later steps (their median). The first row is the starting point's
    evaluation: a step's worth for the gradient method, one batch for CMA-ES, whose steps
    evaluate a generation. With the run's ``snapshots`` (mark -> ``steps`` and ``rollouts``
    or ``gradients`` done by then; two marks or more), the row's share of a step is read from
    the counts; without, it is taken as one step."""
    first, *later = step_walls(history)
    if not later:
        return float("nan")
    share = 1.0
    counts = sorted(
        (snap["steps"], snap.get("rollouts") or snap.get("gradients"))
        for snap in (snapshots or {}).values()
        if snap.get("steps") and (snap.get("rollouts") or snap.get("gradients"))
    )
    if len(counts) >= 2 and counts[-1][0] > counts[0][0]:
        (s0, n0), (s1, n1) = counts[0], counts[-1]
        per_step = (n1 - n0) / (s1 - s0)
        share = (n0 - s0 * per_step) / per_step
    return first - share * statistics.median(later)


def race_problem(settings: dict) -> str:
    """A race's problem in words: constant gains or a schedule, on the campaigns' envelope or
    one widened by ``--range``."""
    problem = f"schedule {settings['schedule']}" if settings.get("schedule") else "constant gains"
    return problem + (f", {' '.join(settings['ranges'])}" if settings.get("ranges") else "")


def seeds_race_rows(record_path: Path) -> list[dict]:
    """The rows of a finished race over seeds (``benchmarks.race_seeds``): one per run and mark,
    its McNemar test against the reference method on the same seed and mark as ``versus``."""
    record = json.loads(record_path.read_text())
    settings, summary, rows = record["settings"], record["summary"], []
    for label, run in record["runs"].items():
        method, seed = label.rsplit("_seed", 1)
        history = record_path.parent / f"seed{seed}" / method / "history.csv"
        compile_s = compile_estimate(history, run["snapshots"]) if history.exists() else float("nan")
        for mark, snapshot in run["snapshots"].items():
            held_out = summary["runs"][f"{label}_{mark}min"]
            versus = held_out.get(f"vs_{summary['reference']}")
            rows.append(
                {
                    "race": record_path.parent.name,
                    "paired_with": None,
                    "problem": race_problem(settings),
                    "training_seed": int(seed),
                    "heldout_seed": settings["heldout_seed"],
                    "method": method,
                    "minutes": float(mark),
                    "success": held_out["success"],
                    "versus": None if versus is None else {"method": summary["reference"], **versus},
                    "vs_cmaes_same_mark": None,
                    "steps": snapshot.get("steps"),
                    "rollouts": snapshot.get("rollouts"),
                    "gradients": snapshot.get("gradients"),
                    "compile_s": compile_s,
                }
            )
    return rows


def seeds_race_summaries(root: Path) -> list[dict]:
    """Per finished race over seeds under ``root``, method and mark: the interquartile mean
    of the seeds' held-out success and of their paired differences to the reference method,
    each with its bootstrap interval over the seeds."""
    summaries = []
    for record_path in sorted(root.glob("*/race.json")):
        record = json.loads(record_path.read_text())
        if "runs" not in record or "summary" not in record:
            continue
        reference = record["summary"]["reference"]
        for method, marks in record["summary"]["methods"].items():
            for mark, entry in marks.items():
                summaries.append(
                    {
                        "race": record_path.parent.name,
                        "problem": race_problem(record["settings"]),
                        "method": method,
                        "minutes": float(mark),
                        "success": entry["success"],
                        "reference": reference,
                        "difference_to_reference": entry.get(f"difference_to_{reference}"),
                    }
                )
    return summaries


def race_rows(root: Path) -> list[dict]:
    """One row per finished race under ``root``, method and mark (module docstring)."""
    rows = []
    for record_path in sorted(root.glob("*/race.json")):
        record = json.loads(record_path.read_text())
        if "runs" in record:  # a race over seeds
            rows += seeds_race_rows(record_path) if "summary" in record else []
            continue
        if "heldout" not in record:
            continue
        settings = record["settings"]
        for method, run in record["methods"].items():
            history = record_path.parent / method / "history.csv"
            compile_s = compile_estimate(history) if history.exists() else float("nan")
            for mark, snapshot in run["snapshots"].items():
                held_out = record["heldout"][f"{method}_{mark}min"]
                rows.append(
                    {
                        "race": record_path.parent.name,
                        "paired_with": (record_path.parent / record["against"]).resolve().name
                        if "against" in record
                        else None,
                        "problem": f"schedule {settings['schedule']}" if "schedule" in settings else "constant gains",
                        "training_seed": settings["seed"],
                        "heldout_seed": settings["heldout_seed"],
                        "method": method,
                        "minutes": float(mark),
                        "success": held_out["success"],
                        "vs_cmaes_same_mark": held_out.get("vs_cmaes_same_mark"),
                        "steps": snapshot.get("steps"),
                        "rollouts": snapshot.get("rollouts"),
                        "gradients": snapshot.get("gradients"),
                        "compile_s": compile_s,
                    }
                )
    return sorted(rows, key=lambda row: (row["problem"], row["training_seed"], row["method"], row["minutes"]))


#: A win: the gradient method captures at least this much more of the held-out captures
#: than CMA-ES at the same mark, with an exact McNemar p below ``WIN_P``.
WIN_POINTS, WIN_P = 0.03, 0.05


def race_verdicts(rows: list[dict]) -> list[dict]:
    """Per problem and mark that every training seed of the problem reached: on how many
    seeds a gradient-using method won (``WIN_POINTS``, ``WIN_P``) against CMA-ES."""
    verdicts = []
    for problem in sorted({row["problem"] for row in rows}):
        ours = [row for row in rows if row["problem"] == problem and row["vs_cmaes_same_mark"]]
        # The races of one method against CMA-ES on a fixed batch (a race over seeds has its own
        # summary, ``seeds_race_summaries``).
        seeds = sorted({row["training_seed"] for row in rows if row["problem"] == problem and "versus" not in row})
        for minutes in sorted({row["minutes"] for row in ours}):
            at_mark = [row for row in ours if row["minutes"] == minutes]
            if sorted({row["training_seed"] for row in at_mark}) != seeds:
                continue
            won = [
                row["training_seed"]
                for row in at_mark
                if row["vs_cmaes_same_mark"]["rate_difference"] >= WIN_POINTS
                and row["vs_cmaes_same_mark"]["p_value"] < WIN_P
            ]
            verdicts.append({"problem": problem, "minutes": minutes, "seeds": seeds, "won_on": sorted(set(won))})
    return verdicts


def race_table(rows: list[dict]) -> str:
    """The rows as a markdown table."""
    lines = [
        "| problem | training seed | minutes | method | held-out success [95% CI] | steps | rollouts or gradients "
        "| compile, s | against the reference at the same mark (McNemar) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for row in rows:
        success = row["success"]
        versus = row.get("versus") or (row["vs_cmaes_same_mark"] and {"method": "cmaes", **row["vs_cmaes_same_mark"]})
        used = f"{row['rollouts']} rollouts" if row["rollouts"] is not None else f"{row['gradients']} gradients"
        margin = (
            f"{100 * versus['rate_difference']:+.1f} points against {versus['method']}, {versus['only_candidate']} vs "
            f"{versus['only_reference']}, p = {versus['p_value']:.2g}"
            if versus
            else ""
        )
        lines.append(
            f"| {row['problem']} | {row['training_seed']} | {row['minutes']:g} | {row['method']} | "
            f"{100 * success['rate']:.1f}% [{100 * success['low']:.1f}, {100 * success['high']:.1f}] | "
            f"{row['steps']} | {used} | {row['compile_s']:.0f} | {margin} |"
        )
    return "\n".join(lines)


def seeds_summary_table(summaries: list[dict]) -> str:
    """The races over seeds as a markdown table: interquartile means over the seeds."""
    lines = [
        "| problem | minutes | method | held-out success, IQM over seeds [95% CI] | seeds | "
        "difference to the reference, IQM [95% CI] |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for row in sorted(summaries, key=lambda row: (row["problem"], row["minutes"], row["method"])):
        success, difference = row["success"], row["difference_to_reference"]
        versus = (
            f"{100 * difference['iqm']:+.1f} points [{100 * difference['low']:+.1f}, {100 * difference['high']:+.1f}] "
            f"against {row['reference']}"
            if difference
            else "(the reference)"
        )
        lines.append(
            f"| {row['problem']} | {row['minutes']:g} | {row['method']} | {100 * success['iqm']:.1f}% "
            f"[{100 * success['low']:.1f}, {100 * success['high']:.1f}] | {success['runs']} | {versus} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="results/benchmarks")
    parser.add_argument("--methods", default=",".join(METHODS), help=f"comma-separated subset of {', '.join(METHODS)}")
    parser.add_argument("--races", metavar="DIR", help="report the finished races under DIR instead of running")
    args = parser.parse_args(argv)
    if args.races is not None:
        if not Path(args.races).is_dir():
            parser.error(f"--races: {args.races} is not a folder")
        rows = race_rows(Path(args.races))
        if not rows:
            parser.error(
                f"--races: no finished race (a folder with race.json and its held-out results) in {args.races}"
            )
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        verdicts = race_verdicts(rows)
        report = {"rows": rows, "verdicts": verdicts, "across_seeds": seeds_race_summaries(Path(args.races))}
        (out / "races.json").write_text(json.dumps(report, indent=1) + "\n")
        print(race_table(rows))
        summaries = seeds_race_summaries(Path(args.races))
        if summaries:
            print()
            print(seeds_summary_table(summaries))
        for verdict in verdicts:
            print(
                f"{verdict['problem']}, {verdict['minutes']:g} min: the gradient method beats CMA-ES by "
                f"{100 * WIN_POINTS:g} points or more (McNemar p < {WIN_P:g}) on {len(verdict['won_on'])} of "
                f"{len(verdict['seeds'])} training seeds"
            )
        print(f"wrote {out / 'races.json'}")
        return 0
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
            if method == "cmaes":  # the CMA-ES flight recipe: does it give the gains it shipped?
                total["largest_relative_difference_from_cmaes_flight_gains"] = cmaes_gains_difference(
                    calls[-1]["gains"]
                )
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
