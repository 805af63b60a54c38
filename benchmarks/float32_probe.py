"""What float32 would gain on this machine: the same flight-like captures in float64 and in
float32, timed in one process, their verdicts compared.

    python -m spacegrasp_jax.benchmarks.float32_probe [--n 64] [--duration 17] [--out results/benchmarks]

``--n`` captures of the campaigns' envelope (seed 20261207) with the shipped constant flight
gains on the flight-like loop are drawn in float64 (``montecarlo.sample_loops``, as a
campaign draws them); the float32 run takes every floating-point input (the perturbed
robots, scenarios and realisms, the gains) cast to float32, so both run the same captures,
but for the sensor noise, which the loop draws in its own precision from the same keys (other
numbers: the verdicts' agreement is indicative; the speed is the probe's point), traced with
JAX's 64-bit mode off so that the constants the code writes in float64 are float32 too.
Each runs as one batch (``vmap`` of ``closed_loop`` with the campaign's folded metrics) on one
CPU device, compiled with the package's options; the median of ``--repeats`` runs after
compiling. Reports captures per second of each, their ratio, the verdicts that agree and the
largest difference of each metric. A probe, not a feature: the package runs float64 only
(documentation, Performance).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np


def cast(tree, dtype):
    """Every floating-point leaf of ``tree`` as ``dtype``; other leaves as they are."""
    import jax
    import jax.numpy as jnp

    def leaf(x):
        return jnp.asarray(x, dtype) if jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating) else x

    return jax.tree.map(leaf, tree)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=64, help="captures (default 64)")
    parser.add_argument("--duration", type=float, default=17.0, help="scenario length, s (default 17)")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs of each (default 3)")
    parser.add_argument("--out", default="results/benchmarks")
    args = parser.parse_args(argv)
    if args.n < 1 or args.repeats < 1 or not args.duration > 0:
        parser.error("--n and --repeats must be at least 1, --duration positive")

    from spacegrasp_jax.jobs.compilation import configure

    configure()
    import jax
    import jax.numpy as jnp

    import spacegrasp_jax as sg
    from spacegrasp_jax.benchmarks.dynamics import machine
    from spacegrasp_jax.envelope.criteria import CaptureCriteria
    from spacegrasp_jax.envelope.perturbations import PerturbationRanges
    from spacegrasp_jax.envelope.scenario import paper_scenario
    from spacegrasp_jax.jobs import compilation
    from spacegrasp_jax.jobs.montecarlo import FoldedMetrics, sample_loops, success
    from spacegrasp_jax.loop.control.schedule import named_gain_set
    from spacegrasp_jax.loop.realism import flight
    from spacegrasp_jax.loop.simulate import RunSpec, closed_loop

    robot = sg.paper_robot()
    scenario = paper_scenario(robot, duration=args.duration)
    spec = RunSpec(robot, scenario, "admittance", realism=flight(), observer=FoldedMetrics())
    samples = sample_loops(
        robot, scenario, np.uint32(20261207), jnp.arange(args.n, dtype=jnp.uint32), PerturbationRanges(), flight()
    )
    gains = named_gain_set("flight")

    def run(robots, scenarios, realisms, keys, model_robot, gains):
        def one(robot, scenario, realism, key):
            sample = dataclasses.replace(spec, robot=robot, scenario=scenario, realism=realism, model_robot=model_robot)
            return closed_loop(sample, gains, key)[1]

        return jax.vmap(one)(robots, scenarios, realisms, keys)[0]

    results = {}
    for name, dtype in (("float64", jnp.float64), ("float32", jnp.float32)):
        if dtype == jnp.float32:
            # Every constant the code writes in float64 traced as float32 (this script's
            # process only: the package itself never changes JAX's configuration).
            jax.config.update("jax_enable_x64", False)
        arguments = (
            cast(samples.robots, dtype),
            cast(samples.scenarios, dtype),
            cast(samples.realisms, dtype),
            samples.keys,
            cast(samples.model_robot, dtype),
            cast(gains, dtype),
        )
        started = time.perf_counter()
        compiled = compilation.jit(run).lower(*arguments).compile()
        compile_s = time.perf_counter() - started
        metrics = jax.block_until_ready(compiled(*arguments))
        walls = []
        for _ in range(args.repeats):
            started = time.perf_counter()
            jax.block_until_ready(compiled(*arguments))
            walls.append(time.perf_counter() - started)
        run_s = float(np.median(walls))
        metrics = {key: np.asarray(value, dtype=np.float64) for key, value in metrics.items()}
        results[name] = {"compile_s": compile_s, "run_s": run_s, "captures_per_s": args.n / run_s, "metrics": metrics}
        print(f"{name}: compile {compile_s:.1f} s, {args.n / run_s:.2f} captures/s", flush=True)

    criteria = CaptureCriteria()
    verdict64 = success(results["float64"]["metrics"], criteria)
    verdict32 = success(results["float32"]["metrics"], criteria)
    differences = {
        key: float(np.nanmax(np.abs(value - results["float32"]["metrics"][key])))
        for key, value in results["float64"]["metrics"].items()
        if np.isfinite(value).any()
    }
    document = {
        "machine": machine(),
        "n": args.n,
        "duration_s": args.duration,
        "float64_captures_per_s": results["float64"]["captures_per_s"],
        "float32_captures_per_s": results["float32"]["captures_per_s"],
        "speedup": results["float32"]["captures_per_s"] / results["float64"]["captures_per_s"],
        "compile_s": {name: r["compile_s"] for name, r in results.items()},
        "verdicts_agree": int(np.sum(verdict64 == verdict32)),
        "success": {"float64": int(verdict64.sum()), "float32": int(verdict32.sum())},
        "largest_metric_difference": differences,
    }
    print(json.dumps({k: v for k, v in document.items() if k != "largest_metric_difference"}, indent=1))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "float32_probe.json").write_text(json.dumps(document, indent=1) + "\n")
    print(f"wrote {out / 'float32_probe.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
