"""Cholesky factorisation and solves for the small symmetric positive-definite systems of
the closed loop (the 13x13 mass matrix, its 6x6 satellite block, the 6x6 Gram matrix of the
pseudoinverse), written as unrolled ``jnp`` arithmetic instead of LAPACK calls.

Why not ``jax.scipy.linalg``: on CPU, every LAPACK call is an opaque custom call that XLA can
neither fuse nor vectorise across a ``vmap`` batch. Under ``vmap`` jaxlib runs the batch
through its own thread pool (``ParallelBatchMap``), and with jax 0.10.2 on a 2-core machine
that deadlocks for batches of about 512 and more (all threads parked on futexes; see the
README's modelling notes). Unrolled over the static size ``n`` (at most 13 here), the
factorisation is a few hundred scalar expressions per system, which XLA fuses and, under
``vmap``, vectorises across the batch; autodiff goes through them as through any ``jnp`` code.

All functions take one (unbatched) system; ``vmap`` adds batch axes.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def _cholesky_entries(A: jax.Array) -> list[list[jax.Array]]:
    """``L[i][j]`` for ``j <= i`` as scalars (0-d arrays): one fused scalar expression per
    entry, which XLA vectorises across a vmap batch."""
    n = A.shape[-1]
    L: list[list[jax.Array]] = [[] for _ in range(n)]
    for i in range(n):
        for j in range(i + 1):
            s = A[i, j]
            for k in range(j):
                s = s - L[i][k] * L[j][k]
            L[i].append(jnp.sqrt(s) if i == j else s / L[j][j])
    return L


def cholesky(A: jax.Array) -> jax.Array:
    """Lower-triangular ``L`` (n, n) with ``L L^T = A`` for symmetric positive-definite
    ``A`` (n, n); only the lower triangle of ``A`` is read. NaN if ``A`` is not positive
    definite (a diverging simulation then shows as non-finite values)."""
    n = A.shape[-1]
    L = _cholesky_entries(A)
    zero = jnp.zeros((), dtype=A.dtype)
    return jnp.stack([jnp.stack(L[i] + [zero] * (n - 1 - i)) for i in range(n)])


def _solve_lower(L, B: jax.Array) -> list[jax.Array]:
    rows = []
    for i in range(len(L)):
        row = B[i]
        for k, solved in enumerate(rows):
            row = row - L[i][k] * solved
        rows.append(row / L[i][i])
    return rows


def _solve_upper_transposed(L, Y) -> list[jax.Array]:
    n = len(L)
    rows = [None] * n
    for i in reversed(range(n)):
        row = Y[i]
        for k in range(i + 1, n):
            row = row - L[k][i] * rows[k]
        rows[i] = row / L[i][i]
    return rows


def _entries(L: jax.Array) -> list[list[jax.Array]]:
    return [[L[i, j] for j in range(i + 1)] for i in range(L.shape[-1])]


def solve_lower(L: jax.Array, B: jax.Array) -> jax.Array:
    """``X = L^-1 B`` for lower-triangular ``L`` (n, n) and ``B`` (n,) or (n, m)."""
    return jnp.stack(_solve_lower(_entries(L), B))


def solve_upper_transposed(L: jax.Array, B: jax.Array) -> jax.Array:
    """``X = L^-T B`` for lower-triangular ``L`` (n, n) and ``B`` (n,) or (n, m)."""
    return jnp.stack(_solve_upper_transposed(_entries(L), B))


def cho_solve(L: jax.Array, B: jax.Array) -> jax.Array:
    """``A^-1 B`` given ``L = cholesky(A)``; ``B`` (n,) or (n, m)."""
    entries = _entries(L)
    return jnp.stack(_solve_upper_transposed(entries, _solve_lower(entries, B)))


@jax.custom_jvp
def solve_spd(A: jax.Array, B: jax.Array) -> jax.Array:
    """``A^-1 B`` for symmetric positive-definite ``A`` (n, n); ``B`` (n,) or (n, m).

    Differentiated by its own rule, ``dX = A^-1 (dB - dA X)``, which reuses the factor:
    autodiff through the unrolled factorisation would store and replay its hundreds of
    scalar steps (measured: 4x the compile time and memory of the tuning gradient)."""
    L = _cholesky_entries(A)
    return jnp.stack(_solve_upper_transposed(L, _solve_lower(L, B)))


@solve_spd.defjvp
def _solve_spd_jvp(primals, tangents):
    A, B = primals
    dA, dB = tangents
    L = _cholesky_entries(A)
    X = jnp.stack(_solve_upper_transposed(L, _solve_lower(L, B)))
    dX = jnp.stack(_solve_upper_transposed(L, _solve_lower(L, dB - dA @ X)))
    return X, dX
