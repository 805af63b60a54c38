"""The package's process settings and compile options: nothing changed by importing the
package, each setting in effect once asked for, options dropped when XLA rejects them, and
loops compiled whole without effect on the results beyond rounding."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest

from spacegrasp_jax.envelope.scenario import paper_scenario
from spacegrasp_jax.jobs import compilation
from spacegrasp_jax.loop.simulate import rollout


def test_the_installed_xla_accepts_the_cpu_options():
    # If a jax upgrade drops the option, the probe turns it off silently: this test says so.
    assert compilation.compiler_options() == compilation.CPU_OPTIONS


def test_options_that_xla_rejects_are_dropped(monkeypatch):
    monkeypatch.setattr(compilation, "CPU_OPTIONS", {"xla_cpu_no_such_option": True})
    compilation.compiler_options.cache_clear()
    try:
        assert compilation.compiler_options() == {}
        assert compilation.jit(lambda x: 2.0 * x)(3.0) == 6.0
    finally:
        monkeypatch.undo()
        compilation.compiler_options.cache_clear()
    assert compilation.compiler_options() == compilation.CPU_OPTIONS


@pytest.mark.slow
def test_a_rollout_compiled_with_the_options_matches_the_default_compile(robot, gains):
    scenario = paper_scenario(robot, duration=0.3)
    arguments = (robot, scenario, gains)
    ours = compilation.jit(rollout, static_argnames=("controller",))(*arguments, controller="admittance")[1]
    default = jax.jit(rollout, static_argnames=("controller",))(*arguments, controller="admittance")[1]
    for name, value in vars(default).items():
        if value is not None:  # the flight-like loop's fields
            np.testing.assert_allclose(getattr(ours, name), value, rtol=1e-9, atol=1e-12, err_msg=name)


@pytest.mark.slow
def test_loops_compiled_whole_give_the_results_of_loops_run_kernel_by_kernel(robot, gains, tmp_path):
    # The same rollout in a process where XLA runs loops kernel by kernel (the user's opt-out,
    # spacegrasp_jax.jobs.compilation): same log to rounding.
    script = (
        "import sys, numpy as np, spacegrasp_jax as sg\n"
        "from spacegrasp_jax import compilation\n"
        "sg.configure()  # XLA_FLAGS already sets backend options: the user's choice stands\n"
        "from spacegrasp_jax.loop.control import paper_gains\n"
        "from spacegrasp_jax.envelope.scenario import paper_scenario\n"
        "from spacegrasp_jax.loop.simulate import rollout\n"
        "assert not compilation.loops_compile_whole()\n"
        "robot = sg.paper_robot()\n"
        "function = compilation.jit(rollout, static_argnames=('controller',))\n"
        "log = function(robot, paper_scenario(robot, duration=0.3), paper_gains(), controller='admittance')[1]\n"
        "np.savez(sys.argv[1], **{name: np.asarray(value) for name, value in vars(log).items() if value is not None})\n"
    )
    flags = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=0"
    env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")
    subprocess.run([sys.executable, "-c", script, str(tmp_path / "log.npz")], env=env, check=True, timeout=600)
    assert compilation.loops_compile_whole()
    ours = compilation.jit(rollout, static_argnames=("controller",))(
        robot, paper_scenario(robot, duration=0.3), gains, controller="admittance"
    )[1]
    kernel_by_kernel = np.load(tmp_path / "log.npz")
    for name, value in vars(ours).items():
        if value is None:
            continue
        np.testing.assert_allclose(value, kernel_by_kernel[name], rtol=1e-9, atol=1e-12, err_msg=name)


# A user's program: a loop over 4,096 numbers, compiled whole only with the package's option
# (XLA's own threshold is far smaller). It
# prints its optimised HLO, the state of the JAX options the package cares about, and the
# environment, before and after importing the package.
USER_PROGRAM = """
import json, os, sys
before = dict(os.environ)
if sys.argv[1] == "with-package":
    import spacegrasp_jax
