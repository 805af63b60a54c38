"""Compile cost of every program a user meets: time to trace, to lower and to compile, cold,
the compiled program's size, and its run time.

    python -m spacegrasp_jax.benchmarks.compile [--out results/benchmarks] [--duration 17]
        [--programs rollout_ideal,...] [--repeats 3] [--compiler-options JSON]

Each program is built in a process of its own, with no persistent compilation cache, through
the same code the commands use (``PROGRAMS``):

* ``rollout_ideal``, ``rollout_flight``: one admittance rollout (``spacegrasp simulate``),
  the paper's loop and the ``flight`` preset;
* ``tuning_gradient_ideal``: the gradient of the tuning objective (reverse mode,
  checkpointed) over one scenario (``spacegrasp tune --method gradient``);
* ``tuning_gradient_flight``: the same under the ``flight`` preset, one sample per device;
* ``montecarlo_chunk_ideal``, ``montecarlo_chunk_flight``: one campaign chunk of 64 samples
  (``spacegrasp montecarlo``);
* ``gradients_command``: the envelope gradients of ``spacegrasp gradients`` (four horizons,
  8 items a call).

Trace, lower and compile are JAX's own records of the build (``jax.monitoring`` events: the
jaxpr's tracing, its lowering to StableHLO, XLA's compile); ``hlo_instructions`` counts the
compiled (optimised) HLO's instructions, every computation's (a loop body counts once).
``run_s`` is the median of ``--repeats`` calls after the first and ``WARMUP`` untimed ones.
The gradients' ``run_s`` is compared with ``forward_s``, one forward rollout of the same
scenario in the same process, timed in turn with it (``over_forward``: the ratio of the
medians; ``over_forward_spread``: the smallest and largest ratio of a gradient and the
rollout timed after it). ``output_sha256`` is a digest of every number the program's first
call returned, bit for bit: two builds whose digests agree computed the same numbers.

``--compiler-options JSON`` adds XLA options (a JSON object, e.g.
``{"xla_llvm_disable_expensive_passes": true}``) to those the package compiles with
(``compilation.CPU_OPTIONS``), for a probe of what a compiler setting costs in build time and
run time, and whether it changes a number.
Writes ``compile.json``.
"""

from __future__ import annotations

import argparse
import collections
import json
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path

#: The programs, in the order they are measured.
PROGRAMS = (
    "rollout_ideal",
    "rollout_flight",
    "tuning_gradient_ideal",
    "tuning_gradient_flight",
    "montecarlo_chunk_ideal",
    "montecarlo_chunk_flight",
    "gradients_command",
)

#: Untimed rounds of calls after the build, before timing (the forward rollout's first call
#: compiles it).
WARMUP = 2

#: JAX's events for the three phases of a build.
EVENTS = {
    "trace_s": "/jax/core/compile/jaxpr_trace_duration",
    "lower_s": "/jax/core/compile/jaxpr_to_mlir_module_duration",
    "compile_s": "/jax/core/compile/backend_compile_duration",
}

#: Executables compiled outside ``compilation.compile_once`` by a program's build.
_SEEN: list = []

_INSTRUCTION = re.compile(r"^\s*(ROOT\s+)?[%\w.\-]+ = ")


def hlo_instructions(executable) -> int:
    """Instructions of a compiled program's optimised HLO, summed over its computations."""
    text = executable.as_text() or ""
    return sum(1 for line in text.splitlines() if _INSTRUCTION.match(line))


