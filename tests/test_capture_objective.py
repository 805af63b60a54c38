"""The capture objective on hand-made logs: its value by hand, its zero inside the margins, its
gradient against central differences, and the campaigns' success flag it stands in for."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hand_logs import log_of

from spacegrasp_jax.envelope.criteria import CaptureCriteria
from spacegrasp_jax.jobs import anatomy
from spacegrasp_jax.loop.simulate import Log
from spacegrasp_jax.tuning.objective import Objective, Weights, objective_parts

LIMITS = (10.0, 10.0, 10.0, 5.0, 5.0, 2.0, 2.0)
OBJECTIVE = Objective(weights=Weights(), torque_scale_Nm=(1.0,) * 7, kind="capture", torque_constraint_Nm=LIMITS)


def make_log(final_offset_m, final_yaw_rad, torque_peaks_Nm, n: int = 50) -> Log:
    """A run of ``n`` rows whose EE ends ``final_offset_m`` (3,) from the desired point with
    ``final_yaw_rad`` of yaw, and whose joint i's torque rises to ``torque_peaks_Nm[i]``."""
    t = jnp.arange(n) * 0.01
    ramp = jnp.sin(jnp.pi * t / t[-1])[:, None]  # 0 -> 1 -> 0
    pose_ee = jnp.zeros((n, 6)).at[-1, :3].set(final_offset_m).at[-1, 5].set(final_yaw_rad)
    return log_of(t, pose_ee=pose_ee, u=ramp * jnp.asarray(torque_peaks_Nm))


def test_a_capture_with_room_to_spare_costs_next_to_nothing():
    spare = objective_parts(make_log([0.001, 0.0, 0.0], 0.002, np.array(LIMITS) * 0.3), OBJECTIVE, free_target=False)
    failing = objective_parts(make_log([0.006, 0.0, 0.0], 0.002, np.array(LIMITS) * 0.3), OBJECTIVE, free_target=False)
    assert float(spare["loss"]) < 1e-3 < 0.1 < float(failing["loss"])
    assert float(spare["loss"]) == float(spare["capture_loss"])


def test_one_failing_margin_by_hand():
    # 7.5 mm off (margin 1.5); orientation and torque far inside theirs.
    parts = objective_parts(make_log([0.0, 0.0, 0.0075], 0.0, np.array(LIMITS) * 0.1), OBJECTIVE, free_target=False)
    margin = (0.0075 + 1e-6) / 0.005
    assert float(parts["position_margin"]) == pytest.approx(margin)
    # The smooth maximum of the log margins is the largest one, exceeding it by at most
    # S log(count) and by far less when the others are far below.
    expected = 0.1 * math.log1p(math.exp((math.log(margin) - math.log(0.8)) / 0.1))
    assert float(parts["loss"]) == pytest.approx(expected, rel=1e-6)


def test_torque_is_a_constraint_at_the_motors_limits():
    inside = objective_parts(make_log([0.001, 0.0, 0.0], 0.0, np.array(LIMITS) * 0.5), OBJECTIVE, free_target=False)
    at_limit = objective_parts(make_log([0.001, 0.0, 0.0], 0.0, np.array(LIMITS) * 1.0), OBJECTIVE, free_target=False)
    beyond = objective_parts(make_log([0.001, 0.0, 0.0], 0.0, np.array(LIMITS) * 2.0), OBJECTIVE, free_target=False)
    assert float(inside["loss"]) < 0.01 < 0.1 < float(at_limit["loss"]) < float(beyond["loss"])
    # Well below the limits, halving the torque buys next to nothing: no trade of precision
    # for torque, where the weighted objective would halve its torque term.
    halved = objective_parts(make_log([0.001, 0.0, 0.0], 0.0, np.array(LIMITS) * 0.25), OBJECTIVE, free_target=False)
    assert float(inside["loss"]) - float(halved["loss"]) < 0.005


def test_a_runaway_weighs_its_log_not_its_size():
    hundredfold = objective_parts(
        make_log([0.001, 0.0, 0.0], 0.0, np.array(LIMITS) * 100.0), OBJECTIVE, free_target=False
    )
    assert float(hundredfold["loss"]) == pytest.approx(math.log(100.0 / 0.8), rel=0.02)


