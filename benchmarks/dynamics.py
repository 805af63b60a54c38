"""Forward-dynamics benchmark: spacegrasp-jax against Pinocchio called from Python.

    python -m spacegrasp_jax.benchmarks.dynamics [--out results/benchmarks] [--repeats 7] [--batch 1024]

Measures, after compilation, with the median (and spread) over repeats:
* one ``forward_dynamics`` call from Python (jit, includes dispatch);
* the cost of one evaluation inside ``lax.scan`` (what a rollout pays; no dispatch);
* a ``vmap`` batch of 1,024 evaluations;
* Pinocchio ``crba`` + ``nonLinearEffects`` + a NumPy solve, and ``aba``, called from a
  Python loop, one state at a time and over the same 1,024 states.
Prints a table and writes ``dynamics.json`` (with the machine description) into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import spacegrasp_jax as sg
from spacegrasp_jax.jobs import compilation
from spacegrasp_jax.jobs.compilation import configure


def machine() -> dict:
    cpu = platform.processor()
    try:
        with open("/proc/cpuinfo") as handle:
            cpu = next(line.split(":", 1)[1].strip() for line in handle if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "devices": [str(device) for device in jax.devices()],
        "backend": jax.default_backend(),
        "jax": jax.__version__,
        "python": platform.python_version(),
        "loops_compiled_whole": compilation.loops_compile_whole(),
    }


def chosen_parts(parser: argparse.ArgumentParser, text: str, known: tuple[str, ...]) -> list[str]:
    """The parts named in ``text`` (comma-separated) of a benchmark measuring ``known`` ones;
    an unknown one ends the command with the parser's error (exit 2)."""
    parts = [part for part in text.split(",") if part]
    unknown = sorted(set(parts) - set(known))
    if unknown:
        parser.error(f"--parts: unknown {unknown}; expected some of {list(known)}")
    return parts


def pin_to_one_core() -> None:
    """Run this process on one core (where the OS allows it): call it before XLA starts its
    threads."""
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})


def timed(function, repeats: int) -> dict:
    """Median, min and max wall time (s) of ``function()`` over ``repeats`` calls."""
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        samples.append(time.perf_counter() - start)
    return {"median_s": statistics.median(samples), "min_s": min(samples), "max_s": max(samples)}


def timed_program(function, arguments: tuple, repeats: int) -> dict:
    """[`timed()`][spacegrasp_jax.benchmarks.dynamics.timed] of ``function(*arguments)``
    compiled with the package's options (``compilation.jit``), after one untimed call."""
    compiled = compilation.jit(function).lower(*arguments).compile()
    jax.block_until_ready(compiled(*arguments))
    return timed(lambda: jax.block_until_ready(compiled(*arguments)), repeats)