import jax, jax.numpy as jnp
loop = jax.jit(lambda x: jax.lax.fori_loop(0, 5, lambda i, y: jnp.sin(y) + 1.0, x))
hlo = loop.lower(jnp.zeros(4096)).compile().as_text()
print(json.dumps({
    "environment_unchanged": dict(os.environ) == before,
    "x64": bool(jax.config.jax_enable_x64),
    "cache_dir": jax.config.jax_compilation_cache_dir,
    "hlo": hlo,
}))
"""


def test_importing_the_package_changes_nothing_in_the_process():
    """``import spacegrasp_jax`` leaves os.environ, JAX's options and XLA's flags as they
    were: a user's program compiles to the same code as in a process without the package."""
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_ENABLE_X64", "JAX_COMPILATION_CACHE_DIR")}
    reports = {}
    for case in ("with-package", "without"):
        result = subprocess.run(
            [sys.executable, "-c", USER_PROGRAM, case], capture_output=True, text=True, env=env, timeout=300
        )
        assert result.returncode == 0, result.stderr
        reports[case] = json.loads(result.stdout)
    ours, theirs = reports["with-package"], reports["without"]
    assert ours["environment_unchanged"]
    assert ours["x64"] is False and ours["cache_dir"] == theirs["cache_dir"]
    assert "xla_cpu_small_call" not in ours["hlo"]  # the loop runs kernel by kernel, as JAX's default
    assert ours["hlo"] == theirs["hlo"]


IMPORT_EVERY_MODULE = """
import importlib, pkgutil
import spacegrasp_jax
from jax._src import xla_bridge  # no public way to ask whether a backend has started
names = [m.name for m in pkgutil.walk_packages(spacegrasp_jax.__path__, "spacegrasp_jax.")]
for name in names:
    importlib.import_module(name)
print(len(names), xla_bridge.backends_are_initialized())
"""


def test_importing_any_module_starts_no_jax_backend():
    """No module makes an array at import: a backend started then would make
    ``jax.distributed.initialize`` (multi-host campaigns) fail and would write XLA's log before
    a command could hide it."""
    result = subprocess.run([sys.executable, "-c", IMPORT_EVERY_MODULE], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    count, started = result.stdout.split()
    assert int(count) > 30 and started == "False"


@pytest.mark.parametrize(
    "call, expected",
    [
        ("sg.configure()", "{xdg}/spacegrasp-jax/xla"),
        ("sg.configure(compile_cache=None)", "{xdg}/spacegrasp-jax/xla"),
        ("sg.configure(compile_cache=False)", "None"),
        ("sg.configure(compile_cache='none')", "None"),
        ("sg.configure(compile_cache='{tmp}/mine')", "{tmp}/mine"),
    ],
)
def test_configure_keeps_compiled_programs_in_the_per_user_cache_unless_told_not_to(tmp_path, call, expected):
    script = (
        f"import jax, spacegrasp_jax as sg\n{call.format(tmp=tmp_path)}\nprint(jax.config.jax_compilation_cache_dir)\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_COMPILATION_CACHE_DIR")}
    env["XDG_CACHE_HOME"] = str(tmp_path / "xdg")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == expected.format(xdg=tmp_path / "xdg", tmp=tmp_path)


def test_configure_turns_on_each_setting_and_constructors_demand_float64(tmp_path):
    script = """
import os, sys, warnings, jax
import spacegrasp_jax as sg
from spacegrasp_jax import compilation
try:
    sg.paper_robot()
except sg.Float64Required as error:
    print("refused:", error)
with warnings.catch_warnings():
    warnings.simplefilter("error")  # nothing has run yet: no warning
    sg.configure(compile_cache=sys.argv[1])
print("x64", jax.config.jax_enable_x64)
print("loops whole", compilation.loops_compile_whole())
print("cache", jax.config.jax_compilation_cache_dir)
print("robot dtype", sg.paper_robot().link_mass.dtype)
"""
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_ENABLE_X64", "JAX_COMPILATION_CACHE_DIR")}
    result = subprocess.run(
        [sys.executable, "-c", script, str(tmp_path / "cache")], capture_output=True, text=True, env=env, timeout=300
    )
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines[0].startswith("refused: a Robot: spacegrasp_jax computes in float64") and "configure()" in lines[0]
    assert lines[1:] == ["x64 True", "loops whole True", f"cache {tmp_path / 'cache'}", "robot dtype float64"]


