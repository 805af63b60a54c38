"""Time-domain stability margins (``spacegrasp_jax.analysis.margins``, ``spacegrasp margins``).

The searches are checked on stand-in probes whose answer is known, then on the flight-like
loop of a 2 s capture: the extra delay at the controller's output against the realism's own
delay line (the same loop, built another way), the delay margin against a brute-force
sweep over every delay, and the gain margin's bracket re-run through a Monte-Carlo
campaign's program (which knows nothing of margins).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spacegrasp_jax import cli
from spacegrasp_jax.analysis import margins, stability
from spacegrasp_jax.envelope.criteria import CaptureCriteria
from spacegrasp_jax.jobs import campaign
from spacegrasp_jax.jobs.montecarlo import success
from spacegrasp_jax.loop import simulate
from spacegrasp_jax.loop.control import paper_gains
from spacegrasp_jax.loop.realism import flight

# ---- the searches, on stand-in probes ----------------------------------------------------------


@dataclasses.dataclass
class ThresholdProbes:
    """Probes whose loop holds below a known factor (or delay) and fails from it on."""

    threshold: float
    settings: margins.MarginSettings = margins.MarginSettings(factor_resolution=1.01, max_delay_periods=100)
    probes: list = dataclasses.field(default_factory=list)

    def holds(self, loop, value):
        self.probes.append(value)
        if loop == "delay" or self.threshold >= 1.0:
            return value < self.threshold
        return value > self.threshold


@pytest.mark.parametrize("threshold", [1.3, 3.7, 50.0])
def test_the_gain_margin_brackets_a_known_threshold_upward(threshold):
    found = margins.gain_margin(ThresholdProbes(threshold), "pid", "increase")
    assert found["holds"] < threshold <= found["fails"]
    assert found["fails"] / found["holds"] <= 1.01
    assert found["margin_db"] == pytest.approx(20 * math.log10(found["holds"]))


def test_the_gain_margin_brackets_a_known_threshold_downward():
    found = margins.gain_margin(ThresholdProbes(0.21), "law", "decrease")
    assert found["fails"] <= 0.21 < found["holds"]
    assert found["holds"] / found["fails"] <= 1.01
    assert found["margin_db"] < 0


def test_a_loop_that_never_fails_reports_the_searchs_limit():
    probes = ThresholdProbes(1e9)
    found = margins.gain_margin(probes, "pid", "increase")
    assert found == {"holds": 64.0, "fails": None, "margin_db": 20 * math.log10(64.0), "probes": 3, "limited_by": None}
    assert probes.probes == [2.0, 8.0, 64.0]  # doubling the step in log2: 2^1, 2^3, then the limit 2^6


@pytest.mark.parametrize("threshold", [1, 2, 13, 64, 100])
def test_the_delay_margin_is_the_first_failing_delay(threshold):
    found = margins.delay_margin(ThresholdProbes(threshold), period_s=0.01)
    assert found["fails_periods"] == threshold
    assert found["holds_periods"] == threshold - 1
    assert found["fails_s"] == pytest.approx(0.01 * threshold)


def test_a_delay_that_never_fails_reports_the_searchs_limit():
    found = margins.delay_margin(ThresholdProbes(1000), period_s=0.001)
    assert (found["holds_periods"], found["fails_periods"], found["fails_s"]) == (100, None, None)


@pytest.mark.parametrize("controller", ["admittance", "cartesian"])
def test_a_law_gain_factor_scales_the_laws_loop_gain_only(controller):
    gains = paper_gains()
    scaled = margins.scaled_loop(gains, controller, "law", 4.0)
    for name in ("kp", "ki", "kd", "pinv_damping"):
        np.testing.assert_array_equal(getattr(scaled, name), getattr(gains, name))
    if controller == "cartesian":
        np.testing.assert_allclose(scaled.K_lin, 4.0 * gains.K_lin, rtol=1e-15)
        np.testing.assert_allclose(scaled.K_eul, 4.0 * gains.K_eul, rtol=1e-15)
    else:  # motion per newton 4x, pose-tracking dynamics unchanged
        np.testing.assert_allclose(1 / scaled.Md, 4.0 / gains.Md, rtol=1e-15)
        np.testing.assert_allclose(scaled.Bd / scaled.Md, gains.Bd / gains.Md, rtol=1e-15)
        np.testing.assert_allclose(scaled.Kd / scaled.Md, gains.Kd / gains.Md, rtol=1e-15)
    pid = margins.scaled_loop(gains, controller, "pid", 0.5)
    for name in ("kp", "ki", "kd"):
        np.testing.assert_allclose(getattr(pid, name), 0.5 * np.asarray(getattr(gains, name)), rtol=1e-15)
    np.testing.assert_array_equal(pid.Kd, gains.Kd)


def test_bad_settings_are_refused():
    for fields, message in (
        (dict(samples=0), "samples"),
        (dict(max_factor=1.0), "max_factor"),
        (dict(factor_resolution=1.0), "factor_resolution"),
        (dict(max_factor=2.0, factor_resolution=2.5), "factor_resolution"),
        (dict(max_delay_periods=0), "max_delay_periods"),
    ):
        with pytest.raises(margins.MarginError, match=message):
            margins.MarginSettings(**fields)


# ---- the flight-like loop of a 2 s capture ----------------------------------------------------

SAMPLES = 4
MAX_DELAY = 32


@pytest.fixture(scope="module")
def flight_capture(robot, short_scenario):
    """The criteria loosened to what 2 s of approach reaches (25 mm, 2 deg: one of the four
    samples captures at the nominal gains), under the flight preset."""
    config = campaign.CampaignConfig(
        n=SAMPLES,
        chunk=SAMPLES,
        realism=flight(),
        criteria=CaptureCriteria(position_tolerance_m=0.025, orientation_tolerance_rad=math.radians(2.0)),
    )
    settings = margins.MarginSettings(samples=SAMPLES, max_delay_periods=MAX_DELAY)
    prober = margins.Prober(robot, short_scenario, paper_gains(), "admittance", config, settings)
    return robot, short_scenario, config, prober


def _campaign_outcome(robot, scenario, config, gains):
    """Success and boundedness of the samples through a Monte-Carlo campaign's program."""
    metrics = campaign.evaluate_indices(
        robot, scenario, campaign.Variant("admittance", gains), config, np.arange(SAMPLES)
    )
    captured = success(metrics, config.criteria)
    bounded = ~(np.isfinite(metrics["first_runaway_s"]) | np.isfinite(metrics["first_nonfinite_s"]))
    return metrics, captured, bounded


