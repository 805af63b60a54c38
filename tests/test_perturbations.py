"""The seeded sampler: nominal at zero range, reproducible, chunk-independent, in range,
validated."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest
import scipy.optimize

from spacegrasp_jax.envelope.perturbations import (
    PerturbationError,
    PerturbationRanges,
    draw,
    load_ranges,
    sample,
    sample_scenarios,
)
from spacegrasp_jax.envelope.scenario import paper_scenario


@pytest.fixture(scope="module")
def nominal(robot):
    return paper_scenario(robot)


def test_zero_ranges_give_the_nominal_robot_and_scenario_exactly(robot, nominal):
    robots, scenarios, _ = sample(robot, nominal, 7, range(3), PerturbationRanges.nominal())
    for original, batch in ((robot, robots), (nominal, scenarios)):
        for leaf, batched in zip(jax.tree.leaves(original), jax.tree.leaves(batch)):
            for i in range(3):
                np.testing.assert_array_equal(batched[i], leaf)


def test_same_seed_same_samples_whatever_the_batch(robot, nominal):
    ranges = PerturbationRanges()
    _, whole, drawn = sample(robot, nominal, 3, range(8), ranges)
    _, tail, tail_drawn = sample(robot, nominal, 3, range(5, 8), ranges)  # a later chunk on its own
    np.testing.assert_array_equal(whole.initial.q[5:], tail.initial.q)
    np.testing.assert_array_equal(whole.R_lar[5:], tail.R_lar)
    for a, b in zip(jax.tree.leaves(drawn), jax.tree.leaves(tail_drawn)):
        np.testing.assert_array_equal(a[5:], b)
    _, other, _ = sample(robot, nominal, 4, range(8), ranges)
    assert not np.allclose(whole.initial.q, other.initial.q)


def test_samples_stay_within_their_ranges(robot, nominal):
    ranges = PerturbationRanges(
        q_init_rad=0.02,
        lar_position_m=0.004,
        lar_angle_rad=0.01,
        stiffness_factor=3.0,
        base_speed_mps=0.002,
        base_rate_radps=0.003,
        joint_rate_radps=0.01,
        radius_fraction=0.2,
        satellite_mass_fraction=0.1,
        satellite_inertia_fraction=0.3,
    )
    robots, batch, _ = sample(robot, nominal, 0, range(200), ranges)
    dq = np.asarray(batch.initial.q) - np.asarray(nominal.initial.q)
    assert np.abs(dq).max() <= 0.02 and np.abs(dq).max() > 0.015  # bounded, and the range is used
    dp_lar = np.einsum("ji,nj->ni", np.asarray(nominal.R_lar), np.asarray(batch.p_lar) - np.asarray(nominal.p_lar))
    assert 0.003 < np.abs(dp_lar).max() <= 0.004 + 1e-15
    k = np.asarray(batch.contact_stiffness) / float(nominal.contact_stiffness)
    assert k.min() >= 1 / 3 - 1e-12 and k.max() <= 3 + 1e-12
    for R in np.asarray(batch.R_lar[:5]):
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)  # still rotations
    V = np.asarray(batch.initial.V_base)
    assert 0.0015 < np.abs(V[:, :3]).max() <= 0.002 and 0.002 < np.abs(V[:, 3:]).max() <= 0.003
    assert 0.008 < np.abs(np.asarray(batch.initial.qd)).max() <= 0.01
    radius = np.asarray(batch.sphere_radius) / float(nominal.sphere_radius)
    assert radius.min() >= 0.8 and radius.max() <= 1.2
    mass = np.asarray(robots.satellite_mass) / float(robot.satellite_mass)
    assert 0.9 <= mass.min() < 0.92 and 1.08 < mass.max() <= 1.1
    for inertia in np.asarray(robots.satellite_inertia):
        np.testing.assert_allclose(inertia, inertia.T, atol=1e-12)
        assert np.linalg.eigvalsh(inertia).min() > 0.0
    diagonal = np.einsum("nii->ni", np.asarray(robots.satellite_inertia)) / np.diag(np.asarray(robot.satellite_inertia))
    assert 0.7 <= diagonal.min() < 0.75 and 1.25 < diagonal.max() <= 1.3
    # Only the satellite's mass and inertia vary in the robot.
    for name in ("link_mass", "frame_position", "ee_mass"):
        np.testing.assert_array_equal(getattr(robots, name)[17], getattr(robot, name))


def test_scenario_only_sampler_refuses_model_perturbations(nominal):
    with pytest.raises(PerturbationError, match="use sample()"):
        sample_scenarios(nominal, 0, range(2), PerturbationRanges())
    ranges = dataclasses.replace(PerturbationRanges(), satellite_mass_fraction=0.0, satellite_inertia_fraction=0.0)
    assert sample_scenarios(nominal, 0, range(2), ranges).initial.q.shape == (2, 7)


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(q_init_rad=-0.1), "q_init_rad: must be non-negative"),
        (dict(lar_position_m=float("nan")), "lar_position_m: must be a finite number"),
        (dict(stiffness_factor=0.5), "stiffness_factor: must be >= 1"),
        (dict(radius_fraction=1.0), "radius_fraction: must be below 1"),
        (dict(satellite_mass_fraction=2.0), "satellite_mass_fraction: must be below 1"),
        (dict(base_speed_mps="fast"), "base_speed_mps: must be a finite number"),
    ],
)
def test_ranges_are_validated(change, message):
    with pytest.raises(PerturbationError, match=message):
        PerturbationRanges(**change)


def test_ranges_from_a_file(tmp_path):
    path = tmp_path / "ranges.toml"
    path.write_text("[perturbations]\nq_init_rad = 0.05\nsatellite_mass_fraction = 0.2\n")
    ranges = load_ranges(path)
    assert ranges.q_init_rad == 0.05 and ranges.satellite_mass_fraction == 0.2
    assert ranges.lar_position_m == PerturbationRanges().lar_position_m  # the rest keep the defaults
    path.write_text("q_init = 0.05\n")
    with pytest.raises(PerturbationError, match="ranges.toml: unknown perturbation range 'q_init'"):
        load_ranges(path)
    path.write_text("q_init_rad = [0.05\n")
    with pytest.raises(PerturbationError, match="not valid TOML"):
        load_ranges(path)


def test_an_envelope_scaled_by_k_draws_each_sample_k_times_as_far():
    # The same keys draw the same units: every additive draw is k times the base envelope's,
    # a fraction's deviation from 1 k times, and the stiffness's factor (drawn in its
    # logarithm) the base's to the power k.
    base = PerturbationRanges(target_mass_log_range=0.3, target_com_offset_m=0.1)
    wide = base.scaled(2.5)
    key = jax.random.PRNGKey(11)
    drawn, scaled = draw(key, base), draw(key, wide)
    for name in ("dq_init", "dp_lar", "dr_lar", "V_base_init", "dp_lar_estimate", "target_com_offset"):
        np.testing.assert_allclose(getattr(scaled, name), 2.5 * getattr(drawn, name), rtol=1e-12, atol=0)
    np.testing.assert_allclose(scaled.satellite_mass_scale - 1.0, 2.5 * (drawn.satellite_mass_scale - 1.0), rtol=1e-12)
    np.testing.assert_allclose(scaled.target_mass_log_scale, 2.5 * drawn.target_mass_log_scale, rtol=1e-12)
    np.testing.assert_allclose(scaled.stiffness_scale, drawn.stiffness_scale**2.5, rtol=1e-12)
    assert base.scaled(1.0) == base
    assert base.scaled(0.0) == dataclasses.replace(PerturbationRanges.nominal(), stiffness_factor=1.0)
    # the default envelope's 10% fractions reach 1 at k = 10: refused, naming the first
    with pytest.raises(PerturbationError, match="radius_fraction: 0.1 times 10 reaches 1"):
        PerturbationRanges().scaled(10.0)
    with pytest.raises(PerturbationError, match="scale: must be a finite number of 0 or more"):
        base.scaled(-1.0)


@pytest.mark.slow
def test_the_free_target_envelope_stays_within_its_bounds_and_fills_them(robot):
    from spacegrasp_jax.core.target import lar_frame
    from spacegrasp_jax.envelope.perturbations import FREE_TARGET_RANGES, sample
    from spacegrasp_jax.envelope.scenario import load_scenario

    nominal = load_scenario(robot, "configs/free_target_envelope.toml")
    _, scenarios, _ = sample(robot, nominal, 4242, np.arange(3000), FREE_TARGET_RANGES)
    body, state = scenarios.target, scenarios.initial.target
    mass = np.asarray(body.mass)
    assert mass.min() >= 200.0 - 1e-9 and mass.max() <= 2000.0 + 1e-9
    assert mass.min() < 210.0 and mass.max() > 1900.0  # log-uniform: both ends are reached
    assert abs(np.median(np.log(mass)) - np.log(632.5)) < 0.05
    # Proportionate inertia: the same shape, scaled with the mass.
    np.testing.assert_allclose(
        np.asarray(body.inertia) / mass[:, None, None],
        np.broadcast_to(np.asarray(nominal.target.inertia) / float(nominal.target.mass), (3000, 3, 3)),
        rtol=1e-12,
    )
    speed = np.linalg.norm(np.asarray(state.v), axis=1)
    rate = np.linalg.norm(np.asarray(state.w), axis=1)
    assert speed.max() <= 0.005 + 1e-12 and speed.max() > 0.004
    assert rate.max() <= np.radians(1.0) + 1e-12 and rate.max() > 0.8 * np.radians(1.0)
    com_distance = np.linalg.norm(np.asarray(body.com_in_lar), axis=1)
    assert com_distance.max() <= 0.5 + 1e-12 and com_distance.max() > 0.48
    # The CoM sits where the target's state puts it, relative to the (perturbed) LAR frame.
    p_lar, _ = jax.vmap(lar_frame)(body, state)
    np.testing.assert_allclose(p_lar, scenarios.p_lar, atol=1e-12)


def test_the_envelope_draws_leave_the_other_samples_as_they_were(robot, nominal):
    from spacegrasp_jax.envelope.perturbations import FREE_TARGET_RANGES, PerturbationRanges, sample

    _, plain, _ = sample(robot, nominal, 7, np.arange(8), PerturbationRanges())
    _, with_envelope, _ = sample(robot, nominal, 7, np.arange(8), FREE_TARGET_RANGES)
    for a, b in zip(jax.tree.leaves(plain), jax.tree.leaves(with_envelope)):
        np.testing.assert_array_equal(a, b)  # no target: the envelope's draws change nothing


def test_an_approach_offset_replans_the_approach_from_the_end_effector_at_its_speed(robot, nominal):
    from spacegrasp_jax.core.trajectory import desired_state
    from spacegrasp_jax.envelope.perturbations import check_for_scenario, replanned

    ranges = PerturbationRanges(approach_offset_m=0.012)
    _, scenarios, drawn = sample(robot, nominal, 3, np.arange(16), ranges)
    offsets = np.asarray(drawn.approach_offset)
    assert np.abs(offsets).max() <= 0.012 and np.ptp(offsets) > 0.012
    # The LAR (and the target with it) moved along its own z axis by the offset; the
    # desired approach starts where the end-effector is, the offset farther back.
    _, plain, _ = sample(robot, nominal, 3, np.arange(16), PerturbationRanges())
    moved = np.einsum("ij,nj->ni", np.asarray(nominal.R_lar).T, scenarios.p_lar - plain.p_lar)
    np.testing.assert_allclose(moved, np.stack([0 * offsets, 0 * offsets, offsets], axis=1), atol=1e-15)
    np.testing.assert_allclose(scenarios.trajectory.start_pose[:, 2], -0.08 - offsets, atol=1e-15)
    np.testing.assert_array_equal(scenarios.trajectory.end_pose, plain.trajectory.end_pose)
    # Minimum jerk over a move of L in T peaks at 1.875 L / T: the same speed whatever the
    # offset, and the desired end-effector reaches the sphere's near side (z = -0.045 m,
    # LAR) later where the LAR is farther.
    times = np.linspace(0.0, 17.0, 17001)
    nominal_speed = jax.vmap(lambda t: desired_state(nominal.trajectory, t)[1][2])(times)
    assert float(nominal_speed.max()) == pytest.approx(1.875 * 0.095 / 10.0, rel=1e-6)
    reach = {}
    for offset in (-0.012, 0.0, 0.012):
        trajectory = replanned(nominal.trajectory, offset)
        pose, twist, _ = jax.vmap(lambda t, trajectory=trajectory: desired_state(trajectory, t))(times)
        assert float(twist[:, 2].max()) == pytest.approx(float(nominal_speed.max()), rel=1e-6)
        reach[offset] = times[np.argmax(np.asarray(pose[:, 2]) >= -0.045)]  # the sphere moves with the LAR
    # minimum jerk s(tau) = tau^3 (10 - 15 tau + 6 tau^2) reaches (35 mm + d) / (95 mm + d) of
    # the move at tau T': about 1 s either way for 12 mm (module docstring)
    for offset, time in reach.items():
        length = 0.095 + offset
        tau = scipy.optimize.brentq(lambda x, f=(0.035 + offset) / length: x**3 * (10 - 15 * x + 6 * x**2) - f, 0, 1)
        assert time == pytest.approx(tau * 10.0 * length / 0.095, abs=2e-3)
    assert reach[-0.012] < reach[0.0] - 0.99 and reach[0.012] > reach[0.0] + 0.97
    assert jax.tree.all(
        jax.tree.map(lambda a, b: bool(np.all(a == b)), replanned(nominal.trajectory, 0.0), nominal.trajectory)
    )
    # the other draws are as they were without it
    for name in ("dq_init", "dp_lar", "dr_lar", "dp_lar_estimate", "V_base_init"):
        np.testing.assert_array_equal(
            getattr(drawn, name), getattr(sample(robot, nominal, 3, np.arange(16), PerturbationRanges())[2], name)
        )
    with pytest.raises(PerturbationError, match="approach_offset_m: 0.2 m needs an approach .* moves 0.095 m"):
        check_for_scenario(PerturbationRanges(approach_offset_m=0.2), nominal)


def test_sensor_and_actuator_draws_reach_the_flight_like_loop_of_each_sample(robot, nominal):
    from spacegrasp_jax.jobs.montecarlo import sample_loops
    from spacegrasp_jax.loop.realism import Stage, flight

    base = flight(robot)
    ranges = PerturbationRanges(
        ft_force_bias_N=0.5, ft_torque_bias_Nm=0.02, ft_force_noise_std_N=0.3, actuator_torque_loss_fraction=0.6
    )
    loops = sample_loops(robot, nominal, 5, np.arange(64), ranges, base)
    realisms = loops.realisms
    assert Stage.SENSORS in realisms.stages and Stage.ACTUATORS in realisms.stages
    bias = np.asarray(realisms.force_bias) - np.asarray(base.force_bias)
    assert np.abs(bias).max() <= 0.5 and np.abs(bias).max() > 0.45
    assert np.abs(np.asarray(realisms.torque_bias) - np.asarray(base.torque_bias)).max() <= 0.02
    noise = np.asarray(realisms.force_noise_std) - np.asarray(base.force_noise_std)
    assert noise.min() >= 0.0 and noise.max() <= 0.3 and np.ptp(noise[:, 0]) > 0.25
    np.testing.assert_array_equal(noise[:, 0], noise[:, 2])  # one level for the sensor's axes
    np.testing.assert_array_equal(realisms.torque_noise_std, np.broadcast_to(base.torque_noise_std, (64, 3)))
    # one joint a sample at 40-100% of its limit, the others at theirs
    ratio = np.asarray(realisms.torque_limit_Nm) / np.asarray(base.torque_limit_Nm)
    weakened = ratio < 1.0
    assert weakened.sum(axis=1).max() == 1 and (ratio[weakened] >= 0.4).all()
    np.testing.assert_array_equal(ratio[~weakened], 1.0)
    assert set(np.argmax(weakened, axis=1)[weakened.any(axis=1)]) == set(range(7))  # every joint drawn in 64
    # their streams leave the other draws alone
    plain = sample_loops(robot, nominal, 5, np.arange(64), PerturbationRanges(), base)
    for name in ("dq_init", "dp_lar", "dp_lar_estimate", "V_base_init"):
        np.testing.assert_array_equal(getattr(loops.perturbations, name), getattr(plain.perturbations, name))
    np.testing.assert_array_equal(plain.realisms.force_bias, np.broadcast_to(base.force_bias, (64, 3)))
