"""Where a gradient's time goes, part by part of the closed-loop step: each part's forward
pass against its reverse pass.

    python -m spacegrasp_jax.benchmarks.gradient_parts [--out results/benchmarks] [--states 2000] [--parts ...]

A checkpointed reverse-mode gradient (``RunSpec(options=LoopOptions(checkpoint=True))``, the tuning gradient's
loop) runs the closed loop forward once, keeping each step's inputs, then goes back through
the steps; for each step it runs the checkpointed parts forward again and then their
adjoints. So a part's cost in the backward pass is its *reverse* time here: ``jax.vjp`` of
the part (the forward pass again, keeping what the adjoint needs) and the pull-back of a
cotangent. The forward pass, a part alone, is what a forward rollout pays for it.

Each part runs on ``--states`` loop states of the paper's 17 s capture (smooth contact, as
the tuning gradient's; one state every 8 steps, so the approach and the contact are in the
sample), in one ``lax.scan`` over them compiled whole (``spacegrasp_jax.jobs.compilation``), on
one core. Every output (forward) or every input's cotangent (reverse) is summed into the
scan's carry, so that nothing is left out.

Parts, each including what it reads:
* ``plant_kinematics``: ``simulate.plant_kinematics`` (kinematics, mass matrix blocks, EE
  Jacobian, contact force), with respect to the plant state;
* ``plant_rate``: ``simulate.plant_rate`` given the kinematics (Newton-Euler bias, the
  block solve; its derivative is inverse dynamics), with respect to the state, the
  kinematics and the torques;
* ``stage``: one RK4 stage, ``plant_kinematics`` then ``plant_rate``, with respect to the
  state and the torques;
* ``controller``: ``plant_kinematics``, the ideal observation, the admittance law's update
  and the joint PID, with respect to the state and the gains;
* ``period``: one control period of the checkpointed loop (the controller, the log row and
  RK4's four stages under their checkpoints), with respect to the loop state and the gains:
  the gradient's whole step. Its parts being checkpointed, its reverse runs them forward
  twice, as the gradient does: once keeping their inputs, once again before their adjoints.

Writes ``gradient_parts.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from spacegrasp_jax.benchmarks.dynamics import chosen_parts, machine, pin_to_one_core
from spacegrasp_jax.jobs.compilation import configure

PARTS = ("plant_kinematics", "plant_rate", "stage", "controller", "period")

#: Steps between two of the sampled states.
STRIDE = 8


def _part_functions(robot, scenario):
    """``name -> part(state, gains, k, kinematics) -> (function, inputs)``: on a loop state
    (its kinematics and step number at hand), the part as a function of the inputs that
    reverse mode differentiates, and those inputs; ``function(*inputs)`` is its forward pass."""
    import jax.numpy as jnp

    from spacegrasp_jax.jobs import experiment
    from spacegrasp_jax.loop import simulate
    from spacegrasp_jax.loop.control import as_controller

    spec = simulate.RunSpec(robot, scenario, "admittance", options=experiment.loop_options(checkpoint=True))
    control = as_controller("admittance")

    def plant_kinematics(plant):
        return simulate.plant_kinematics(robot, scenario, plant)

    def plant_rate(plant, kinematics, u):
        return simulate.plant_rate(robot, scenario, plant, kinematics, u)

    def stage(plant, u):
        return plant_rate(plant, plant_kinematics(plant), u)

    def controller(state, gains):
        shared = plant_kinematics(state.plant)
        observed = simulate.observe(robot, scenario, state.plant, shared, 1.0)
        command, law_state = control.law.update(gains, observed.inputs, state.controller.law, scenario.dt)
        u, servo_state = control.torque(gains, command, state.plant.qd, state.controller.pid, 1.0, scenario.dt)
        return u, law_state, servo_state

    def torques(state):  # of the loop's size, not zeros, so that no product vanishes
        return jnp.full_like(state.plant.qd, 0.5)

    return dict(
        plant_kinematics=lambda state, gains, k, kin: (plant_kinematics, (state.plant,)),
        plant_rate=lambda state, gains, k, kin: (plant_rate, (state.plant, kin, torques(state))),
        stage=lambda state, gains, k, kin: (stage, (state.plant, torques(state))),
        controller=lambda state, gains, k, kin: (controller, (state, gains)),
        period=lambda state, gains, k, kin: (lambda s, g: simulate.loop_body(spec, g).period(s, k), (state, gains)),
    )


def _sum(tree):
    """The sum of every floating-point leaf of ``tree`` (a scalar)."""
    import jax
    import jax.numpy as jnp

    leaves = [leaf for leaf in jax.tree.leaves(tree) if jnp.issubdtype(leaf.dtype, jnp.floating)]
    return sum(jnp.sum(leaf) for leaf in leaves)


def _cotangent(tree):
    """A cotangent for ``tree``: 0.5 in every floating-point entry (no symbolic zeros)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    def one(leaf):
        if jnp.issubdtype(leaf.dtype, jnp.floating):
            return jnp.full(leaf.shape, 0.5, leaf.dtype)
        return np.zeros(leaf.shape, jax.dtypes.float0)

    return jax.tree.map(one, tree)


