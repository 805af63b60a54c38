"""Rotation helpers: round trips and derivatives."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jax.test_util
import numpy as np
from random_states import random_rotation

from spacegrasp_jax.core import spatial


def test_quaternion_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(50):
        R = random_rotation(rng)
        quat = spatial.rotation_to_quat(R)
        assert float(quat[0]) >= 0.0
        np.testing.assert_allclose(jnp.linalg.norm(quat), 1.0, atol=1e-15)
        np.testing.assert_allclose(spatial.quat_to_rotation(quat), R, atol=1e-14)


def test_quaternion_round_trip_near_half_turns():
    for axis in np.eye(3):
        R = np.asarray(jax.scipy.linalg.expm(spatial.skew(axis * (np.pi - 1e-9))))
        np.testing.assert_allclose(spatial.quat_to_rotation(spatial.rotation_to_quat(R)), R, atol=1e-14)


def test_euler_zyx_round_trip_and_order():
    rng = np.random.default_rng(1)
    for _ in range(50):
        angles = rng.uniform([-np.pi, -1.5, -np.pi], [np.pi, 1.5, np.pi])
        R = spatial.euler_zyx_to_rotation(angles)
        np.testing.assert_allclose(spatial.euler_zyx(R), angles, atol=1e-12)
    # roll is about x: a pure rotation about x shows up in the first entry only.
    np.testing.assert_allclose(spatial.euler_zyx(spatial.rot_x(0.3)), [0.3, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(spatial.euler_zyx(spatial.rot_z(0.3)), [0.0, 0.0, 0.3], atol=1e-15)


def test_quaternion_derivative_matches_finite_difference():
    rng = np.random.default_rng(2)
    R = random_rotation(rng)
    omega = rng.normal(size=3)
    quat = spatial.rotation_to_quat(R)
    h = 1e-6
    R_next = np.asarray(jax.scipy.linalg.expm(spatial.skew(omega * h))) @ R
    R_prev = np.asarray(jax.scipy.linalg.expm(spatial.skew(-omega * h))) @ R
    numeric = (spatial.rotation_to_quat(R_next) - spatial.rotation_to_quat(R_prev)) / (2 * h)
    np.testing.assert_allclose(spatial.quat_derivative(quat, omega), numeric, atol=1e-8)


def test_skew_and_rotation_log():
    rng = np.random.default_rng(3)
    v, u = rng.normal(size=3), rng.normal(size=3)
    np.testing.assert_allclose(spatial.skew(v) @ u, np.cross(v, u), atol=1e-15)
    for scale in [1e-8, 1e-3, 1.0, 3.0]:
        vector = rng.normal(size=3)
        vector = scale * vector / np.linalg.norm(vector)
        R = jax.scipy.linalg.expm(spatial.skew(vector))
        np.testing.assert_allclose(spatial.rotation_log(R), vector, atol=1e-12)
    gradient = jax.grad(lambda x: jnp.sum(spatial.rotation_log(jax.scipy.linalg.expm(spatial.skew(x)))))(jnp.zeros(3))
    assert np.all(np.isfinite(gradient))


def test_cross_matches_numpy_with_broadcasting_and_its_derivatives_match_finite_differences():
    rng = np.random.default_rng(5)
    shapes = [((3,), (3,)), ((7, 3), (3,)), ((3,), (7, 3)), ((7, 3), (7, 3)), ((2, 7, 3), (7, 3))]
    for shape_a, shape_b in shapes:
        a, b = rng.normal(size=shape_a), rng.normal(size=shape_b)
        np.testing.assert_allclose(spatial.cross(a, b), np.cross(a, b), atol=1e-15)
        np.testing.assert_allclose(
            (spatial.skew(a) @ np.broadcast_to(b, np.broadcast_shapes(a.shape, b.shape))[..., None])[..., 0],
            np.cross(a, b),
            atol=1e-15,
        )
        # Both modes, both arguments and each alone (the other a constant: a symbolic zero
        # tangent), against central finite differences.
        jax.test_util.check_grads(spatial.cross, (a, b), order=1, modes=("fwd", "rev"), eps=1e-6)
        jax.test_util.check_grads(lambda x: spatial.cross(x, b), (a,), order=1, modes=("fwd", "rev"), eps=1e-6)
        jax.test_util.check_grads(lambda y: spatial.cross(a, y), (b,), order=1, modes=("fwd", "rev"), eps=1e-6)


def test_matvec_and_matmul_match_numpy_alone_and_under_vmap_with_their_derivatives():
    rng = np.random.default_rng(6)
    A, x, B = rng.normal(size=(7, 3, 3)), rng.normal(size=(2, 3)), rng.normal(size=(3, 4))
    np.testing.assert_allclose(spatial.matvec(A, x[0]), A @ x[0], atol=1e-14)
    np.testing.assert_allclose(spatial.matvec(A[0], x), x @ A[0].T, atol=1e-14)
    np.testing.assert_allclose(spatial.matmul(A, B), A @ B, atol=1e-14)
    # Under vmap with either operand, or both, batched, and leading axes
    # that differ between the operands.
    batch_A, batch_x, batch_B = rng.normal(size=(5, 3, 3)), rng.normal(size=(5, 2, 3)), rng.normal(size=(5, 3, 4))
    for in_axes in [(0, 0), (0, None), (None, 0)]:
        a = batch_A if in_axes[0] == 0 else A[0]
        v = batch_x if in_axes[1] == 0 else x
        m = batch_B if in_axes[1] == 0 else B
        np.testing.assert_allclose(
            jax.vmap(spatial.matvec, in_axes)(a, v), np.einsum("...ij,...kj->...ki", a, v), atol=1e-14
        )
        np.testing.assert_allclose(jax.vmap(spatial.matmul, in_axes)(a, m), a @ m, atol=1e-14)
    for function, args in [(spatial.matvec, (A, x[0])), (spatial.matmul, (A, B))]:
        jax.test_util.check_grads(function, args, order=1, modes=("fwd", "rev"), eps=1e-6)
        jax.test_util.check_grads(lambda a: function(a, args[1]), args[:1], order=1, modes=("fwd", "rev"), eps=1e-6)
        jax.test_util.check_grads(lambda b: function(args[0], b), args[1:], order=1, modes=("fwd", "rev"), eps=1e-6)
    jax.test_util.check_grads(jax.vmap(spatial.matvec), (batch_A, batch_x), order=1, modes=("fwd", "rev"), eps=1e-6)
