"""Telling reverse mode, before it traces a loop, which parts of the loop's carry carry a
derivative.

JAX differentiates a ``lax.scan`` by linearising its body for the set of carry parts that
have a derivative. A part that starts without one but gets one after an iteration makes JAX
linearise the body again with the larger set, until the set stops growing. The closed
loop's initial state is fixed by the scenario, and the gains give it a derivative after one
control period, so the period, most of a gradient's program, was linearised twice, and RK4's
stages inside it four times: about 2.5 of the 7 s the 17 s tuning gradient took to trace.
[`with_derivative_of()`][spacegrasp_jax.core.tangents.with_derivative_of] gives the initial
state the derivative the gains will give it, and JAX linearises the period once (RK4's
stages twice: their sums start at zero, and giving those a derivative too saved 0.3 s more
and cost a few percent of the gradient's run). The values and the derivatives are the same,
bit for bit; the compiled program gains a few multiplications by zero (documentation,
Performance).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


@jax.custom_jvp
def with_derivative_of(value, anchor):
    """``value`` itself; under differentiation, ``value``'s own derivative, which JAX then
    holds to be present wherever ``anchor`` (any pytree) has a derivative (zeros where
    ``value`` has none).

    Args:
        value: a pytree of arrays (any shapes; an integer leaf, such as a delay line's
            head, has no derivative and passes as it is).
        anchor: a pytree whose derivative makes ``value``'s present.

    Returns:
        ``value``, unchanged (no operation in a program that is not differentiated).
    """
    return value


@with_derivative_of.defjvp
def _with_derivative_of_jvp(primals, tangents):
    value, _ = primals
    value_dot, anchor_dot = tangents
    # A zero that depends on the anchor's derivative: a zeros array alone is folded into
    # "no derivative" by JAX.
    floating = [
        leaf for leaf in map(jnp.asarray, jax.tree.leaves(anchor_dot)) if jnp.issubdtype(leaf.dtype, jnp.inexact)
    ]
    zero = jnp.asarray(0.0 * sum(jnp.sum(leaf) for leaf in floating))  # 0.0 for an integer anchor
    return value, jax.tree.map(
        lambda leaf: leaf if leaf.dtype == jax.dtypes.float0 else leaf + zero.astype(leaf.dtype), value_dot
    )
