"""How XLA:CPU compiles the loops that run the closed loop's steps, read from the optimised HLO
of the single-rollout programs and of the one-scenario tuning gradient.

1. **Compiled whole.** Importing the package asks XLA:CPU to compile a small loop that calls
   no library into one kernel (``spacegrasp_jax.jobs.compilation``): the step loops, and RK4's
   stage loops inside them, must lie in the computations XLA marks ``xla_cpu_small_call``,
   and the programs must hold no custom call (a LAPACK solve, a YNNPACK fusion), which
   would keep a loop kernel by kernel. These tests fail when such a call creeps back or
   when an XLA upgrade drops the option.
2. **Sequential when not.** Where loops run kernel by kernel (another XLA, or a user who
   turns the option off), XLA:CPU runs a loop body as a task graph on its thread pool
   unless every buffer its kernels use is at most 512 bytes (64 float64 numbers; fixed in
   ``CpuExecutable``, ``ThunkExecutor::Options::execute_sequential_buffer_threshold``),
   which cost about half of a rollout's time. No array produced in the step loops may
   exceed 512 bytes: the tests fail when a change brings back a large array (a 13x13 mass
   matrix, a stacked (8, 3, 3) rotation, a scanned-over time vector).
3. **Loops over runs are not compiled whole.** A ``lax.map`` over short runs falls under the
   threshold and is compiled whole, its inner loops inside one function that takes LLVM up
   to three times as long; ``compilation.map_one_at_a_time`` keeps the outer loop kernel by
   kernel and its outputs ``lax.map``'s, bit for bit.
"""

from __future__ import annotations

import math
import re

import jax
import pytest

from spacegrasp_jax.envelope.scenario import paper_scenario
from spacegrasp_jax.jobs import compilation
from spacegrasp_jax.jobs.montecarlo import FoldedMetrics
from spacegrasp_jax.loop.simulate import RunSpec, closed_loop, rollout

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
    return [
        BYTES[dtype] * math.prod(int(n) for n in dims.split(",") if n)
        for dtype, dims in re.findall(r"(\w+)\[([\d,]*)\]", match.group(1))
    ]


def loops_within(name: str, bodies: dict[str, list[str]]) -> list[str]:
    """Bodies of the while loops, and branches of the conditionals, that run inside
    computation ``name``, at any depth (through the calls that wrap loops compiled whole
    too). A forward loop's controller runs in a conditional's branch inside RK4's stage loop
    (``integrator.rk4_step_with_start``)."""
    text = "\n".join(bodies[name])
    inner = re.findall(r"body=(%[\w.\-]+)", text)
    branches = [b.strip() for group in re.findall(r"branch_computations=\{([^}]*)\}", text) for b in group.split(",")]
    calls = re.findall(r" call\(.*?to_apply=(%[\w.\-]+)", text)
    return [loop for body in inner + branches for loop in [body, *loops_within(body, bodies)]] + [
        loop for called in calls for loop in loops_within(called, bodies)
    ]


def loops_compiled_whole(hlo: str) -> set[str]:
    """Bodies of the loops that XLA compiles into one kernel: those inside the calls it marks
    ``xla_cpu_small_call``."""
    bodies = computations(hlo)
    marked = re.findall(r'to_apply=(%[\w.\-]+), frontend_attributes=\{xla_cpu_small_call="true"\}', hlo)
    return {loop for called in marked for loop in loops_within(called, bodies)}


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


@pytest.fixture(scope="module")
def compiled_hlo(robot, gains):
    """Optimised HLO text of a program, compiled once for this module's tests: ``"rollout"``
    and ``"folded_metrics"`` (a campaign's loop) per controller, and the one-scenario tuning
    ``"gradient"``, as traced in this process (loops compiled whole) and as traced where
    loops run kernel by kernel (``"gradient_kernel_by_kernel"``)."""
    texts = {}

    def get(program: str, controller: str = "admittance") -> str:
        if (program, controller) not in texts:
            if program == "gradient":
                texts[program, controller] = _gradient_hlo(robot, gains)
            elif program == "gradient_kernel_by_kernel":
                texts[program, controller] = _gradient_hlo(robot, gains, loops_whole=False)
            else:
                scenario = paper_scenario(robot, duration=0.1)
                function = {"rollout": rollout, "folded_metrics": _folded_metrics}[program]
                jitted = compilation.jit(function, static_argnames=("controller",))
                texts[program, controller] = (
                    jitted.lower(robot, scenario, gains, controller=controller).compile().as_text()
                )
        return texts[program, controller]

    return get


