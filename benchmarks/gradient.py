"""Cost of one gradient of the tuning objective against one forward rollout.

    python -m spacegrasp_jax.benchmarks.gradient [--out results/benchmarks] [--duration 17] [--repeats 3]
        [--modes ...] [--gradient-from S]

Modes, each in its own process so that peak memory is its own:
* ``forward``: the objective alone (one rollout of the 17 s paper scenario, smooth contact);
* ``reverse_checkpointed``: ``jax.value_and_grad`` with each step's parts under
  ``jax.checkpoint``, in inner scans of 2 steps (``spacegrasp_jax.tuning.tune.block_steps``, the
  tuning default);
* ``reverse_truncated``: ``reverse_checkpointed`` with truncated backpropagation from
  ``--gradient-from`` s (default: half the duration; ``LoopOptions.gradient_from_s``): the
  loop before the cut runs forward only;
* ``reverse_plain``: ``jax.value_and_grad`` of ``rollout`` as a user writes it (inner scans of
  ``LOG_BLOCK`` steps, the parts of each step still under ``jax.checkpoint``: ``rollout`` always puts them there);
* ``forward_mode``: ``jax.jacfwd`` over the 39 admittance log-gains;
* ``flight_forward``, ``flight_reverse``, ``flight_truncated``: the flight-like tuner's
  program for one capture (``tuning.tune._per_sample_gradients``: the capture objective
  with a 4 N m budget, the campaigns' first sample of seed 0, one control period a
  checkpoint): its loss alone, its gradient, and its gradient cut at ``--gradient-from``
  (default: half the duration). Their ratios are to ``flight_forward``.
Reports wall time after compilation (median of ``--repeats``), its ratio to ``forward``,
XLA's ``memory_analysis`` (temporary and argument/output buffers) and the process's peak RSS.
With ``--compile-cache DIR``, run twice: the second run loads the compiled programs from
DIR, and its peak RSS is what a gradient needs once compiled. Writes ``gradient.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

from spacegrasp_jax.jobs.compilation import configure

MODES = (
    "forward",
    "reverse_checkpointed",
    "reverse_truncated",
    "reverse_plain",
    "forward_mode",
    "flight_forward",
    "flight_reverse",
    "flight_truncated",
)


def measure_flight(mode: str, duration: float, repeats: int, gradient_from_s: float | None = None) -> dict:
    """One of the ``flight_*`` modes (module docstring)."""
    import jax
    import numpy as np

    import spacegrasp_jax as sg
    from spacegrasp_jax.envelope.scenario import paper_scenario
    from spacegrasp_jax.jobs import compilation
    from spacegrasp_jax.loop.control import paper_gains
    from spacegrasp_jax.loop.realism import flight
    from spacegrasp_jax.tuning.objective import objective_spec, scenario_parts
    from spacegrasp_jax.tuning.parameters import gains_from_params, initial_params, make_mask
    from spacegrasp_jax.tuning.tune import (
        TuneConfig,
        _per_sample_gradients,
        flight_batch,
        make_objective,
        tuning_loop_options,
    )

    robot, gains = sg.paper_robot(), paper_gains()
    scenario = paper_scenario(robot, contact_law="smooth", duration=duration)
    cut = (duration / 2 if gradient_from_s is None else gradient_from_s) if mode == "flight_truncated" else None
    config = TuneConfig.of(
        method="gradient", batch=1, realism=flight(robot).to_dict(), torque_cap_Nm=4.0, gradient_from_s=cut
    )
    objective = make_objective(robot, config, np.ones(7))
    mask, params = make_mask(gains, "admittance"), initial_params(gains, "admittance")
    batch = flight_batch(robot, scenario, config, seed=0, count=1)
    samples = (batch.robots, batch.scenarios, batch.realisms, batch.keys)
    options = tuning_loop_options(config)

    if mode == "flight_forward":

        def program(params, samples):
            r, s, realism, key = jax.tree.map(lambda x: x[0], samples)
            spec = objective_spec(r, s, "admittance", 1, realism, batch.model_robot, options)
            return scenario_parts(spec, gains_from_params(params, gains, mask), objective, key)["loss"]
    else:

        def program(params, samples):
            return _per_sample_gradients(
                params, gains, mask, batch.model_robot, objective, samples, controller="admittance", options=options
            )

    return {"mode": mode, "gradient_from_s": cut} | _compiled_and_timed(
        compilation.jit(program), (params, samples), repeats
    )


def _compiled_and_timed(program, arguments: tuple, repeats: int) -> dict:
    """Compile the jitted ``program`` for ``arguments``, run it once, then time it
    (median of ``repeats``): its compile and run times, XLA's memory analysis and the
    process's peak RSS."""
    import jax

    from spacegrasp_jax.benchmarks.dynamics import timed

    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    start = time.perf_counter()
    executable = program.lower(*arguments).compile()
    compile_s = time.perf_counter() - start
    memory = executable.memory_analysis()
    jax.block_until_ready(executable(*arguments))
    run = timed(lambda: jax.block_until_ready(executable(*arguments)), repeats)
    return {
        "compile_s": compile_s,
        "run_s": run["median_s"],
        "run_spread_s": [run["min_s"], run["max_s"]],
        "xla_temp_mb": memory.temp_size_in_bytes / 1e6,
        "xla_argument_output_mb": (memory.argument_size_in_bytes + memory.output_size_in_bytes) / 1e6,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3,
        "rss_before_compile_mb": rss_before / 1e3,
    }