def test_asking_for_loops_compiled_whole_after_xla_ignored_it_warns():
    # A user who set the threshold to 0 and then asks the package for loops compiled whole
    # keeps their setting; the package says the option is not in effect.
    script = """
import warnings, jax, jax.numpy as jnp
jax.jit(lambda x: x + 1.0)(1.0)  # JAX has started
import spacegrasp_jax as sg
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    sg.compile_loops_whole()
print([str(w.message) for w in caught])
"""
    env = dict(os.environ, XLA_FLAGS="--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=0")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300)
    assert result.returncode == 0, result.stderr
    assert "came too late" in result.stdout and "kernel by kernel" in result.stdout


class _Heard:
    """A compile listener that keeps what it hears."""

    def __init__(self):
        self.events = []

    def before(self, label, key):
        self.events.append(("before", label, key))

    def after(self, label, key, seconds):
        self.events.append(("after", label, key, seconds))


def test_compiles_are_announced_once_each_with_a_history_across_processes(tmp_path):
    """``compile_once`` tells the listeners of the one compile of a program (not of its
    reuse), and so does a tuning program bound to its values, whose key is derived from its
    settings and its arguments' shapes: other values run it again unannounced, other shapes
    compile another; the command line's announcer names the program and, from the history
    file, the last compile's time."""
    from spacegrasp_jax.tuning.tune import BoundProgram

    heard = _Heard()
    key = ("test.square", 3)
    with compilation.listening(heard):
        for _ in range(2):
            compilation.compile_once(key, lambda: jax.jit(lambda x: x * x).lower(np.ones(3)), label="the square")
        scale = jax.jit(lambda params, values: params["gain"] * values)
        for values in (np.ones(2), np.full(2, 3.0), np.ones(5)):
            bound = BoundProgram(scale, values, settings=("test.scale",), label="the scale")
            np.testing.assert_array_equal(bound({"gain": 2.0}), 2.0 * values)
    bound_keys = [event[2] for event in heard.events if event[1] == "the scale"]
    assert [event[:2] for event in heard.events] == [
        ("before", "the square"),
        ("after", "the square"),
        ("before", "the scale"),  # values of two shapes: two programs
        ("after", "the scale"),
        ("before", "the scale"),
        ("after", "the scale"),
    ]
    assert heard.events[0][2] == heard.events[1][2] == key and bound_keys[0] != bound_keys[2]
    assert all(event[3] >= 0.0 for event in heard.events if event[0] == "after")
    compilation.compile_once(("test.unheard",), lambda: jax.jit(lambda x: x + 1).lower(1.0))  # no listener: silent
    assert len(heard.events) == 6

    history = tmp_path / "times.json"
    first, second = io.StringIO(), io.StringIO()
    compilation.CompileAnnouncer(first, history).before("the square", key)
    compilation.CompileAnnouncer(first, history).after("the square", key, 12.34)
    compilation.CompileAnnouncer(second, history).before("the square", key)  # a later process, same program
    # a program with no build documented: the range of the package's programs
    assert first.getvalue() == (
        "compiling the square (first time on this machine: 4 to 90 s on a quiet 2-core VM, longer on a busy one)...\n"
    )
    assert compilation.documented_build_s("program:test.square") == (3.5, 90.0)
    assert compilation.documented_build_s("program:tuning.flight_gradient") == (20.0, 70.0)
    assert second.getvalue() == "compiling the square (last time 12.3 s on this machine)...\n"
    other_settings = io.StringIO()  # the same program for another static setting: not the same compile
    compilation.CompileAnnouncer(other_settings, history).before("the square", ("test.square", 4))
    assert other_settings.getvalue() == "compiling the square (first time for these settings, about 12 s)...\n"
    silent = io.StringIO()  # no history file: nothing to say about earlier compiles
    compilation.CompileAnnouncer(silent).before("the square", key)
    assert silent.getvalue() == "compiling the square...\n"


