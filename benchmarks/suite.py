"""``spacegrasp benchmark``: every speed and memory figure of the project, with its peers, in
one run on one machine.

    spacegrasp benchmark [--quick] [--out results/benchmarks] [--repeats 3]

Measures, after compilation and a warm-up, medians over ``--repeats``:
1. compile and run time of one closed-loop rollout per controller (``benchmarks.rollout``);
2. throughput of batches of 1, 64, 256 and 1,024 perturbed scenarios against sequential single
   rollouts, with peak memory (``benchmarks.montecarlo``, each batch in its own process);
3. one gradient of the tuning objective, reverse mode with checkpointing (whole, and truncated
   at half the capture) and forward mode, as a ratio to one forward rollout, with peak memory
   (``benchmarks.gradient``);
4. the floating-point work of one closed-loop step from XLA's cost analysis, and the rate
   achieved by the single rollout against an estimate of the machine's peak;
5. the cost of building each program a user meets, cold: trace, lower and compile times and
   the compiled program's size (``benchmarks.compile``; ``--quick``: the rollout alone);
6. the peers (``benchmarks.peers``): MuJoCo's ``mj_step`` and ``mujoco.rollout`` on the same
   robot, and the same closed loop written as a Python loop over Pinocchio (whose final pose
   must agree with ours, else the comparison is void and the run fails).
Prints one table with the ratios and writes ``benchmark.json`` (the keys are listed in
``KEYS``). ``--quick`` runs every part at toy sizes (0.2-0.5 s scenarios, batches of 1 and
4) so CI exercises the whole command in about two minutes; its numbers mean nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from spacegrasp_jax.benchmarks import compile as compile_benchmark
from spacegrasp_jax.jobs.compilation import configure
from spacegrasp_jax.loop.control import PAPER_CONTROLLERS
from spacegrasp_jax.loop.simulate import RunSpec

#: Keys of benchmark.json (seconds unless the name says otherwise).
KEYS = (
    "machine",
    "quick",
    "duration_s",
    "rollout_s",
    "compile_s",
    "us_per_step",
    "flight_over_ideal_step",
    "free_target_over_stationary_step",
    "schedule_over_constant_step",
    "batch_steps_per_s",
    "batch_peak_rss_mb",
    "sequential_steps_per_s",
    "gradient_over_forward",
    "gradient_peak_mb",
    "gradient_xla_temp_mb",
    "flops_per_step",
    "achieved_gflops",
    "peak_gflops_estimate",
    "pinocchio_loop_rollout_s",
    "pinocchio_loop_max_pose_difference",
    "mujoco_mj_step_17s_s",
    "mujoco_us_per_step",
    "mujoco_rollout_steps_per_s",
    "mujoco_rollout_batches",
    "programs",
)


def _child(module: str, out: Path, *options: str) -> dict:
    """Run ``python -m <module> --out <out> <options>`` and read the JSON it writes."""
    subprocess.run([sys.executable, "-m", module, "--out", str(out), *options], check=True, stdout=subprocess.DEVNULL)
    name = {
        "spacegrasp_jax.benchmarks.rollout": "rollout.json",
        "spacegrasp_jax.benchmarks.montecarlo": "montecarlo.json",
        "spacegrasp_jax.benchmarks.gradient": "gradient.json",
        "spacegrasp_jax.benchmarks.compile": "compile.json",
    }[module]
    return json.loads((out / name).read_text())


def peak_gflops_estimate() -> float | None:
    """Cores x clock x double-precision FLOPs per cycle (16 with AVX2 FMA, 32 with AVX-512),
    from /proc/cpuinfo; ``None`` where it cannot be read."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return None
    clocks = [float(line.split(":")[1]) for line in text.splitlines() if line.startswith("cpu MHz")]
    flags = next((line.split(":")[1].split() for line in text.splitlines() if line.startswith("flags")), [])
    if not clocks:
        return None
    per_cycle = 32 if "avx512f" in flags else 16 if {"avx2", "fma"} <= set(flags) else 8
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return cores * max(clocks) * 1e6 * per_cycle / 1e9


