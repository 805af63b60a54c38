"""What batching buys per core, part by part of the closed-loop step.

    python -m spacegrasp_jax.benchmarks.batch_efficiency [--out results/benchmarks] [--batch 128] [--iterations 1000] [--parts ...]

The Monte-Carlo target (documentation, Performance) is a batch of 1,024 rollouts at 10x the
throughput of single rollouts run one after another. On a CPU that can only come from the
cores and from each core computing several samples at once (SIMD lanes). This measures the
second factor where it is decided: each part of one closed-loop step runs ``--iterations``
times in a ``fori_loop`` compiled whole (``spacegrasp_jax.jobs.compilation``), once for a single
sample and once ``vmap``-ped over ``--batch`` samples of the default campaign, both pinned to
one core. It reports the time per sample and their ratio: 1 means the batch computes no
faster per sample than a single rollout; the SIMD width of a float64 vector (4 or 8 lanes)
bounds it, except where one sample's code waits on latencies (divisions, square roots).

Parts, each including the ones it needs (so the cost of a part alone is a difference):
* ``kinematics``: ``dynamics.frames_at_base``, the poses of the DH frames;
* ``kinematics_by_component``: the same poses from ``forward_kinematics_by_component()``,
  the kinematics written component by component (a probe, not the package's code);
* ``mass_matrix``: kinematics and the mass matrix's blocks;
* ``plant_kinematics``: everything computed once per state (``simulate.plant_kinematics``:
  kinematics, mass matrix, EE Jacobian, satellite block solve, contact force);
* ``plant_rate``: plant_kinematics and the state rate (``simulate.plant_rate``: Newton-Euler
  bias, the block solve of the mass matrix), one RK4 stage;
* ``controller``: plant_kinematics, the ideal observation and one controller update;
* ``step``: one whole closed-loop step (controller, four RK4 stages), the scan's body.

A part's outputs are folded into the next iteration's joint angles (times 1e-12), so that no
iteration can be skipped or hoisted; ``step`` carries its state as the rollout does. Writes
``batch_efficiency.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from spacegrasp_jax.benchmarks.dynamics import chosen_parts, machine, pin_to_one_core
from spacegrasp_jax.jobs.compilation import configure

PARTS = ("kinematics", "kinematics_by_component", "mass_matrix", "plant_kinematics", "plant_rate", "controller", "step")


def forward_kinematics_by_component(robot, p_base, R_base, q):
    """[`spacegrasp_jax.core.kinematics.forward_kinematics()`][spacegrasp_jax.core.kinematics.forward_kinematics] written component by component:
    every vector a list of 3 arrays, every rotation a 3x3 list, ``R Rz(theta) Rx(alpha)``
    column by column, stacked into the same [`Frames`][spacegrasp_jax.core.kinematics.Frames] only
    at the end. Under ``vmap`` each component is an array of the batch's shape, so the chain's
    arithmetic runs across the batch (the last axis). The probe for a batch-last rewrite of the
    step (documentation, Performance); not used by the package."""
    import jax.numpy as jnp

    from spacegrasp_jax.core.kinematics import Frames

    theta = q + robot.joint_offset
    ct, st = jnp.cos(theta), jnp.sin(theta)
    # A DH chain (the paper's arm): frame_rotation is Rx(alpha), frame_position (L, 0, lambda).
    ca, sa = robot.frame_rotation[..., 2, 2], robot.frame_rotation[..., 2, 1]
    R = [[R_base[i, j] for j in range(3)] for i in range(3)]
    p = [p_base[i] + sum(R[i][j] * robot.mount_position[j] for j in range(3)) for i in range(3)]
    R_link, origins, axes = [], [p], [[R[0][2], R[1][2], R[2][2]]]
    for i in range(len(theta)):
        c, s, length, offset = ct[i], st[i], robot.frame_position[i, 0], robot.frame_position[i, 2]
        p = [p[r] + R[r][0] * (length * c) + R[r][1] * (length * s) + R[r][2] * offset for r in range(3)]
        x = [R[r][0] * c + R[r][1] * s for r in range(3)]
        y_rz = [R[r][1] * c - R[r][0] * s for r in range(3)]
        y = [y_rz[r] * ca[i] + R[r][2] * sa[i] for r in range(3)]
        z = [R[r][2] * ca[i] - y_rz[r] * sa[i] for r in range(3)]
        R = [[x[r], y[r], z[r]] for r in range(3)]
        R_link.append(R)
        origins.append(p)
        axes.append(z)
    matrix = lambda M: jnp.stack([jnp.stack(row) for row in M])
    vectors = lambda vs: jnp.stack([jnp.stack(v) for v in vs])
    p_ee = [p[r] + sum(R[r][j] * robot.ee_offset[j] for j in range(3)) for r in range(3)]
    return Frames(
        joint_origin=vectors(origins[:-1]),
        link_origin=vectors(origins[1:]),
        joint_axis=vectors(axes[:-1]),
        R_mount=R_base,
        R_link=jnp.stack([matrix(M) for M in R_link]),
        p_ee=jnp.stack(p_ee),
        R_ee=matrix(R),
    )


def _part_functions(gains):
    """name -> ``f(robot, scenario, state) -> outputs`` (``state`` a ``LoopState``); ``step``'s
    output is the next ``LoopState``."""
    import jax.numpy as jnp

    from spacegrasp_jax.core.dynamics import frames_at_base, mass_matrix_parts_from_frames
    from spacegrasp_jax.loop import simulate
    from spacegrasp_jax.loop.control import as_controller

    def kinematics(robot, scenario, state):
        return frames_at_base(robot, state.plant.R_base, state.plant.q)

    def kinematics_by_component(robot, scenario, state):
        R_base = state.plant.R_base
        return forward_kinematics_by_component(robot, jnp.zeros(3, dtype=R_base.dtype), R_base, state.plant.q)

    def mass_matrix(robot, scenario, state):
        return mass_matrix_parts_from_frames(robot, kinematics(robot, scenario, state))

    def plant_kinematics(robot, scenario, state):
        return simulate.plant_kinematics(robot, scenario, state.plant)

    def plant_rate(robot, scenario, state):
        shared = simulate.plant_kinematics(robot, scenario, state.plant)
        return simulate.plant_rate(robot, scenario, state.plant, shared, jnp.zeros_like(state.plant.qd))

    def controller(robot, scenario, state):
        control = as_controller("admittance")
        shared = simulate.plant_kinematics(robot, scenario, state.plant)
        observed = simulate.observe(robot, scenario, state.plant, shared, 1.0)
        command, law_state = control.law.update(gains, observed.inputs, state.controller.law, scenario.dt)
        u, servo_state = control.torque(gains, command, state.plant.qd, state.controller.pid, 1.0, scenario.dt)
        return u, law_state, servo_state

    def step(robot, scenario, state):
        body = simulate.loop_body(simulate.RunSpec(robot, scenario, "admittance"), gains)
        return body.period(state, jnp.ones((), state.plant.q.dtype))[0]

    return dict(
        kinematics=kinematics,
        kinematics_by_component=kinematics_by_component,
        mass_matrix=mass_matrix,
        plant_kinematics=plant_kinematics,
        plant_rate=plant_rate,
        controller=controller,
        step=step,
    )


def _looped(part, carries_state: bool, iterations: int):
    """``(robot, scenario, state) -> state`` running ``part`` ``iterations`` times in one loop:
    its output is the next state if ``carries_state``, else folded into the joint angles."""
    import jax
    import jax.numpy as jnp

    def body(robot, scenario, state):
        output = part(robot, scenario, state)
        if carries_state:
            return output
        total = sum(jnp.sum(leaf) for leaf in jax.tree.leaves(output))
        return dataclasses.replace(state, plant=dataclasses.replace(state.plant, q=state.plant.q + 1e-12 * total))

    def run(robot, scenario, state):
        return jax.lax.fori_loop(0, iterations, lambda _, s: body(robot, scenario, s), state)

    return run


def measure(parts: list[str], batch: int, iterations: int, repeats: int) -> list[dict]:
    import jax

    import spacegrasp_jax as sg
    from spacegrasp_jax.benchmarks.dynamics import timed_program
    from spacegrasp_jax.envelope.perturbations import PerturbationRanges, sample
    from spacegrasp_jax.envelope.scenario import paper_scenario
    from spacegrasp_jax.loop import simulate
    from spacegrasp_jax.loop.control import paper_gains

    robot, gains = sg.paper_robot(), paper_gains()
    scenario = paper_scenario(robot, duration=1.0)
    robots, scenarios, _ = sample(robot, scenario, 0, range(batch), PerturbationRanges())
    states = jax.vmap(lambda r, s: simulate.initial_state(simulate.RunSpec(r, s)))(robots, scenarios)
    batched = (robots, scenarios, states)
    single = jax.tree.map(lambda x: x[0], batched)
    functions = _part_functions(gains)
    results = []
    for name in parts:
        row = {"part": name}
        looped = _looped(functions[name], name == "step", iterations)
        for label, function, arguments, samples in (
            ("single", looped, single, 1),
            ("batch", jax.vmap(looped), batched, batch),
        ):
            timing = timed_program(function, arguments, repeats)
            row[f"{label}_us_per_sample"] = timing["median_s"] / iterations / samples * 1e6
        row["batch_gain"] = row["single_us_per_sample"] / row["batch_us_per_sample"]
        results.append(row)
        print(
            f"{name:>23} {row['single_us_per_sample']:>10.3f} {row['batch_us_per_sample']:>10.3f} {row['batch_gain']:>9.2f}x",
            flush=True,
        )
    return results


def main(argv: list[str] | None = None) -> int:
    configure(compile_cache=False)  # this process is the benchmark's: float64, loops compiled whole, no cache
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="results/benchmarks")
    parser.add_argument(
        "--batch", type=int, default=128, help="samples in the vmapped batch (the campaign's sub-batch per CPU device)"
    )
    parser.add_argument("--iterations", type=int, default=1000, help="loop iterations per timed call")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--parts", default=",".join(PARTS), help=f"comma-separated, from {', '.join(PARTS)}")
    args = parser.parse_args(argv)
    parts = chosen_parts(parser, args.parts, PARTS)
    if args.batch < 1 or args.iterations < 1 or args.repeats < 1:
        parser.error("--batch, --iterations and --repeats must be positive")
    pin_to_one_core()

    print(f"{'part':>23} {'single':>10} {'batch':>10} {'gain':>10}   (us per sample, one core, batch {args.batch})")
    results = measure(parts, args.batch, args.iterations, args.repeats)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report = {"machine": machine(), "batch": args.batch, "iterations": args.iterations, "results": results}
    (out / "batch_efficiency.json").write_text(json.dumps(report, indent=2))
    print(f"wrote {out / 'batch_efficiency.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
