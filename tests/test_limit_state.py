"""A capture's margin as the limit state of the reliability methods
(``spacegrasp_jax.analysis.limit_state``) and ``spacegrasp reliability``.

The margin is checked against the campaign's own verdict (``montecarlo.success()``, which knows
nothing of margins), sample for sample; its gradient against central differences; the
command's most probable failures against ``spacegrasp simulate --perturbation``, which knows
nothing of the estimator. Every capture is a 2 s approach: what is checked does not depend on
the scenario's length.
"""

from __future__ import annotations

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spacegrasp_jax import cli
from spacegrasp_jax.analysis import limit_state, reliability, worstcase
from spacegrasp_jax.envelope.criteria import CaptureCriteria
from spacegrasp_jax.envelope.perturbations import PerturbationRanges
from spacegrasp_jax.envelope.scenario import paper_scenario
from spacegrasp_jax.envelope.standard_space import StandardSpace
from spacegrasp_jax.jobs import campaign
from spacegrasp_jax.jobs.montecarlo import success
from spacegrasp_jax.loop.control import paper_gains

pytest.importorskip("openturns")

#: The campaigns' envelope and, as a 2 s approach ends 12-77 mm from the LAR (the median 43
#: mm, 0.7-3.2 deg), tolerances that half the captures meet.
RANGES = PerturbationRanges()
CRITERIA = CaptureCriteria(position_tolerance_m=0.045, orientation_tolerance_rad=math.radians(3.0))
SAMPLES = 32


def _metrics(**values) -> dict:
    """Campaign metrics of three captures, every criterion met but what ``values`` sets."""
    n = 3
    base = {
        "final_position_error_m": np.full(n, 0.001),
        "final_orientation_error_rad": np.full(n, 0.001),
        "largest_peak_torque_Nm": np.full(n, 2.0),
        "max_range_excess_rad": np.full((n, 7), np.nan),
        "max_joint_rate_radps": np.full((n, 7), 0.1),
        "first_runaway_s": np.full(n, np.nan),
        "first_nonfinite_s": np.full(n, np.nan),
    }
    return base | {name: np.asarray(value, dtype=float) for name, value in values.items()}


@pytest.mark.parametrize(
    ("values", "criteria"),
    [
        ({"final_position_error_m": [0.004, 0.005, 0.0051]}, CaptureCriteria()),
        ({"final_orientation_error_rad": [0.01, 0.0175, 0.02]}, CaptureCriteria()),
        ({"largest_peak_torque_Nm": [99.0, 100.0, 1e4]}, CaptureCriteria()),
        ({"first_runaway_s": [np.nan, 3.0, np.nan], "first_nonfinite_s": [np.nan, np.nan, 1.0]}, CaptureCriteria()),
        ({"max_range_excess_rad": [[-0.1] * 7, [0.0] * 7, [-0.1] * 6 + [0.01]]}, CaptureCriteria()),
        (
            {"max_joint_rate_radps": [[0.5] * 7, [0.6] * 7, [0.2] * 6 + [0.7]]},
            CaptureCriteria(joint_rate_limits_radps=(0.6,) * 7),
        ),
        ({"final_target_speed_mps": [0.001, 0.005, 0.006]}, CaptureCriteria()),
        ({"final_position_error_m": [0.004, 0.02, 0.0051]}, CaptureCriteria(torque_threshold_Nm=None)),
    ],
)
def test_the_margin_is_negative_exactly_where_a_criterion_is_missed(values, criteria):
    """Captures at, inside and past each criterion: ``g < 0`` exactly where the campaign's
    ``success()`` says failed, a capture exactly at a tolerance a success with ``g = 0``."""
    metrics = _metrics(**values)
    g = np.asarray(limit_state.capture_margin(metrics, criteria))
    np.testing.assert_array_equal(g < 0.0, ~success(metrics, criteria))
    assert np.all(np.isfinite(g))


@pytest.fixture(scope="module")
def short_campaign(robot):
    """The limit state of the paper's gains on a 2 s approach, forward only, and the campaign's
    own samples 0-31 run by the campaign's program."""
    scenario = paper_scenario(robot, duration=2.0, move_duration=2.0)
    config = campaign.CampaignConfig(n=SAMPLES, chunk=SAMPLES, ranges=RANGES, criteria=CRITERIA, seed=3)
    state = limit_state.limit_state(robot, scenario, paper_gains(), "admittance", config, block=16, gradient=False)
    variant = campaign.Variant("admittance", paper_gains())
    samples = campaign.evaluate_indices(robot, scenario, variant, config, np.arange(SAMPLES))
    return state, samples, scenario, config


def test_the_margin_fails_exactly_the_campaigns_failed_samples(short_campaign):
    """The limit state's Monte-Carlo runs the campaign's samples: each sample's margin is
    negative exactly where the campaign's verdict is a failure (some of both), and the same
    samples evaluated at their standard normal coordinates give the same margins."""
    state, samples, _, config = short_campaign
    metrics = {name: value for name, value in samples.items() if not name.startswith("perturbation.")}
    captured = success(metrics, config.criteria)
    assert 0 < np.sum(captured) < SAMPLES
    from_campaign = state.limit_state.campaign_values(0, SAMPLES)
    np.testing.assert_array_equal(from_campaign["g"] < 0.0, ~captured)
    np.testing.assert_allclose(from_campaign["g"], limit_state.capture_margin(metrics, config.criteria), rtol=1e-12)
    at_coordinates = state.limit_state.values(from_campaign["z"], 0)  # point k: the noise of sample k
    np.testing.assert_array_equal(at_coordinates["g"] < 0.0, ~captured)
    np.testing.assert_allclose(at_coordinates["g"], from_campaign["g"], rtol=1e-9, atol=1e-12)
    assert state.space.dimension == 38