def _build(name: str, duration: float):
    """``(run, forward)``: ``run()`` builds (first call) and runs the program ``name`` and
    returns what it computed; ``forward()`` runs one forward rollout of the same scenario
    (``None`` for the rollouts themselves)."""
    import jax
    import numpy as np

    import spacegrasp_jax as sg
    from spacegrasp_jax.envelope.scenario import paper_scenario
    from spacegrasp_jax.jobs import campaign, experiment
    from spacegrasp_jax.loop.control import paper_gains
    from spacegrasp_jax.loop.realism import flight
    from spacegrasp_jax.loop.simulate import RunSpec
    from spacegrasp_jax.tuning import gradients, tune
    from spacegrasp_jax.tuning.objective import Objective

    robot, gains = sg.paper_robot(), paper_gains()
    flight_like = name.endswith("_flight")
    realism = flight() if flight_like else None
    scenario = paper_scenario(robot, contact_law="smooth" if "gradient" in name else "exact", duration=duration)

    def forward():
        return experiment.run(RunSpec(robot, scenario, "admittance", realism=realism), gains, check=False).log

    if name.startswith("rollout_"):
        return (
            lambda: experiment.run(RunSpec(robot, scenario, "admittance", realism=realism), gains, check=False).log
        ), None
    if name.startswith("tuning_gradient_"):
        config = tune.TuneConfig(
            batch=1 if realism is None else jax.device_count(),
            method="gradient",
            realism=None if realism is None else realism.to_dict(),
        )
        _, _, params, value_and_grad = tune.setup(robot, scenario, gains, config, (1.0,) * 7)
        if realism is None:  # a jitted function: compile it here, where its program can be read
            compiled = []

            def gradient():
                if not compiled:
                    compiled.append(value_and_grad.lower(params).compile())
                    _SEEN.append(compiled[0])
                return compiled[0](params, value_and_grad.values)

            return gradient, forward
        return (lambda: value_and_grad(params)), forward
    if name.startswith("montecarlo_chunk_"):
        config = campaign.CampaignConfig(n=64, chunk=64, realism=realism)
        variant = campaign.Variant("admittance", gains, "paper")
        return (lambda: campaign.evaluate_indices(robot, scenario, variant, config, np.arange(64))), forward
    if name == "gradients_command":
        objective = Objective(weights=tune.TuneConfig().weights, torque_scale_Nm=(1.0,) * 7, kind="capture")

        def envelope():
            return gradients.envelope_gradients(RunSpec(robot, scenario, "admittance"), gains, objective, n=7, chunk=8)[
                0
            ]

        return envelope, forward
    raise ValueError(f"unknown program {name!r}; expected one of {', '.join(PROGRAMS)}")


def measure(name: str, duration: float, repeats: int, warmup: int = WARMUP) -> dict:
    """Build and run ``name`` once, cold, then time it (module docstring)."""
    import jax

    from spacegrasp_jax.jobs import compilation

    totals = collections.Counter()
    counts = collections.Counter()

    def listener(event: str, duration_s: float, **_):
        totals[event] += duration_s
        counts[event] += 1

    jax.monitoring.register_event_duration_secs_listener(listener)
    run, forward = _build(name, duration)
    compiled_before = set(compilation._EXECUTABLES)
    start = time.perf_counter()
    first = jax.block_until_ready(run())
    first_call_s = time.perf_counter() - start
    phases = {key: totals[event] for key, event in EVENTS.items()}
    compiles = counts[EVENTS["compile_s"]]
    new = [compilation._EXECUTABLES[key][0] for key in compilation._EXECUTABLES if key not in compiled_before]
    new += _SEEN
    report = {
        "program": name,
        "duration_s": duration,
        **phases,
        "build_s": sum(phases.values()),
        "first_call_s": first_call_s,
        "xla_compiles": compiles,
        "hlo_instructions": sum(hlo_instructions(executable) for executable in new) if new else None,
        "output_sha256": output_digest(first),
        "compiler_options": compilation.compiler_options(),
    }
    calls = {"run": lambda: jax.block_until_ready(run())}
    if forward is not None:
        calls["forward"] = lambda: jax.block_until_ready(forward())
    times = timed_after_warmup(calls, warmup, repeats)
    report["run_s"] = statistics.median(times["run"])
    report["run_spread_s"] = [min(times["run"]), max(times["run"])]
    report["run_times_s"] = times["run"]
    if forward is not None:
        report["forward_s"] = statistics.median(times["forward"])
        report["forward_times_s"] = times["forward"]
        report["over_forward"] = report["run_s"] / report["forward_s"]
        pairs = [a / b for a, b in zip(times["run"], times["forward"], strict=True)]
        report["over_forward_spread"] = [min(pairs), max(pairs)]
    return report


