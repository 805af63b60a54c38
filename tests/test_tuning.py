"""Tuning: the objective, the parameterisation, gradients against finite differences, the
divergence guard, and the shipped tuned gains. A batch's gradient: test_tuning_batch.py; the
``spacegrasp tune`` command: test_tune_cli.py."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from central_differences import check_each_group
from toy_problems import descend

from spacegrasp_jax.envelope.scenario import paper_scenario
from spacegrasp_jax.loop.simulate import RunSpec, rollout
from spacegrasp_jax.tuning.objective import Objective, Weights, objective_parts, smooth_max
from spacegrasp_jax.tuning.parameters import GROUPS, gains_from_params, initial_params, make_mask
from spacegrasp_jax.tuning.tune import (
    BLOCK_STEPS,
    TuneConfig,
    make_loss,
    make_objective,
    make_value_and_grad,
    torque_constraint_Nm,
    training_scenarios,
)

SHORT = dict(duration=1.0, move_duration=1.0)  # contact starts at about 0.45 s


def test_a_runs_settings_split_into_the_problem_and_the_methods_own_and_read_back_flat():
    """A ``TuneConfig`` holds the method's settings as its own dataclass; the flat table its
    files write (the command line's names) reads back to the same settings, and a record of
    an older version, which held every method's settings, reads as the method's alone."""
    from spacegrasp_jax.tuning import CMAESSettings, GradientSettings

    structured = TuneConfig(method="gradient", settings=GradientSettings(learning_rate=0.05, optimizer="sgd"), batch=3)
    assert TuneConfig.of(method="gradient", learning_rate=0.05, optimizer="sgd", batch=3) == structured
    flat = structured.to_dict()
    assert flat["learning_rate"] == 0.05 and "population" not in flat and "settings" not in flat
    assert TuneConfig.from_dict(flat) == structured
    older = flat | {"population": None, "step_size": CMAESSettings().step_size, "separable": False}
    assert TuneConfig.from_dict(older) == structured
    assert TuneConfig(method="cmaes").settings == CMAESSettings()  # None: the method's defaults
    with pytest.raises(ValueError, match="settings: CMA-ES's are a CMAESSettings, got GradientSettings"):
        TuneConfig(method="cmaes", settings=GradientSettings())
    with pytest.raises(ValueError, match="population: a setting of CMA-ES; the gradient method does not use it"):
        TuneConfig.from_dict(flat | {"population": 8})


def _with_aggregate(config, aggregate: str):
    """``config`` with the gradient method's ``aggregate`` setting replaced."""
    return dataclasses.replace(config, settings=dataclasses.replace(config.settings, aggregate=aggregate))


def test_smooth_max_bounds_the_hard_max():
    rng = np.random.default_rng(0)
    values = jnp.asarray(rng.uniform(0.0, 1.0, size=(500, 7)))
    for temperature in (0.1, 0.02, 0.005):
        smooth = float(smooth_max(values, temperature))
        hard = float(jnp.max(values))
        assert hard <= smooth <= hard + temperature * math.log(values.size)
    assert float(smooth_max(values, 1e-4)) == pytest.approx(float(jnp.max(values)), abs=1e-3)


def test_weights_parse():
    assert Weights.parse("peak_torque=4, final_position=2") == Weights(final_position=2.0, peak_torque=4.0)
    assert Weights.parse("") == Weights()
    for bad, message in [
        ("speed=1", "unknown weight 'speed'"),
        ("peak_torque=x", "needs a number"),
        ("rms_tracking=-1", "non-negative"),
    ]:
        with pytest.raises(ValueError, match=message):
            Weights.parse(bad)


def test_config_validation():
    for change, message in [
        (dict(controller="pid"), "controller"),
        (dict(method="gradient", learning_rate=0.0), "learning_rate: must be positive"),
        (dict(steps=0), "steps"),
        (dict(cvar_alpha=1.0), "cvar_alpha"),
        (dict(method="gradient", optimizer="newton"), "'newton' is not an optax optimiser"),
        (dict(method="gradient", optimizer="clip"), "'clip' is not an optax optimiser"),
        (dict(frozen=("K_lin",)), "K_lin not a gain group of the admittance law"),
        (dict(frozen=("Md", "Bd", "Kd", "kp", "ki", "kd", "pinv_damping")), "nothing to tune"),
        (dict(method="newton"), "method: expected one of gradient, cmaes"),
        (dict(objective="speed"), "objective: expected one of capture, weighted"),
        (dict(population=1), "population: must be a whole number"),
        (dict(torque_fraction=0.0), "torque_fraction: must be positive"),
        (dict(weights=Weights(peak_torque=2.0)), "choose it \\(--objective weighted\\)"),
        (dict(objective="weighted", torque_fraction=0.5), "the weighted objective has none"),
        (dict(torque_cap_Nm=0.0), "torque_cap_Nm: must be positive and finite"),
        (dict(torque_cap_Nm=float("nan")), "torque_cap_Nm: must be positive and finite"),
        (dict(objective="weighted", torque_cap_Nm=4.0), "the weighted objective has none"),
        (dict(step_size=0.0), "step_size: must be positive"),
        (dict(method="gradient", step_size=0.1), "step_size: a setting of CMA-ES; the gradient method does not use it"),
        (dict(learning_rate=0.3), "learning_rate: a setting of the gradient method"),  # CMA-ES: the default method
        (dict(optimizer="sgd"), "optimizer: a setting of the gradient method"),
        (dict(gradient="forward"), "gradient: a setting of the gradient method"),
        (dict(torque_guard_Nm=50.0), "torque_guard_Nm: a setting of the gradient method"),
        (dict(realism={}, aggregate="clip"), "aggregate: a setting of the gradient method"),
        (dict(method="gradient", aggregate="clip"), "aggregate: clip combines the samples' separate gradients"),
        (dict(method="gradient", realism={}, gradient="forward"), "gradient: tuning under a realism"),
        (dict(method="gradient", fresh_batches=True), "fresh_batches: draws each step's samples"),
        (dict(method="gradient", aggregate="trimmed"), "aggregate: trimmed combines the samples' separate"),
        (dict(method="gradient", separable=True), "separable: a setting of CMA-ES"),
        (dict(realism={}, noise_handling=True), "noise_handling: measures the noise .* \\(choose --fresh-batches\\)"),
        (dict(separable=1), "separable: must be true or false"),
    ]:
        with pytest.raises(ValueError, match=message):
            TuneConfig.of(**change)
    assert TuneConfig(realism={}, fresh_batches=True).method == "cmaes"  # a new batch every generation
    assert TuneConfig.of(realism={}, fresh_batches=True, noise_handling=True, separable=True).settings.noise_handling


def test_torque_constraint_is_the_lower_of_the_fraction_and_the_cap(robot):
    limits = np.asarray(robot.joint_torque_limit, dtype=float)  # the paper's arm: 10, 10, 10, 5, 5, 2, 2 N m
    assert torque_constraint_Nm(robot, TuneConfig()) == tuple(limits)
    assert torque_constraint_Nm(robot, TuneConfig(torque_fraction=0.4)) == tuple(0.4 * limits)
    capped = torque_constraint_Nm(robot, TuneConfig(torque_cap_Nm=4.0))
    assert capped == (4.0, 4.0, 4.0, 4.0, 4.0, 2.0, 2.0)
    both = torque_constraint_Nm(robot, TuneConfig(torque_fraction=0.5, torque_cap_Nm=4.0))
    assert both == (4.0, 4.0, 4.0, 2.5, 2.5, 1.0, 1.0)
    assert make_objective(robot, TuneConfig(torque_cap_Nm=4.0), (1.0,) * 7).torque_constraint_Nm == capped


def test_an_objective_has_one_torque_scale_and_constraint_a_joint():
    """A 6-joint arm's objective with the paper's seven limits is refused when it is made."""
    Objective(weights=Weights(), torque_scale_Nm=(1.0,) * 6, torque_constraint_Nm=(5.0,) * 6)
    with pytest.raises(ValueError, match=r"torque_constraint_Nm: need 6 positive numbers \(one a joint\)"):
        Objective(weights=Weights(), torque_scale_Nm=(1.0,) * 6)
    with pytest.raises(ValueError, match=r"torque_scale_Nm: need one positive number a joint"):
        Objective(weights=Weights(), torque_scale_Nm=(1.0,) * 6 + (0.0,), torque_constraint_Nm=(5.0,) * 7)


def test_parameters_round_trip_and_mask(gains):
    params = initial_params(gains, "admittance")
    assert sum(p.size for p in params.values()) == 39 + 1  # the gains and the damping
    rebuilt = gains_from_params(params, gains, make_mask(gains, "admittance"))
    for name in ("Md", "Bd", "Kd", "kp", "ki", "kd"):
        np.testing.assert_allclose(getattr(rebuilt, name), getattr(gains, name), rtol=1e-14)
    np.testing.assert_allclose(rebuilt.pinv_damping, [1e-3], rtol=1e-14)  # tuned from its start
    frozen = gains_from_params(params, gains, make_mask(gains, "admittance", frozen=("pinv_damping",)))
    np.testing.assert_array_equal(frozen.pinv_damping, [0.0])  # frozen: the paper's exact law
    mask = make_mask(gains, "admittance", frozen=("kd",))
    moved = gains_from_params({k: v + 1.0 for k, v in params.items()}, gains, mask)
    np.testing.assert_array_equal(moved.kd, gains.kd)  # frozen
    np.testing.assert_allclose(moved.kp, np.e * np.asarray(gains.kp), rtol=1e-14)
    assert set(initial_params(gains, "cartesian")) == set(GROUPS["cartesian"])
    with pytest.raises(ValueError, match="unknown gain group"):
        make_mask(gains, "admittance", frozen=("Kx",))


def test_objective_parts_on_a_synthetic_log(full_runs):
    log = full_runs["admittance"].log
    scale = tuple(np.max(np.abs(log.u), axis=0))
    weights = Weights(final_position=1.0, final_orientation=0.1, rms_tracking=0.1, peak_torque=10.0, contact_force=0.5)
    parts = objective_parts(log, Objective(weights=weights, torque_scale_Nm=scale), free_target=False)
    assert float(parts["peak_torque_hard"]) == pytest.approx(1.0)  # the log's own peaks
    assert 0.0 <= float(parts["peak_torque_gap"]) <= 0.02 * math.log(log.u.size)
    expected = (
        float(parts["final_position_error_m"]) / 1e-3
        + 0.1 * float(parts["final_orientation_error_rad"]) / 1e-2
        + 0.1 * float(parts["rms_tracking_m"]) / 1e-2
        + 10.0 * float(parts["peak_torque_smooth"])
        + 0.5 * float(parts["peak_contact_smooth_N"]) / 10.0
    )
    assert float(parts["loss"]) == pytest.approx(expected, rel=1e-12)


@pytest.fixture(scope="module")
def short_problem(robot, gains, full_runs):
    """``build(controller, scenario=None, segment=BLOCK_STEPS) -> (loss, params,
    value_and_grad)``: the loss of a law on a scenario (by default 1 s with smooth contact),
    its initial parameters and its jitted reverse-mode gradient. The default scenario's are
    built once per law, so the tests share one compiled gradient."""
    built = {}

    def build(controller, scenario=None, segment=BLOCK_STEPS):  # the tuning default (1,000 steps)
        shared = scenario is None and segment == BLOCK_STEPS
        if shared and controller in built:
            return built[controller]
        scenario = scenario or paper_scenario(robot, contact_law="smooth", **SHORT)
        config = TuneConfig(
            controller=controller, batch=1, objective="weighted", method="gradient"
        )  # the nominal scenario alone
        scale = tuple(float(x) for x in full_runs[controller].summary["max_abs_torque_Nm"])
        objective = Objective(weights=Weights(contact_force=0.1), torque_scale_Nm=scale)
        mask = make_mask(gains, controller)
        params = initial_params(gains, controller)
        loss = make_loss(robot, training_scenarios(scenario, config), gains, mask, config, objective, segment)
        problem = loss, params, make_value_and_grad(loss, params, "reverse")
        if shared:
            built[controller] = problem
        return problem

    return build


@pytest.mark.slow
@pytest.mark.parametrize("controller", ["admittance", "cartesian"])
def test_gradient_of_each_gain_group_matches_central_differences(short_problem, controller):
    loss, params, value_and_grad = short_problem(controller)
    (value, aux), gradient = value_and_grad(params)
    assert float(aux["peak_contact_hard_N"]) > 0.0  # the scenario does include contact
    check_each_group(loss, params, gradient, GROUPS[controller], seed=5)


@pytest.mark.slow
def test_forward_mode_gradient_equals_reverse_mode(short_problem):
    loss, params, value_and_grad = short_problem("cartesian")  # shared with the central-differences test
    (_, _), reverse = value_and_grad(params)
    (_, _), forward = make_value_and_grad(loss, params, "forward")(params)
    for group in params:
        np.testing.assert_allclose(forward[group], reverse[group], rtol=1e-8, atol=1e-12)


@pytest.mark.slow
def test_gradient_finite_when_the_ee_passes_through_the_sphere_centre(robot, gains, short_problem):
    """With a tiny stiffness the EE follows its path undisturbed; the sphere's centre is put
    half a millimetre off that path at 0.5 s, so the EE passes by the contact law's singular
    point (the force grows as 1/distance^2 there): no NaN or inf. The scenario has the shared
    program's shapes (its centre and stiffness are values), so no gradient is compiled for it."""
    scenario = paper_scenario(robot, contact_law="smooth", contact_stiffness=1e-6, **SHORT)
    simulate = jax.jit(rollout, static_argnums=3)
    params = initial_params(gains, "admittance")
    tuned_start = gains_from_params(params, gains, make_mask(gains, "admittance"))
    _, free_path = simulate(robot, scenario, tuned_start, "admittance")
    centre = np.asarray(free_path.pose_ee[500, :3]) + np.array([0.0, 0.0, 5e-4])  # LAR frame
    scenario = dataclasses.replace(scenario, sphere_centre=jnp.asarray(centre))
    _, params, value_and_grad = short_problem("admittance", scenario)
    (value, aux), gradient = value_and_grad(params)
    assert np.isfinite(float(value))
    assert all(np.all(np.isfinite(g)) for g in jax.tree.leaves(gradient))
    _, log = simulate(robot, scenario, tuned_start, "admittance")
    distance = np.linalg.norm(np.asarray(log.pose_ee[:, :3]) - centre, axis=1)
    assert distance.min() < 1e-3  # within a millimetre of the centre


@pytest.mark.slow
def test_divergence_guard_rejects_and_shrinks_the_step(short_problem):
    """A learning rate of 3 in log space multiplies gains by up to e^3 in one step: the
    closed loop blows up, the step is rejected, the step size halved and the event logged;
    the run goes on from finite gains."""
    _, params, value_and_grad = short_problem("admittance")  # shared with the central-differences test
    config = TuneConfig.of(steps=2, learning_rate=3.0, torque_guard_Nm=20.0, objective="weighted", method="gradient")
    result = descend(value_and_grad, params, config)
    state, method_state = result.state, result.state.method_state
    assert result.status == "done" and state.step == 2
    assert len(state.events) >= 1 and all(event["event"] == "rejected" for event in state.events)
    assert method_state.scale < 1.0
    assert np.isfinite(method_state.loss) and method_state.aux["max_largest_peak_torque_Nm"] <= 20.0
    assert sum(row["rejected_candidates"] for row in state.history) == len(state.events)


def test_shipped_tuned_gains_capture_with_less_torque_on_the_nominal_scenario(robot, full_runs):
    """``tuned_gains()`` (tuned for capture success in the paper's loop, the torque constraint
    at a quarter of the motors' limits) on the nominal 17 s scenario with the exact contact
    law: a capture by the campaigns' criteria, a largest peak torque below the paper's gains',
    every joint within a quarter of its motor's limit, no runaway (documentation, "Tuning the
    gains")."""
    from spacegrasp_jax.jobs import experiment
    from spacegrasp_jax.loop.control import tuned_gains

    paper = full_runs["admittance"].summary
    tuned = experiment.run(RunSpec(robot, paper_scenario(robot), "admittance"), tuned_gains()).summary
    assert tuned["final_position_error_m"] < 0.005 and tuned["final_orientation_error_rad"] < np.radians(1.0)
    assert tuned["largest_peak_torque_Nm"] < 0.8 * paper["largest_peak_torque_Nm"]
    limits = 0.25 * np.asarray(robot.joint_torque_limit)
    assert all(peak < limit for peak, limit in zip(tuned["max_abs_torque_Nm"], limits))
    assert np.isnan(tuned["first_runaway_s"])


def test_the_shipped_flight_gains_are_the_races_winner_and_their_settings_say_what_the_data_say():
    """``tuned_gains("flight")`` are bit for bit the race's best gradient-recipe run at 15
    minutes on its held-out campaign (seed 730001), and the gains the confirmation campaign
    (seed 7312071, fixed before) ran; the ``settings.json``'s counts, McNemar tests and
    torques are that campaign's, and the data meet the bar the gains shipped on: at least
    94% of 1,000 captures, a 95th-percentile largest peak of at most 3.0 N m, no runaway,
    McNemar p < 0.05 against the gains shipped before."""
    import json
    from pathlib import Path

    from spacegrasp_jax.envelope import statistics
    from spacegrasp_jax.jobs.campaign import campaign_record, load_samples
    from spacegrasp_jax.loop.control import tuned_gains
    from spacegrasp_jax.loop.control.gains import load_gains, tuned_gains_file

    race = Path(__file__).resolve().parents[1] / "notebooks" / "data" / "race_seeds_constant"
    shipped = tuned_gains("flight")
    winner = load_gains(race / "gains" / "gradient_fresh_seed1_15min.json", "admittance")
    assert shipped.to_dict("admittance") == winner.to_dict("admittance")
    summary = json.loads((race / "race.json").read_text())["summary"]["runs"]
    fifteen = {label: run["success"]["rate"] for label, run in summary.items() if label.startswith("gradient_fresh")}
    fifteen = {label: rate for label, rate in fifteen.items() if label.endswith("_15min")}
    assert max(fifteen, key=fifteen.get) == "gradient_fresh_seed1_15min"

    settings = json.loads(tuned_gains_file("flight").with_suffix(".settings.json").read_text())["heldout"]
    record, _ = campaign_record(race / "confirm_7312071")
    ran = {variant.label: variant.gains for variant in record.variants}
    assert ran[settings["labels"]["these"].split("/", 1)[1]].to_dict("admittance") == shipped.to_dict("admittance")
    _, by_variant = load_samples(race / "confirm_7312071" / "samples.npz")
    success = {name: np.asarray(by_variant[label]["success"], bool) for name, label in settings["labels"].items()}
    peaks = np.asarray(by_variant[settings["labels"]["these"]]["largest_peak_torque_Nm"])
    assert settings["successes"] == {name: int(hits.sum()) for name, hits in success.items()}
    for reference in ("previous", "paper"):
        expected = statistics.compare_success(success[reference], success["these"])["p_value"]
        assert settings["mcnemar_p"][reference] == pytest.approx(expected, rel=1e-12)
    assert settings["largest_peak_torque_Nm_p50_p95"][1] == round(float(np.percentile(peaks, 95)), 2)
    assert len(success["these"]) == 1000 and success["these"].mean() >= 0.94
    assert np.percentile(peaks, 95) <= 3.0 and settings["mcnemar_p"]["previous"] < 0.05
    assert not np.any(np.isfinite(np.asarray(by_variant[settings["labels"]["these"]]["first_runaway_s"])))


@pytest.mark.slow
def test_shipped_flight_tuned_gains_capture_closer_than_the_paper_under_flight(robot):
    """``tuned_gains("flight")`` (tuned for capture success) under the flight preset, nominal
    17 s scenario, exact contact law, noise key 0: a capture by the campaigns' criteria,
    ending closer to the ring than the paper's gains under the same loop and key, with every
    joint's peak within its motor's limit (the robot's ``joint_torque_limit``) and no runaway
    (documentation, "Tuning the gains")."""
    from spacegrasp_jax.jobs import experiment
    from spacegrasp_jax.loop.control import paper_gains, tuned_gains
    from spacegrasp_jax.loop.realism import flight

    scenario, key = paper_scenario(robot), jax.random.PRNGKey(0)
    paper, tuned = (
        experiment.run(RunSpec(robot, scenario, "admittance", realism=flight()), gains, key=key).summary
        for gains in (paper_gains(), tuned_gains("flight"))
    )
    assert tuned["final_position_error_m"] < 0.8 * paper["final_position_error_m"] < 0.005
    assert tuned["final_orientation_error_rad"] < np.radians(1.0)
    assert all(peak < limit for peak, limit in zip(tuned["max_abs_torque_Nm"], np.asarray(robot.joint_torque_limit)))
    assert np.isnan(tuned["first_runaway_s"])
    with pytest.raises(ValueError, match="loop must be one of ideal, flight, free_target"):
        tuned_gains("orbit")


@pytest.mark.slow
def test_shipped_free_target_gains_capture_the_envelopes_nominal_target_without_pushing_it_away(robot):
    """``tuned_gains("free_target")`` under the flight preset against the free_target
    envelope's nominal target (632 kg at rest, CoM 0.25 m behind the ring), 17 s, exact
    contact law, noise key 0: a capture by the campaigns' criteria (within 5 mm and 1 deg,
    the target's final speed within 5 mm/s), every joint within its motor's limit and no
    runaway (documentation, "Tuning the gains")."""
    from pathlib import Path

    from spacegrasp_jax.envelope.scenario import load_scenario
    from spacegrasp_jax.jobs import experiment
    from spacegrasp_jax.loop.control import tuned_gains
    from spacegrasp_jax.loop.realism import flight

    scenario = load_scenario(robot, Path(__file__).resolve().parents[1] / "configs" / "free_target_envelope.toml")
    summary = experiment.run(
        RunSpec(robot, scenario, "admittance", realism=flight()), tuned_gains("free_target"), key=jax.random.PRNGKey(0)
    ).summary
    assert summary["final_position_error_m"] < 0.005 and summary["final_orientation_error_rad"] < np.radians(1.0)
    assert summary["final_target_speed_mps"] < 0.005
    assert all(peak < limit for peak, limit in zip(summary["max_abs_torque_Nm"], np.asarray(robot.joint_torque_limit)))
    assert np.isnan(summary["first_runaway_s"])


def test_a_chaotic_samples_gradient_is_clipped_to_a_multiple_of_the_median():
    from spacegrasp_jax.tuning.tune import CLIP_FACTOR, aggregate_gradients

    losses = jnp.array([1.0, 2.0, 3.0, 4.0])
    gradients = {"kp": jnp.array([[1.0, 0.0], [0.0, 1.0], [0.6, 0.8], [100.0, 0.0]])}  # norms 1, 1, 1, 100
    total, plain, clipped = aggregate_gradients(losses, gradients, TuneConfig.of(aggregate="mean"))
    clipping = TuneConfig.of(method="gradient", realism={}, aggregate="clip")  # the flight-like batch's option
    assert float(total) == 2.5 and int(clipped) == 0
    np.testing.assert_allclose(plain["kp"], [101.6 / 4, 1.8 / 4])
    total, robust, clipped = aggregate_gradients(losses, gradients, clipping)
    assert float(total) == 2.5 and int(clipped) == 1
    # The fourth gradient scaled to 3 x the median norm (1), its direction kept.
    np.testing.assert_allclose(robust["kp"], [(1.6 + CLIP_FACTOR) / 4, 1.8 / 4])
    # CVaR: the worst half only.
    total, worst, _ = aggregate_gradients(losses, gradients, dataclasses.replace(clipping, cvar_alpha=0.5))
    assert float(total) == 3.5
    np.testing.assert_allclose(worst["kp"], [(0.6 + CLIP_FACTOR) / 2, 0.8 / 2])
    with pytest.raises(ValueError, match="aggregate"):
        TuneConfig.of(aggregate="median")


def test_robust_estimators_of_the_batch_gradient_keep_the_gradients_structure():
    """``trimmed`` and ``median_of_means`` on a batch of two gain groups: per gain, SciPy's
    trimmed mean and NumPy's median of the group means, over the samples' flattened
    gradients, back in the groups' shapes."""
    from scipy import stats

    from spacegrasp_jax.tuning.tune import aggregate_gradients

    rng = np.random.default_rng(0)
    gradients = {"kp": jnp.asarray(rng.standard_normal((20, 3))), "Md": jnp.asarray(rng.standard_normal((20, 2, 2)))}
    gradients["kp"] = gradients["kp"].at[4].mul(1e3)  # a chaotic sample
    losses = jnp.asarray(rng.random(20))
    flat = np.concatenate([np.asarray(gradients["kp"]), np.asarray(gradients["Md"]).reshape(20, 4)], axis=1)
    base = TuneConfig(method="gradient", realism={})
    total, trimmed, clipped = aggregate_gradients(losses, gradients, _with_aggregate(base, "trimmed"))
    expected = stats.trim_mean(flat, 0.1, axis=0)
    assert float(total) == pytest.approx(float(jnp.mean(losses))) and int(clipped) == 0
    np.testing.assert_allclose(trimmed["kp"], expected[:3], rtol=1e-14)
    np.testing.assert_allclose(trimmed["Md"], expected[3:].reshape(2, 2), rtol=1e-14)
    _, median, _ = aggregate_gradients(losses, gradients, _with_aggregate(base, "median_of_means"))
    groups = np.median(np.stack([part.mean(axis=0) for part in np.array_split(flat, 4)]), axis=0)
    np.testing.assert_allclose(median["kp"], groups[:3], rtol=1e-14)
    np.testing.assert_allclose(median["Md"], groups[3:].reshape(2, 2), rtol=1e-14)
    assert abs(float(median["kp"][0])) < 5.0 and abs(float(trimmed["kp"][0])) < 5.0  # the chaotic sample ignored
    with pytest.raises(ValueError, match="aggregate: trimmed estimates the batch mean's gradient; CVaR"):
        dataclasses.replace(_with_aggregate(base, "trimmed"), cvar_alpha=0.5)


def test_a_candidate_whose_loss_runs_away_is_rejected_even_within_the_torque_guard():
    """With saturating motors an unstable candidate keeps its torques small while the EE
    drifts away: the loss guard (10x the starting loss) catches it. A toy loss whose
    candidates past ``p = 1`` blow up: the first step (to p = 2) is rejected, the half step
    (to p = 1) accepted."""
    calls = []

    def value_and_grad(params):
        p = float(params["kp"][0])
        calls.append(p)
        loss = 1.0 - p if p <= 1.5 else 1e3
        return (jnp.asarray(loss), {"max_largest_peak_torque_Nm": jnp.asarray(1.0)}), {"kp": -jnp.ones(1)}

    config = TuneConfig.of(
        steps=1,
        learning_rate=2.0,
        optimizer="sgd",
        clip_norm=10.0,
        loss_guard=10.0,
        objective="weighted",
        method="gradient",
    )
    result = descend(value_and_grad, {"kp": jnp.zeros(1)}, config)
    assert result.status == "done" and calls == [0.0, 2.0, 1.0]
    assert len(result.state.events) == 1 and result.state.events[0]["loss"] == 1e3
    assert float(result.state.method_state.params["kp"][0]) == 1.0


def test_a_run_that_can_take_no_further_step_ends_diverged_keeping_its_best_step():
    """A toy loss whose candidates past ``p = 1.2`` blow up: the first step (to p = 1) is
    accepted, every candidate of the second (p = 2, 1.5, 1.25, 1.125, ...) is rejected until
    the step scale falls below 1e-6: the run ends ``"diverged"`` at step 1, its best step
    being step 1, instead of raising."""

    def value_and_grad(params):
        p = float(params["kp"][0])
        loss = 1.0 - p if p <= 1.0 + 1e-9 else 1e3
        return (jnp.asarray(loss), {"max_largest_peak_torque_Nm": jnp.asarray(1.0)}), {"kp": -jnp.ones(1)}

    config = TuneConfig.of(
        steps=5, learning_rate=1.0, optimizer="sgd", clip_norm=10.0, objective="weighted", method="gradient"
    )
    result = descend(value_and_grad, {"kp": jnp.zeros(1)}, config)
    state = result.state
    assert result.status == "diverged"
    assert state.step == 1 and state.best_step == 1 and float(state.best_point["kp"][0]) == 1.0
    assert float(result.point["kp"][0]) == 1.0 and result.kept["step"] == 1
    assert len(state.events) == 20 and state.method_state.scale < 1e-6  # 2^-20 < 1e-6 <= 2^-19


def test_a_cmaes_record_that_wrote_the_unused_clip_still_resumes():
    """Records written before the gradient method's settings were refused under CMA-ES hold
    ``aggregate = "clip"`` for flight-like CMA-ES runs, which never read it: such a record
    reads as the same run, and a resume that asks for the same options finds no difference."""
    from spacegrasp_jax.tuning.run import resume_differences

    config = TuneConfig(realism={}, batch=2)
    old_record = {"config": config.to_dict() | {"aggregate": "clip"}}
    assert TuneConfig.from_dict(old_record["config"]) == config
    assert resume_differences(old_record, config, None, None, None) == []


def test_a_resume_checks_the_options_given_against_the_recorded_run(tmp_path, capsys):
    """``tune --resume --lr 0.5`` on a gradient-method run: the options given are compared
    with the record, not checked against the command line's defaults of the others (CMA-ES,
    which takes no learning rate); on a CMA-ES run the same option is refused as unused."""
    import json

    from spacegrasp_jax import cli
    from spacegrasp_jax.loop.realism import flight
    from spacegrasp_jax.tuning.run import new_record

    runs = {
        "gradient": TuneConfig.of(method="gradient", realism=flight().to_dict(), aggregate="clip", batch=2),
        "cmaes": TuneConfig(realism=flight().to_dict(), batch=2),
    }
    for name, config in runs.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / "run.json").write_text(json.dumps(new_record(config, None, None, None, 3)))
        (tmp_path / name / ".spacegrasp-run.json").write_text(json.dumps({"command": "tune"}))
    capsys.readouterr()
    assert cli.main(["tune", "--out", str(tmp_path / "gradient"), "--resume", "--lr", "0.5", "--batch", "2"]) == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert "--lr 0.5 (the run's: 0.15)" in line and "--batch" not in line, line
    assert cli.main(["tune", "--out", str(tmp_path / "cmaes"), "--resume", "--lr", "0.5"]) == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert "--lr: a setting of the gradient method" in line, line


