"""The worst-case search against a campaign of the same rollouts, over seeds.

    python -m spacegrasp_jax.benchmarks.worstcase --out notebooks/data/worstcase \\
        [--seeds 100-109] [--budgets 64,512] [--realisms ideal,flight] [--durations 3,17] \\
        [--methods cem,ascent]

For every approach duration (s; 17 is the paper's scenario, a shorter one ends its approach
then), realism, budget, seed and method, runs ``spacegrasp_jax.analysis.worstcase.search()`` on the
paper's admittance gains over the default envelope (measure ``final_error``) and the
campaign of the same number of rollouts and seed (``compare_with_campaign()``; the
screening's samples are its first). Appends one row a run to ``rows.jsonl`` as it goes (an
interrupted run resumes where it stopped: rows already there are not run again), then
writes ``summary.json``: per configuration and method, the seeds where the search's worst is
at least as bad as the campaign's, those where it is worse by 10% of the campaign's or more,
and the median ratio of the two. Programs are shared across the rows of one process.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import spacegrasp_jax as sg
from spacegrasp_jax.analysis import worstcase
from spacegrasp_jax.benchmarks.dynamics import machine
from spacegrasp_jax.envelope.scenario import paper_scenario, scenario_from_mapping
from spacegrasp_jax.jobs import batching
from spacegrasp_jax.jobs.campaign import CampaignConfig
from spacegrasp_jax.loop.control import paper_gains
from spacegrasp_jax.loop.realism import load_realism

#: A search is counted as clearly worse when its worst exceeds the campaign's by this share.
CLEAR_MARGIN = 0.10


def _numbers(text: str, kind=int) -> list:
    """``"64,512"`` or ``"100-109"`` (whole numbers only) as a list."""
    values = []
    for part in text.split(","):
        low, dash, high = part.partition("-")
        if dash and kind is int:
            values += list(range(int(low), int(high) + 1))
        else:
            values.append(kind(part))
    return values


def scenario_of(robot, duration_s: float):
    """The paper's scenario, or one whose approach and run last ``duration_s`` (s)."""
    if duration_s == 17.0:
        return paper_scenario(robot)
    return scenario_from_mapping(robot, {"duration": duration_s, "trajectory": {"duration": duration_s}})


def row_key(row: dict) -> tuple:
    return (float(row["duration_s"]), row["realism"], int(row["budget"]), int(row["seed"]), row["method"])


def run_one(robot, duration_s: float, realism: str, budget: int, seed: int, method: str) -> dict:
    """One search and the campaign of its rollouts: a row of ``rows.jsonl``."""
    scenario = scenario_of(robot, duration_s)
    config = CampaignConfig(n=1, seed=seed, realism=None if realism == "ideal" else load_realism(realism, robot))
    settings = worstcase.SearchSettings(budget=budget, method=method)
    started = time.perf_counter()
    found = worstcase.search(robot, scenario, paper_gains(), "admittance", config, settings)
    campaign = worstcase.compare_with_campaign(
        robot,
        scenario,
        paper_gains(),
        "admittance",
        config,
        budget,
        settings.measure,
        chunk=settings.campaign_chunk,
        screened=found.screening,
    )
    ratio = (
        found.value / campaign["value"] if np.isfinite(campaign["value"]) else (1.0 if np.isinf(found.value) else 0.0)
    )
    return {
        "duration_s": duration_s,
        "realism": realism,
        "budget": budget,
        "seed": seed,
        "method": method,
        "search_worst": found.value,
        "campaign_worst": campaign["value"],
        "campaign_worst_sample": campaign["sample"],
        "ratio": ratio,
        "at_least_as_bad": bool(found.value >= campaign["value"]),
        "clearly_worse": bool(ratio >= 1.0 + CLEAR_MARGIN),
        "found_by": found.found_by,
        "rollouts": found.rollouts,
        "compile_s": found.compile_s,
        "search_s": found.search_s,
        "wall_s": time.perf_counter() - started,
    }


def _beats(value: float, other: float) -> bool:
    """``value`` is worse (larger) than ``other`` by more than rounding: the same capture
    measured by two programs (the campaign's and the ascent's) differs in its last digits."""
    if np.isinf(value) or np.isinf(other):
        return bool(value > other)
    return bool(value > other * (1.0 + 1e-9))


def sign_test(wins: int, losses: int) -> float:
    """The two-sided exact sign test's p-value of ``wins`` against ``losses`` (ties left out;
    1 without a decided pair)."""
    from scipy import stats

    return float(stats.binomtest(wins, wins + losses, 0.5).pvalue) if wins + losses else 1.0