@pytest.mark.slow
def test_an_extra_output_delay_is_the_realisms_delay_line_made_longer(flight_capture):
    robot, scenario, config, prober = flight_capture
    longer = dataclasses.replace(config, realism=dataclasses.replace(config.realism, delay_periods=1 + 3))
    expected, _, _ = _campaign_outcome(robot, scenario, longer, paper_gains())
    delayed = prober.outcome(paper_gains(), delay_periods=3)
    undelayed = prober.outcome(paper_gains(), delay_periods=0)
    for name in ("final_position_error_m", "final_orientation_error_rad", "max_abs_torque_Nm", "rms_position_error_m"):
        np.testing.assert_allclose(delayed[name], expected[name], rtol=1e-12, atol=1e-15, err_msg=name)
    assert not np.allclose(undelayed["final_position_error_m"], expected["final_position_error_m"], rtol=1e-6)


@pytest.mark.slow
def test_the_delay_margin_under_flight_matches_a_sweep_over_every_delay(flight_capture):
    _, _, config, prober = flight_capture
    found = margins.delay_margin(prober, period_s=config.realism.control_period)
    assert found["fails_periods"] is not None, "the search must reach a failure for the sweep to check it"
    # Every delay up to the one the search says fails, one by one: the first failure is it.
    swept = margins.sweep_delays(prober, range(found["fails_periods"] + 1))
    first_failure = swept.index(False)
    assert first_failure > 2, "a search that ends at its first probes checks little"
    assert found["fails_periods"] == first_failure
    assert found["holds_periods"] == first_failure - 1
    assert found["fails_s"] == pytest.approx(first_failure * 0.01)


@pytest.mark.slow
def test_the_servo_input_delay_margin_matches_a_sweep_over_every_delay(flight_capture):
    _, _, _, prober = flight_capture
    assert prober.servo_delay  # flight: ten servo ticks a control period
    found = margins.delay_margin(prober, period_s=0.001, loop="servo_delay")
    assert found["fails_periods"] is not None, "the search must reach a failure for the sweep to check it"
    # Every delay up to the one the search says fails, one by one: the first failure is it.
    swept = margins.sweep_delays(prober, range(found["fails_periods"] + 1), loop="servo_delay")
    first_failure = swept.index(False)
    assert first_failure > 2
    assert (found["holds_periods"], found["fails_periods"]) == (first_failure - 1, first_failure)
    assert found["fails_s"] == pytest.approx(first_failure * 0.001)


