"""Margin search benchmark: what ``spacegrasp margins`` costs on its default settings.

    python -m spacegrasp_jax.benchmarks.margins [--out results/benchmarks] [--realism ideal|flight]

Runs every search of ``spacegrasp_jax.margins.find_margins()`` (the paper's admittance gains,
the paper's 17 s scenario, 8 envelope samples a probe, the campaign's criteria) over every
CPU core, with the compilation cache off, and reports the compile time of the probes'
program, the search's time, the probes and rollouts it ran, and the process's peak memory.
Writes ``margins.json``.
"""

from __future__ import annotations

import argparse
import json
import resource
import time
from pathlib import Path

import jax

import spacegrasp_jax as sg
from spacegrasp_jax import batching, margins
from spacegrasp_jax.benchmarks.dynamics import machine
from spacegrasp_jax.campaign import CampaignConfig
from spacegrasp_jax.control import paper_gains
from spacegrasp_jax.realism import load_realism
from spacegrasp_jax.scenario import paper_scenario


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
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
    wall = time.perf_counter() - started
    report = {
        "machine": machine(),
        "devices": jax.device_count(),
        "realism": args.realism,
        "wall_s": wall,
        "compile_s": result["compile_s"],
        "search_s": result["search_s"],
        "probes": len(result["probes"]),
        "rollouts": result["rollouts"],
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "margins": margins.margin_lines(result),
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "margins.json").write_text(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))
    return report


if __name__ == "__main__":
    main()
