"""Telling reverse mode, before it traces a loop, which parts of the loop's carry carry a
derivative.

JAX differentiates a ``lax.scan`` by linearising its body for the set of carry parts that
have a derivative. A part that starts without one (the loop's initial state, fixed by the
scenario; RK4's sums, starting at zero) but gets one after an iteration makes JAX linearise
the body again with the larger set, until the set stops growing. The closed loop's step is
most of a gradient's program, so the 17 s tuning gradient traced the step's derivative four
times (twice per closed-loop iteration, twice per RK4 iteration inside each): 3 of its 7 s
of tracing. [`with_derivative_of()`][spacegrasp_jax.tangents.with_derivative_of] gives a part
the derivative it will have from its start, and JAX linearises each body once. The values are
the same, and so is the compiled program but for a few multiplications by zero of its
tangents (documentation, Performance).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


@jax.custom_jvp
def with_derivative_of(value, anchor):
    """``value`` itself; under differentiation, a derivative of zeros wherever ``anchor``
    (any pytree) has a derivative, and none where it has none.

    Args:
        value: a pytree of floating arrays (any shapes).
        anchor: a pytree whose derivative decides ``value``'s.

    Returns:
        ``value``, unchanged (no operation in a program that is not differentiated).
    """
    return value


@with_derivative_of.defjvp
def _with_derivative_of_jvp(primals, tangents):
    value, _ = primals
    _, anchor_dot = tangents
    # A zero that depends on the anchor's derivative: a zeros array alone is folded into
    # "no derivative" by JAX.
    floating = [
        leaf for leaf in map(jnp.asarray, jax.tree.leaves(anchor_dot)) if jnp.issubdtype(leaf.dtype, jnp.inexact)
    ]
    zero = 0.0 * sum(jnp.sum(leaf) for leaf in floating)
    return value, jax.tree.map(lambda leaf: jnp.zeros_like(leaf) + zero.astype(leaf.dtype), value)