def _folded_metrics(robot, scenario, gains, controller):
    """A campaign sample's loop: its metrics folded in the scan."""
    return closed_loop(RunSpec(robot, scenario, controller, observer=FoldedMetrics()), gains)[1]


def _gradient_hlo(robot, gains, loops_whole: bool = True) -> str:
    """The tuning gradient's program as traced in a process whose loops compile whole, or
    (``loops_whole=False``) as traced where they run kernel by kernel."""
    from spacegrasp_jax.tuning.objective import Objective, Weights
    from spacegrasp_jax.tuning.parameters import initial_params, make_mask
    from spacegrasp_jax.tuning.tune import (
        TuneConfig,
        block_steps,
        make_loss,
        make_value_and_grad,
        training_scenarios,
    )

    scenario = paper_scenario(robot, contact_law="smooth", duration=0.1)
    config = TuneConfig(batch=1, objective="weighted", method="gradient")
    objective = Objective(weights=Weights(), torque_scale_Nm=(1.0,) * 7)
    # The host asks once, when it builds the loss (experiment.loop_options), never the loop
    # while it is traced.
    with pytest.MonkeyPatch.context() as patch:
        if not loops_whole:
            patch.setattr(compilation, "loops_compile_whole", lambda: False)
        loss = make_loss(
            robot,
            training_scenarios(scenario, config),
            gains,
            make_mask(gains, "admittance"),
            config,
            objective,
            block_steps(scenario.n_steps),
        )
    params = initial_params(gains, "admittance")
    if loops_whole:
        return make_value_and_grad(loss, params, "reverse").lower(params).compile().as_text()
    # A jit of its own: the package's gradient program keeps its first trace for the process.
    gradient = compilation.jit(jax.value_and_grad(loss.function, has_aux=True))
    return gradient.lower(params, loss.values).compile().as_text()


def gradient_step_loops(hlo: str) -> set[str]:
    """The gradient's loops over the steps (forward and backward) and RK4's stage loops inside
    them: every loop inside another loop (the outermost loops run over blocks of steps)."""
    bodies = computations(hlo)
    return {inner for body in set(re.findall(r"body=(%[\w.\-]+)", hlo)) for inner in loops_within(body, bodies)}


def test_the_hlo_reader_finds_loops_compiled_whole():
    # The reader must tell a loop compiled whole from one that is not: a LAPACK call (a custom
    # call) in the body keeps it kernel by kernel.
    def loop(x, n):
        return jax.lax.fori_loop(0, n, lambda i, y: y * 0.5 + 1.0, x)

    def loop_with_lapack(x, n):
        return jax.lax.fori_loop(
            0, n, lambda i, y: y * 0.5 + jax.numpy.linalg.cholesky(jax.numpy.diag(2.0 + y * y))[0], x
        )

    assert len(loops_compiled_whole(jax.jit(loop).lower(jax.numpy.ones(3), 10).compile().as_text())) == 1
    assert loops_compiled_whole(jax.jit(loop_with_lapack).lower(jax.numpy.ones(3), 10).compile().as_text()) == set()


def test_importing_the_package_makes_xla_compile_small_loops_whole():
    # If an XLA upgrade renames the backend option, XLA ignores it silently: this says so.
    assert compilation.loops_compile_whole()


def _runs_of(items):
    # A loop over "runs": each item runs an inner loop of 50 steps.
    return jax.lax.fori_loop(0, 50, lambda i, y: y * 0.5 + jax.numpy.sin(y), items)


def test_a_map_over_runs_is_not_compiled_whole_but_its_runs_are():
    # jax.lax.map over short runs is compiled whole, inner loop inside (the premise); the
    # package's map over runs leaves the outer loop kernel by kernel and the inner one whole.
    items = jax.numpy.linspace(-1.0, 1.0, 12).reshape(4, 3)
    plain = jax.jit(lambda x: jax.lax.map(_runs_of, x)).lower(items).compile().as_text()
    ours = jax.jit(lambda x: compilation.map_one_at_a_time(_runs_of, x)).lower(items).compile().as_text()
    assert len(loops_compiled_whole(plain)) == 2
    bodies = computations(ours)
    loops = set(re.findall(r"body=(%[\w.\-]+)", ours))
    outer = [body for body in loops if loops_within(body, bodies)]
    assert len(loops) == 2 and len(outer) == 1
    assert loops_compiled_whole(ours) == loops - set(outer) == set(loops_within(outer[0], bodies))