def test_a_program_keyed_by_a_function_is_known_again_in_a_later_process(tmp_path):
    """A batch program's key holds the function it maps, whose ``repr`` carries its memory
    address: another process's function of the same name has another. The history still
    finds the program's last time; another function's program is another program."""

    def part_factory():
        def candidate_parts(x):
            return x

        return candidate_parts

    def other_part(x):
        return x

    this_process, later_process = part_factory(), part_factory()
    assert repr(this_process) != repr(later_process)  # what a later process's key looks like
    history = tmp_path / "times.json"
    compilation.CompileAnnouncer(io.StringIO(), history).after("the population", ("batch", "p", this_process), 6.2)
    later, other = io.StringIO(), io.StringIO()
    compilation.CompileAnnouncer(later, history).before("the population", ("batch", "p", later_process))
    compilation.CompileAnnouncer(other, history).before("the population", ("batch", "p", other_part))
    assert later.getvalue() == "compiling the population (last time 6.2 s on this machine)...\n"
    assert other.getvalue() == "compiling the population (first time for these settings, about 6 s)...\n"


def test_numpy_and_jax_arrays_on_the_default_device_share_one_program():
    """One program for arguments placed alike: NumPy arrays and numbers, and jax.Arrays on
    the default device (the same executable takes either); a sharded placeholder is another."""
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    function = jax.jit(lambda x, y: 2.0 * x + y)
    as_numpy = (np.arange(3.0), np.float64(1.0))
    as_jax = (jax.numpy.arange(3.0), jax.numpy.asarray(1.0))
    lowered = []

    def lower(arguments):
        lowered.append(arguments)
        return function.lower(*arguments)

    def compiled(arguments):
        key = ("test.shared-program", compilation.argument_signature(arguments))
        return compilation.compile_once(key, lambda: lower(arguments))[0]

    executable = compiled(as_numpy)
    assert compiled(as_jax) is executable and len(lowered) == 1
    np.testing.assert_array_equal(executable(*as_jax), executable(*as_numpy))
    mesh = Mesh(np.array(jax.devices()[:1]), ("batch",))
    placeholder = jax.ShapeDtypeStruct((3,), np.float64, sharding=NamedSharding(mesh, PartitionSpec("batch")))
    assert compilation.argument_signature((placeholder,)) != compilation.argument_signature(as_numpy[:1])


#: Both laws' 17 s reproduction logs, and the reverse-mode derivatives of one closed-loop step
#: in contact (the next state with respect to the state and the gains), as a user's process
#: computes them, saved to the file named by the first argument.
RESULTS_AT_THIS_COMPILER_LEVEL = """
import os, sys
import jax, numpy as np
import spacegrasp_jax as sg
sg.configure(compile_cache=os.environ.get("JAX_COMPILATION_CACHE_DIR") or False)
from jax.flatten_util import ravel_pytree
from spacegrasp_jax import experiment
from spacegrasp_jax.loop.control import paper_gains
from spacegrasp_jax.envelope.scenario import paper_scenario
from spacegrasp_jax.loop.simulate import RunSpec, loop_body, rollout
robot, gains = sg.paper_robot(), paper_gains()
out = {"xla_flags": np.asarray(os.environ.get("XLA_FLAGS", ""))}
for law in ("admittance", "cartesian"):
    log = experiment.run(RunSpec(robot, paper_scenario(robot), law), gains).log
    out.update({f"{law}/{name}": np.asarray(v) for name, v in vars(log).items() if v is not None})
# The 2 s approach stopped at 1.15 s, pressing on the sphere (about 27 N).
short = paper_scenario(robot, duration=1.15, move_duration=2.0, contact_law="smooth")
state, log = jax.jit(rollout, static_argnames="controller")(robot, short, gains, "admittance")
out["step/contact_force_n"] = np.linalg.norm(np.asarray(log.contact_force)[-1])
def next_state(state, gains):
    period = loop_body(RunSpec(robot, short, "admittance"), gains).period
    return ravel_pytree(period(state, jax.numpy.asarray(float(short.n_steps)))[0])[0]
by_state, by_gains = jax.jit(jax.jacrev(next_state, argnums=(0, 1)))(state, gains)
out["step/by_state"] = ravel_pytree(by_state)[0]
out["step/by_gains"] = ravel_pytree(by_gains)[0]
np.savez(sys.argv[1], **out)
"""


