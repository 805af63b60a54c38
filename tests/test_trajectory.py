"""Desired trajectory: endpoints, hold, and derivatives against finite differences."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax.core import spatial
from spacegrasp_jax.core.trajectory import Trajectory, desired_state, minimum_jerk

PAPER = Trajectory(
    start_pose=jnp.array([0.0, 0.0, -0.08, 0.0, 0.0, 0.0]),
    end_pose=jnp.array([0.0, 0.0, 0.015, 0.0, 0.0, 0.0]),
    duration=jnp.array(10.0),
)
TURNING = Trajectory(
    start_pose=jnp.array([0.01, -0.02, -0.08, 0.1, -0.2, 0.3]),
    end_pose=jnp.array([0.03, 0.01, 0.015, -0.2, 0.3, -0.4]),
    duration=jnp.array(10.0),
)


def test_endpoints_and_hold():
    for trajectory in (PAPER, TURNING):
        pose, twist, rate = desired_state(trajectory, 0.0)
        np.testing.assert_allclose(pose, trajectory.start_pose, atol=1e-15)
        np.testing.assert_allclose(twist, 0.0, atol=1e-15)
        for t in (10.0, 12.5, 17.0):
            pose, twist, rate = desired_state(trajectory, t)
            np.testing.assert_allclose(pose, trajectory.end_pose, atol=1e-15)
            np.testing.assert_allclose(twist, 0.0, atol=1e-15)
            np.testing.assert_allclose(rate, 0.0, atol=1e-15)


def test_minimum_jerk_profile():
    s, ds, dds = minimum_jerk(5.0, 10.0)
    assert float(s) == 0.5
    np.testing.assert_allclose(ds, 30 * 0.25 * 0.25 / 10.0)  # peak speed 1.875 / T
    np.testing.assert_allclose(dds, 0.0, atol=1e-15)


def test_linear_derivatives_match_finite_differences():
    h = 1e-5
    for t in (1.0, 3.7, 8.2):
        pose, twist, rate = desired_state(PAPER, t)
        pose_a, twist_a, _ = desired_state(PAPER, t + h)
        pose_b, twist_b, _ = desired_state(PAPER, t - h)
        np.testing.assert_allclose(twist[:3], (pose_a[:3] - pose_b[:3]) / (2 * h), rtol=1e-8, atol=1e-12)
        np.testing.assert_allclose(rate[:3], (twist_a[:3] - twist_b[:3]) / (2 * h), rtol=1e-6, atol=1e-10)


def test_angular_velocity_matches_rotation_finite_differences():
    """Eqs 10-12: the angular velocity in LAR is the rate of the rotation built from the
    desired Euler angles, w = vee(dR/dt R^T); eq 13's rate is its derivative."""
    h = 1e-5
    for t in (2.0, 5.5, 9.0):
        pose, twist, rate = desired_state(TURNING, t)
        R_a = spatial.euler_zyx_to_rotation(desired_state(TURNING, t + h)[0][3:])
        R_b = spatial.euler_zyx_to_rotation(desired_state(TURNING, t - h)[0][3:])
        measured = spatial.rotation_log(R_a @ R_b.T) / (2 * h)
        np.testing.assert_allclose(twist[3:], measured, rtol=1e-7, atol=1e-10)
        w_a, w_b = desired_state(TURNING, t + h)[1][3:], desired_state(TURNING, t - h)[1][3:]
        np.testing.assert_allclose(rate[3:], (w_a - w_b) / (2 * h), rtol=1e-6, atol=1e-9)


def test_euler_rate_map_matches_rotation_derivative():
    angles, rates = jnp.array([0.3, -0.4, 1.1]), jnp.array([0.2, -0.5, 0.7])
    R, R_dot = jax.jvp(spatial.euler_zyx_to_rotation, (angles,), (rates,))
    w_body = jnp.array([(R.T @ R_dot)[2, 1], (R.T @ R_dot)[0, 2], (R.T @ R_dot)[1, 0]])
    np.testing.assert_allclose(spatial.euler_rates_to_body(angles) @ rates, w_body, atol=1e-14)