def test_the_gradient_method_keeps_its_best_step_and_a_checkpoint_keeps_it_too(tmp_path):
    """Plain SGD on loss = (p - 1)^2 plus a penalty of 5 for 0.9 < p < 1.1 (its gradient left
    out), learning rates 0.8, 0.62, 0.26 (the cosine schedule over 3 steps, down to a tenth:
    0.08 + 0.72 (1 + cos(pi k / 3)) / 2): p goes 0, 1.6, 0.856, 0.93088, the losses 1, 0.36,
    0.020736, 5.0047775744. The last step is worse than step 2: step 2's parameters are kept, and
    a checkpoint keeps them too."""
    from spacegrasp_jax.tuning import driver
    from spacegrasp_jax.tuning.tune import make_method

    def value_and_grad(params):
        p = params["kp"][0]
        loss = (p - 1.0) ** 2 + jnp.where((p > 0.9) & (p < 1.1), 5.0, 0.0)
        return (loss, {"max_largest_peak_torque_Nm": jnp.asarray(1.0)}), {"kp": jnp.atleast_1d(2.0 * (p - 1.0))}

    config = TuneConfig.of(
        steps=3,
        learning_rate=0.8,
        optimizer="sgd",
        clip_norm=100.0,
        loss_guard=100.0,
        objective="weighted",
        method="gradient",
    )
    path = tmp_path / "checkpoint.npz"
    result = descend(value_and_grad, {"kp": jnp.zeros(1)}, config, checkpoint_path=path, write_atomically=_write)
    state = result.state
    np.testing.assert_allclose([row["loss"] for row in state.history], [1.0, 0.36, 0.020736, 5.0047775744], rtol=1e-12)
    assert result.status == "done" and state.step == 3 and state.best_step == 2
    assert float(state.best_point["kp"][0]) == pytest.approx(0.856, rel=1e-12)
    assert float(result.point["kp"][0]) == float(state.best_point["kp"][0]) and result.kept["step"] == 2
    assert float(state.method_state.params["kp"][0]) == pytest.approx(0.93088, rel=1e-12)
    template = {"kp": jnp.zeros(1)}
    restored = driver.load_checkpoint(path, make_method(config), template, {"kp": np.ones(1, bool)}, seed=0)
    assert restored.best_step == 2 and float(restored.best_point["kp"][0]) == float(state.best_point["kp"][0])


