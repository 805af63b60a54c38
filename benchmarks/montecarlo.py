"""Monte-Carlo throughput: batches of perturbed captures against sequential single rollouts.

    python -m spacegrasp_jax.benchmarks.montecarlo [--out results/benchmarks] [--batches 1,64,256,1024] [--sequential 8] [--duration 17]

Each measurement runs in its own process, so that its peak memory is its own:
* ``sequential``: ``--sequential`` samples of the campaign, one after the other, each a call
  of the jit-compiled single-sample ``closed_loop`` folding its metrics (``FoldedMetrics``;
  what a loop over ``spacegrasp simulate`` would cost, without its log);
* ``batch B``: one chunk of B samples through the campaign's compiled, sharded kernel
  (``campaign.evaluate_indices``: sampling, vmapped rollouts, metrics gathered to the host),
  with one CPU device per core as ``spacegrasp montecarlo`` sets up (on a GPU host: the GPUs;
  a batch that does not divide among the cores, such as 1, runs on one CPU device), and on
  a CPU in sub-batches of 128 samples per device, as ``spacegrasp montecarlo`` defaults to.
All use the admittance law, the paper scenario (exact contact) and the default campaign
ranges. Times are after compilation: the median of ``--repeats`` for the sequential loop and
for batches up to 256, a single run for larger ones (minutes on a laptop). Reports rollouts/s,
simulated seconds per wall second, scenario-steps/s, the ratio to the sequential loop, XLA's
``memory_analysis`` and the process's peak RSS. Writes ``montecarlo.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from spacegrasp_jax.jobs.compilation import configure


def measure(kind: str, size: int, duration: float, repeats: int) -> dict:
    import jax

    from spacegrasp_jax.jobs import batching, campaign

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    if kind in ("batch", "flight") and size % cores == 0:
        batching.use_all_cpu_cores()  # as `spacegrasp montecarlo` does; before any device use
    import spacegrasp_jax as sg
    from spacegrasp_jax.benchmarks.dynamics import timed
    from spacegrasp_jax.envelope.perturbations import PerturbationRanges, sample
    from spacegrasp_jax.envelope.scenario import paper_scenario
    from spacegrasp_jax.jobs import compilation
    from spacegrasp_jax.jobs.montecarlo import FoldedMetrics
    from spacegrasp_jax.loop.control import paper_gains
    from spacegrasp_jax.loop.realism import flight
    from spacegrasp_jax.loop.simulate import RunSpec, closed_loop

    robot, gains = sg.paper_robot(), paper_gains()
    scenario = paper_scenario(robot, duration=duration)
    start = time.perf_counter()
    if kind == "sequential":
        robots, scenarios, _ = sample(robot, scenario, 0, range(size), PerturbationRanges())
        samples = [(jax.tree.map(lambda x: x[i], robots), jax.tree.map(lambda x: x[i], scenarios)) for i in range(size)]
        specs = [RunSpec(r, s, "admittance", observer=FoldedMetrics()) for r, s in samples]
        compiled = compilation.jit(closed_loop).lower(specs[0], gains).compile()
        compile_s = time.perf_counter() - start

        def run():
            for spec in specs:
                jax.block_until_ready(compiled(spec, gains))

    else:
        variant = campaign.Variant("admittance", gains)
        device_batch = 128 if jax.default_backend() == "cpu" else None
        if kind == "batch":  # the paper's loop: the controller told each sample's satellite
            ranges = dataclasses.replace(PerturbationRanges(), lar_estimate_position_m=0.0, lar_estimate_angle_rad=0.0)
            config = campaign.CampaignConfig(
                n=size, chunk=size, device_batch=device_batch, ranges=ranges, identified=True
            )
        else:  # the default campaign under the flight preset
            config = campaign.CampaignConfig(n=size, chunk=size, device_batch=device_batch, realism=flight())
        compiled, compile_s = campaign.compiled_chunk(robot, scenario, variant, config)

        def run():
            campaign.evaluate_indices(robot, scenario, variant, config, np.arange(size))

    memory = compiled.memory_analysis()
    run()  # warm-up
    timing = timed(run, repeats if kind == "sequential" or size <= 256 else 1)
    seconds = timing["median_s"]
    return {
        "kind": kind,
        "size": size,
        "compile_s": compile_s,
        "run_s": seconds,
        "run_spread_s": [timing["min_s"], timing["max_s"]],
        "rollouts_per_s": size / seconds,
        "simulated_s_per_wall_s": size * duration / seconds,
        "scenario_steps_per_s": size * scenario.n_steps / seconds,
        "xla_temp_mb": memory.temp_size_in_bytes / 1e6,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3,
        "devices": jax.device_count(),
    }


def main(argv: list[str] | None = None) -> int:
    configure(compile_cache=False)  # this process is the benchmark's: float64, loops compiled whole, no cache
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="results/benchmarks")
    parser.add_argument("--batches", default="1,64,256,1024", help="comma-separated batch sizes")
    parser.add_argument("--sequential", type=int, default=8, help="single rollouts in the sequential baseline")
    parser.add_argument("--duration", type=float, default=17.0, help="simulated seconds per rollout (17 in the paper)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--flight",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also the largest batch under the flight preset",
    )
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(measure(args.child[0], int(args.child[1]), args.duration, args.repeats)))
        return 0
    try:
        batches = [int(size) for size in args.batches.split(",") if size]
    except ValueError:
        parser.error(f"--batches: expected integers, got {args.batches!r}")
    if any(size < 1 for size in batches) or args.sequential < 1 or args.repeats < 1 or args.duration <= 0:
        parser.error("--batches, --sequential, --repeats and --duration must be positive")

    runs = (
        [("sequential", args.sequential)]
        + [("batch", size) for size in batches]
        + ([("flight", batches[-1])] if args.flight else [])
    )
    results = []
    for kind, size in runs:
        command = [
            sys.executable,
            "-m",
            "spacegrasp_jax.benchmarks.montecarlo",
            "--child",
            kind,
            str(size),
            "--duration",
            str(args.duration),
            "--repeats",
            str(args.repeats),
        ]
        output = subprocess.run(command, capture_output=True, text=True, check=True).stdout
        results.append(json.loads(output.strip().splitlines()[-1]))
        print(f"measured {kind} {size}", flush=True)

    sequential = results[0]["rollouts_per_s"]
    print(
        f"\n{'run':>16} {'compile [s]':>11} {'run [s]':>9} {'rollouts/s':>10} {'sim s/wall s':>12} {'steps/s':>10} {'vs sequential':>13} {'XLA temp [MB]':>13} {'peak RSS [MB]':>13}"
    )
    for r in results:
        r["over_sequential"] = r["rollouts_per_s"] / sequential
        label = f"{r['kind']} {r['size']}"
        print(
            f"{label:>16} {r['compile_s']:>11.1f} {r['run_s']:>9.2f} {r['rollouts_per_s']:>10.2f} {r['simulated_s_per_wall_s']:>12.1f} "
            f"{r['scenario_steps_per_s']:>10.3g} {r['over_sequential']:>12.1f}x {r['xla_temp_mb']:>13.1f} {r['peak_rss_mb']:>13.0f}"
        )
    from spacegrasp_jax.benchmarks.dynamics import machine

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "montecarlo.json").write_text(
        json.dumps({"machine": machine(), "duration_s": args.duration, "results": results}, indent=2)
    )
    print(f"wrote {out / 'montecarlo.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
