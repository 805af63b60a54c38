"""Margin search benchmark: what ``spacegrasp margins`` costs on its default settings.

    python -m spacegrasp_jax.benchmarks.margins [--out results/benchmarks] [--realism ideal|flight]

Runs what the command runs on its defaults (the paper's admittance gains, the paper's 17 s
scenario, 8 envelope samples a probe, the campaign's criteria) over every CPU core, with the
compilation cache off: every search of ``spacegrasp_jax.analysis.margins.find_margins()``, then the
linear analysis of ``spacegrasp_jax.analysis.stability.linear_analysis()``. Reports each part's
compile time and search time, the probes, rollouts and linearisations, and the process's
peak memory. Writes ``margins.json``.
"""

from __future__ import annotations

import argparse
import json
import resource
import time
from pathlib import Path

import jax

import spacegrasp_jax as sg
from spacegrasp_jax.analysis import margins, stability
from spacegrasp_jax.benchmarks.dynamics import machine
from spacegrasp_jax.envelope.scenario import paper_scenario
from spacegrasp_jax.jobs import batching
from spacegrasp_jax.jobs.campaign import CampaignConfig
from spacegrasp_jax.loop.control import paper_gains
from spacegrasp_jax.loop.realism import load_realism
from spacegrasp_jax.loop.simulate import RunSpec


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="results/benchmarks")
    parser.add_argument("--realism", default="ideal", help="ideal, flight or a TOML file (default ideal)")
    args = parser.parse_args(argv)
    batching.use_all_cpu_cores()
    sg.configure(compile_cache=False)  # cold: float64, loops compiled whole, no persistent cache
    robot = sg.paper_robot()
    scenario = paper_scenario(robot)
    realism = load_realism(args.realism)
    config = CampaignConfig(n=margins.MarginSettings.samples, realism=None if args.realism == "ideal" else realism)
    started = time.perf_counter()
    result = margins.find_margins(robot, scenario, paper_gains(), "admittance", config)
    time_domain_s = time.perf_counter() - started
    linear = stability.linear_analysis(RunSpec(robot, scenario, "admittance", realism=config.realism), paper_gains())
    wall = time.perf_counter() - started
    report = {
        "machine": machine(),
        "devices": jax.device_count(),
        "realism": args.realism,
        "wall_s": wall,
        "time_domain_s": time_domain_s,
        "compile_s": result["compile_s"],
        "search_s": result["search_s"],
        "probes": len(result["probes"]),
        "rollouts": result["rollouts"],
        "linear_s": wall - time_domain_s,
        "linear_compile_s": linear["compile_s"],
        "linear_search_s": linear["search_s"],
        "linearisations": len(linear["probes"]),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "margins": margins.margin_lines(result) + stability.linear_lines(linear),
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "margins.json").write_text(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))
    return report


if __name__ == "__main__":
    main()