def flops_per_step(controller: str = "admittance") -> float:
    """XLA's count of floating-point operations in one compiled closed-loop step (one control
    update and one RK4 step of the plant). XLA's cost analysis counts a loop body once: RK4's
    stages 2-4 are one loop, so the step's count holds one of them, and two more evaluations
    of the plant's rate are added."""
    import jax

    import spacegrasp_jax as sg
    from spacegrasp_jax.envelope.scenario import paper_scenario
    from spacegrasp_jax.jobs import compilation
    from spacegrasp_jax.loop.control import paper_gains
    from spacegrasp_jax.loop.simulate import loop_body, plant_derivative

    def flops(function, *arguments) -> float:
        analysis = compilation.jit(function).lower(*arguments).compile().cost_analysis()
        return float((analysis[0] if isinstance(analysis, list) else analysis)["flops"])

    robot = sg.paper_robot()
    scenario = paper_scenario(robot, duration=1.0)
    body = loop_body(RunSpec(robot, scenario, controller), paper_gains())
    stage = flops(lambda plant, u: plant_derivative(robot, scenario, plant, u), scenario.initial, jax.numpy.zeros(7))
    return flops(body.period, body.start, 0.0) + 2 * stage


def run(out: Path, quick: bool, repeats: int) -> dict:
    """Run every measurement and return the report (the content of benchmark.json)."""
    duration = 0.5 if quick else 17.0
    batches = [1, 4] if quick else [1, 64, 256, 1024]
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="benchmark-", dir=out) as parts:
        return _measure(Path(parts), quick, repeats, duration, batches)