def test_gradient_matches_central_differences():
    @jax.jit  # one program for the loss's 13 calls, not each operation dispatched alone
    def loss(x):
        offset, yaw, torque = x[:3], x[3], x[4:]
        return objective_parts(make_log(offset, yaw, torque), OBJECTIVE, free_target=False)["loss"]

    rng = np.random.default_rng(2)
    for x in (
        np.concatenate([[0.004, -0.003, 0.002], [0.015], np.array(LIMITS) * 0.9]),  # every margin near 1
        np.concatenate([[0.0, 0.0, 0.0062], [0.001], np.array(LIMITS) * 0.4]),  # position failing
    ):
        x = jnp.asarray(x)
        gradient = jax.grad(loss)(x)
        assert np.all(np.isfinite(gradient)) and float(jnp.linalg.norm(gradient)) > 0.0
        for _ in range(3):
            direction = jnp.asarray(rng.normal(size=x.shape)) * jnp.abs(x).clip(1e-3)
            h = 1e-6
            central = (loss(x + h * direction) - loss(x - h * direction)) / (2 * h)
            np.testing.assert_allclose(float(gradient @ direction), float(central), rtol=1e-6, atol=1e-12)


def test_the_gradient_is_finite_at_an_exact_capture():
    gradient = jax.grad(lambda d: objective_parts(make_log(d, 0.0, np.ones(7)), OBJECTIVE, free_target=False)["loss"])(
        jnp.zeros(3)
    )
    assert np.all(np.isfinite(gradient))


@pytest.mark.parametrize(
    "offset, yaw, scale",
    [([0.001, 0, 0], 0.0, 0.3), ([0.0051, 0, 0], 0.0, 0.3), ([0.001, 0, 0], 0.02, 0.3), ([0, 0.002, 0], 0.0, 1.2)],
)
def test_the_margins_agree_with_the_campaigns_criteria(offset, yaw, scale):
    parts = objective_parts(make_log(offset, yaw, np.array(LIMITS) * scale), OBJECTIVE, free_target=False)
    margins = [float(parts[name]) for name in ("position_margin", "orientation_margin", "torque_margin")]
    sample = {
        "final_position_error_m": np.array([float(parts["final_position_error_m"])]),
        "final_orientation_error_rad": np.array([float(parts["final_orientation_error_rad"])]),
        "largest_peak_torque_Nm": np.array([scale * max(LIMITS)]),
        "first_nonfinite_s": np.array([np.nan]),
    }
    classes = anatomy.failure_classes(sample, CaptureCriteria(torque_threshold_Nm=None))
    # The smooth torque margin sits above the hard one by at most T log(count).
    fails_errors = classes["failure"][0] != "success"
    assert (max(margins[:2]) > 1.0) == fails_errors
    assert (margins[2] > 1.0) == (scale >= 1.0)


def test_a_tuning_runs_held_out_success_is_the_campaigns():
    """Held-out samples counted as captured by the campaigns' criteria (5 mm, 1 deg, 100 N m,
    a free target's 5 mm/s, finite), and the rates and paired test built on them."""
    from scipy import stats

    from spacegrasp_jax.tuning.run import captured, holdout_success

    criteria = CaptureCriteria()
    start = {
        "final_position_error_m": np.array([0.001, 0.006, 0.001, 0.001, np.nan, 0.004]),
        "final_orientation_error_rad": np.array([0.001, 0.001, 0.03, 0.001, np.nan, 0.001]),
        "largest_peak_torque_Nm": np.array([2.0, 2.0, 2.0, 200.0, np.nan, 3.0]),
        "loss": np.array([0.1, 0.1, 0.1, 0.1, np.nan, 0.1]),
        "first_nonfinite_s": np.full(6, np.nan),  # the NaN sample's objective says it diverged
    }
    np.testing.assert_array_equal(captured(start, criteria), [True, False, False, False, False, True])
    pushed = start | {"final_target_speed_mps": np.array([0.001, 0.001, 0.001, 0.001, 0.001, 0.006])}
    np.testing.assert_array_equal(captured(pushed, criteria), [True, False, False, False, False, False])
    tuned = start | {"final_position_error_m": np.array([0.001, 0.002, 0.001, 0.001, 0.001, 0.004])}
    tuned["loss"] = np.full(6, 0.1)
    tuned["largest_peak_torque_Nm"] = np.array([2.0, 2.0, 2.0, 200.0, 2.0, 3.0])
    tuned["final_orientation_error_rad"] = np.full(6, 0.001)
    report = holdout_success(start, tuned, criteria)  # start captures 2 of 6, tuned 5 of 6 (all but the 200 N m)
    assert (report["success_start"]["successes"], report["success_tuned"]["successes"]) == (2, 5)
    wilson = stats.binomtest(5, 6).proportion_ci(confidence_level=0.95, method="wilson")
    assert report["success_tuned"]["low"] == pytest.approx(wilson.low) and report["success_tuned"][
        "high"
    ] == pytest.approx(wilson.high)
    paired = report["success_tuned_vs_start"]
    assert (paired["only_candidate"], paired["only_reference"]) == (3, 0)
    assert paired["p_value"] == pytest.approx(0.25)  # all 3 discordant samples one way: 2 * 0.5**3


