"""Joint ranges and stated rate limits as success criteria, on hand-made logs: the campaigns'
metric and failure class, the capture objective's margin and the worst-case measure, each
against the excess or ratio worked out by hand; and the paper's arm, which has no ranges and
whose assumed rate limits are no criterion, judged exactly as before."""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np
import pytest
from hand_logs import log_of

import spacegrasp_jax as sg
from spacegrasp_jax.analysis import worstcase
from spacegrasp_jax.core import joint_limits
from spacegrasp_jax.envelope import metrics
from spacegrasp_jax.envelope.criteria import CaptureCriteria
from spacegrasp_jax.jobs import anatomy, campaign
from spacegrasp_jax.tuning.objective import Objective, Weights, objective_parts

LIMITS = (10.0, 10.0, 10.0, 5.0, 5.0, 2.0, 2.0)


def ranged_robot(low: float = -1.0, high: float = 1.0):
    """The paper's robot with joint 3 given the range [low, high] rad."""
    limits = np.tile([-np.inf, np.inf], (7, 1))
    limits[2] = [low, high]
    return dataclasses.replace(sg.paper_robot(), joint_position_limit=jnp.asarray(limits))


def swinging_log(peak_rad: float, n: int = 41):
    """Joint 3 swings 0 -> ``peak_rad`` -> 0 (a sine arch), the others still; EE on target."""
    t = np.arange(n) * 0.01
    q = np.zeros((n, 7))
    q[:, 2] = peak_rad * np.sin(np.pi * t / t[-1])
    return log_of(t, q=q)


def test_the_running_metrics_find_how_far_and_when_a_joint_left_its_range():
    robot = ranged_robot()
    log = swinging_log(1.3)
    found = {name: np.asarray(value) for name, value in metrics.log_metrics(log, robot, free_target=False).items()}
    q3 = np.asarray(log.q)[:, 2]
    assert found["max_range_excess_rad"][2] == pytest.approx(np.max(q3) - 1.0, rel=1e-12)
    assert np.all(np.isnan(np.delete(found["max_range_excess_rad"], 2)))  # the joints without a range
    assert found["first_range_exit_s"] == pytest.approx(np.asarray(log.t)[np.argmax(q3 > 1.0)], abs=1e-15)
    inside = {
        name: np.asarray(value)
        for name, value in metrics.log_metrics(swinging_log(0.7), robot, free_target=False).items()
    }
    assert inside["max_range_excess_rad"][2] == pytest.approx(0.7 - 1.0, abs=1e-12) and np.isnan(
        inside["first_range_exit_s"]
    )
    paper = metrics.log_metrics(log, sg.paper_robot(), free_target=False)
    assert np.all(np.isnan(np.asarray(paper["max_range_excess_rad"]))) and np.isnan(paper["first_range_exit_s"])


def test_a_joint_out_of_its_range_fails_the_capture_and_the_verdict_says_which():
    robot = ranged_robot()
    summary = metrics.summary(swinging_log(1.3), robot, free_target=False)
    classes = campaign.run_failure_classes(summary)
    assert classes["failure"][0] == "joint_range" and classes["range_excess_rad"][0] == pytest.approx(0.3, rel=1e-12)
    line = anatomy.verdict_line(summary, classes, CaptureCriteria())
    assert line.startswith("capture failed (joint_range): joint 3 went 0.3 rad beyond its range (first left at t = ")
    for robot_without in (sg.paper_robot(), ranged_robot(-np.inf, np.inf)):  # no ranges: as before
        classes = campaign.run_failure_classes(metrics.summary(swinging_log(1.3), robot_without, free_target=False))
        assert classes["failure"][0] == "success" and np.isnan(classes["range_excess_rad"][0])


