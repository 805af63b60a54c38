"""Contact sphere (eq 20) and the F/T sensor transport (eqs 18-19)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spacegrasp_jax.core.contact import (
    contact_force_exact,
    contact_force_smooth,
    rotate_wrench,
    sensor_wrench,
    wrench_at_ee,
)

R, K = 0.03, 0.1  # m, N m^2 (the paper)


def test_exact_law_hand_values():
    # Half-way in, along +z: k (r - d) / r^3 = 0.1 * 0.015 / 2.7e-5 = 55.5... N, outward.
    force = contact_force_exact(jnp.array([0.0, 0.0, 0.015]), R, K)
    np.testing.assert_allclose(force, [0.0, 0.0, 0.1 * 0.015 / 0.03**3], rtol=1e-14)
    # d = 0.01 along (3, 4, 0)/5: magnitude 0.1 * 0.02 / 2.7e-5, direction (0.6, 0.8, 0).
    force = contact_force_exact(jnp.array([0.006, 0.008, 0.0]), R, K)
    np.testing.assert_allclose(force, 0.1 * 0.02 / 2.7e-5 * np.array([0.6, 0.8, 0.0]), rtol=1e-14)
    # On and outside the boundary: no force.
    np.testing.assert_array_equal(contact_force_exact(jnp.array([0.0, 0.03, 0.0]), R, K), 0.0)
    np.testing.assert_array_equal(contact_force_exact(jnp.array([0.1, 0.0, 0.0]), R, K), 0.0)


@pytest.mark.parametrize("point", [[0.0, 0.0, 0.015], [0.006, 0.008, 0.0], [0.01, -0.01, 0.02], [0.0, 0.04, 0.0]])
def test_smooth_law_converges_to_exact(point):
    p = jnp.array(point)
    exact = contact_force_exact(p, R, K)
    errors = [float(jnp.max(jnp.abs(contact_force_smooth(p, R, K, s) - exact))) for s in (1e3, 1e4, 1e5, 1e6)]
    assert errors[-1] <= 1e-4 * max(float(jnp.max(jnp.abs(exact))), 1.0)
    assert all(later <= earlier for earlier, later in zip(errors, errors[1:]))


def test_smooth_law_is_c1_across_the_boundary():
    """The exact law's radial slope jumps from -k/r^3 to 0 at d = r; the smooth law's
    slope is continuous: its values just inside and outside the boundary agree to the
    resolution of the step."""
    slope = jax.grad(lambda d: contact_force_smooth(jnp.array([0.0, 0.0, d]), R, K, 1e4)[2])
    h = 1e-7
    for d in (R - 1e-3, R, R + 1e-3):
        assert abs(float(slope(d + h)) - float(slope(d - h))) <= 1e-3 * K / R**3
    exact_slope = jax.grad(lambda d: contact_force_exact(jnp.array([0.0, 0.0, d]), R, K)[2])
    assert abs(float(exact_slope(R - h)) - float(exact_slope(R + h))) == pytest.approx(K / R**3)


def test_gradients_finite_at_and_near_the_centre():
    for law in (lambda p: contact_force_smooth(p, R, K, 1e4), lambda p: contact_force_exact(p, R, K)):
        for p in (jnp.zeros(3), jnp.array([1e-12, 0.0, 0.0]), jnp.array([0.0, 1e-5, -1e-5])):
            jacobian = jax.jacfwd(law)(p)
            assert np.all(np.isfinite(jacobian))
            assert np.all(np.isfinite(jax.jacrev(law)(p)))
    # The smooth law is zero at the centre and continuous there.
    np.testing.assert_allclose(contact_force_smooth(jnp.zeros(3), R, K, 1e4), 0.0, atol=0)


def test_gradient_of_smooth_law_matches_finite_differences():
    p = jnp.array([0.01, -0.005, 0.012])
    jacobian = jax.jacfwd(lambda x: contact_force_smooth(x, R, K, 1e4))(p)
    h = 1e-8
    numeric = np.column_stack(
        [
            (contact_force_smooth(p + h * e, R, K, 1e4) - contact_force_smooth(p - h * e, R, K, 1e4)) / (2 * h)
            for e in np.eye(3)
        ]
    )
    np.testing.assert_allclose(jacobian, numeric, rtol=1e-6, atol=1e-6)


def test_sensor_transport_gives_zero_torque_for_a_force_at_the_ee_point():
    rng = np.random.default_rng(0)
    for _ in range(10):
        force, p_ee = rng.normal(size=3), rng.normal(size=3)
        f_fts, n_fts = sensor_wrench(force, p_ee)
        assert np.linalg.norm(n_fts) > 0.0  # the sensor does feel a moment
        wrench = wrench_at_ee(f_fts, n_fts, p_ee)
        np.testing.assert_allclose(wrench[:3], force, rtol=1e-15)
        np.testing.assert_allclose(wrench[3:], 0.0, atol=1e-14)


def test_sensor_transport_keeps_a_pure_torque_and_rotation_preserves_norms():
    torque = np.array([0.1, -0.2, 0.3])
    wrench = wrench_at_ee(np.zeros(3), torque, np.array([0.0, 0.0, 0.175]))
    np.testing.assert_allclose(wrench, np.r_[np.zeros(3), torque])
    angle = 0.7
    R_ab = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    rotated = rotate_wrench(R_ab, np.r_[1.0, 2.0, 3.0, torque])
    np.testing.assert_allclose(rotated[:3], R_ab @ [1.0, 2.0, 3.0])
    np.testing.assert_allclose(rotated[3:], R_ab @ torque)
