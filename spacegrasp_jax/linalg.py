"""Cholesky factorisation and solves for the small symmetric positive-definite systems of
the closed loop: the 13x13 mass matrix, its 6x6 satellite block, and the 6x6 Gram matrix
of the pseudoinverse.

One system at a time, these call LAPACK (``jnp.linalg.cholesky``,
``jax.scipy.linalg.cho_solve``). That is the fastest choice for a single rollout and the
cheapest to compile. Under ``vmap`` they switch (``jax.custom_batching.custom_vmap``) to
unrolled code written entry by entry. XLA fuses that code and vectorises it across the
batch, where batched LAPACK is an opaque call per system. There is a second reason: with
jax 0.10.2 on a 2-core CPU, batched LAPACK deadlocked for batches of about 512 and more,
because jaxlib's ``ParallelBatchMap`` waits inside its own thread pool (README, modelling
notes).

``solve_spd`` has its own derivative rule, ``dX = A^-1 (dB - dA X)``, built from the
factor and differentiable ``triangular_solve`` calls. Neither autodiff mode ever goes
through the factorisation.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap


def _unrolled_cholesky(A: jax.Array) -> jax.Array:
    """Lower Cholesky factor of ``A`` (..., n, n), one scalar expression per entry."""
    n = A.shape[-1]
    L: list[list[jax.Array]] = [[] for _ in range(n)]
    for i in range(n):
        for j in range(i + 1):
            s = A[..., i, j]
            for k in range(j):
                s = s - L[i][k] * L[j][k]
            L[i].append(jnp.sqrt(s) if i == j else s / L[j][j])
    zero = jnp.zeros_like(L[0][0])
    return jnp.stack([jnp.stack(L[i] + [zero] * (n - 1 - i), axis=-1) for i in range(n)], axis=-2)


def _unrolled_cho_solve(L: jax.Array, B: jax.Array) -> jax.Array:
    """``A^-1 B`` from ``L`` (b, n, n) and ``B`` (b, n, m) by forward and back substitution."""
    n = L.shape[-1]

    def entry(i, k):
        return L[:, i, k][:, None]

    y = []
    for i in range(n):
        row = B[:, i]
        for k in range(i):
            row = row - entry(i, k) * y[k]
        y.append(row / entry(i, i))
    x = [None] * n
    for i in reversed(range(n)):
        row = y[i]
        for k in range(i + 1, n):
            row = row - entry(k, i) * x[k]
        x[i] = row / entry(i, i)
    return jnp.stack(x, axis=1)


@custom_vmap
def cholesky(A: jax.Array) -> jax.Array:
    """Lower-triangular ``L`` (n, n) with ``L L^T = A`` for symmetric positive-definite
    ``A`` (n, n). NaN if ``A`` is not positive definite (a diverging simulation then shows
    as non-finite values). Not differentiable by itself: differentiate :func:`solve_spd`."""
    return jnp.linalg.cholesky(A)


@cholesky.def_vmap
def _cholesky_batched(axis_size, in_batched, A):
    return _unrolled_cholesky(A), True


@custom_vmap
def cho_solve(L: jax.Array, B: jax.Array) -> jax.Array:
    """``A^-1 B`` given ``L = cholesky(A)`` (n, n); ``B`` (n,) or (n, m)."""
    return jax.scipy.linalg.cho_solve((L, True), B)


@cho_solve.def_vmap
def _cho_solve_batched(axis_size, in_batched, L, B):
    L_batched, B_batched = in_batched
    L = L if L_batched else jnp.broadcast_to(L, (axis_size, *L.shape))
    B = B if B_batched else jnp.broadcast_to(B, (axis_size, *B.shape))
    if B.ndim == 2:  # a batch of vectors
        return _unrolled_cho_solve(L, B[..., None])[..., 0], True
    return _unrolled_cho_solve(L, B), True


@jax.custom_jvp
def solve_spd(A: jax.Array, B: jax.Array) -> jax.Array:
    """``A^-1 B`` for symmetric positive-definite ``A`` (n, n); ``B`` (n,) or (n, m)."""
    return cho_solve(cholesky(A), B)


@solve_spd.defjvp
def _solve_spd_jvp(primals, tangents):
    A, B = primals
    dA, dB = tangents
    L = cholesky(A)
    X = cho_solve(L, B)
    R = dB - dA @ X
    R = R[:, None] if R.ndim == 1 else R
    Y = jax.lax.linalg.triangular_solve(L, R, left_side=True, lower=True)
    dX = jax.lax.linalg.triangular_solve(L, Y, left_side=True, lower=True, transpose_a=True)
    return X, dX.reshape(X.shape)