def test_the_capture_objective_counts_a_joint_range_as_a_margin():
    """One ranged joint, one row: the margin is exp(excess / 0.05 rad) exactly (a smooth
    maximum of one entry is that entry); over a run it is a smooth upper bound of the hard
    maximum. The paper's arm adds no margin, so its objective is the one it was."""
    robot = ranged_robot()
    ranges = joint_limits.finite_ranges(robot)
    assert ranges == ((2, -1.0, 1.0),) and joint_limits.finite_ranges(sg.paper_robot()) == ()
    one_row = jnp.zeros((1, 7)).at[0, 2].set(1.02)
    assert float(joint_limits.range_margin(one_row, ranges, 0.02)) == pytest.approx(math.exp(0.02 / 0.05), rel=1e-12)
    objective = Objective(Weights(), (1.0,) * 7, kind="capture", torque_constraint_Nm=LIMITS, joint_ranges=ranges)
    plain = dataclasses.replace(objective, joint_ranges=())
    out, inside = swinging_log(1.3), swinging_log(0.5)
    parts_out = objective_parts(out, objective, free_target=False)
    hard = math.exp(0.3 / joint_limits.RANGE_MARGIN_SCALE_RAD)
    assert hard <= float(parts_out["joint_range_margin"]) <= hard * math.exp(0.02 * math.log(41 * 1) / 0.05) * 1.0001
    assert (
        float(parts_out["capture_loss"]) > float(objective_parts(out, plain, free_target=False)["capture_loss"]) + 1.0
    )
    parts_in = objective_parts(inside, objective, free_target=False)
    assert float(parts_in["joint_range_margin"]) < 1e-3  # 0.5 rad inside: far from binding
    assert float(parts_in["capture_loss"]) == pytest.approx(
        float(objective_parts(inside, plain, free_target=False)["capture_loss"]), abs=1e-12
    )
    assert "joint_range_margin" not in objective_parts(out, plain, free_target=False)


def test_the_worst_case_criteria_measure_counts_a_joint_range():
    config = campaign.CampaignConfig(n=1)
    sample = {
        name: np.asarray([value], dtype=float)
        for name, value in {
            "final_position_error_m": 0.001,
            "final_orientation_error_rad": 0.001,
            "largest_peak_torque_Nm": 1.0,
            "first_nonfinite_s": np.nan,
            "first_runaway_s": np.nan,
        }.items()
    }
    without = worstcase.measure_of_metrics(sample, "criteria", config)
    assert without[0] == pytest.approx(0.2)  # 1 mm of 5
    sample["max_range_excess_rad"] = np.array([[np.nan, np.nan, 0.1, np.nan, np.nan, np.nan, np.nan]])
    assert worstcase.measure_of_metrics(sample, "criteria", config)[0] == pytest.approx(math.exp(0.1 / 0.05))
    ranges = joint_limits.finite_ranges(ranged_robot())
    log = swinging_log(1.1)
    measured = float(worstcase._measure_of_log(log, "criteria", config.criteria, ranges))
    assert measured == pytest.approx(math.exp((np.max(np.asarray(log.q)[:, 2]) - 1.0) / 0.05), rel=1e-12)


# ---- rate limits ----------------------------------------------------------------------------

RATES = (0.5,) * 7


def turning_log(peak_radps: float, n: int = 41):
    """Joint 5 turns at up to ``peak_radps`` (a sine arch of rate), the others still; EE on target."""
    t = np.arange(n) * 0.01
    qd = np.zeros((n, 7))
    qd[:, 4] = peak_radps * np.sin(np.pi * t / t[-1])
    return log_of(t, qd=qd)


def rate_sample(peaks) -> dict:
    """One sample's campaign metrics: a clean capture with the joints' peak rates ``peaks``."""
    return {
        "final_position_error_m": np.array([0.001]),
        "final_orientation_error_rad": np.array([0.001]),
        "largest_peak_torque_Nm": np.array([1.0]),
        "first_nonfinite_s": np.array([np.nan]),
        "first_runaway_s": np.array([np.nan]),
        "max_joint_rate_radps": np.asarray([peaks], dtype=float),
    }


def test_a_joint_faster_than_a_stated_rate_limit_fails_the_capture_and_the_verdict_says_which():
    peaks = [0.1, 0.2, 0.3, 0.4, 0.9, 0.3, 0.2]  # joint 5 at 0.9 rad/s against 0.5
    config = campaign.CampaignConfig(n=1, criteria=CaptureCriteria(joint_rate_limits_radps=RATES))
    classes = campaign.classify(rate_sample(peaks), config)
    assert classes["failure"][0] == "joint_rate" and classes["joint_rate_margin"][0] == pytest.approx(0.9 / 0.5)
    summary = {
        "final_position_error_m": 0.001,
        "final_orientation_error_rad": 0.001,
        "largest_peak_torque_Nm": 1.0,
        "first_nonfinite_s": None,
        "max_joint_rate_radps": peaks,
    }
    line = anatomy.verdict_line(summary, classes, config.criteria)
    assert line == "capture failed (joint_rate): joint 5 turned at 0.9 rad/s > its limit 0.5"
    # Without stated limits (the paper's arm), the same sample is a capture, as before.
    plain = campaign.classify(rate_sample(peaks), campaign.CampaignConfig(n=1))
    assert plain["failure"][0] == "success" and np.isnan(plain["joint_rate_margin"][0])
    assert CaptureCriteria().to_dict()["joint_rate_limits_radps"] is None
    # Within the limits, a capture; a runaway (ten times the robot's limit) stays a runaway.
    assert campaign.classify(rate_sample([0.49] * 7), config)["failure"][0] == "success"
    runaway = rate_sample([9.0] * 7) | {"first_runaway_s": np.array([1.0])}
    assert campaign.classify(runaway, config)["failure"][0] == "runaway"