def _write(path, write):
    write(path)


def test_cmaes_best_is_the_least_objective_it_told_or_the_final_mean():
    from spacegrasp_jax.tuning.cmaes import CMAES, CMAESState

    class Strategy:
        mean = np.array([9.0, 9.0])

    asked = [np.array([[0.0, 0.0], [1.0, 1.0]]), np.array([[2.0, 2.0], [3.0, 3.0]])]
    told = [np.array([5.0, 4.0]), np.array([3.0, 6.0])]
    state = CMAESState(Strategy(), {"x": np.zeros(2)}, {"x": np.ones(2, bool)}, asked, told, 2, "candidates")
    history = [{"loss": 7.0}, {"loss": 6.5}, {"loss": 3.5}]
    point, step, what, value = CMAES().best(state, history, 2, None)
    assert point["x"].tolist() == [2.0, 2.0] and value == 3.0 and step is None
    assert what == "the best candidate of generation 2"
    history[-1]["loss"] = 3.0  # the final mean as good: it is kept
    point, step, what, value = CMAES().best(state, history, 2, None)
    assert point["x"].tolist() == [9.0, 9.0] and value == 3.0 and step == 2 and what == "the mean after generation 2"


def test_early_stopping_ends_a_gradient_run_when_the_validation_objective_stalls():
    """The training loss keeps falling (SGD on (p - 1)^2: p goes 0, 0.6, 0.83, 0.93, ...) while
    a made-up validation objective, (p - 0.5)^2, is least at step 1 (0.01, then 0.11, 0.18):
    with a patience of 2 the run stops at step 3, and its best step is the validation's, not
    the training loss's."""

    def value_and_grad(params):
        p = params["kp"][0]
        return ((p - 1.0) ** 2, {"max_largest_peak_torque_Nm": jnp.asarray(1.0)}), {
            "kp": jnp.atleast_1d(2.0 * (p - 1.0))
        }

    config = TuneConfig.of(
        steps=10,
        learning_rate=0.3,
        optimizer="sgd",
        clip_norm=100.0,
        objective="weighted",
        method="gradient",
        patience=2,
    )
    validated = []

    def validate(params):
        validated.append(float(params["kp"][0]))
        return (float(params["kp"][0]) - 0.5) ** 2

    result = descend(value_and_grad, {"kp": jnp.zeros(1)}, config, validate=validate)
    state = result.state
    losses = [row["validation_loss"] for row in state.history]
    assert result.status == "stopped_early" and state.best_step == 1 and state.step == 3
    assert state.best_step == int(np.argmin(losses)) and float(state.best_point["kp"][0]) == validated[state.best_step]
    assert result.kept["rule"] == "best by validation" and float(result.point["kp"][0]) == validated[1]
    assert [row["loss"] for row in state.history] == sorted([row["loss"] for row in state.history], reverse=True)
    with pytest.raises(ValueError, match="patience: must be at least 1"):
        dataclasses.replace(config, patience=0)
    with pytest.raises(ValueError, match="validation_size: the validation set of early stopping"):
        TuneConfig(validation_size=8)