def test_montecarlo_is_the_campaigns_failure_rate(short_campaign):
    state, samples, _, config = short_campaign
    metrics = {name: value for name, value in samples.items() if not name.startswith("perturbation.")}
    failures = int(np.sum(~success(metrics, config.criteria)))
    result = reliability.estimate(
        state.limit_state, reliability.Settings(method="montecarlo", budget=SAMPLES, block=16)
    )
    assert result.probability == failures / SAMPLES
    assert (result.low, result.high) == reliability.binomial_interval(failures, SAMPLES)
    assert result.failing == failures and result.design_points[0]["failure"] in ("position", "orientation")


@pytest.mark.slow
def test_the_margins_gradient_matches_central_differences(robot):
    """At three of the campaign's samples of the short approach, the margin's reverse-mode
    gradient in the standard normal coordinates, along a random direction, equals the central
    difference of the forward program's margins (the fixed noise draw), and the gradient
    program's margin is the forward program's."""
    scenario = paper_scenario(robot, duration=2.0, move_duration=2.0)
    config = campaign.CampaignConfig(n=4, ranges=RANGES, criteria=CRITERIA, seed=3)
    state = limit_state.limit_state(robot, scenario, paper_gains(), "admittance", config, block=4, gradient=True)
    z = state.limit_state.campaign_values(0, 3)["z"]
    direction = np.random.default_rng(4).normal(size=z.shape)
    h = 1e-6
    for point, d in zip(z, direction, strict=True):
        at = state.limit_state.value_and_gradient(point)
        forward = state.limit_state.fixed_values(np.stack([point, point + h * d, point - h * d]))["g"]
        np.testing.assert_allclose(at["g"], forward[0], rtol=1e-10, atol=1e-12)
        slope = float(np.dot(at["gradient"], d))
        assert abs(slope) > 0
        np.testing.assert_allclose(slope, (forward[1] - forward[2]) / (2 * h), rtol=1e-4, atol=1e-9)


def test_the_command_writes_failures_that_simulate_replays_and_resumes(tmp_path, capsys, short_campaign):
    """``spacegrasp reliability --method montecarlo`` on the short approach: its estimate is
    the campaign's failure rate; each most probable failure's perturbation file, run by
    ``spacegrasp simulate --perturbation``, gives the capture's margin to 1e-9; run again with
    ``--resume`` it replays its journal to the same estimate."""
    _, samples, _, config = short_campaign
    scenario_file = tmp_path / "short.toml"
    scenario_file.write_text("duration = 2.0\n[trajectory]\nduration = 2.0\n")
    out = tmp_path / "reliability"
    argv = [
        "reliability",
        "--scenario",
        str(scenario_file),
        "--method",
        "montecarlo",
        "--budget",
        str(SAMPLES),
        "--block",
        "16",
        "--seed",
        "3",
        "--tolerance-mm",
        "45",
        "--tolerance-deg",
        "3",
        "--design-points",
        "2",
        "--out",
        str(out),
    ]
    assert cli.main(argv) == 0
    document = json.loads((out / "reliability.json").read_text())
    metrics = {name: value for name, value in samples.items() if not name.startswith("perturbation.")}
    failures = int(np.sum(~success(metrics, config.criteria)))
    assert document["estimate"]["probability"] == failures / SAMPLES
    assert (out / "reliability.png").stat().st_size > 0
    assert "montecarlo: p = " in capsys.readouterr().out
    for k, replay in enumerate(document["design_point_files"]):
        command = replay["replay"].split()[1:]
        assert command[:3] == ["simulate", "--controller", "admittance"]
        assert cli.main(command) == 0
        summary = json.loads((out / f"replay_{k + 1}" / "summary.json").read_text())["admittance"]
        needed = ("final_position_error_m", "final_orientation_error_rad", "largest_peak_torque_Nm")
        needed += ("max_range_excess_rad", "first_runaway_s", "first_nonfinite_s")
        replayed = {name: np.asarray(summary[name], dtype=float) for name in needed}
        margin = float(limit_state.capture_margin(replayed, config.criteria))
        np.testing.assert_allclose(margin, replay["margin"], rtol=1e-9, atol=1e-12)
        assert margin < 0.0
    assert cli.main([*argv, "--resume"]) == 0
    again = json.loads((out / "reliability.json").read_text())
    assert again["estimate"]["probability"] == document["estimate"]["probability"]
    assert again["estimate"]["wall_s"] == document["estimate"]["wall_s"]  # replayed, not run again
    capsys.readouterr()
    changed = [*argv, "--resume"]
    changed[changed.index("--budget") + 1] = "48"
    assert cli.main(changed) == 2  # refused before anything compiles
    assert f"--resume: {out} was run with estimator setting budget = 32, this command has 48" in capsys.readouterr().err


def test_units_of_a_design_point_stay_in_the_box():
    space = StandardSpace.of(RANGES, free_target=False, n_joints=7)
    far = jnp.full(space.dimension, 40.0)
    units = jax.tree.map(np.asarray, space.to_units(far))
    assert all(np.all(np.abs(value) <= 1.0) for value in vars(units).values())
    worstcase.units_from_dict(worstcase.units_to_dict(units))  # a perturbation file's units