@pytest.mark.slow
def test_the_suites_compiler_level_gives_the_users_results(tmp_path):
    """The suite compiles with LLVM's -O0 (``tests/conftest.py``); users' processes with
    XLA's default -O3. The same programs at both levels: the reproduction's every logged field
    and the reverse-mode derivatives of a step in contact agree to rounding, so what the suite
    checks at -O0 holds for what users run. Measured: both to 3e-12 of each field's largest
    magnitude; the tolerance, 1e-9, leaves room for other CPUs' instructions."""
    suite_flags = os.environ.get("XLA_FLAGS", "")
    if "xla_backend_optimization_level=0" not in suite_flags:
        pytest.skip(f"this run compiles at another level (XLA_FLAGS={suite_flags!r}): nothing to compare")
    results = {}
    for level, flags in (("suite", suite_flags), ("users", "")):
        # The suite's level may load the programs other tests compiled (the run's cache is
        # keyed by the flags too); the users' level compiles its own, with no cache.
        dropped = ("XLA_FLAGS",) if level == "suite" else ("XLA_FLAGS", "JAX_COMPILATION_CACHE_DIR")
        env = {k: v for k, v in os.environ.items() if k not in dropped}
        env["XLA_FLAGS"] = flags
        path = tmp_path / f"{level}.npz"
        result = subprocess.run(
            [sys.executable, "-c", RESULTS_AT_THIS_COMPILER_LEVEL, str(path)],
            capture_output=True,
            text=True,
            env=env,
            timeout=600,
        )
        assert result.returncode == 0, result.stderr[-3000:]
        results[level] = dict(np.load(path))
    suite, users = results["suite"], results["users"]
    assert "xla_backend_optimization_level=0" in str(suite.pop("xla_flags"))
    assert "optimization_level" not in str(users.pop("xla_flags"))
    assert suite.keys() == users.keys() and len(suite) > 20
    assert users["step/contact_force_n"] > 10.0  # the step is differentiated in contact
    for name, ours in suite.items():
        scale = float(np.max(np.abs(users[name])))
        np.testing.assert_allclose(ours, users[name], rtol=0, atol=1e-9 * scale, err_msg=name)
    differing = [name for name in suite if not np.array_equal(suite[name], users[name])]
    assert differing, "the two levels gave identical bits: is the suite's flag still in effect?"


def test_compile_estimates_follow_the_machines_pace(tmp_path):
    """Each program keeps its last compile times; once a compile of this process has taken 4x
    its history (a loaded machine), the next estimate is scaled by that pace; a spread of
    times is given as a range. A history of one number, as older versions wrote, still reads."""
    history = tmp_path / "times.json"
    square, cube = ("test.square", 3), ("test.cube", 3)
    old = {compilation.CompileAnnouncer.digest(square): 3.0}  # an older version's single number
    old[compilation.CompileAnnouncer.digest(cube)] = [2.0, 2.0]
    history.write_text(json.dumps(old))
    stream = io.StringIO()
    announcer = compilation.CompileAnnouncer(stream, history)
    announcer.before("the square", square)
    announcer.after("the square", square, 12.0)  # 4x its history
    announcer.before("the cube", cube)
    lines = stream.getvalue().splitlines()
    assert lines[0] == "compiling the square (last time 3.0 s on this machine)..."
    assert lines[1] == (
        "compiling the cube (about 8.0 s: 2.0 s before on this machine, and this run's compiles take 4.0x their "
        "usual time)..."
    )
    assert json.loads(history.read_text())[compilation.CompileAnnouncer.digest(square)] == [3.0, 12.0]
    later = io.StringIO()  # a later process, no pace yet: the range of the square's times
    compilation.CompileAnnouncer(later, history).before("the square", square)
    assert later.getvalue() == "compiling the square (3.0 to 12.0 s the last 2 times on this machine)...\n"
    for seconds in range(10):  # the history keeps the last five
        announcer.after("the cube", cube, float(seconds))
    assert json.loads(history.read_text())[compilation.CompileAnnouncer.digest(cube)] == [5.0, 6.0, 7.0, 8.0, 9.0]
