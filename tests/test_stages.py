"""The flight-like loop's stages (``spacegrasp_jax.stages``) one by one, in milliseconds:
each against its definition worked by hand, and each off when the realism leaves it off."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax import stages
from spacegrasp_jax.model import paper_robot
from spacegrasp_jax.realism import ideal, make_realism

RNG = np.random.default_rng(8)


def test_an_ideal_realism_leaves_every_stage_off():
    realism = ideal()
    force, torque, noise = (jnp.asarray(RNG.normal(size=size)) for size in (3, 3, 6))
    np.testing.assert_array_equal(
        stages.wrench_reading(realism, force, torque, noise), jnp.concatenate([force, torque])
    )
    q, qd = jnp.asarray(RNG.normal(size=7)), jnp.asarray(RNG.normal(size=7))
    read_q, read_qd = stages.joint_reading(realism, q, qd, jnp.ones(7))
    np.testing.assert_array_equal(read_q, q)
    np.testing.assert_array_equal(read_qd, qd)
    assert stages.low_pass_gain(realism, 0.01) == 1.0
    previous, reading = jnp.zeros(6), jnp.ones(6)
    np.testing.assert_array_equal(stages.low_pass(realism, previous, reading, 1.0), reading)
    p, R = jnp.asarray(RNG.normal(size=3)), jnp.eye(3)
    assert all(np.array_equal(a, b) for a, b in zip(stages.lar_estimate(realism, p, R), (p, R)))
    command, line = stages.delay_line(realism, jnp.zeros((0, 7)), qd)
    np.testing.assert_array_equal(command, qd)
    assert line.shape == (0, 7)


def test_the_wrench_reading_adds_the_bias_and_the_scaled_noise():
    realism = make_realism(
        {
            "force_torque_sensor": {
                "force_noise_std": [0.1, 0.2, 0.3],
                "torque_noise_std": [0.01, 0.02, 0.03],
                "force_bias": [1.0, -2.0, 3.0],
                "torque_bias": [0.5, 0.0, -0.5],
            }
        }
    )
    force, torque, noise = np.array([4.0, 5.0, 6.0]), np.array([0.1, 0.2, 0.3]), RNG.normal(size=6)
    expected = np.concatenate(
        [
            force + [1.0, -2.0, 3.0] + np.array([0.1, 0.2, 0.3]) * noise[:3],
            torque + [0.5, 0.0, -0.5] + np.array([0.01, 0.02, 0.03]) * noise[3:],
        ]
    )
    reading = stages.wrench_reading(realism, jnp.asarray(force), jnp.asarray(torque), jnp.asarray(noise))
    np.testing.assert_allclose(reading, expected, rtol=1e-15)


def test_the_low_pass_samples_the_continuous_filters_step_response_exactly():
    """A first-order filter of cutoff f_c answers a unit step with 1 - exp(-2 pi f_c t); the
    exact discretisation at period T hits that curve at every sample."""
    cutoff, period = 7.0, 0.01
    realism = make_realism({"force_torque_sensor": {"cutoff_hz": cutoff}})
    gain = stages.low_pass_gain(realism, period)
    filtered, samples = jnp.zeros(6), []
    for _ in range(40):
        filtered = stages.low_pass(realism, filtered, jnp.ones(6), gain)
        samples.append(float(filtered[0]))
    t = period * np.arange(1, 41)
    np.testing.assert_allclose(samples, 1.0 - np.exp(-2.0 * math.pi * cutoff * t), rtol=1e-12)


def test_the_encoder_grid_and_the_rate_noise_with_a_straight_through_gradient():
    quantum = 1e-3
    realism = make_realism({"joint_sensors": {"angle_resolution_rad": quantum, "rate_noise_std_radps": 0.05}})
    q = jnp.asarray([0.00049, 0.00051, -0.0123456, 1.0, 2.5e-4, -2.6e-4, 0.3])
    qd, noise = jnp.asarray(RNG.normal(size=7)), jnp.asarray(RNG.normal(size=7))
    read_q, read_qd = stages.joint_reading(realism, q, qd, noise)
    np.testing.assert_allclose(read_q, [0.0, 0.001, -0.012, 1.0, 0.0, -0.0, 0.3], atol=1e-15)
    np.testing.assert_allclose(read_qd, qd + 0.05 * noise, rtol=1e-15)
    # The gradient passes the grid as if it were not there.
    gradient = jax.grad(lambda q: jnp.sum(stages.joint_reading(realism, q, qd, noise)[0]))(q)
    np.testing.assert_array_equal(gradient, np.ones(7))


def test_the_lar_estimate_moves_the_frame_by_its_errors_in_lar_axes():
    angle = 0.2
    realism = make_realism(
        {"target_estimate": {"position_error_m": [0.01, 0.0, 0.0], "angle_error_rad": [0.0, 0.0, angle]}}
    )
    R_lar = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # LAR x along inertial y
    p, R = stages.lar_estimate(realism, jnp.asarray([1.0, 2.0, 3.0]), jnp.asarray(R_lar))
    np.testing.assert_allclose(p, [1.0, 2.01, 3.0], rtol=1e-15)
    Rz = np.array([[math.cos(angle), -math.sin(angle), 0.0], [math.sin(angle), math.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(R, R_lar @ Rz, atol=1e-15)


def test_the_delay_line_gives_each_command_back_after_its_periods_and_zeros_before():
    realism = make_realism({"timing": {"delay_periods": 3}})
    line, applied = jnp.zeros((3, 2)), []
    for k in range(8):
        command, line = stages.delay_line(realism, line, jnp.asarray([k + 1.0, -(k + 1.0)]))
        applied.append(np.asarray(command)[0])
    np.testing.assert_array_equal(applied, [0.0, 0.0, 0.0, 1.0, 2.0, 3.0, 4.0, 5.0])


def test_the_controllers_model_scales_the_satellites_mass_and_inertia_only():
    robot = paper_robot()
    realism = make_realism({"controller_model": {"satellite_mass_factor": 1.1, "satellite_inertia_factor": 0.9}})
    believed = stages.believed_robot(robot, realism)
    np.testing.assert_allclose(believed.satellite_mass, 1.1 * robot.satellite_mass, rtol=1e-15)
    np.testing.assert_allclose(believed.satellite_inertia, 0.9 * robot.satellite_inertia, rtol=1e-15)
    np.testing.assert_array_equal(believed.link_mass, robot.link_mass)