@pytest.mark.parametrize("limits", [(), (0.5, -1.0), (0.5, math.inf), ("fast",), (True,)])
def test_rate_limits_as_criteria_must_be_positive_finite_numbers(limits):
    with pytest.raises(ValueError, match="joint_rate_limits_radps"):
        CaptureCriteria(joint_rate_limits_radps=limits)


def test_the_capture_objective_counts_a_stated_rate_limit_as_a_margin():
    """The margin is a smooth upper bound of the hard largest |qd_i| / limit_i (within the
    smooth maximum's T log(entries)); without rate limits the objective is as before."""
    objective = Objective(
        Weights(),
        (1.0,) * 7,
        kind="capture",
        torque_constraint_Nm=LIMITS,
        criteria=CaptureCriteria(joint_rate_limits_radps=RATES),
    )
    plain = dataclasses.replace(objective, criteria=CaptureCriteria())
    fast, slow = turning_log(0.9), turning_log(0.01)  # slow: 2% of the limit, far below the other margins
    parts_fast = objective_parts(fast, objective, free_target=False)
    hard = np.max(np.abs(np.asarray(fast.qd)) / np.asarray(RATES))
    assert hard == pytest.approx(1.8, rel=1e-12)
    assert hard <= float(parts_fast["joint_rate_margin"]) <= hard + 0.02 * math.log(41 * 7) + 1e-12
    assert float(parts_fast["capture_loss"]) > float(objective_parts(fast, plain, free_target=False)["capture_loss"])
    assert "joint_rate_margin" not in objective_parts(fast, plain, free_target=False)
    parts_slow = objective_parts(slow, objective, free_target=False)  # well inside: the loss stays ~0
    assert float(parts_slow["joint_rate_margin"]) < 0.2 and float(parts_slow["capture_loss"]) < 1e-9
    with pytest.raises(ValueError, match="joint_rate_limits_radps: need 7 numbers"):
        Objective(
            Weights(),
            (1.0,) * 7,
            kind="capture",
            torque_constraint_Nm=LIMITS,
            criteria=CaptureCriteria(joint_rate_limits_radps=(0.5,) * 6),
        )


def test_a_tuning_run_judges_its_held_out_captures_by_the_stated_rate_limits():
    from spacegrasp_jax.tuning.run import captured
    from spacegrasp_jax.tuning.tune import TuneConfig, make_objective

    parts = {
        "final_position_error_m": np.array([0.001, 0.001]),
        "final_orientation_error_rad": np.array([0.001, 0.001]),
        "largest_peak_torque_Nm": np.array([1.0, 1.0]),
        "loss": np.array([0.0, 0.0]),
        "first_nonfinite_s": np.full(2, np.nan),
        "max_joint_rate_radps": np.array([[0.1] * 6 + [0.45], [0.1] * 6 + [0.6]]),  # the second passes 0.5 rad/s
    }
    assert captured(parts, CaptureCriteria()).tolist() == [True, True]  # no rate limits: rates are no criterion
    assert captured(parts, CaptureCriteria(joint_rate_limits_radps=(0.5,) * 7)).tolist() == [True, False]
    config = TuneConfig(joint_rate_limits_radps=[0.5] * 7)
    assert config.joint_rate_limits_radps == RATES
    assert make_objective(sg.paper_robot(), config, (1.0,) * 7).criteria.joint_rate_limits_radps == RATES
    assert make_objective(sg.paper_robot(), TuneConfig(), (1.0,) * 7).criteria.joint_rate_limits_radps is None
    with pytest.raises(ValueError, match="joint_rate_limits_radps"):
        TuneConfig(joint_rate_limits_radps=(0.5, 0.0))


def test_the_worst_case_criteria_measure_counts_a_stated_rate_limit():
    sample = rate_sample([0.1, 0.2, 0.3, 0.4, 0.9, 0.3, 0.2])
    plain = campaign.CampaignConfig(n=1)
    assert worstcase.measure_of_metrics(sample, "criteria", plain)[0] == pytest.approx(0.2)  # 1 mm of 5
    config = campaign.CampaignConfig(n=1, criteria=CaptureCriteria(joint_rate_limits_radps=RATES))
    assert worstcase.measure_of_metrics(sample, "criteria", config)[0] == pytest.approx(1.8)
    log = turning_log(0.9)
    assert float(worstcase._measure_of_log(log, "criteria", config.criteria, ())) == pytest.approx(1.8, rel=1e-12)