def test_a_capture_that_a_campaign_calls_a_runaway_fails_the_held_out_verdict():
    """Within both tolerances and under the torque threshold at the end, a sample whose joint
    rate or torque passed ten times its limit on the way (the campaign's ``first_runaway_s``)
    is a failure for the tuner's held-out verdict as for a campaign."""
    from spacegrasp_jax.jobs.montecarlo import success
    from spacegrasp_jax.tuning.run import captured

    parts = {
        "final_position_error_m": np.array([0.001, 0.001, 0.001]),
        "final_orientation_error_rad": np.array([0.001, 0.001, 0.001]),
        "largest_peak_torque_Nm": np.array([2.0, 2.0, 2.0]),
        "loss": np.array([0.1, 0.1, 0.1]),
        "first_runaway_s": np.array([np.nan, 4.2, np.nan]),
        "first_nonfinite_s": np.array([np.nan, np.nan, 9.5]),
    }
    campaign = {name: value for name, value in parts.items() if name != "loss"}
    assert success(campaign, CaptureCriteria()).tolist() == [True, False, False]
    assert captured(parts, CaptureCriteria()).tolist() == [True, False, False]


@pytest.mark.slow
def test_the_held_out_evaluation_holds_the_campaigns_runaway_metric(robot, short_scenario):
    """The held-out evaluation's parts (``tuning.run.evaluate``) carry the campaign's own
    ``first_runaway_s`` and ``first_nonfinite_s``: on the 2 s approach with the paper's gains
    and with their PID gains times 30 (past the PID's gain margin), each equals the same
    run's metric as a campaign computes it, folded step by step (``montecarlo.FoldedMetrics``),
    to a few steps."""
    import dataclasses

    from spacegrasp_jax.jobs import experiment
    from spacegrasp_jax.jobs.montecarlo import FoldedMetrics
    from spacegrasp_jax.loop.control import paper_gains
    from spacegrasp_jax.loop.simulate import RunSpec, closed_loop
    from spacegrasp_jax.tuning.run import captured, evaluate
    from spacegrasp_jax.tuning.tune import TuneConfig, ideal_batch, make_objective

    gains = paper_gains()
    wild = dataclasses.replace(gains, kp=30.0 * gains.kp, ki=30.0 * gains.ki, kd=30.0 * gains.kd)
    scenarios = jax.tree.map(lambda x: jnp.stack([x, x]), short_scenario)
    objective = make_objective(
        robot, TuneConfig(), experiment.run(RunSpec(robot, short_scenario), gains).summary["max_abs_torque_Nm"]
    )
    folded = jax.jit(closed_loop)
    for candidate, runs_away in ((gains, False), (wild, True)):
        parts = evaluate(ideal_batch(robot, scenarios), candidate, "admittance", objective)
        _, (observed, _) = folded(
            RunSpec(robot, short_scenario, "admittance", observer=FoldedMetrics()), candidate, None
        )
        for name in ("first_runaway_s", "first_nonfinite_s"):
            # A run that blows up doubles its error every few steps: the batched program's
            # rounding moves the crossings by a few steps (0.705 s against 0.704 s, 0.729 s
            # against 0.727 s here).
            np.testing.assert_allclose(parts[name], np.full(2, float(observed[name])), rtol=0, atol=5e-3, err_msg=name)
        assert np.isfinite(parts["first_runaway_s"][0]) == runs_away
        if runs_away:
            assert not np.any(captured(parts, CaptureCriteria()))
