"""The free-floating target (spacegrasp_jax.core.target): the stationary limit, momentum shared
with the chaser, torque-free motion against invariants and the analytic precession, the
contact's impulse, the relative twist against finite differences, gradients, and the
scenario's [target] table."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spacegrasp_jax.core import spatial
from spacegrasp_jax.envelope import metrics
from spacegrasp_jax.envelope.scenario import ScenarioError, paper_scenario, scenario_from_mapping
from spacegrasp_jax.loop.simulate import rollout

ROLLOUT = jax.jit(rollout, static_argnames=("controller",))

#: A few hundred kilograms, its CoM half a metre behind the LAR plane.
TARGET = dict(mass=300.0, inertia=[[50.0, 2.0, 0.0], [2.0, 60.0, 0.0], [0.0, 0.0, 70.0]], com_in_lar=[0.0, 0.0, 0.5])


def free(scenario, robot, **target):
    """``scenario``'s settings with a free-floating target (2 s, the approach compressed)."""
    return paper_scenario(robot, duration=2.0, move_duration=2.0, contact_law="smooth", target={**TARGET, **target})


@pytest.fixture(scope="module")
def pushed(robot, gains):
    """The admittance law pushing a 300 kg target at rest (contact from about 0.9 s)."""
    scenario = free(None, robot)
    return scenario, ROLLOUT(robot, scenario, gains, "admittance")[1]


def rotations(log):
    return np.asarray(jax.vmap(spatial.quat_to_rotation)(log.target_quat))


