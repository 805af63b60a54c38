"""Scalar measures of a rollout, on hand-made logs."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spacegrasp_jax.envelope import metrics
from spacegrasp_jax.loop.simulate import Log


def hand_log():
    t = np.arange(4) * 0.5
    pose_des = np.zeros((4, 6))
    pose_ee = np.zeros((4, 6))
    pose_ee[:, 0] = [0.0, 0.003, 0.0, 0.004]  # m
    pose_ee[-1, 5] = 0.1  # 0.1 rad of yaw at the end
    u = np.array([[0.0] * 7, [1.0, -2.0, 0, 0, 0, 0, 0], [0.5, 3.0, 0, 0, 0, 0, -0.1], [0.0] * 7])
    contact = np.array([[0, 0, 0], [0, 0, 0], [3.0, 4.0, 0.0], [0, 0, 0]], dtype=float)
    zeros = lambda width: np.zeros((4, width))  # noqa: E731
    return Log(
        t=t,
        pose_ee=pose_ee,
        pose_des=pose_des,
        twist_ee=zeros(6),
        contact_force=contact,
        momentum=zeros(6),
        V_base=zeros(6),
        u=u,
        fts_force=zeros(3),
        fts_torque=zeros(3),
        V_ref=zeros(6),
        qd_des=zeros(7),
        q=zeros(7),
        qd=zeros(7),
        target_position=zeros(3),
        target_quat=np.tile([1.0, 0.0, 0.0, 0.0], (4, 1)),
        target_velocity=zeros(3),
        target_angular_velocity=zeros(3),
        momentum_total=zeros(6),
    )


def test_hand_computed_measures():
    log = hand_log()
    np.testing.assert_allclose(metrics.final_position_error(log), 0.004)
    np.testing.assert_allclose(metrics.final_orientation_error(log), 0.1, rtol=1e-12)
    np.testing.assert_allclose(metrics.rms_position_error(log), np.sqrt((0.003**2 + 0.004**2) / 4))
    np.testing.assert_array_equal(metrics.max_abs_torque(log), [1.0, 3.0, 0, 0, 0, 0, 0.1])
    assert float(metrics.first_contact_time(log)) == 1.0
    summary = metrics.summary(log, free_target=False)
    assert summary["max_contact_force_N"] == 5.0 and summary["first_contact_s"] == 1.0
    assert summary["largest_peak_torque_Nm"] == 3.0 and summary["max_abs_torque_Nm"] == [1.0, 3.0, 0, 0, 0, 0, 0.1]
    np.testing.assert_allclose(summary["final_position_error_m"], 0.004)
    np.testing.assert_allclose(summary["final_orientation_error_rad"], 0.1, rtol=1e-12)
    np.testing.assert_allclose(summary["rms_position_error_m"], np.sqrt((0.003**2 + 0.004**2) / 4))
    assert np.isnan(summary["first_nonfinite_s"])


def test_folding_rows_one_by_one_gives_the_whole_log_metrics():
    # The in-scan path (one row at a time) and the whole-log path share one definition.
    log = hand_log()
    running = metrics.start()
    for k in range(4):
        running = metrics.accumulate(running, jax.tree.map(lambda x: x[k : k + 1], log))
    one_by_one, whole = metrics.finish(running, free_target=False), metrics.log_metrics(log, free_target=False)
    for name in metrics.METRICS:
        np.testing.assert_allclose(one_by_one[name], whole[name], rtol=1e-15, err_msg=name)


@pytest.mark.parametrize("free_target", [False, True])
def test_the_summary_is_the_whole_log_metrics_in_the_declared_order(free_target):
    # summary() runs log_metrics as one compiled program, whose outputs come back sorted by
    # name: the values must be the operation-by-operation ones, the keys in METRICS' order
    # (then TARGET_METRICS'), as summary.json lists them.
    log = hand_log()
    summary = metrics.summary(log, free_target=free_target)
    declared = [*metrics.METRICS, *(metrics.TARGET_METRICS if free_target else ())]
    assert list(summary) == declared
    whole = metrics.log_metrics(log, free_target=free_target)
    for name in declared:
        np.testing.assert_array_equal(summary[name], np.asarray(whole[name]), err_msg=name)


def test_missing_values_are_nan_in_both_paths_and_null_in_json(tmp_path):
    from spacegrasp_jax.jobs import runfiles

    log = dataclasses.replace(hand_log(), contact_force=np.zeros((4, 3)))
    assert np.isnan(float(metrics.first_contact_time(log)))
    summary = metrics.summary(log, free_target=False)
    assert np.isnan(summary["first_contact_s"]) and np.isnan(summary["first_nonfinite_s"])
    runfiles.write_json(tmp_path / "summary.json", summary)
    written = json.loads((tmp_path / "summary.json").read_text())
    assert written["first_contact_s"] is None and written["max_contact_force_N"] == 0.0


def test_a_non_finite_row_is_reported_and_the_peaks_before_it_kept():
    log = hand_log()
    u = log.u.copy()
    u[3, 2] = np.nan
    summary = metrics.summary(dataclasses.replace(log, u=u), free_target=False)
    assert summary["first_nonfinite_s"] == 1.5
    assert summary["max_abs_torque_Nm"] == [1.0, 3.0, 0, 0, 0, 0, 0.1]


def test_safe_norm_has_zero_gradient_at_zero():
    gradient = jax.grad(lambda x: metrics.safe_norm(x))(jnp.zeros(3))
    np.testing.assert_array_equal(gradient, 0.0)
    np.testing.assert_allclose(jax.grad(lambda x: metrics.safe_norm(x))(jnp.array([3.0, 4.0, 0.0])), [0.6, 0.8, 0.0])