def sampled_states(robot, scenario, gains, count: int):
    """``count`` loop states of the paper's loop (stacked), one every ``STRIDE`` steps from
    the start, their kinematics and step numbers ``k`` (floats)."""
    import jax
    import jax.numpy as jnp

    from spacegrasp_jax.loop import simulate

    body = simulate.loop_body(simulate.RunSpec(robot, scenario, "admittance"), gains)
    dtype = scenario.initial.q.dtype

    @jax.jit
    def run(start):
        def stride(state, first):
            steps = first + jnp.arange(STRIDE, dtype=dtype)
            after, _ = jax.lax.scan(lambda s, k: (body.period(s, k)[0], None), state, steps)
            return after, state

        _, states = jax.lax.scan(stride, start, STRIDE * jnp.arange(count, dtype=dtype))
        return states

    states = run(body.start)
    kinematics = jax.jit(jax.vmap(lambda plant: simulate.plant_kinematics(robot, scenario, plant)))(states.plant)
    return states, kinematics, STRIDE * jnp.arange(count, dtype=dtype)


def measure(parts: list[str], count: int, repeats: int) -> list[dict]:
    import jax

    import spacegrasp_jax as sg
    from spacegrasp_jax.benchmarks.dynamics import timed_program
    from spacegrasp_jax.envelope.scenario import paper_scenario
    from spacegrasp_jax.loop.control import paper_gains

    robot, gains = sg.paper_robot(), paper_gains()
    scenario = paper_scenario(robot, contact_law="smooth", duration=17.0)
    if count * STRIDE > scenario.n_steps:
        raise ValueError(f"count: at most {scenario.n_steps // STRIDE} in a 17 s capture (one every {STRIDE} steps)")
    states, kinematics, steps = sampled_states(robot, scenario, gains, count)
    functions = _part_functions(robot, scenario)
    results = []
    for name in parts:
        part = functions[name]

        def forward_scan(states, kinematics, steps, gains, part=part):
            def one(total, x):
                state, kin, k = x
                function, inputs = part(state, gains, k, kin)
                return total + _sum(function(*inputs)), None

            return jax.lax.scan(one, 0.0, (states, kinematics, steps))[0]

        def reverse_scan(states, kinematics, steps, gains, part=part):
            def one(total, x):
                state, kin, k = x
                function, inputs = part(state, gains, k, kin)
                outputs, pull_back = jax.vjp(function, *inputs)
                return total + _sum(pull_back(_cotangent(outputs))), None

            return jax.lax.scan(one, 0.0, (states, kinematics, steps))[0]

        row = {"part": name}
        for label, scan in (("forward", forward_scan), ("reverse", reverse_scan)):
            timing = timed_program(scan, (states, kinematics, steps, gains), repeats)
            row[f"{label}_us"] = timing["min_s"] / count * 1e6
        row["reverse_over_forward"] = row["reverse_us"] / row["forward_us"]
        results.append(row)
        print(
            f"{name:>17} {row['forward_us']:>10.2f} {row['reverse_us']:>10.2f} {row['reverse_over_forward']:>9.2f}x",
            flush=True,
        )
    return results


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="results/benchmarks")
    parser.add_argument("--states", type=int, default=2000, help=f"loop states, one every {STRIDE} steps of 17 s")
    parser.add_argument("--repeats", type=int, default=5, help="timed calls of each scan (the fastest is kept)")
    parser.add_argument("--parts", default=",".join(PARTS), help=f"comma-separated, from {', '.join(PARTS)}")
    args = parser.parse_args(argv)
    parts = chosen_parts(parser, args.parts, PARTS)
    if not 1 <= args.states <= 17_000 // STRIDE:
        parser.error(f"--states must be between 1 and {17_000 // STRIDE} (one every {STRIDE} steps of 17 s)")
    if args.repeats < 1:
        parser.error("--repeats must be positive")
    configure(compile_cache=False)  # this process is the benchmark's: float64, loops compiled whole, no cache
    pin_to_one_core()

    print(
        f"{'part':>17} {'forward':>10} {'reverse':>10} {'ratio':>10}   (us per call, one core, fastest of {args.repeats})"
    )
    results = measure(parts, args.states, args.repeats)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report = {"machine": machine(), "states": args.states, "stride_steps": STRIDE, "results": results}
    (out / "gradient_parts.json").write_text(json.dumps(report, indent=2))
    print(f"wrote {out / 'gradient_parts.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
