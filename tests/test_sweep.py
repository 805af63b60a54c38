"""Gain sweeps: the batched, sharded evaluation against single rollouts, the grid and the
Pareto front against brute force."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest

from spacegrasp_jax.analysis import sweep
from spacegrasp_jax.analysis.sweep import SweepError
from spacegrasp_jax.jobs import experiment
from spacegrasp_jax.loop.simulate import RunSpec


def test_scale_grid_is_the_cartesian_product_first_axis_slowest():
    grid = sweep.scale_grid(Kd=[0.5, 2.0], Bd=[1.0, 3.0, 4.0])
    expected = list(itertools.product([0.5, 2.0], [1.0, 3.0, 4.0]))
    assert list(zip(grid["Kd"], grid["Bd"])) == expected


def test_scaled_gains_scale_whole_groups_and_leave_the_rest(gains):
    batch = sweep.scaled_gains(gains, {"Kd": [0.5, 2.0], "kp": [1.0, 3.0]})
    np.testing.assert_array_equal(batch.Kd[1], 2.0 * np.asarray(gains.Kd))
    np.testing.assert_array_equal(batch.kp[1], 3.0 * np.asarray(gains.kp))
    np.testing.assert_array_equal(batch.Md, np.stack([gains.Md, gains.Md]))
    assert batch.ki.shape == (2, 7)


@pytest.mark.parametrize(
    "scales, message",
    [
        ({"Kx": [1.0]}, "unknown gain group 'Kx'"),
        ({"Kd": [1.0, -1.0]}, "Kd: scale factors must be finite and positive"),
        ({"Kd": [1.0, np.nan]}, "Kd: scale factors must be finite and positive"),
        ({"Kd": [1.0, 2.0], "Bd": [1.0]}, "same number of factors"),
        ({}, "empty"),
    ],
)
def test_bad_scales_are_rejected_by_name(gains, scales, message):
    with pytest.raises(SweepError, match=message):
        sweep.scaled_gains(gains, scales)


def test_bad_sweep_input_fails_before_compiling(robot, short_scenario, gains):
    batch = sweep.scaled_gains(gains, {"Kd": [1.0, 2.0]})
    with pytest.raises(SweepError, match="controller"):
        sweep.evaluate_gains(robot, short_scenario, batch, "computed_torque")
    with pytest.raises(SweepError, match="chunk"):
        sweep.evaluate_gains(robot, short_scenario, batch, "admittance", chunk=0)
    with pytest.raises(SweepError, match=r"expected a batch \(N, size\)"):
        sweep.evaluate_gains(robot, short_scenario, gains, "admittance")


@pytest.mark.slow
def test_a_sweep_equals_single_rollouts_of_each_gain_set(robot, short_scenario, gains):
    # 3 sets in chunks of 2: the second chunk is padded, and the padding must not leak.
    scales = {"Kd": [0.5, 1.0, 2.0], "kp": [1.5, 1.0, 0.5]}
    results = sweep.evaluate_gains(
        robot, short_scenario, sweep.scaled_gains(gains, scales), "admittance", chunk=2, progress=None
    )
    assert results["final_position_error_m"].shape == (3,) and results["max_abs_torque_Nm"].shape == (3, 7)
    for n in range(3):
        single = dataclasses.replace(gains, Kd=gains.Kd * scales["Kd"][n], kp=gains.kp * scales["kp"][n])
        summary = experiment.run(RunSpec(robot, short_scenario, "admittance"), single).summary
        np.testing.assert_allclose(results["max_abs_torque_Nm"][n], summary["max_abs_torque_Nm"], rtol=1e-10)
        np.testing.assert_allclose(results["largest_peak_torque_Nm"][n], max(summary["max_abs_torque_Nm"]), rtol=1e-10)
        for name in (
            "final_position_error_m",
            "final_orientation_error_rad",
            "rms_position_error_m",
            "max_contact_force_N",
        ):
            np.testing.assert_allclose(results[name][n], summary[name], rtol=1e-9, atol=1e-15, err_msg=name)
    assert not results["diverged"].any()


def _brute_force_front(a, b):
    points = np.column_stack([a, b])
    return np.array(
        [
            np.all(np.isfinite(p))
            and not any(np.all(np.isfinite(o)) and np.all(o <= p) and np.any(o < p) for o in points)
            for p in points
        ]
    )


def test_pareto_front_matches_brute_force_and_ignores_non_finite_points():
    rng = np.random.default_rng(7)
    a, b = rng.uniform(size=200), rng.uniform(size=200)
    a[[3, 17]] = np.nan
    b[40] = np.inf
    front = sweep.pareto_front(a, b)
    np.testing.assert_array_equal(front, _brute_force_front(a, b))
    assert not front[[3, 17, 40]].any()
    # A hand-checked case: (1, 3) and (2, 1) are optimal, (2, 3) is dominated by both,
    # and a duplicate of an optimal point keeps both copies on the front.
    np.testing.assert_array_equal(sweep.pareto_front([1, 2, 2, 2], [3, 1, 3, 1]), [True, True, False, True])