@pytest.mark.slow
def test_the_servo_input_delay_hands_the_pid_the_reading_of_d_ticks_before(robot, short_scenario):
    """In the log, what the PID read at each servo tick is the true joint rate d ticks
    earlier (the sensors' noise off), and zero before the first reading: the margins'
    servo delay line (``margins.delayed_spec()``)."""
    realism, d = stability.quiet(flight()), 7
    spec = simulate.RunSpec(robot, short_scenario, "admittance", realism=realism)
    spec = margins.delayed_spec(spec, 2, jnp.int32(0), 16, jnp.int32(d))
    body = simulate.loop_body(spec, paper_gains(), jax.random.PRNGKey(0))
    _, rows = jax.jit(lambda: jax.lax.scan(body.period, body.start, jnp.arange(50.0)))()
    measured = np.asarray(rows.qd_measured).reshape(-1, 7)  # one row a plant step, one tick a step
    true = np.asarray(rows.qd).reshape(-1, 7)
    assert np.abs(true).max() > 1e-3  # the arm moves
    np.testing.assert_array_equal(measured[d:], true[:-d])
    np.testing.assert_array_equal(measured[:d], 0.0)


@pytest.mark.slow
def test_the_gain_margin_fails_at_its_factor_and_holds_just_below_it(flight_capture):
    """The bracket re-run through a campaign's program: the joint PID gains times the factor
    that fails lose a capture the nominal gains make (or a bounded sample runs away); times
    the factor that holds, they do not; the two factors within the resolution."""
    robot, scenario, config, prober = flight_capture
    found = margins.gain_margin(prober, "pid", "increase")
    assert found["fails"] is not None and found["fails"] / found["holds"] <= prober.settings.factor_resolution
    nominal_metrics, nominal_captured, nominal_bounded = _campaign_outcome(robot, scenario, config, paper_gains())
    np.testing.assert_allclose(  # the margins' program at zero delay is the campaign's loop
        prober.nominal["final_position_error_m"], nominal_metrics["final_position_error_m"], rtol=1e-12
    )
    assert nominal_captured.any()

    def holds(factor):
        _, captured, bounded = _campaign_outcome(
            robot, scenario, config, margins.scaled_loop(paper_gains(), "admittance", "pid", factor)
        )
        return bool(np.all(captured | ~nominal_captured) and np.all(bounded | ~nominal_bounded))

    assert holds(found["holds"])
    assert not holds(found["fails"])


