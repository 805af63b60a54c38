"""The closed loop tells reverse mode up front which parts of its carry carry a derivative
(``spacegrasp_jax.core.tangents``): the derivative is the one JAX finds by itself, and each of the
closed loop's scan bodies (RK4's stages apart) is linearised once where JAX would linearise
it until the set stopped growing.

The counts read JAX's own functions for linearising and differentiating a loop body
(``jax._src.interpreters.ad``); where a JAX release renames them, the counting tests stop
with an error naming them rather than passing without counting.
"""

from __future__ import annotations

import collections
import contextlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spacegrasp_jax.core.tangents import with_derivative_of
from spacegrasp_jax.envelope.scenario import paper_scenario
from spacegrasp_jax.loop import simulate
from spacegrasp_jax.loop.realism import flight
from spacegrasp_jax.loop.simulate import FullLog, LoopOptions, RunSpec, closed_loop


def test_the_value_is_unchanged_and_its_derivative_is_zero():
    value = {"a": jnp.arange(3.0), "b": jnp.ones((2, 2))}
    same = with_derivative_of(value, 2.0)
    assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(same), jax.tree.leaves(value)))
    out, tangent = jax.jvp(lambda g: with_derivative_of(value, g), (2.0,), (1.0,))
    np.testing.assert_array_equal(out["a"], value["a"])
    assert all(np.all(np.asarray(leaf) == 0.0) for leaf in jax.tree.leaves(tangent))


def test_a_scan_started_with_a_derivative_has_the_analytic_gradient():
    # c_{k+1} = c_k / 2 + g from c_0 = 0: c_n = 2 g (1 - 2^-n), so dc_n/dg = 2 (1 - 2^-n).
    def final(g):
        start = with_derivative_of(jnp.zeros(3), g)
        end, _ = jax.lax.scan(lambda c, _: (0.5 * c + g, None), start, None, length=10)
        return end.sum()

    assert jax.grad(final)(1.5) == pytest.approx(3 * 2 * (1 - 2.0**-10), rel=1e-15)


def test_the_values_own_derivative_is_kept():
    # c_{k+1} = c_k / 2 + g from c_0 = x: dc_n/dx = 2^-n, whether or not g is differentiated.
    def final(g, x):
        start = with_derivative_of(x * jnp.ones(3), g)
        end, _ = jax.lax.scan(lambda c, _: (0.5 * c + g, None), start, None, length=10)
        return end.sum()

    assert jax.grad(final, 1)(1.5, 0.3) == pytest.approx(3 * 2.0**-10, rel=1e-15)
    assert jax.grad(final, (0, 1))(1.5, 0.3)[1] == pytest.approx(3 * 2.0**-10, rel=1e-15)


def test_an_anchor_without_a_floating_derivative_leaves_the_value_alone():
    # An integer anchor has no derivative to lend: the value keeps its own, d(3 x)/dx = 3.
    assert jax.grad(lambda x: with_derivative_of(x * jnp.ones(3), 7).sum())(0.3) == 3.0


@contextlib.contextmanager
def counting_linearisations():
    """Counts, per ``lax.scan`` body (a jaxpr object) and its length, how often JAX linearises or
    differentiates it (its rules for ``scan`` call these once per round of their search for
    the carry's derivatives)."""
    from jax._src.interpreters import ad
    from jax._src.lax.control_flow import loops

    names = ("linearize_jaxpr", "jvp_jaxpr")
    missing = [name for name in names if not hasattr(ad, name)] + [n for n in ("scan_p",) if not hasattr(loops, n)]
    if missing:
        raise AssertionError(f"this JAX has no {', '.join(missing)} where the count reads them: update the count")
    bodies, counts = {}, collections.Counter()
    tables = (ad.primitive_linearizations, ad.primitive_jvps)
    rules = [table[loops.scan_p] for table in tables]
    functions = {name: getattr(ad, name) for name in names}

    def noting_the_body(rule):
        def wrapper(*args, jaxpr, length, **params):
            bodies[id(jaxpr)] = length
            return rule(*args, jaxpr=jaxpr, length=length, **params)

        return wrapper

    def counted(function):
        def wrapper(jaxpr, *args, **kwargs):
            if id(jaxpr) in bodies:
                counts[id(jaxpr), bodies[id(jaxpr)]] += 1
            return function(jaxpr, *args, **kwargs)

        return wrapper

    try:
        for table, rule in zip(tables, rules):
            table[loops.scan_p] = noting_the_body(rule)
        for name, function in functions.items():
            setattr(ad, name, counted(function))
        yield counts
    finally:
        for table, rule in zip(tables, rules):
            table[loops.scan_p] = rule
        for name, function in functions.items():
            setattr(ad, name, function)


def without_hints(monkeypatch):
    """The loops as JAX would differentiate them without being told (the reference)."""
    monkeypatch.setattr(simulate, "with_derivative_of", lambda value, anchor: value)


SPECS = {
    "ideal": lambda robot: RunSpec(
        robot,
        paper_scenario(robot, contact_law="smooth", duration=0.004),
        observer=FullLog(2),
        options=LoopOptions(checkpoint=True),
    ),
    "flight": lambda robot: RunSpec(
        robot,
        paper_scenario(robot, contact_law="smooth", duration=0.02),
        realism=flight(),
        observer=FullLog(),
        options=LoopOptions(checkpoint=True),
    ),
}


RK4_STAGES = 4  # the length of RK4's scan; the loops' scans in SPECS are 2 and 10 long


def most_linearisations_of_a_loop_body(spec, gains) -> int:
    """The most times JAX linearised one of the closed loop's scan bodies (periods, steps,
    blocks of them: not RK4's stages) to trace the gradient of a loss of its log."""

    def loss(gains):
        _, log = closed_loop(spec, gains, jax.random.key(0))
        return jnp.sum(log.u**2) + jnp.sum(log.pose_ee**2)

    with counting_linearisations() as counts:
        jax.jit(jax.grad(loss)).trace(gains)
    return max(count for (_, length), count in counts.items() if length != RK4_STAGES)


@pytest.mark.parametrize("loop", ["ideal", "flight"])
def test_each_closed_loop_body_is_linearised_once(robot, gains, loop):
    # What the derivative is, is checked against finite differences where the tuning's
    # gradient is (tests/test_tuning.py).
    assert most_linearisations_of_a_loop_body(SPECS[loop](robot), gains) == 1


def test_without_being_told_jax_linearises_a_body_again(robot, gains, monkeypatch):
    without_hints(monkeypatch)  # shows that the count above can fail
    assert most_linearisations_of_a_loop_body(SPECS["ideal"](robot), gains) >= 2
