"""The closed-loop step is built so that XLA's CPU runtime runs it as a sequence of kernels.

XLA:CPU executes a loop body as a task graph on its thread pool unless every buffer the
body's kernels use is at most 512 bytes (64 float64 numbers; the threshold is fixed in
``CpuExecutable``, ``ThunkExecutor::Options::execute_sequential_buffer_threshold``). The
task graph cost about half of a single rollout's time (README, Performance). These tests
compile the single-rollout programs and the one-scenario tuning gradient and read the
optimised HLO: no array produced in the loops that run the steps (and RK4's stage loops
inside them) may exceed 512 bytes. They fail when a change brings back a large
array (a 13x13 mass matrix, a stacked (8, 3, 3) rotation, a scanned-over time vector).
"""

from __future__ import annotations

import math
import re

import jax
import pytest

from spacegrasp_jax import compilation
from spacegrasp_jax.montecarlo import rollout_metrics
from spacegrasp_jax.scenario import paper_scenario
from spacegrasp_jax.simulate import rollout

SEQUENTIAL_LIMIT_BYTES = 512
BYTES = {"f64": 8, "s64": 8, "u64": 8, "f32": 4, "s32": 4, "u32": 4, "pred": 1, "s8": 1, "u8": 1}


def computations(hlo: str) -> dict[str, list[str]]:
    """Instruction lines of each computation of an optimised HLO module, by name."""
    bodies, name = {}, None
    for line in hlo.splitlines():
        header = re.match(r"^(?:ENTRY )?(%[\w.\-]+) .*\{$", line)
        if header:
            name = header.group(1)
            bodies[name] = []
        elif line.strip() == "}":
            name = None
        elif name:
            bodies[name].append(line)
    return bodies


def array_bytes(instruction: str) -> list[int]:
    """Sizes in bytes of the arrays an HLO instruction line produces (one per tuple element)."""
    match = re.match(r"\s*(?:ROOT )?%[\w.\-]+ = (.*?) [\w\-]+\(", instruction)
    if not match:
        return []
    return [BYTES[dtype] * math.prod(int(n) for n in dims.split(",") if n) for dtype, dims in re.findall(r"(\w+)\[([\d,]*)\]", match.group(1))]


def loops_within(name: str, bodies: dict[str, list[str]]) -> list[str]:
    """Bodies of the while loops that run inside computation ``name``, at any depth."""
    inner = re.findall(r"body=(%[\w.\-]+)", "\n".join(bodies[name]))
    return [loop for body in inner for loop in [body, *loops_within(body, bodies)]]


def step_loop_oversized(hlo: str) -> tuple[int, list[str]]:
    """The loop that runs the steps (the largest loop body) with the loops inside it (RK4's
    stage loop): their instruction count and their instructions that produce an array over
    the limit."""
    bodies = computations(hlo)
    loops = re.findall(r"body=(%[\w.\-]+)", hlo)
    assert loops, "no while loop in the compiled program"
    step = max(loops, key=lambda name: len(bodies[name]))
    lines = [line for body in [step, *loops_within(step, bodies)] for line in bodies[body]]
    too_big = [line.strip()[:160] for line in lines if any(size > SEQUENTIAL_LIMIT_BYTES for size in array_bytes(line))]
    return len(lines), too_big


def test_the_hlo_reader_finds_an_oversized_array():
    # The reader itself must see a large array when there is one: a loop carrying 65 numbers.
    def loop(x, n):  # a trip count known only at run time: the loop stays a loop
        return jax.lax.fori_loop(0, n, lambda i, y: y * 0.5 + 1.0, x)

    hlo = jax.jit(loop).lower(jax.numpy.ones(65), 10).compile().as_text()
    assert step_loop_oversized(hlo)[1]
    hlo = jax.jit(loop).lower(jax.numpy.ones(64), 10).compile().as_text()
    assert step_loop_oversized(hlo)[1] == []


@pytest.mark.parametrize("controller", ["admittance", "cartesian"])
@pytest.mark.parametrize("program", ["rollout", "rollout_metrics"])
def test_the_step_loop_holds_no_array_over_512_bytes(robot, gains, controller, program):
    scenario = paper_scenario(robot, duration=0.1)
    function = {"rollout": rollout, "rollout_metrics": rollout_metrics}[program]
    hlo = compilation.jit(function, static_argnames=("controller",)).lower(robot, scenario, gains, controller=controller).compile().as_text()
    instructions, too_big = step_loop_oversized(hlo)
    assert instructions > 300  # the whole step: controller, contact, the RK4 stages
    assert too_big == [], f"{len(too_big)} arrays over {SEQUENTIAL_LIMIT_BYTES} B in the step loop: {too_big[:5]}"


def test_the_gradient_step_loops_hold_no_array_over_512_bytes(robot, gains):
    # The one-scenario tuning gradient: its loops over the steps (forward and backward) and the
    # RK4 stage loops inside them must stay sequential. The outermost loops, over 8-step
    # blocks, hold the tape and are exempt. Without jax.checkpoint on RK4's stage loop, the
    # backward loops hold the stages' stacked residuals and this fails.
    from tuning.objective import Objective, Weights
    from tuning.parameters import initial_params, make_mask
    from tuning.tune import TuneConfig, checkpoint_segment, make_loss, make_value_and_grad, training_scenarios

    scenario = paper_scenario(robot, contact_law="smooth", duration=0.1)
    config = TuneConfig(batch=1)
    objective = Objective(weights=Weights(), torque_scale_Nm=(1.0,) * 7)
    loss = make_loss(robot, training_scenarios(scenario, config), gains, make_mask(gains, "admittance"), config,
                     objective, checkpoint_segment(scenario.n_steps))
    params = initial_params(gains, "admittance")
    hlo = make_value_and_grad(loss, params, "reverse").lower(params).compile().as_text()
    bodies = computations(hlo)
    nested = {inner for body in set(re.findall(r"body=(%[\w.\-]+)", hlo)) for inner in loops_within(body, bodies)}
    assert len(nested) >= 4  # forward and backward: the step loops and the stage loops in them
    lines = [line for body in nested for line in bodies[body]]
    too_big = [line.strip()[:160] for line in lines if any(size > SEQUENTIAL_LIMIT_BYTES for size in array_bytes(line))]
    assert too_big == [], f"{len(too_big)} arrays over {SEQUENTIAL_LIMIT_BYTES} B in the gradient's step loops: {too_big[:5]}"