def test_the_papers_fixed_target_is_a_body_at_rest_that_never_moves(robot, gains, short_scenario):
    # The fixed target is in the state and the log like a free one, and stays exactly where
    # the scenario put it: the LAR's origin and attitude, at rest; it counts no momentum.
    assert not short_scenario.free_target and not short_scenario.initial.target.free
    final, log = ROLLOUT(robot, short_scenario, gains, "cartesian")
    assert float(jnp.max(jnp.linalg.norm(log.contact_force, axis=1))) > 0.1  # it was pushed
    rows = len(log.t)
    np.testing.assert_array_equal(log.target_position, np.tile(short_scenario.p_lar, (rows, 1)))
    np.testing.assert_array_equal(log.target_quat, np.tile(short_scenario.initial.target.quat, (rows, 1)))
    np.testing.assert_allclose(rotations(log)[0], short_scenario.R_lar, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(log.target_velocity, 0.0)
    np.testing.assert_array_equal(log.target_angular_velocity, 0.0)
    np.testing.assert_array_equal(log.momentum_total, log.momentum)
    assert jax.tree.all(jax.tree.map(np.array_equal, final.plant.target, short_scenario.initial.target))
    # Its report keeps the paper's metrics only (its speeds and drift are zero by construction).
    assert "final_target_speed_mps" not in metrics.summary(log, free_target=False)


@pytest.mark.slow
@pytest.mark.parametrize("controller", ["admittance", "cartesian"])
def test_a_very_heavy_target_is_the_stationary_target(robot, gains, short_scenario, controller):
    heavy = free(None, robot, mass=1e9, inertia=[1e9, 1e9, 1e9])
    logs = [ROLLOUT(robot, scenario, gains, controller)[1] for scenario in (short_scenario, heavy)]
    assert float(jnp.max(jnp.linalg.norm(logs[0].contact_force, axis=1))) > 0.1  # there is contact
    for measure in (metrics.final_position_error, metrics.final_orientation_error):
        np.testing.assert_allclose(measure(logs[1]), measure(logs[0]), rtol=0, atol=1e-6)
    np.testing.assert_allclose(metrics.max_abs_torque(logs[1]), metrics.max_abs_torque(logs[0]), rtol=1e-6)


def test_chaser_and_target_share_one_conserved_momentum(pushed):
    scenario, log = pushed
    total = np.asarray(log.momentum_total)
    exchanged = np.abs(np.asarray(log.momentum) - np.asarray(log.momentum)[0]).max()
    assert exchanged > 1e-2  # the contact moved momentum from one body to the other
    np.testing.assert_array_less(np.abs(total - total[0]).max(), 1e-9 * exchanged)
    assert np.linalg.norm(np.asarray(log.target_velocity[-1])) > 1e-4  # pushed away


def test_the_contacts_impulse_is_the_targets_change_of_momentum(pushed):
    scenario, log = pushed
    body, dt = scenario.target, scenario.dt
    R = rotations(log)  # LAR axes to inertial
    force_on_target = -np.einsum("nij,nj->ni", R, np.asarray(log.contact_force))  # inertial
    # The logged force is sampled at each step's start: trapezoids over the steps.
    impulse = dt * (force_on_target[1:] + force_on_target[:-1]).sum(axis=0) / 2
    change = float(body.mass) * (np.asarray(log.target_velocity[-1]) - np.asarray(log.target_velocity[0]))
    np.testing.assert_allclose(impulse, change, rtol=0, atol=1e-4 * np.abs(change).max())
    # The angular impulse about the target's CoM is the change of its spin momentum.
    p_lar = np.asarray(log.target_position) - np.einsum("nij,j->ni", R, np.asarray(body.com_in_lar))
    p_ee = p_lar + np.einsum("nij,nj->ni", R, np.asarray(log.pose_ee[:, :3]))
    moment = np.cross(p_ee - np.asarray(log.target_position), force_on_target)
    angular_impulse = dt * (moment[1:] + moment[:-1]).sum(axis=0) / 2
    spin = np.einsum("nij,jk,nk->ni", R, np.asarray(body.inertia), np.asarray(log.target_angular_velocity))
    np.testing.assert_allclose(angular_impulse, spin[-1] - spin[0], rtol=0, atol=1e-4 * np.abs(spin[-1]).max())


def test_a_torque_free_target_keeps_its_energy_and_momentum_and_precesses_as_predicted(robot, gains):
    # Axisymmetric (I1 = I2): in body axes w3 stays constant and (w1, w2) turns at
    # Omega = (I3 - I1) / I1 w3, the torque-free precession.
    I1, I3, w = 40.0, 70.0, np.array([0.3, 0.0, 1.0])
    scenario = free(None, robot, inertia=[I1, I1, I3], com_in_lar=[0.1, -0.2, 0.5], angular_velocity=w.tolist())
    scenario = dataclasses.replace(scenario, contact_stiffness=jnp.zeros(()))  # no contact: alone
    scenario = dataclasses.replace(
        scenario,
        initial=dataclasses.replace(
            scenario.initial, target=dataclasses.replace(scenario.initial.target, v=jnp.array([0.01, 0.0, -0.02]))
        ),
    )
    log = ROLLOUT(robot, scenario, gains, "admittance")[1]
    body, t = scenario.target, np.asarray(log.t)
    omega = np.asarray(log.target_angular_velocity)
    v, R = np.asarray(log.target_velocity), rotations(log)
    inertia = np.asarray(body.inertia)
    energy = 0.5 * float(body.mass) * (v**2).sum(axis=1) + 0.5 * np.einsum("ni,ij,nj->n", omega, inertia, omega)
    np.testing.assert_allclose(energy, energy[0], rtol=1e-12)
    L = np.einsum("nij,jk,nk->ni", R, inertia, omega) + np.cross(np.asarray(log.target_position), float(body.mass) * v)
    np.testing.assert_allclose(L, np.broadcast_to(L[0], L.shape), rtol=0, atol=1e-12 * np.abs(L[0]).max())
    precession = (I3 - I1) / I1 * w[2]
    expected = w[0] * np.exp(1j * precession * t)
    np.testing.assert_allclose(omega[:, 0] + 1j * omega[:, 1], expected, rtol=0, atol=1e-10)
    np.testing.assert_allclose(omega[:, 2], w[2], rtol=1e-13)


@pytest.mark.slow
def test_the_controllers_relative_twist_is_the_rate_of_the_relative_pose(robot, gains):
    # A drifting, tumbling target: the relative twist must include the frame's motion.
    scenario = free(None, robot, velocity=[0.01, -0.005, 0.002], angular_velocity=[0.02, -0.03, 0.05])
    log = ROLLOUT(robot, scenario, gains, "cartesian")[1]
    dt, twist = scenario.dt, np.asarray(log.twist_ee)
    # The frame moves the relative pose by ~1e-2 m/s and rad/s; the central difference is
    # good to ~5e-6 (it is as good for a stationary target: the torques jump between steps).
    position = np.asarray(log.pose_ee[:, :3])
    central = (position[2:] - position[:-2]) / (2 * dt)
    np.testing.assert_allclose(twist[1:-1, :3], central, rtol=0, atol=1e-4 * np.abs(central).max())
    # Angular: dR_rel/dt R_rel^T = [w_rel]x, R_rel from the logged ZYX angles.
    R_rel = np.asarray(jax.vmap(spatial.euler_zyx_to_rotation)(log.pose_ee[:, 3:]))
    rate = np.einsum("nij,nkj->nik", (R_rel[2:] - R_rel[:-2]) / (2 * dt), R_rel[1:-1])
    w_rel = np.stack([rate[:, 2, 1], rate[:, 0, 2], rate[:, 1, 0]], axis=1)
    np.testing.assert_allclose(twist[1:-1, 3:], w_rel, rtol=0, atol=1e-4 * np.abs(w_rel).max())


@pytest.mark.slow
def test_gradients_through_a_free_target_match_central_differences(robot, gains):
    scenario = free(None, robot, velocity=[0.0, 0.0, 0.002], angular_velocity=[0.0, 0.0, 0.01])

    def error(Kd):
        log = rollout(robot, scenario, dataclasses.replace(gains, Kd=Kd), "admittance")[1]
        return metrics.final_position_error(log) + jnp.linalg.norm(log.target_velocity[-1])

    value, gradient = jax.jit(jax.value_and_grad(error))(gains.Kd)
    assert np.isfinite(value) and np.all(np.isfinite(gradient)) and np.abs(gradient).max() > 0
    forward = jax.jit(error)
    for axis in (0, 1, 2, 3):  # the components of some size (Kd's rotational ones barely act in 2 s)
        h = 1e-4 * float(gains.Kd[axis])
        step = jnp.zeros(6).at[axis].set(h)
        central = (forward(gains.Kd + step) - forward(gains.Kd - step)) / (2 * h)
        np.testing.assert_allclose(gradient[axis], central, rtol=1e-4, atol=1e-15)


def test_the_target_table_is_checked_key_by_key(robot):
    scenario = scenario_from_mapping(robot, {"target": {"mass": 250, "inertia": [30.0, 40.0, 50.0]}})
    assert float(scenario.target.mass) == 250.0 and scenario.initial.target is not None
    np.testing.assert_allclose(scenario.target.inertia, np.diag([30.0, 40.0, 50.0]))
    # The target's LAR frame starts where the stationary one is.
    np.testing.assert_allclose(scenario.initial.target.p, scenario.p_lar, atol=1e-15)
    bad = {
        "mass": ({"inertia": [1.0, 1.0, 1.0]}, "target.mass: required"),
        "unknown": ({"mass": 1.0, "inertia": [1.0, 1.0, 1.0], "spin": 1.0}, "unknown scenario key target.spin"),
        "string": ({"mass": "300", "inertia": [1.0, 1.0, 1.0]}, "target.mass: expected numbers"),
        "boolean": ({"mass": True, "inertia": [1.0, 1.0, 1.0]}, "target.mass: expected numbers"),
        "negative": ({"mass": -1.0, "inertia": [1.0, 1.0, 1.0]}, "target.mass: must be positive"),
        "asymmetric": ({"mass": 1.0, "inertia": [[1.0, 0.5, 0], [0, 1.0, 0], [0, 0, 1.0]]}, "must be symmetric"),
        "indefinite": ({"mass": 1.0, "inertia": [1.0, 1.0, -1.0]}, "positive definite"),
        "triangle": ({"mass": 1.0, "inertia": [1.0, 1.0, 3.0]}, "triangle inequality"),
        "shape": (
            {"mass": 1.0, "inertia": [1.0, 1.0, 1.0], "velocity": [1.0, 2.0]},
            r"target.velocity: expected shape",
        ),
        "fast": ({"mass": 1.0, "inertia": [1.0, 1.0, 1.0], "angular_velocity": [20.0, 0, 0]}, "beyond 10"),
        "nan": ({"mass": float("nan"), "inertia": [1.0, 1.0, 1.0]}, "target.mass: must be finite"),
    }
    for case, (table, message) in bad.items():
        with pytest.raises(ScenarioError, match=message):
            scenario_from_mapping(robot, {"target": table})


def test_the_summary_reports_what_the_contact_did_to_the_target(pushed):
    scenario, log = pushed
    summary = metrics.summary(log, free_target=True)
    velocity, position = np.asarray(log.target_velocity), np.asarray(log.target_position)
    speed = np.linalg.norm(velocity, axis=1)
    assert summary["final_target_speed_mps"] == pytest.approx(speed[-1], rel=1e-12)
    assert summary["max_target_speed_mps"] == pytest.approx(speed.max(), rel=1e-12)
    assert summary["target_displacement_m"] == pytest.approx(np.linalg.norm(position[-1] - position[0]), rel=1e-12)
    # The impulse (a sum of the logged force over the steps) is the momentum it gave.
    change = float(scenario.target.mass) * np.linalg.norm(velocity[-1] - velocity[0])
    assert summary["target_impulse_Ns"] == pytest.approx(change, rel=1e-2)
    assert summary["final_target_rate_radps"] > 0.0  # pushed off its CoM: it turns


def test_samples_move_and_vary_the_target_with_its_frame(robot):
    from spacegrasp_jax.core.target import lar_frame
    from spacegrasp_jax.envelope.perturbations import PerturbationRanges, sample_scenarios

    nominal = free(None, robot, velocity=[0.001, 0.0, 0.0])
    ranges = dataclasses.replace(PerturbationRanges(), satellite_mass_fraction=0.0, satellite_inertia_fraction=0.0)
    samples = sample_scenarios(nominal, 3, range(4), ranges)
    for i in range(4):
        sample = jax.tree.map(lambda x, i=i: x[i], samples)
        p_lar, R_lar = lar_frame(sample.target, sample.initial.target)
        np.testing.assert_allclose(p_lar, sample.p_lar, atol=1e-14)  # the target carries the perturbed LAR
        np.testing.assert_allclose(R_lar, sample.R_lar, atol=1e-14)
        assert abs(float(sample.target.mass) / 300.0 - 1.0) <= ranges.target_mass_fraction
        drift = np.asarray(R_lar.T @ sample.initial.target.v) - np.array([0.001, 0.0, 0.0])
        assert np.all(np.abs(drift) <= ranges.target_speed_mps) and np.any(drift != 0.0)
    # A stationary scenario's samples are what they were (the target's draws have a stream of their own).
    stationary = paper_scenario(robot, duration=2.0, move_duration=2.0)
    again = sample_scenarios(stationary, 3, range(4), ranges)
    assert not again.free_target
    np.testing.assert_array_equal(again.initial.target.p, again.p_lar)  # the fixed target moves with the LAR
    before = sample_scenarios(stationary, 3, range(4), dataclasses.replace(ranges, target_mass_fraction=0.0))
    np.testing.assert_array_equal(again.p_lar, before.p_lar)


@pytest.mark.slow
def test_a_campaign_counts_a_pushed_away_target_as_a_failed_capture(robot, gains):
    from spacegrasp_jax.envelope.criteria import CaptureCriteria
    from spacegrasp_jax.envelope.perturbations import PerturbationRanges
    from spacegrasp_jax.jobs import campaign

    scenario = free(None, robot)
    config = campaign.CampaignConfig(n=2, chunk=2, ranges=PerturbationRanges.nominal())
    variants = [campaign.Variant("admittance", gains, "paper")]
    with_speed_limit = lambda limit: dataclasses.replace(config, criteria=CaptureCriteria(1.0, 1.0, 100.0, limit))
    loose = campaign.run_campaign(robot, scenario, variants, with_speed_limit(1.0))
    strict = campaign.run_campaign(robot, scenario, variants, with_speed_limit(1e-6))
    speeds = loose.metrics["admittance/paper"]["final_target_speed_mps"]
    assert np.all(speeds > 1e-6) and np.all(speeds < 1.0)
    assert loose.summary["variants"]["admittance/paper"]["success_rate"] == 1.0
    assert strict.summary["variants"]["admittance/paper"]["success_rate"] == 0.0
    assert "final_target_speed_mps" in strict.summary["variants"]["admittance/paper"]["statistics_over_non_diverged"]
    with pytest.raises(ValueError, match="target_speed_limit_mps"):
        with_speed_limit(float("nan"))


def test_montecarlo_names_a_bad_target_speed_limit(tmp_path):
    import subprocess
    import sys

    command = [sys.executable, "-m", "spacegrasp_jax.cli", "montecarlo", "--n", "2", "--out", str(tmp_path / "mc")]
    for value in ("nan", "-1"):
        result = subprocess.run([*command, "--target-speed-limit", value], capture_output=True, text=True, timeout=300)
        assert result.returncode == 2 and "--target-speed-limit" in result.stderr and "Traceback" not in result.stderr
    assert not (tmp_path / "mc").exists()


def test_the_tuning_objective_can_weigh_the_targets_final_speed(pushed, tmp_path):
    from spacegrasp_jax.tuning.objective import Objective, Weights, objective_parts
    from spacegrasp_jax.tuning.run import TuneSetupError, tune
    from spacegrasp_jax.tuning.tune import TuneConfig

    _, log = pushed
    scale = tuple(float(x) for x in metrics.max_abs_torque(log))
    plain = objective_parts(log, Objective(Weights(), scale), free_target=True)
    weighed = objective_parts(log, Objective(Weights(target_speed=2.0), scale), free_target=True)
    speed = float(jnp.linalg.norm(log.target_velocity[-1]))
    assert float(plain["final_target_speed_mps"]) == pytest.approx(speed, rel=1e-12)
    assert float(weighed["loss"] - plain["loss"]) == pytest.approx(2.0 * speed / 1e-3, rel=1e-9)
    with pytest.raises(TuneSetupError, match="needs a scenario with a free-floating"):
        tune(
            tmp_path / "run", config=TuneConfig(weights=Weights(target_speed=1.0), objective="weighted"), progress=None
        )
    assert not (tmp_path / "run" / "run.json").exists()


@pytest.mark.slow
def test_the_flight_like_loop_carries_the_target_as_the_ideal_loop_does(robot, gains):
    # Every realism stage on at neutral values: the sensed loop's plant, controller view and
    # log with a drifting, tumbling target are the paper's loop's.
    from spacegrasp_jax.loop.realism import Stage, ideal
    from spacegrasp_jax.loop.simulate import rollout

    scenario = free(None, robot, velocity=[0.002, 0.0, -0.001], angular_velocity=[0.0, 0.01, 0.02])
    reference = ROLLOUT(robot, scenario, gains, "admittance")[1]
    neutral = dataclasses.replace(ideal(), stages=Stage.SENSORS | Stage.ACTUATORS | Stage.MODEL | Stage.ESTIMATE)
    log = jax.jit(
        lambda: rollout(robot, scenario, gains, "admittance", realism=neutral, key=jax.random.PRNGKey(0))[1]
    )()
    # The neutral stages' arithmetic is exact (x + 0 noise, R exp(0)), but it is another
    # program, whose sums XLA may order otherwise; the first touch of the exact contact law
    # magnifies that last bit to a few 1e-12 of the force there.
    for name, value in vars(reference).items():
        if value is not None:
            np.testing.assert_allclose(getattr(log, name), value, rtol=1e-9, atol=1e-12, err_msg=name)


@pytest.mark.slow
def test_simulate_reports_the_target_and_whether_it_was_a_capture(tmp_path):
    import json
    import subprocess
    import sys

    scenario = tmp_path / "free.toml"
    scenario.write_text(
        "duration = 2.0\n[trajectory]\nduration = 2.0\n[target]\nmass = 300.0\ninertia = [50.0, 60.0, 70.0]\n"
        "com_in_lar = [0.0, 0.0, 0.5]\n"
    )
    out = tmp_path / "run"
    command = [sys.executable, "-m", "spacegrasp_jax.cli", "simulate", "--controller", "admittance"]
    command += ["--scenario", str(scenario), "--out", str(out), "--compile-cache", "none"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    summary = json.loads((out / "summary.json").read_text())["admittance"]
    assert summary["final_target_speed_mps"] > 0.005  # pushed away faster than a capture allows
    assert summary["capture_success"] is False and summary["capture_criteria"]["target_speed_limit_mps"] == 0.005
    with np.load(out / "timeseries_admittance.npz") as series:
        assert series["target_position"].shape == (2000, 3) and series["momentum_total"].shape == (2000, 6)


@pytest.mark.parametrize("kind", ["fixed", "free"])
def test_a_scenario_is_written_and_read_back_leaf_for_leaf(robot, kind):
    # A run folder's config.json records the scenario: a fixed target as null (what folders
    # written before the target was always a body hold), a free one as its numbers.
    import json

    from spacegrasp_jax.envelope.scenario import scenario_from_dict, scenario_to_dict

    scenario = paper_scenario(robot, duration=2.0) if kind == "fixed" else free(None, robot, velocity=[0.001, 0, 0])
    document = json.loads(json.dumps(scenario_to_dict(scenario)))
    assert (document["target"] is None and document["initial"]["target"] is None) == (kind == "fixed")
    again = scenario_from_dict(document)
    assert again.free_target == scenario.free_target
    assert jax.tree.structure(again) == jax.tree.structure(scenario)
    assert jax.tree.all(jax.tree.map(np.array_equal, again, scenario))
