"""Scalar measures of a rollout, on hand-made logs."""

from __future__ import annotations

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax import metrics


def hand_log():
    t = np.arange(4) * 0.5
    pose_des = np.zeros((4, 6))
    pose_ee = np.zeros((4, 6))
    pose_ee[:, 0] = [0.0, 0.003, 0.0, 0.004]  # m
    pose_ee[-1, 5] = 0.1  # 0.1 rad of yaw at the end
    u = np.array([[0.0] * 7, [1.0, -2.0, 0, 0, 0, 0, 0], [0.5, 3.0, 0, 0, 0, 0, -0.1], [0.0] * 7])
    contact = np.array([[0, 0, 0], [0, 0, 0], [3.0, 4.0, 0.0], [0, 0, 0]], dtype=float)
    return SimpleNamespace(t=t, pose_ee=pose_ee, pose_des=pose_des, u=u, contact_force=contact,
                           momentum=np.zeros((4, 6)), V_base=np.zeros((4, 6)))


def test_hand_computed_measures():
    log = hand_log()
    np.testing.assert_allclose(metrics.final_position_error(log), 0.004)
    np.testing.assert_allclose(metrics.final_orientation_error(log), 0.1, rtol=1e-12)
    np.testing.assert_allclose(metrics.rms_position_error(log), np.sqrt((0.003**2 + 0.004**2) / 4))
    np.testing.assert_array_equal(metrics.max_abs_torque(log), [1.0, 3.0, 0, 0, 0, 0, 0.1])
    assert float(metrics.first_contact_time(log)) == 1.0
    assert metrics.summary(log)["max_contact_force_N"] == 5.0


def test_no_contact_gives_nan_first_contact_and_null_in_summary():
    log = hand_log()
    log.contact_force = np.zeros((4, 3))
    assert np.isnan(float(metrics.first_contact_time(log)))
    assert metrics.summary(log)["first_contact_s"] is None


def test_safe_norm_has_zero_gradient_at_zero():
    gradient = jax.grad(lambda x: metrics.safe_norm(x))(jnp.zeros(3))
    np.testing.assert_array_equal(gradient, 0.0)
    np.testing.assert_allclose(jax.grad(lambda x: metrics.safe_norm(x))(jnp.array([3.0, 4.0, 0.0])), [0.6, 0.8, 0.0])