def _measure(parts: Path, quick: bool, repeats: int, duration: float, batches: list[int]) -> dict:
    """Every measurement; the parts' own JSON files go to ``parts`` (removed afterwards)."""
    import spacegrasp_jax as sg
    from spacegrasp_jax.benchmarks import peers
    from spacegrasp_jax.benchmarks.dynamics import machine
    from spacegrasp_jax.envelope.scenario import paper_scenario
    from spacegrasp_jax.jobs import experiment
    from spacegrasp_jax.loop.control import paper_gains

    report = {"machine": machine(), "quick": quick, "duration_s": duration}

    print(f"1/6 single rollouts ({duration:g} s)...", flush=True)
    rollout = _child("spacegrasp_jax.benchmarks.rollout", parts, "--duration", str(duration), "--repeats", str(repeats))
    report["rollout_s"] = {c: rollout[c]["run_s"] for c in PAPER_CONTROLLERS}
    report["compile_s"] = {c: rollout[c]["compile_s"] for c in PAPER_CONTROLLERS}
    report["us_per_step"] = {c: rollout[c]["us_per_step"] for c in PAPER_CONTROLLERS}
    report["flight_over_ideal_step"] = {
        c: rollout[f"{c}/flight"]["us_per_step"] / rollout[c]["us_per_step"] for c in PAPER_CONTROLLERS
    }
    report["free_target_over_stationary_step"] = (
        rollout["admittance/free-target"]["us_per_step"] / rollout["admittance"]["us_per_step"]
    )
    report["schedule_over_constant_step"] = (
        rollout["admittance/flight-schedule"]["us_per_step"] / rollout["admittance/flight"]["us_per_step"]
    )

    print(f"2/6 batches {batches}...", flush=True)
    montecarlo = _child(
        "spacegrasp_jax.benchmarks.montecarlo",
        parts,
        "--duration",
        str(duration),
        "--batches",
        ",".join(map(str, batches)),
        "--sequential",
        "2" if quick else "8",
        "--repeats",
        str(repeats),
        "--no-flight" if quick else "--flight",
    )
    batch_results = [r for r in montecarlo["results"] if r["kind"] == "batch"]
    report["batch_steps_per_s"] = {str(r["size"]): r["scenario_steps_per_s"] for r in batch_results}
    report["batch_peak_rss_mb"] = {str(r["size"]): r["peak_rss_mb"] for r in batch_results}
    report["sequential_steps_per_s"] = montecarlo["results"][0]["scenario_steps_per_s"]
    flight_chunk = next((r for r in montecarlo["results"] if r["kind"] == "flight"), None)
    if flight_chunk is not None:  # not at the quick sizes
        same_size = next(r for r in batch_results if r["size"] == flight_chunk["size"])
        report["flight_over_ideal_chunk"] = flight_chunk["run_s"] / same_size["run_s"]

    print("3/6 gradients...", flush=True)
    gradient_duration = 0.2 if quick else 17.0
    gradient = _child(
        "spacegrasp_jax.benchmarks.gradient",
        parts,
        "--duration",
        str(gradient_duration),
        "--repeats",
        str(repeats),
        "--modes",
        "forward,reverse_checkpointed,reverse_truncated,forward_mode",
    )["results"]
    report["gradient_over_forward"] = {
        "reverse": gradient["reverse_checkpointed"]["over_forward"],
        "truncated": gradient["reverse_truncated"]["over_forward"],
        "forward": gradient["forward_mode"]["over_forward"],
    }
    report["gradient_peak_mb"] = {
        "reverse": gradient["reverse_checkpointed"]["peak_rss_mb"],
        "forward": gradient["forward_mode"]["peak_rss_mb"],
        "rollout": gradient["forward"]["peak_rss_mb"],
    }
    report["gradient_xla_temp_mb"] = {
        "reverse": gradient["reverse_checkpointed"]["xla_temp_mb"],
        "forward": gradient["forward_mode"]["xla_temp_mb"],
    }

    print("4/6 cost analysis...", flush=True)
    report["flops_per_step"] = flops_per_step()
    report["achieved_gflops"] = report["flops_per_step"] / (report["us_per_step"]["admittance"] * 1e-6) / 1e9
    report["peak_gflops_estimate"] = peak_gflops_estimate()

    print("5/6 building each program, cold...", flush=True)
    programs = _child(
        "spacegrasp_jax.benchmarks.compile",
        parts,
        "--duration",
        str(0.2 if quick else 17.0),
        "--repeats",
        str(repeats),
        "--programs",
        "rollout_ideal" if quick else ",".join(compile_benchmark.PROGRAMS),
    )
    report["programs"] = programs["programs"]

    print("6/6 peers: MuJoCo and a Python loop over Pinocchio...", flush=True)
    robot, gains = sg.paper_robot(), paper_gains()
    scenario = paper_scenario(robot, duration=duration)
    mj_step = peers.mujoco_mj_step(robot, scenario, repeats)
    report["mujoco_mj_step_17s_s"] = mj_step["run_s"] * 17.0 / duration
    report["mujoco_us_per_step"] = mj_step["us_per_step"]
    mujoco_batches = {str(b): peers.mujoco_rollout(robot, scenario, b) for b in batches}
    report["mujoco_rollout_batches"] = {b: r["scenario_steps_per_s"] for b, r in mujoco_batches.items()}
    report["mujoco_rollout_steps_per_s"] = mujoco_batches[str(batches[-1])]["scenario_steps_per_s"]
    pinocchio = peers.pinocchio_closed_loop(robot, scenario, gains)
    ours = experiment.run(RunSpec(robot, scenario, "admittance"), gains)
    difference = float(np.max(np.abs(np.asarray(pinocchio["final_pose"]) - ours.log.pose_ee[-1])))
    report["pinocchio_loop_rollout_s"] = pinocchio["run_s"]
    report["pinocchio_loop_max_pose_difference"] = difference
    if not difference < 1e-6:
        raise RuntimeError(
            f"the Pinocchio loop ends {difference:.3g} from our rollout: the peers do not simulate the same thing"
        )
    return report