def test_early_stopping_ends_a_cmaes_run_and_its_checkpoint_keeps_the_validations(tmp_path):
    from toy_problems import ToyProblem, start

    from spacegrasp_jax.tuning import cmaes, driver

    def batch_parts(vectors):
        losses = np.sum((vectors - 1.0) ** 2, axis=1, keepdims=True)
        return {"loss": losses, "final_position_error_m": losses, "largest_peak_torque_Nm": losses}

    calls = []

    def validate(mean):  # least at the start: every later mean is worse, so the run stops at once
        calls.append(np.asarray(mean["x"]))
        return float(np.sum(np.asarray(mean["x"]) ** 2))

    path = tmp_path / "cmaes.npz"
    point, mask = start(3)
    method = cmaes.CMAES(population=6)
    common = dict(steps=30, seed=1, validate=validate, patience=3)
    result = driver.optimise(
        ToyProblem(batch_parts), method, point, mask, checkpoint_path=path, write_atomically=lambda p, w: w(p), **common
    )
    state = result.state
    assert result.status == "stopped_early" and state.step == 3 and len(calls) == 4
    assert (
        result.kept["step"] == 0
        and result.kept["validation_objective"] == 0.0
        and result.point["x"].tolist() == [0.0] * 3
    )
    resumed = driver.load_checkpoint(path, method, point, mask, seed=1)
    assert [row["validation_loss"] for row in resumed.history] == [row["validation_loss"] for row in state.history]
    calls.clear()
    again = driver.optimise(ToyProblem(batch_parts), method, point, mask, resume=resumed, **common)
    assert again.status == "stopped_early" and calls == [] and again.kept == result.kept


