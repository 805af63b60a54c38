"""Why captures fail: failure classes, margins and the final error's parts on constructed runs
whose answer is known (a pure estimate error, a pure compliance offset, a runaway)."""

from __future__ import annotations

import dataclasses
import math

import jax
import numpy as np
import pytest
from hand_logs import log_of
from scipy.spatial.transform import Rotation

import spacegrasp_jax as sg
from spacegrasp_jax.core.contact import contact_force_exact
from spacegrasp_jax.envelope import metrics
from spacegrasp_jax.envelope.criteria import CaptureCriteria
from spacegrasp_jax.envelope.scenario import paper_scenario
from spacegrasp_jax.jobs import anatomy
from spacegrasp_jax.loop.realism import make_realism
from spacegrasp_jax.loop.simulate import Log

CRITERIA = CaptureCriteria(
    position_tolerance_m=0.005, orientation_tolerance_rad=math.radians(1.0), torque_threshold_Nm=100.0
)


@pytest.fixture(scope="module")
def scenario():
    return paper_scenario(sg.paper_robot())


def one_run(scenario, error_lar, force_lar, realism=None) -> dict:
    """The metrics and error parts of a run that ended with EE error ``error_lar`` and
    contact force ``force_lar`` (LAR axes), as one-sample arrays."""
    final = {"final_contact_force_N": np.asarray(force_lar, float)}
    parts = anatomy.error_parts(final, scenario, realism)
    run = {
        "final_position_error_m": np.linalg.norm(error_lar),
        "final_orientation_error_rad": 0.001,
        "largest_peak_torque_Nm": 3.0,
        "first_nonfinite_s": np.nan,
        "first_runaway_s": np.nan,
        "final_position_error_lar_m": np.asarray(error_lar, float),
    } | {name: np.asarray(value) for name, value in parts.items()}
    return {name: np.asarray(value)[None] for name, value in run.items()}


def test_a_pure_estimate_error_is_all_estimate(scenario):
    dp, dr = np.array([0.004, -0.003, 0.002]), np.array([0.02, -0.01, 0.03])
    realism = make_realism({"target_estimate": {"position_error_m": dp.tolist(), "angle_error_rad": dr.tolist()}})
    # The controller puts the EE on the desired point of the frame it believes:
    # p_hat + R_hat p_des, seen from the true LAR frame (Rotation: an independent exponential map).
    p_des = np.array(scenario.trajectory.end_pose[:3])
    error = dp + Rotation.from_rotvec(dr).apply(p_des) - p_des
    run = one_run(scenario, error, np.zeros(3), realism)
    parts = anatomy.error_decomposition(run)
    np.testing.assert_allclose(parts["final_error_estimate_m"], np.linalg.norm(error), rtol=1e-12)
    np.testing.assert_allclose(parts["final_error_residual_m"], 0.0, atol=1e-15)
    np.testing.assert_allclose(parts["final_error_compliance_m"], 0.0)
    np.testing.assert_allclose(parts["final_error_along_m"], error[2])
    np.testing.assert_allclose(parts["final_error_across_m"], np.hypot(error[0], error[1]))
    classes = anatomy.failure_classes(run, CRITERIA)
    assert classes["failure"][0] == "position"  # 5.4 mm > 5 mm
    np.testing.assert_allclose(classes["position_margin"], np.linalg.norm(error) / 0.005)
    # Without the estimate stage the same error is the controller's own.
    parts = anatomy.error_decomposition(one_run(scenario, error, np.zeros(3)))
    np.testing.assert_allclose(parts["final_error_residual_m"], np.linalg.norm(error), rtol=1e-12)


@pytest.mark.parametrize("direction", [(0.0, 0.0, 1.0), (0.6, 0.0, 0.8), (0.0, -0.28, 0.96)])
def test_a_pure_compliance_offset_is_all_compliance(scenario, direction):
    # The law holds the EE 0.7 mm deep in the sphere, on the normal through the desired
    # point's direction; the contact law (eq 20) gives the force there.
    centre, radius = np.array(scenario.sphere_centre), float(scenario.sphere_radius)
    normal = np.asarray(direction) / np.linalg.norm(direction)
    depth = 7e-4
    surface = centre + radius * normal  # where the EE would rest without a force
    ee = centre + (radius - depth) * normal
    force = np.asarray(contact_force_exact(ee - centre, radius, float(scenario.contact_stiffness)))
    run = one_run(scenario, ee - surface, force)
    parts = anatomy.error_decomposition(run)
    np.testing.assert_allclose(parts["final_error_compliance_m"], depth, rtol=1e-9)
    np.testing.assert_allclose(parts["final_error_residual_m"], 0.0, atol=1e-12)
    np.testing.assert_allclose(run["compliance_offset_lar_m"][0], ee - surface, atol=1e-12)


