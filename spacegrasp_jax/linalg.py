"""Cholesky factorisation and solves for the small symmetric positive-definite systems of
the closed loop (the 13x13 mass matrix, its 6x6 satellite block, the 6x6 Gram matrix of the
pseudoinverse), written as unrolled ``jnp`` arithmetic instead of LAPACK calls.

Why not ``jax.scipy.linalg``: on CPU, every LAPACK call is an opaque custom call that XLA can
neither fuse nor vectorise across a ``vmap`` batch. Under ``vmap`` jaxlib runs the batch
through its own thread pool (``ParallelBatchMap``), and with jax 0.10.2 on a 2-core machine
that deadlocks for batches of about 512 and more (all threads parked on futexes; see the
README's modelling notes). Unrolled over the static size ``n`` (at most 13 here), the
factorisation is a few hundred fused element-wise operations, identical for one system or a
batch, and differentiable by ordinary autodiff.

All functions take one (unbatched) system; ``vmap`` adds batch axes.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def cholesky(A: jax.Array) -> jax.Array:
    """Lower-triangular ``L`` (n, n) with ``L L^T = A`` for symmetric positive-definite
    ``A`` (n, n); only the lower triangle of ``A`` is read. NaN if ``A`` is not positive
    definite (a diverging simulation then shows as non-finite values)."""
    n = A.shape[-1]
    below_diagonal = jnp.tri(n, dtype=A.dtype)  # column j keeps rows i >= j
    columns = []
    for j in range(n):
        v = A[:, j]
        for column in columns:
            v = v - column * column[j]
        columns.append(v / jnp.sqrt(v[j]) * below_diagonal[:, j])
    return jnp.stack(columns, axis=1)


def solve_lower(L: jax.Array, B: jax.Array) -> jax.Array:
    """``X = L^-1 B`` for lower-triangular ``L`` (n, n) and ``B`` (n,) or (n, m)."""
    rows = []
    for i in range(L.shape[-1]):
        row = B[i]
        for k, solved in enumerate(rows):
            row = row - L[i, k] * solved
        rows.append(row / L[i, i])
    return jnp.stack(rows)


def solve_upper_transposed(L: jax.Array, B: jax.Array) -> jax.Array:
    """``X = L^-T B`` for lower-triangular ``L`` (n, n) and ``B`` (n,) or (n, m)."""
    n = L.shape[-1]
    rows = [None] * n
    for i in reversed(range(n)):
        row = B[i]
        for k in range(i + 1, n):
            row = row - L[k, i] * rows[k]
        rows[i] = row / L[i, i]
    return jnp.stack(rows)


def cho_solve(L: jax.Array, B: jax.Array) -> jax.Array:
    """``A^-1 B`` given ``L = cholesky(A)``; ``B`` (n,) or (n, m)."""
    return solve_upper_transposed(L, solve_lower(L, B))


def solve_spd(A: jax.Array, B: jax.Array) -> jax.Array:
    """``A^-1 B`` for symmetric positive-definite ``A`` (n, n); ``B`` (n,) or (n, m)."""
    return cho_solve(cholesky(A), B)
