"""Closed-loop rollout benchmark: compile time and run time of one 17 s rollout per controller.

    python -m spacegrasp_jax.benchmarks.rollout [--out results/benchmarks] [--repeats 5] [--duration 17]

Run time is measured after compilation, as the median (and spread) of ``--repeats`` runs of
the paper scenario (dt = 1 ms, 17,000 RK4 steps); besides the paper's gains, the flight-like
loop with the shipped flight schedule (``admittance/flight-schedule``). For the figure "on one CPU core", run it
pinned to one core: ``taskset -c 0 python -m spacegrasp_jax.benchmarks.rollout``. Batched throughput is
``benchmarks.montecarlo``'s. Writes ``rollout.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import jax

import spacegrasp_jax as sg
from spacegrasp_jax.benchmarks.dynamics import machine, timed
from spacegrasp_jax.envelope.scenario import paper_scenario
from spacegrasp_jax.jobs import compilation
from spacegrasp_jax.jobs.compilation import configure
from spacegrasp_jax.loop.control import PAPER_CONTROLLERS, paper_gains
from spacegrasp_jax.loop.control.schedule import tuned_schedule
from spacegrasp_jax.loop.realism import flight
from spacegrasp_jax.loop.simulate import rollout

#: The free-floating target of ``configs/free_target.toml``: 400 kg, tumbling at 0.5 deg/s.
FREE_TARGET = dict(
    mass=400.0,
    inertia=[70.0, 80.0, 60.0],
    com_in_lar=[0.0, 0.0, 0.8],
    velocity=[0.0005, -0.0005, 0.0],
    angular_velocity=[0.0, 0.0, 0.0087],
)


def bench_controller(robot, scenario, gains, controller: str, repeats: int, realism=None) -> dict:
    """One rollout's compile and run times; ``realism``: the flight-like loop (noise key 0)."""
    function = compilation.jit(rollout, static_argnames=("controller",))
    extra = {} if realism is None else dict(realism=realism, key=jax.random.PRNGKey(0))
    start = time.perf_counter()
    executable = function.lower(robot, scenario, gains, controller=controller, **extra).compile()
    compile_s = time.perf_counter() - start
    jax.block_until_ready(executable(robot, scenario, gains, **extra))  # warm-up
    run = timed(lambda: jax.block_until_ready(executable(robot, scenario, gains, **extra)), repeats)
    return {
        "compile_s": compile_s,
        "run_s": run["median_s"],
        "run_spread_s": [run["min_s"], run["max_s"]],
        "steps": scenario.n_steps,
        "us_per_step": 1e6 * run["median_s"] / scenario.n_steps,
        "simulated_s_per_wall_s": scenario.duration / run["median_s"],
    }


def main(argv: list[str] | None = None) -> int:
    configure(compile_cache=False)  # this process is the benchmark's: float64, loops compiled whole, no cache
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="results/benchmarks", help="folder for rollout.json")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--duration", type=float, default=17.0, help="simulated seconds (17 in the paper)")
    args = parser.parse_args(argv)
    if args.repeats < 1 or args.duration <= 0:
        parser.error("--repeats and --duration must be positive")

    robot, gains = sg.paper_robot(), paper_gains()
    scenario = paper_scenario(robot, duration=args.duration)
    affinity = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    result = {"machine": {**machine(), "cpu_affinity": affinity}, "duration_s": args.duration}
    for controller in PAPER_CONTROLLERS:
        result[controller] = bench_controller(robot, scenario, gains, controller, args.repeats)
    for controller in PAPER_CONTROLLERS:  # the flight preset: 100 Hz control, own model, sensors, limits
        result[f"{controller}/flight"] = bench_controller(robot, scenario, gains, controller, args.repeats, flight())
    free_target = paper_scenario(robot, duration=args.duration, target=FREE_TARGET)  # a second body in the state
    result["admittance/free-target"] = bench_controller(robot, free_target, gains, "admittance", args.repeats)
    # the shipped flight schedule against the constant gains in the same flight-like loop
    schedule = tuned_schedule("flight_schedule")
    result["admittance/flight-schedule"] = bench_controller(
        robot, scenario, schedule, "admittance", args.repeats, flight()
    )

    info = result["machine"]
    print(
        f"machine: {info['cpu']}, {info['cores']} cores (pinned to {affinity}), backend {info['backend']}, jax {info['jax']}"
    )
    print(
        f"{'controller':18} {'compile [s]':>12} {'run [s]':>10} {'spread [s]':>16} {'us/step':>9} {'sim s / wall s':>15}"
    )
    rows = [*PAPER_CONTROLLERS, *(f"{c}/flight" for c in PAPER_CONTROLLERS)]
    for controller in [*rows, "admittance/free-target", "admittance/flight-schedule"]:
        r = result[controller]
        spread = f"{r['run_spread_s'][0]:.3f}-{r['run_spread_s'][1]:.3f}"
        print(
            f"{controller:18} {r['compile_s']:>12.2f} {r['run_s']:>10.3f} {spread:>16} {r['us_per_step']:>9.1f} {r['simulated_s_per_wall_s']:>15.1f}"
        )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "rollout.json").write_text(json.dumps(result, indent=2))
    print(f"wrote {out / 'rollout.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