@pytest.mark.slow
def test_the_margins_command_writes_its_files_and_prints_the_margins(flight_capture, tmp_path, capsys, monkeypatch):
    """The command on the same loop and samples (it loads the program the tests above built)."""
    probed, find_margins = [], margins.find_margins

    def recording(*args, **kwargs):
        result = find_margins(*args, **kwargs)
        probed.append(copy.deepcopy(result))
        return result

    monkeypatch.setattr(margins, "find_margins", recording)
    scenario_file = tmp_path / "short.toml"
    scenario_file.write_text('duration = 2.0\n[trajectory]\nduration = 2.0\n[contact]\nlaw = "smooth"\n')
    out = tmp_path / "margins"
    argv = ["margins", "--realism", "flight", "--scenario", str(scenario_file), "--samples", str(SAMPLES)]
    argv += ["--max-delay", str(MAX_DELAY), "--tolerance-mm", "25", "--tolerance-deg", "2", "--out", str(out)]
    assert cli.main(argv) == 0
    printed = capsys.readouterr().out
    document = json.loads((out / "margins.json").read_text())
    assert (out / "margins.png").stat().st_size > 10_000
    delay = document["delay_margin"]
    assert f"{delay['holds_periods']} control periods ({delay['holds_s']:.4g} s) holds" in printed
    assert "joint PID gain: increase x" in printed and "admittance law gain:" in printed
    servo = document["servo_delay_margin"]
    assert document["servo_period_s"] == pytest.approx(0.001)
    assert f"{servo['holds_periods']} servo ticks ({servo['holds_s']:.4g} s) holds" in printed
    _, _, _, prober = flight_capture
    assert delay["fails_periods"] == margins.delay_margin(prober, 0.01)["fails_periods"]
    assert document["rollouts"] == len(document["probes"]) * SAMPLES
    assert document["settings"]["record"]["criteria"]["position_tolerance_m"] == pytest.approx(0.025)
    assert set(document["gain_margins"]) == {"pid", "law"}
    # The linear analysis (tests/test_stability.py checks it): its margins, modes and figure.
    linear = document["linear"]
    assert (out / "eigenvalues.png").stat().st_size > 10_000
    assert "linear joint PID gain margin" in printed and "least stable mode" in printed
    assert linear["control_period_s"] == pytest.approx(0.01)
    # What limits each margin, the linear verdict, the frequency response and its figures
    for loop in ("pid", "law"):
        for direction in ("increase", "decrease"):
            entry = document["gain_margins"][loop][direction]
            if entry["fails"] is not None:
                assert entry["limited_by"]["kind"] in ("stability", "capture criteria")
                assert margins.limit_words(entry["limited_by"]) in printed
    assert linear["verdict"]["kind"] in ("stable", "stable within the growth limit", "unstable")
    assert f"linearised loop: {linear['verdict']['words']}" in printed
    assert set(linear["frequency_response"]) == {"pid", "law"} and "bode" not in linear
    # The flight-like loop's servo ticks ten times a control period: its gain enters the
    # period's map as a polynomial, and that loop is not broken at one gain; the law is
    pid, law = linear["frequency_response"]["pid"], linear["frequency_response"]["law"]
    assert pid["affine_residual"] > 1e-2 and "gain_margins" not in pid
    assert "frequency response broken at the joint PID: not available" in printed
    assert law["affine_residual"] < 1e-8 and "frequency response broken at the law (6 channels)" in printed
    for name in ("bode.png", "nichols.png"):
        assert (out / name).stat().st_size > 10_000
    with np.load(out / "frequency_response.npz") as response:
        assert {"law/frequency_hz", "law/magnitude_db", "law/phase_deg"} == set(response.files)
        assert response["law/frequency_hz"][-1] == pytest.approx(50.0)  # the control period's Nyquist frequency
    assert (
        len(linear["modes"])
        == len(linear["operating_point"]["coordinates"]) - linear["operating_point"]["neutral_modes_removed"]
    )
    magnitudes = [mode["magnitude"] for mode in linear["modes"]]
    assert linear["spectral_radius"] == pytest.approx(max(magnitudes))
    for mode in linear["modes"]:
        if mode["growth_rate_per_s"] is not None:
            assert mode["growth_rate_per_s"] == pytest.approx(math.log(mode["magnitude"]) / 0.01)
    # --no-linear: the probes are the run's above (its 43 probes replayed, not run again),
    # and the linear analysis is neither run nor written.
    monkeypatch.setattr(margins, "find_margins", lambda *args, **kwargs: copy.deepcopy(probed[0]))
    monkeypatch.setattr(stability, "linear_analysis", lambda *a, **k: pytest.fail("--no-linear ran the analysis"))
    skipped = tmp_path / "no-linear"
    assert cli.main([*argv[:-1], str(skipped), "--no-linear"]) == 0
    again = json.loads((skipped / "margins.json").read_text())
    assert again["linear"] is None and again["linear_skipped"] == "--no-linear"
    assert not (skipped / "eigenvalues.png").exists()
    assert (skipped / "margins.png").stat().st_size > 10_000


def test_a_failing_probe_says_whether_stability_or_a_capture_criterion_ended_it():
    """``Prober.limited_by``: a sample bounded at the nominal gains that runs away makes it
    stability; samples that captured and now miss a tolerance, the capture criteria, named
    with their counts."""
    from types import SimpleNamespace

    nominal = {"success": np.array([True, True, False]), "bounded": np.array([True, True, True])}
    prober = SimpleNamespace(nominal=nominal, config=campaign.CampaignConfig(n=3, chunk=3))

    def result(position_m, runaway_s, success, bounded):
        return {
            "final_position_error_m": np.asarray(position_m),
            "final_orientation_error_rad": np.zeros(3),
            "largest_peak_torque_Nm": np.ones(3),
            "first_nonfinite_s": np.full(3, np.nan),
            "first_runaway_s": np.asarray(runaway_s),
            "success": np.asarray(success),
            "bounded": np.asarray(bounded),
        }

    accuracy = margins.Prober.limited_by(
        prober, result([0.001, 0.009, 0.02], [np.nan] * 3, [True, False, False], [True] * 3)
    )
    assert accuracy == {"kind": "capture criteria", "criteria": {"position": 1}}
    assert (
        margins.limit_words(accuracy) == "limited by the capture criteria, not stability (captures missed: position 1)"
    )
    unstable = margins.Prober.limited_by(
        prober, result([0.001, 0.001, 0.5], [np.nan, np.nan, 3.0], [True, True, False], [True, True, False])
    )
    assert unstable["kind"] == "stability" and unstable["criteria"]["runaway"] == 1
    assert margins.limit_words(None) == "not limited within the search"