def test_the_settings_walk_counts_modules_and_climbs_to_a_higher_layer():
    """The walk's summary on a walk written by hand: three modules, one climb (jobs back up to
    the tuning); a step within a layer is no climb."""
    from spacegrasp_jax.benchmarks.config_walk import summary

    walk = [
        ("spacegrasp_jax.tuning.run", "tune", "config"),
        ("spacegrasp_jax.tuning.tune", "to_dict", "self"),
        ("spacegrasp_jax.jobs.montecarlo", "sample_loops", "ranges"),
        ("spacegrasp_jax.jobs.montecarlo", "perturbed_loop", "ranges"),
        ("spacegrasp_jax.tuning.run", "evaluate", "config"),
    ]
    found = summary(walk)
    assert found["modules"] == [
        "spacegrasp_jax.tuning.run",
        "spacegrasp_jax.tuning.tune",
        "spacegrasp_jax.jobs.montecarlo",
    ]
    assert found["climbs"] == 1 and len(found["calls"]) == 5


@pytest.mark.slow
def test_a_tuning_runs_settings_visit_few_modules_and_climb_back_rarely(tmp_path):
    """Followed through the calls of a one-step CMA-ES run (``benchmarks.config_walk``), the
    run's settings visit at most 8 modules and climb back to a higher layer at most 3 times."""
    from spacegrasp_jax.benchmarks.config_walk import summary, walk_of_tune

    found = summary(walk_of_tune("cmaes", "ideal", tmp_path))
    assert found["modules"][0] == "spacegrasp_jax.tuning.run"
    assert found["module_count"] <= 8 and found["climbs"] <= 3, found


def test_the_progress_line_says_which_statistic_each_number_is():
    """The torque on a tuning step's line is the objective's peak over its constraint (a
    ratio, batch mean); the largest peak in N m is the batch's largest (the torque guard's)."""
    from spacegrasp_jax.tuning.tune import progress_line

    aux = {
        "final_position_error_m": 0.003,
        "peak_torque_smooth": 1.31,
        "peak_torque_hard": 1.29,
        "peak_torque_gap": 0.02,
        "rms_tracking_m": 0.0135,
        "max_largest_peak_torque_Nm": 0.73,
    }
    line = progress_line(9, 0.0886, aux, 75)
    assert "peak torque / constraint 1.310 (hard 1.290, gap 0.020)" in line
    assert "(batch means) | largest peak 0.73 N m (batch max)" in line