def test_the_map_over_runs_returns_what_lax_map_returns_and_the_same_gradient():
    items = {"x": jax.numpy.linspace(-2.0, 2.0, 15).reshape(5, 3), "n": jax.numpy.arange(5)}

    def run(item):
        return {"y": _runs_of(item["x"]) * item["n"], "n": item["n"] + 1, "negative_zero": -0.0 * item["x"]}

    expected = jax.jit(lambda i: jax.lax.map(run, i))(items)
    got = jax.jit(lambda i: compilation.map_one_at_a_time(run, i))(items)
    for key in expected:  # bit for bit, the sign of a zero too
        assert got[key].dtype == expected[key].dtype
        assert jax.numpy.array_equal(jax.numpy.signbit(got[key]), jax.numpy.signbit(expected[key]))
        assert jax.numpy.array_equal(got[key], expected[key])

    def loss(x, mapper):
        return jax.numpy.sum(mapper(lambda row: _runs_of(row) ** 2, x))

    x = items["x"]
    expected_gradient = jax.jit(jax.grad(lambda x: loss(x, jax.lax.map)))(x)
    assert jax.numpy.array_equal(
        jax.jit(jax.grad(lambda x: loss(x, compilation.map_one_at_a_time)))(x), expected_gradient
    )


@pytest.mark.parametrize("controller", ["admittance", "cartesian"])
@pytest.mark.parametrize("program", ["rollout", pytest.param("folded_metrics", marks=pytest.mark.slow)])
def test_the_step_loop_is_compiled_whole(compiled_hlo, controller, program):
    hlo = compiled_hlo(program, controller)
    bodies = computations(hlo)
    step = max(re.findall(r"body=(%[\w.\-]+)", hlo), key=lambda name: len(bodies[name]))
    assert step in loops_compiled_whole(hlo)
    assert "custom-call" not in hlo


@pytest.mark.slow
def test_the_gradient_step_loops_are_compiled_whole(compiled_hlo):
    hlo = compiled_hlo("gradient")
    step_loops = gradient_step_loops(hlo)
    assert len(step_loops) >= 4  # forward and backward: the step loops and the stage loops in them
    assert step_loops <= loops_compiled_whole(hlo)
    assert "custom-call" not in hlo


@pytest.mark.parametrize("controller", ["admittance", "cartesian"])
@pytest.mark.parametrize("program", ["rollout", pytest.param("folded_metrics", marks=pytest.mark.slow)])
def test_the_step_loop_holds_no_array_over_512_bytes(compiled_hlo, controller, program):
    instructions, too_big = step_loop_oversized(compiled_hlo(program, controller))
    assert instructions > 300  # the whole step: controller, contact, the RK4 stages
    assert too_big == [], f"{len(too_big)} arrays over {SEQUENTIAL_LIMIT_BYTES} B in the step loop: {too_big[:5]}"


@pytest.mark.slow
def test_the_gradient_step_loops_hold_no_array_over_512_bytes(compiled_hlo):
    # Where loops run kernel by kernel, the rule that keeps them in XLA's sequential mode.
    # The outermost loops, over blocks of steps, hold the tape and are exempt. Without
    # jax.checkpoint on RK4's stage loop, the backward loops hold the stages' stacked
    # residuals and this fails; so it does with the controller's kinematics reused by RK4's
    # first stage, which the program compiled whole does (two steps of 7x7 blocks on the tape).
    hlo = compiled_hlo("gradient_kernel_by_kernel")
    bodies = computations(hlo)
    step_loops = gradient_step_loops(hlo)
    assert len(step_loops) >= 4
    lines = [line for body in step_loops for line in bodies[body]]
    too_big = [line.strip()[:160] for line in lines if any(size > SEQUENTIAL_LIMIT_BYTES for size in array_bytes(line))]
    assert too_big == [], (
        f"{len(too_big)} arrays over {SEQUENTIAL_LIMIT_BYTES} B in the gradient's step loops: {too_big[:5]}"
    )
