"""The unrolled Cholesky factorisation and solves against NumPy's LAPACK-backed ones."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spacegrasp_jax import linalg


def random_spd(rng, n):
    A = rng.normal(size=(n, n))
    return A @ A.T + 0.1 * n * np.eye(n)


@pytest.mark.parametrize("n", [1, 6, 13])
def test_factor_and_solves_match_numpy(n):
    rng = np.random.default_rng(n)
    A, b, B = random_spd(rng, n), rng.normal(size=n), rng.normal(size=(n, 7))
    L = np.asarray(linalg.cholesky(jnp.asarray(A)))
    np.testing.assert_allclose(L, np.linalg.cholesky(A), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(linalg.solve_spd(jnp.asarray(A), jnp.asarray(b)), np.linalg.solve(A, b), rtol=1e-10)
    np.testing.assert_allclose(linalg.solve_spd(jnp.asarray(A), jnp.asarray(B)), np.linalg.solve(A, B), rtol=1e-10)
    np.testing.assert_allclose(linalg.solve_lower(jnp.asarray(L), jnp.asarray(b)), np.linalg.solve(L, b), rtol=1e-10)
    np.testing.assert_allclose(linalg.solve_upper_transposed(jnp.asarray(L), jnp.asarray(b)), np.linalg.solve(L.T, b), rtol=1e-10)


def test_not_positive_definite_gives_nan():
    A = jnp.diag(jnp.array([1.0, -1.0, 2.0]))
    assert np.isnan(np.asarray(linalg.solve_spd(A, jnp.ones(3)))).any()


def test_gradient_matches_central_differences():
    rng = np.random.default_rng(0)
    A, b = jnp.asarray(random_spd(rng, 6)), jnp.asarray(rng.normal(size=6))
    direction = jnp.asarray(rng.normal(size=(6, 6)))
    direction = direction + direction.T

    def f(s):
        return jnp.sum(jnp.sin(linalg.solve_spd(A + s * direction, b)))

    h = 1e-6
    numeric = (f(h) - f(-h)) / (2 * h)
    np.testing.assert_allclose(jax.grad(f)(0.0), numeric, rtol=1e-7)


def test_vmap_matches_loop():
    rng = np.random.default_rng(1)
    As = np.stack([random_spd(rng, 13) for _ in range(600)])
    bs = rng.normal(size=(600, 13))
    batched = np.asarray(jax.jit(jax.vmap(linalg.solve_spd))(As, bs))
    np.testing.assert_allclose(batched, np.linalg.solve(As, bs[..., None])[..., 0], rtol=1e-9)