def measure(mode: str, duration: float, repeats: int, gradient_from_s: float | None = None) -> dict:

    import spacegrasp_jax as sg
    from spacegrasp_jax.envelope.scenario import paper_scenario
    from spacegrasp_jax.jobs import compilation
    from spacegrasp_jax.loop.control import paper_gains
    from spacegrasp_jax.tuning.objective import Objective, Weights
    from spacegrasp_jax.tuning.parameters import initial_params, make_mask
    from spacegrasp_jax.tuning.tune import (
        TuneConfig,
        block_steps,
        make_loss,
        make_value_and_grad,
        training_scenarios,
    )

    robot, gains = sg.paper_robot(), paper_gains()
    scenario = paper_scenario(robot, contact_law="smooth", duration=duration)
    cut = (duration / 2 if gradient_from_s is None else gradient_from_s) if mode == "reverse_truncated" else None
    config = TuneConfig.of(
        batch=1, objective="weighted", method="gradient", gradient_from_s=cut
    )  # one scenario: the cost of one gradient against one rollout
    objective = Objective(weights=Weights(), torque_scale_Nm=(0.80, 2.71, 1.82, 0.77, 1.11, 0.24, 0.028))
    params = initial_params(gains, "admittance")
    segment = block_steps(scenario.n_steps) if mode in ("reverse_checkpointed", "reverse_truncated") else None
    loss = make_loss(
        robot, training_scenarios(scenario, config), gains, make_mask(gains, "admittance"), config, objective, segment
    )
    if mode == "forward":
        program = compilation.jit(lambda p, values: loss.function(p, values)[0])
    else:
        program = make_value_and_grad(loss, params, "forward" if mode == "forward_mode" else "reverse").program
    timing = _compiled_and_timed(program, (params, loss.values), repeats)
    return {"mode": mode, "block_steps": segment, "gradient_from_s": cut} | timing


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="results/benchmarks")
    parser.add_argument("--duration", type=float, default=17.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--modes", default=",".join(MODES), help=f"comma-separated subset of {', '.join(MODES)}")
    parser.add_argument(
        "--compile-cache",
        metavar="DIR",
        help="JAX persistent compilation cache for the children: run twice with the same DIR and the "
        "second run loads the programs instead of compiling them ('compile' is then the load time)",
    )
    parser.add_argument(
        "--gradient-from",
        type=float,
        metavar="S",
        help="reverse_truncated's cut: backpropagate from this time on only (default: half the duration)",
    )
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    configure(compile_cache=False)  # this process is the benchmark's: float64, loops compiled whole, no cache
    if args.child:
        measured = measure_flight if args.child.startswith("flight") else measure
        print(json.dumps(measured(args.child, args.duration, args.repeats, args.gradient_from)))
        return 0
    modes = [mode for mode in args.modes.split(",") if mode]
    unknown = set(modes) - set(MODES)
    if unknown:
        parser.error(f"unknown mode(s): {', '.join(sorted(unknown))}")
    if args.gradient_from is not None and not 0.0 <= args.gradient_from < args.duration:
        parser.error(f"--gradient-from: must be a time in [0, {args.duration:g}) s, got {args.gradient_from:g}")
    environment = dict(os.environ)
    if args.compile_cache:
        environment |= {
            "JAX_COMPILATION_CACHE_DIR": args.compile_cache,
            "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
        }
    results = {}
    for mode in modes:
        command = [
            sys.executable,
            "-m",
            "spacegrasp_jax.benchmarks.gradient",
            "--child",
            mode,
            "--duration",
            str(args.duration),
            "--repeats",
            str(args.repeats),
        ] + ([] if args.gradient_from is None else ["--gradient-from", str(args.gradient_from)])
        output = subprocess.run(command, capture_output=True, text=True, check=True, env=environment).stdout
        results[mode] = json.loads(output.strip().splitlines()[-1])
        print(f"measured {mode}", flush=True)
    forwards = {"": results.get("forward", {}).get("run_s"), "flight": results.get("flight_forward", {}).get("run_s")}
    print(
        f"\n{'mode':22} {'compile [s]':>11} {'run [s]':>9} {'/ forward':>9} {'XLA temp [MB]':>13} {'peak RSS [MB]':>13}"
    )
    for mode, r in results.items():
        forward = forwards["flight" if mode.startswith("flight") else ""]
        ratio = r["run_s"] / forward if forward else float("nan")
        r["over_forward"] = ratio
        print(
            f"{mode:22} {r['compile_s']:>11.1f} {r['run_s']:>9.2f} {ratio:>9.2f} {r['xla_temp_mb']:>13.1f} {r['peak_rss_mb']:>13.0f}"
        )
    from spacegrasp_jax.benchmarks.dynamics import machine

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "gradient.json").write_text(
        json.dumps(
            {
                "machine": machine(),
                "duration_s": args.duration,
                "compile_cache": args.compile_cache,
                "results": results,
            },
            indent=2,
        )
    )
    print(f"wrote {out / 'gradient.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
