"""The package's compile options and its loops compiled whole: in effect with the installed
XLA, options dropped when XLA rejects them, and without effect on the results beyond
rounding."""

from __future__ import annotations

import os
import subprocess
import sys

import jax
import numpy as np

from spacegrasp_jax import compilation
from spacegrasp_jax.scenario import paper_scenario
from spacegrasp_jax.simulate import rollout


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


def test_a_rollout_compiled_with_the_options_matches_the_default_compile(robot, gains):
    scenario = paper_scenario(robot, duration=0.3)
    arguments = (robot, scenario, gains)
    ours = compilation.jit(rollout, static_argnames=("controller",))(*arguments, controller="admittance")[1]
    default = jax.jit(rollout, static_argnames=("controller",))(*arguments, controller="admittance")[1]
    for name, value in vars(default).items():
        np.testing.assert_allclose(getattr(ours, name), value, rtol=1e-9, atol=1e-12, err_msg=name)


def test_loops_compiled_whole_give_the_results_of_loops_run_kernel_by_kernel(robot, gains, tmp_path):
    # The same rollout in a process where XLA runs loops kernel by kernel (the user's opt-out,
    # spacegrasp_jax.compilation): same log to rounding.
    script = (
        "import sys, numpy as np, spacegrasp_jax as sg\n"
        "from spacegrasp_jax import compilation\n"
        "from spacegrasp_jax.control import paper_gains\n"
        "from spacegrasp_jax.scenario import paper_scenario\n"
        "from spacegrasp_jax.simulate import rollout\n"
        "assert not compilation.loops_compile_whole()\n"
        "robot = sg.paper_robot()\n"
        "function = compilation.jit(rollout, static_argnames=('controller',))\n"
        "log = function(robot, paper_scenario(robot, duration=0.3), paper_gains(), controller='admittance')[1]\n"
        "np.savez(sys.argv[1], **{name: np.asarray(value) for name, value in vars(log).items()})\n"
    )
    flags = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=0"
    env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")
    subprocess.run([sys.executable, "-c", script, str(tmp_path / "log.npz")], env=env, check=True, timeout=600)
    assert compilation.loops_compile_whole()
    ours = compilation.jit(rollout, static_argnames=("controller",))(robot, paper_scenario(robot, duration=0.3), gains, controller="admittance")[1]
    kernel_by_kernel = np.load(tmp_path / "log.npz")
    for name, value in vars(ours).items():
        np.testing.assert_allclose(value, kernel_by_kernel[name], rtol=1e-9, atol=1e-12, err_msg=name)