def output_digest(outputs) -> str:
    """SHA-256 of every leaf of ``outputs`` (a pytree of arrays), in order, bytes and shapes:
    equal exactly when every number is equal bit for bit."""
    import hashlib

    import jax
    import numpy as np

    digest = hashlib.sha256()
    for leaf in jax.tree.leaves(outputs):
        array = np.ascontiguousarray(np.asarray(leaf))
        digest.update(str((array.dtype, array.shape)).encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def timed_after_warmup(calls: dict, warmup: int, repeats: int) -> dict[str, list[float]]:
    """Wall times (s) of ``repeats`` rounds of ``calls`` (name -> function), after ``warmup``
    untimed rounds. Each round calls every function once, in turn, so that a machine slowing
    down or speeding up during the measurement weighs on all of them alike."""
    for _ in range(warmup):
        for call in calls.values():
            call()
    times = {name: [] for name in calls}
    for _ in range(repeats):
        for name, call in calls.items():
            start = time.perf_counter()
            call()
            times[name].append(time.perf_counter() - start)
    return times


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="results/benchmarks")
    parser.add_argument("--duration", type=float, default=17.0, help="scenario duration (s)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--programs", default=",".join(PROGRAMS), help="comma-separated subset of the programs")
    parser.add_argument(
        "--compiler-options", default="{}", metavar="JSON", help="XLA options added to the package's (a JSON object)"
    )
    parser.add_argument("--one", help=argparse.SUPPRESS)  # internal: measure one program in this process
    args = parser.parse_args(argv)
    try:
        extra = json.loads(args.compiler_options)
    except ValueError as error:
        parser.error(f"--compiler-options: not JSON ({error})")
    if not isinstance(extra, dict) or not all(isinstance(v, (bool, int, float, str)) for v in extra.values()):
        parser.error(f"--compiler-options: a JSON object of XLA option names to values, got {args.compiler_options}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.one:
        from spacegrasp_jax.jobs import compilation
        from spacegrasp_jax.jobs.batching import use_all_cpu_cores
        from spacegrasp_jax.jobs.compilation import configure

        use_all_cpu_cores()
        compilation.CPU_OPTIONS.update(extra)  # before the options are first read (and probed)
        configure(compile_cache=False)  # cold: float64, loops compiled whole, no persistent cache
        if extra and not set(extra) <= set(compilation.compiler_options()):
            raise SystemExit(f"--compiler-options: this XLA refuses {extra}")
        (out / f"compile-{args.one}.json").write_text(json.dumps(measure(args.one, args.duration, args.repeats)))
        return 0
    names = [name for name in args.programs.split(",") if name]
    unknown = sorted(set(names) - set(PROGRAMS))
    if unknown:
        parser.error(f"--programs: unknown {', '.join(unknown)}; expected some of {', '.join(PROGRAMS)}")
    results = {}
    header = f"{'program':26} {'trace':>7} {'lower':>7} {'compile':>8} {'HLO instr':>10} {'run [s]':>8} {'/ fwd':>6}"
    print(header, flush=True)
    for name in names:
        subprocess.run(
            [
                sys.executable,
                "-m",
                "spacegrasp_jax.benchmarks.compile",
                "--one",
                name,
                "--out",
                str(out),
                "--duration",
                str(args.duration),
                "--repeats",
                str(args.repeats),
                "--compiler-options",
                args.compiler_options,
            ],
            check=True,
        )
        part = out / f"compile-{name}.json"
        results[name] = r = json.loads(part.read_text())
        part.unlink()
        ratio = f"{r['over_forward']:.2f}" if "over_forward" in r else ""
        print(
            f"{name:26} {r['trace_s']:>7.1f} {r['lower_s']:>7.1f} {r['compile_s']:>8.1f} "
            f"{r['hlo_instructions'] or 0:>10} {r['run_s']:>8.3f} {ratio:>6}",
            flush=True,
        )
    document = {"duration_s": args.duration, "compiler_options_added": extra, "programs": results}
    (out / "compile.json").write_text(json.dumps(document, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
