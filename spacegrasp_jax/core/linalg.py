"""Cholesky factorisation and solves for the small symmetric positive-definite systems of
the closed loop: the 7x7 Schur complement of the mass matrix and the 6x6 Gram matrix of
the pseudoinverse.

All of it is unrolled code written entry by entry (a 7x7 factor is 28 scalar expressions),
for one system or, under ``vmap``, for a batch. No LAPACK call: a custom call is a kernel
XLA:CPU cannot compile into a loop, and without any the closed loop's step loops compile
to single kernels (``spacegrasp_jax.jobs.compilation``). Under ``vmap`` XLA vectorises the
same code across the batch (batched LAPACK is an opaque call per system; documentation,
modelling notes).

``solve_spd`` has its own derivative rule, ``dX = A^-1 (dB - dA X)``, built from the
factor and the substitutions of [`cho_solve()`][spacegrasp_jax.core.linalg.cho_solve], which are linear in the right-hand side
(so reverse mode transposes them). Neither autodiff mode goes through the factorisation.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def cholesky(A: jax.Array) -> jax.Array:
    """Lower-triangular ``L`` (..., n, n) with ``L L^T = A`` for symmetric positive-definite
    ``A`` (..., n, n), leading axes batched. NaN if ``A`` is not positive definite (a
    diverging simulation then shows as non-finite values). Not meant to be differentiated
    by itself: differentiate [`solve_spd()`][spacegrasp_jax.core.linalg.solve_spd]."""
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


def cho_solve(L: jax.Array, B: jax.Array) -> jax.Array:
    """``A^-1 B`` given ``L = cholesky(A)`` (n, n) and ``B`` (n,) or (n, m), by forward and
    back substitution (``L y = B``, then ``L^T x = y``). Linear in ``B``."""
    n = L.shape[-1]
    y: list[jax.Array] = []
    for i in range(n):
        row = B[i]
        for k in range(i):
            row = row - L[i, k] * y[k]
        y.append(row / L[i, i])
    x: list[jax.Array | None] = [None] * n
    for i in reversed(range(n)):
        row = y[i]
        for k in range(i + 1, n):
            row = row - L[k, i] * x[k]
        x[i] = row / L[i, i]
    return jnp.stack(x)


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
    # dA X as products and sums (a dot would be a library call of its own on a CPU).
    dA_X = jnp.sum(dA * X, axis=-1) if X.ndim == 1 else jnp.sum(dA[:, :, None] * X[None], axis=1)
    return X, cho_solve(L, dB - dA_X)