def random_inputs(count: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    quat = rng.normal(size=(count, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    return {
        "R_base": np.asarray(jax.vmap(sg.core.spatial.quat_to_rotation)(quat)),
        "q": rng.uniform(-np.pi, np.pi, size=(count, 7)),
        "V_base": rng.normal(scale=0.2, size=(count, 6)),
        "qd": rng.normal(size=(count, 7)),
        "Q": rng.normal(size=(count, 13)),
    }


def bench_jax(robot, inputs, repeats: int) -> dict:
    one = {key: jnp.asarray(value[0]) for key, value in inputs.items()}
    single = jax.jit(sg.forward_dynamics)
    args = (robot, one["R_base"], one["q"], one["V_base"], one["qd"], one["Q"])
    start = time.perf_counter()
    single(*args).block_until_ready()
    compile_s = time.perf_counter() - start
    calls = 1000
    single_call = timed(lambda: [single(*args) for _ in range(calls)][-1].block_until_ready(), repeats)

    steps = 10_000

    @jax.jit
    def in_scan(qd):
        def body(rates, _):
            acc = sg.forward_dynamics(robot, one["R_base"], one["q"] + 1e-3 * rates, one["V_base"], rates, one["Q"])
            return rates + 1e-6 * acc[6:], None

        return jax.lax.scan(body, qd, None, length=steps)[0]

    in_scan(one["qd"]).block_until_ready()
    scan = timed(lambda: in_scan(one["qd"]).block_until_ready(), repeats)

    batched = jax.jit(jax.vmap(sg.forward_dynamics, in_axes=(None, 0, 0, 0, 0, 0)))
    batch_args = (robot,) + tuple(jnp.asarray(inputs[key]) for key in ("R_base", "q", "V_base", "qd", "Q"))
    batched(*batch_args).block_until_ready()
    batch = timed(lambda: batched(*batch_args).block_until_ready(), repeats)
    return {
        "compile_s": compile_s,
        "single_call_us": 1e6 * single_call["median_s"] / calls,
        "in_scan_us": 1e6 * scan["median_s"] / steps,
        "in_scan_spread_us": [1e6 * scan["min_s"] / steps, 1e6 * scan["max_s"] / steps],
        "batch_s": batch["median_s"],
        "batch_spread_s": [batch["min_s"], batch["max_s"]],
        "batch_per_state_us": 1e6 * batch["median_s"] / len(inputs["q"]),
    }


def bench_pinocchio(inputs, repeats: int) -> dict | None:
    try:
        import pinocchio as pin
    except ImportError:
        return None
    # The Pinocchio twin of the paper robot lives with the tests (built from the tables).
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    import pinocchio_reference as ref

    model, _ = ref.build_model()
    data = model.createData()
    count = len(inputs["q"])
    maps = [ref.velocity_map(R) for R in inputs["R_base"]]
    configs = [ref.configuration(np.zeros(3), inputs["R_base"][i], inputs["q"][i]) for i in range(count)]
    velocities = [maps[i] @ np.concatenate([inputs["V_base"][i], inputs["qd"][i]]) for i in range(count)]
    torques = [maps[i] @ inputs["Q"][i] for i in range(count)]

    def crba_nle(i):
        M = pin.crba(model, data, configs[i])
        M = np.triu(M) + np.triu(M, 1).T
        bias = pin.nonLinearEffects(model, data, configs[i], velocities[i])
        return np.linalg.solve(M, torques[i] - bias)

    def aba(i):
        return pin.aba(model, data, configs[i], velocities[i], torques[i])

    calls = 1000
    single_crba = timed(lambda: [crba_nle(i % count) for i in range(calls)], repeats)
    single_aba = timed(lambda: [aba(i % count) for i in range(calls)], repeats)
    batch_crba = timed(lambda: [crba_nle(i) for i in range(count)], repeats)
    return {
        "version": pin.__version__,
        "crba_nle_solve_us": 1e6 * single_crba["median_s"] / calls,
        "aba_us": 1e6 * single_aba["median_s"] / calls,
        "batch_crba_nle_s": batch_crba["median_s"],
    }


def main(argv: list[str] | None = None) -> int:
    configure(compile_cache=False)  # this process is the benchmark's: float64, loops compiled whole, no cache
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="results/benchmarks", help="folder for dynamics.json")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--batch", type=int, default=1024)
    args = parser.parse_args(argv)
    if args.repeats < 1 or args.batch < 1:
        parser.error("--repeats and --batch must be positive")

    robot = sg.paper_robot()
    inputs = random_inputs(args.batch)
    result = {"machine": machine(), "batch": args.batch, "jax": bench_jax(robot, inputs, args.repeats)}
    result["pinocchio"] = bench_pinocchio(inputs, args.repeats)

    ours, peer = result["jax"], result["pinocchio"]
    rows = [
        (
            "forward dynamics, one call from Python",
            f"{ours['single_call_us']:.1f} us",
            peer and f"{peer['crba_nle_solve_us']:.1f} us (crba+nle+solve)",
        ),
        (
            "forward dynamics, inside lax.scan",
            f"{ours['in_scan_us']:.2f} us",
            peer and f"{peer['aba_us']:.1f} us (aba)",
        ),
        (
            f"batch of {args.batch}",
            f"{1e3 * ours['batch_s']:.2f} ms",
            peer and f"{1e3 * peer['batch_crba_nle_s']:.2f} ms (crba+nle loop)",
        ),
        ("compile (jit, first call)", f"{ours['compile_s']:.2f} s", "-"),
    ]
    info = result["machine"]
    print(f"machine: {info['cpu']}, {info['cores']} cores, backend {info['backend']}, jax {info['jax']}")
    print(f"{'':40} {'spacegrasp-jax':>16} {'Pinocchio ' + (peer['version'] if peer else ''):>30}")
    for label, mine, theirs in rows:
        print(f"{label:40} {mine:>16} {theirs or 'not installed':>30}")
    if peer:
        print(
            f"batch of {args.batch}: {peer['batch_crba_nle_s'] / ours['batch_s']:.1f}x the Pinocchio loop; "
            f"one in-scan evaluation: {peer['aba_us'] / ours['in_scan_us']:.1f}x one aba call from Python"
        )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "dynamics.json").write_text(json.dumps(result, indent=2))
    print(f"wrote {out / 'dynamics.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
