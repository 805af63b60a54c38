"""The unrolled Cholesky factorisation and solves, one system and under vmap, against NumPy;
their derivative rule against central differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spacegrasp_jax.core import linalg


def random_spd(rng, n):
    A = rng.normal(size=(n, n))
    return A @ A.T + 0.1 * n * np.eye(n)


@pytest.mark.parametrize("n", [1, 6, 13])
def test_factor_and_solves_match_numpy_alone_and_batched(n):
    rng = np.random.default_rng(n)
    As = np.stack([random_spd(rng, n) for _ in range(5)])
    bs, Bs = rng.normal(size=(5, n)), rng.normal(size=(5, n, 7))
    expected_L = np.linalg.cholesky(As)
    np.testing.assert_allclose(jax.vmap(linalg.cholesky)(As), expected_L, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(linalg.cholesky(jnp.asarray(As[0])), expected_L[0], rtol=1e-12, atol=1e-12)
    for rhs in (bs, Bs):
        expected = np.stack([np.linalg.solve(A, b) for A, b in zip(As, rhs)])
        np.testing.assert_allclose(jax.vmap(linalg.solve_spd)(As, rhs), expected, rtol=1e-10)
        np.testing.assert_allclose(jax.jit(jax.vmap(linalg.solve_spd))(As, rhs), expected, rtol=1e-10)
        np.testing.assert_allclose(linalg.solve_spd(jnp.asarray(As[0]), jnp.asarray(rhs[0])), expected[0], rtol=1e-10)
        # One matrix, a batch of right-hand sides, and the converse.
        np.testing.assert_allclose(
            jax.vmap(linalg.solve_spd, in_axes=(None, 0))(As[0], rhs),
            np.stack([np.linalg.solve(As[0], b) for b in rhs]),
            rtol=1e-10,
        )
        np.testing.assert_allclose(
            jax.vmap(linalg.solve_spd, in_axes=(0, None))(As, rhs[0]),
            np.stack([np.linalg.solve(A, rhs[0]) for A in As]),
            rtol=1e-10,
        )


def test_not_positive_definite_gives_nan():
    A = jnp.diag(jnp.array([1.0, -1.0, 2.0]))
    assert np.isnan(np.asarray(linalg.solve_spd(A, jnp.ones(3)))).any()
    assert np.isnan(np.asarray(jax.vmap(linalg.solve_spd)(A[None], jnp.ones((1, 3))))).any()


@pytest.mark.parametrize("batched", [False, True])
def test_gradients_match_central_differences(batched):
    rng = np.random.default_rng(0)
    A, B = jnp.asarray(random_spd(rng, 6)), jnp.asarray(rng.normal(size=(6, 2)))
    direction = jnp.asarray(rng.normal(size=(6, 6)))
    direction = direction + direction.T
    solve = (lambda A, B: jax.vmap(linalg.solve_spd)(A[None], B[None])[0]) if batched else linalg.solve_spd

    def f(s):
        return jnp.sum(jnp.sin(solve(A + s * direction, B * (1 + s))))

    h = 1e-6
    numeric = (f(h) - f(-h)) / (2 * h)
    np.testing.assert_allclose(jax.grad(f)(0.0), numeric, rtol=1e-7)  # reverse mode
    np.testing.assert_allclose(jax.jvp(f, (0.0,), (1.0,))[1], numeric, rtol=1e-7)  # forward mode


def test_large_vmap_batch_matches_loop():
    # Batched LAPACK deadlocked jaxlib 0.10.2 on 2 cores from ~512 systems (the reason the
    # package has none); this is 1,024.
    rng = np.random.default_rng(1)
    As = np.stack([random_spd(rng, 13) for _ in range(1024)])
    bs = rng.normal(size=(1024, 13))
    batched = np.asarray(jax.jit(jax.vmap(linalg.solve_spd))(As, bs))
    np.testing.assert_allclose(batched, np.linalg.solve(As, bs[..., None])[..., 0], rtol=1e-9)