def table(report: dict) -> str:
    """The report as one plain-text table, ratios as this project over the peer or target."""
    d, rows = report["duration_s"], []
    admittance = report["rollout_s"]["admittance"]

    def row(what, ours, peer, ratio, target=""):
        rows.append(f"{what:<52} {ours:>14} {peer:>14} {ratio:>9} {target:>12}")

    row("measure", "spacegrasp-jax", "peer", "ratio", "target")
    row(
        f"closed-loop rollout {d:g} s, admittance law [s]",
        f"{admittance:.3f}",
        f"{report['pinocchio_loop_rollout_s']:.3f}",
        f"{report['pinocchio_loop_rollout_s'] / admittance:.1f}x",
        ">= 10x",
    )
    row("  peer: Python loop over Pinocchio, same closed loop", "", "", "", "")
    row(
        f"closed-loop rollout {d:g} s vs MuJoCo mj_step [s]",
        f"{admittance:.3f}",
        f"{report['mujoco_mj_step_17s_s'] * d / 17.0:.3f}",
        f"{report['mujoco_mj_step_17s_s'] * d / 17.0 / admittance:.2f}x",
        ">= 1x",
    )
    row("  peer: open-loop mj_step, one thread", "", "", "", "")
    for batch, ours in report["batch_steps_per_s"].items():
        peer = report["mujoco_rollout_batches"][batch]
        row(
            f"batch {batch}, scenario-steps/s",
            f"{ours:.3g}",
            f"{peer:.3g}",
            f"{ours / peer:.2f}x",
            ">= 1x" if batch == "1024" else "",
        )
    row("  peer: mujoco.rollout open loop, a thread per core", "", "", "", "")
    row(
        "gradient / forward rollout, reverse (checkpointed)",
        f"{report['gradient_over_forward']['reverse']:.2f}",
        "",
        "",
        "<= 4",
    )
    row(
        "gradient / forward rollout, reverse truncated at half the capture",
        f"{report['gradient_over_forward']['truncated']:.2f}",
        "",
        "",
        "",
    )
    row("gradient / forward rollout, forward mode", f"{report['gradient_over_forward']['forward']:.2f}", "", "", "<= 4")
    row("gradient peak RSS, reverse [MB]", f"{report['gradient_peak_mb']['reverse']:.0f}", "", "", "<= 1000")
    flight = report["flight_over_ideal_step"]
    row(
        "flight-like step / ideal step, admittance / Cartesian",
        f"{flight['admittance']:.2f} / {flight['cartesian']:.2f}",
        "",
        "",
        "<= 1.6",
    )
    row(
        "free-target step / stationary-target step, admittance",
        f"{report['free_target_over_stationary_step']:.2f}",
        "",
        "",
        "<= 1.25",
    )
    row(
        "scheduled step / constant-gain step, admittance flight-like",
        f"{report['schedule_over_constant_step']:.2f}",
        "",
        "",
        "<= 1.1",
    )
    if "flight_over_ideal_chunk" in report:
        row("Monte-Carlo chunk, flight-like / ideal", f"{report['flight_over_ideal_chunk']:.2f}", "", "", "<= 1.6")
    row(
        "compile, admittance / Cartesian rollout [s]",
        f"{report['compile_s']['admittance']:.1f} / {report['compile_s']['cartesian']:.1f}",
        "",
        "",
        "< 30",
    )
    targets = {"rollout": "<= 5", "tuning_gradient_ideal": "<= 30", "tuning_gradient_flight": "<= 45"}
    targets |= {"montecarlo": "<= 30", "gradients_command": "<= 60"}
    for name, program in report["programs"].items():
        target = next((value for prefix, value in targets.items() if name.startswith(prefix)), "")
        row(
            f"build {name} cold: trace+lower+compile [s]",
            f"{program['build_s']:.1f}",
            "",
            f"{program['over_forward']:.2f}x fwd" if "over_forward" in program and "gradient" in name else "",
            target,
        )
    peak = report["peak_gflops_estimate"]
    row("FLOPs per closed-loop step (XLA cost analysis)", f"{report['flops_per_step']:.3g}", "", "", "")
    row(
        "achieved GFLOP/s, single rollout",
        f"{report['achieved_gflops']:.2f}",
        f"{peak:.0f}" if peak else "n/a",
        f"{100 * report['achieved_gflops'] / peak:.1f}%" if peak else "",
        "",
    )
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    configure(compile_cache=False)  # this process is the benchmark's: float64, loops compiled whole, no cache
    parser = argparse.ArgumentParser(
        prog="spacegrasp benchmark", allow_abbrev=False, description=__doc__.splitlines()[0]
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="toy sizes: exercises every part in about two minutes; numbers mean nothing",
    )
    parser.add_argument("--out", default="results/benchmarks", help="folder for benchmark.json")
    parser.add_argument("--repeats", type=int, default=3, help="repeats per timing (median reported)")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats: must be at least 1, got {args.repeats}")
    out = Path(args.out)
    report = run(out, args.quick, 1 if args.quick else args.repeats)
    info = report["machine"]
    loops = "loops compiled whole" if info["loops_compiled_whole"] else "loops kernel by kernel"
    print(
        f"\nmachine: {info['cpu']}, {info['cores']} cores, {info['backend']} backend, jax {info['jax']}, {loops}"
        + (" (--quick: sizes too small to mean anything)" if args.quick else "")
    )
    print(table(report))
    (out / "benchmark.json").write_text(json.dumps(report, indent=2))
    print(f"wrote {out / 'benchmark.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