def runaway_log(rate_radps: float, torque_Nm: float) -> Log:
    """Four rows, 0.5 s apart; in the third, joint 3 turns at ``rate_radps`` and joint 7
    gives ``torque_Nm``."""
    n = 4
    qd, u = np.zeros((n, 7)), np.zeros((n, 7))
    qd[2, 2], u[2, 6] = rate_radps, torque_Nm
    return log_of(np.arange(n) * 0.5, u=u, qd=qd)


@pytest.mark.parametrize(
    "rate, torque, runaway",
    [
        (9.9, 0.0, False),  # the paper arm's joint 3: 1 rad/s, a runaway beyond 10 rad/s
        (10.1, 0.0, True),
        (0.0, 19.9, False),  # joint 7: 2 N m, a runaway beyond 20 N m
        (0.0, 20.1, True),
        (-139.0, 6.9e4, True),
    ],
)
def test_a_runaway_is_caught_in_the_fold(rate, torque, runaway):
    robot = sg.paper_robot()
    log = runaway_log(rate, torque)
    whole = metrics.log_metrics(log, robot, free_target=False)
    running = metrics.start(robot=robot)
    for k in range(4):  # row by row, as the campaign's scan folds them
        running = metrics.accumulate(running, jax.tree.map(lambda x: x[k : k + 1], log))
    one_by_one = metrics.finish(running, free_target=False)
    assert float(one_by_one["first_runaway_s"]) == float(whole["first_runaway_s"]) or (
        np.isnan(one_by_one["first_runaway_s"]) and np.isnan(whole["first_runaway_s"])
    )
    assert (float(whole["first_runaway_s"]) == 1.0) == runaway
    assert np.isnan(float(whole["first_runaway_s"])) == (not runaway)
    np.testing.assert_allclose(whole["max_joint_rate_radps"][2], abs(rate))
    # Without a robot nothing is a runaway.
    assert np.isnan(float(metrics.log_metrics(log, free_target=False)["first_runaway_s"]))
    sample = {name: np.asarray(value)[None] for name, value in whole.items()}
    classes = anatomy.failure_classes(sample, dataclasses.replace(CRITERIA, torque_threshold_Nm=None))
    assert (classes["failure"][0] == "runaway") == runaway
    if runaway:
        summary = {name: np.asarray(value).tolist() for name, value in whole.items()}
        line = anatomy.verdict_line(summary, classes, CaptureCriteria(0.005, 0.01))
        assert line.startswith("capture failed (runaway): at t = 1.00 s") and f"{abs(rate):.3g} rad/s" in line


def test_failure_classes_order_and_margins():
    inf, nan = np.inf, np.nan
    sample = {
        "final_position_error_m": np.array([0.001, 0.006, 0.001, nan, 0.02, 0.001, 0.001]),
        "final_orientation_error_rad": np.array([0.001, 0.001, 0.03, nan, 0.001, 0.001, 0.001]),
        "largest_peak_torque_Nm": np.array([1.0, 1.0, 1.0, 5.0, 200.0, 500.0, 1.0]),
        "first_nonfinite_s": np.array([nan, nan, nan, 3.0, nan, nan, nan]),
        "first_runaway_s": np.array([nan, nan, nan, nan, nan, 2.0, nan]),
        "final_target_speed_mps": np.array([0.001, 0.001, 0.001, 0.0, 0.001, 0.001, 0.009]),
    }
    classes = anatomy.failure_classes(sample, dataclasses.replace(CRITERIA, target_speed_limit_mps=0.005))
    assert list(classes["failure"]) == [
        "success",
        "position",
        "orientation",
        "diverged",
        "torque_threshold",  # 200 N m, also 20 mm off
        "runaway",
        "target_speed",
    ]
    assert classes["failed_position"][4] and classes["failed_torque_threshold"][4]
    np.testing.assert_allclose(classes["position_margin"][:2], [0.2, 1.2])
    np.testing.assert_allclose(classes["torque_margin"][4], 2.0)
    np.testing.assert_allclose(classes["target_speed_margin"][6], 1.8)
    assert inf not in classes["position_margin"]
    summary = anatomy.anatomy_summary(
        sample | classes | {"final_position_error_lar_m": np.tile([0.0, 0.0, 0.001], (7, 1))}
    )
    assert summary["first_failure"]["success"] == 1 and summary["first_failure"]["runaway"] == 1
    assert summary["any_failure"]["position"] == 2


