"""The package's compile options: in effect with the installed XLA, dropped when XLA rejects
them, and without effect on the results beyond rounding."""

from __future__ import annotations

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