def summarise(rows: list[dict]) -> dict:
    """Per configuration and method: seeds, wins, clear wins, the median and the range of the
    ratio, and the sign test of the search against the campaign over the seeds; per
    configuration, the sign test of the methods against each other on the same seeds."""
    groups: dict[tuple, list[dict]] = {}
    for row in rows:
        groups.setdefault((row["duration_s"], row["realism"], row["budget"], row["method"]), []).append(row)
    summary = {}
    for (duration, realism, budget, method), group in sorted(groups.items()):
        wins = sum(_beats(row["search_worst"], row["campaign_worst"]) for row in group)
        losses = sum(_beats(row["campaign_worst"], row["search_worst"]) for row in group)
        summary[f"{duration:g} s, {realism}, budget {budget}, {method}"] = {
            "seeds": len(group),
            "at_least_as_bad": sum(row["at_least_as_bad"] for row in group),
            "clearly_worse": sum(row["clearly_worse"] for row in group),
            "median_ratio": float(np.median([row["ratio"] for row in group])),
            "min_ratio": float(np.min([row["ratio"] for row in group])),
            "max_ratio": float(np.max([row["ratio"] for row in group])),
            "worse_than_campaign": wins,
            "milder_than_campaign": losses,
            "sign_test_p": sign_test(wins, losses),
        }
    configurations = {key[:3] for key in groups}
    for duration, realism, budget in sorted(configurations):
        by_seed = {
            method: {row["seed"]: row["search_worst"] for row in groups.get((duration, realism, budget, method), [])}
            for method in worstcase.METHODS
        }
        seeds = sorted(set(by_seed["cem"]) & set(by_seed["ascent"]))
        if seeds:
            wins = sum(_beats(by_seed["cem"][seed], by_seed["ascent"][seed]) for seed in seeds)
            losses = sum(_beats(by_seed["ascent"][seed], by_seed["cem"][seed]) for seed in seeds)
            summary[f"{duration:g} s, {realism}, budget {budget}, cem against ascent"] = {
                "seeds": len(seeds),
                "cem_worse": wins,
                "ascent_worse": losses,
                "sign_test_p": sign_test(wins, losses),
            }
    return summary


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, help="folder for rows.jsonl and summary.json")
    parser.add_argument("--seeds", default="100-109")
    parser.add_argument("--budgets", default="64,512")
    parser.add_argument("--realisms", default="ideal,flight")
    parser.add_argument("--durations", default="3,17")
    parser.add_argument("--methods", default=",".join(worstcase.METHODS))
    args = parser.parse_args(argv)
    try:
        seeds, budgets = _numbers(args.seeds), _numbers(args.budgets)
        durations = _numbers(args.durations, float)
    except ValueError as error:
        parser.error(f"--seeds, --budgets, --durations: {error}")
    realisms, methods = args.realisms.split(","), args.methods.split(",")
    for method in methods:
        if method not in worstcase.METHODS:
            parser.error(f"--methods: {method!r} is not one of {', '.join(worstcase.METHODS)}")
    for realism in realisms:
        if realism not in ("ideal", "flight"):
            parser.error(f"--realisms: {realism!r} is not ideal or flight")
    for duration in durations:
        if not 0.0 < duration <= 17.0:
            parser.error(f"--durations: {duration:g} s is outside (0, 17]")
    for budget in budgets:
        for method in methods:
            try:  # refused here, not after hours
                worstcase.SearchSettings(budget=budget, method=method)
            except worstcase.WorstCaseError as error:
                parser.error(f"--budgets: {method}: {error}")
    batching.use_all_cpu_cores()
    sg.configure()
    robot = sg.paper_robot()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows_path = out / "rows.jsonl"
    rows = [json.loads(line) for line in rows_path.read_text().splitlines()] if rows_path.exists() else []
    done = {row_key(row) for row in rows}
    for duration in durations:
        for realism in realisms:
            for budget in budgets:
                for seed in seeds:
                    for method in methods:
                        if (duration, realism, budget, seed, method) in done:
                            continue
                        row = run_one(robot, duration, realism, budget, seed, method)
                        rows.append(row)
                        with rows_path.open("a") as stream:
                            stream.write(json.dumps(row) + "\n")
                        print(
                            f"{duration:g} s {realism} budget {budget} seed {seed} {method}: "
                            f"search {row['search_worst']:.6g}, campaign {row['campaign_worst']:.6g} "
                            f"(x{row['ratio']:.3f}), {row['wall_s']:.0f} s",
                            flush=True,
                        )
    report = {"machine": machine(), "rows": len(rows), "summary": summarise(rows)}
    (out / "summary.json").write_text(json.dumps(report, indent=1) + "\n")
    return report


if __name__ == "__main__":
    main()