def test_the_decomposition_adds_up(scenario):
    rng = np.random.default_rng(5)
    realism = make_realism({"target_estimate": {"position_error_m": [0.001, 0.002, -0.001]}})
    for _ in range(20):
        error, force = rng.normal(0, 0.003, 3), rng.normal(0, 2.0, 3)
        run = one_run(scenario, error, force, realism)
        total = run["estimate_offset_lar_m"][0] + run["compliance_offset_lar_m"][0]
        residual = anatomy.error_decomposition(run)["final_error_residual_m"][0]
        np.testing.assert_allclose(residual, np.linalg.norm(error - total), rtol=1e-12)
    assert dataclasses.is_dataclass(scenario)


def test_a_position_failure_is_said_in_one_line_with_its_parts(scenario):
    realism = make_realism({"target_estimate": {"position_error_m": [0.004, -0.003, 0.002]}})
    run = one_run(scenario, [0.0046, -0.0031, 0.0019], np.zeros(3), realism)
    summary = {name: np.asarray(value[0]).tolist() for name, value in run.items()}
    classes = anatomy.failure_classes(run, CRITERIA)
    line = anatomy.verdict_line(summary, classes, CaptureCriteria(0.005, 0.01745))
    # |(4.6, -3.1, 1.9)| = 5.86 mm; across sqrt(4.6^2 + 3.1^2) = 5.55; estimate |(4, -3, 2)| = 5.39;
    # residual |(0.6, -0.1, -0.1)| = 0.62.
    assert line.startswith("capture failed (position): final position error 5.86 mm > 5")
    assert "along the approach +1.90, across 5.55; estimate 5.39, compliance 0.00, residual 0.62" in line


def test_one_runs_capture_verdict_is_its_margins_over_the_campaigns_tolerances():
    # A run's summary.json verdict, from the library: each margin is the value over its
    # tolerance (defaults: 5 mm, 1 deg, 100 N m), the first missed criterion names the class.
    from spacegrasp_jax.jobs import campaign

    summary = {
        "final_position_error_m": 0.003,
        "final_orientation_error_rad": np.radians(0.25),
        "largest_peak_torque_Nm": 150.0,
        "max_abs_torque_Nm": [150.0] + [1.0] * 6,
        "first_nonfinite_s": float("nan"),
        "first_runaway_s": float("nan"),
        "final_position_error_lar_m": [0.0, 0.0, -0.003],
        "estimate_offset_lar_m": [0.0, 0.0, 0.0],
        "compliance_offset_lar_m": [0.0, 0.0, -0.001],
    }
    verdict = campaign.with_capture_verdict(summary)
    assert verdict["capture_margins"]["position_margin"] == pytest.approx(0.6)
    assert verdict["capture_margins"]["orientation_margin"] == pytest.approx(0.25)
    assert verdict["capture_margins"]["torque_margin"] == pytest.approx(1.5)
    assert verdict["capture_margins"]["target_speed_margin"] is None  # a fixed target: no such criterion
    assert not verdict["capture_success"] and verdict["capture_missed"] == ["torque_threshold"]
    assert verdict["final_error_parts_m"]["along"] == pytest.approx(-0.003)
    assert verdict["final_error_parts_m"]["residual"] == pytest.approx(0.002)
    loose = CaptureCriteria(torque_threshold_Nm=200.0)
    assert campaign.with_capture_verdict(summary, loose)["capture_success"]
    assert campaign.with_capture_verdict(summary, loose)["capture_criteria"]["torque_threshold_Nm"] == 200.0
    assert campaign.with_capture_verdict({"diverged": True}) == {"diverged": True}
