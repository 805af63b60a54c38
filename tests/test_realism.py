"""The flight-like loop (spacegrasp_jax.loop.realism): neutral settings give the paper's loop,
sensor statistics, saturation with anti-windup, control period and delay, the controller's
own model, gradients, and the settings' files."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spacegrasp_jax.core.integrator import rk4_step
from spacegrasp_jax.core.robot_files import load_robot
from spacegrasp_jax.envelope import metrics
from spacegrasp_jax.envelope.scenario import paper_scenario
from spacegrasp_jax.loop.control import paper_gains
from spacegrasp_jax.loop.realism import FLIGHT, RealismError, Stage, flight, ideal, load_realism, make_realism
from spacegrasp_jax.loop.simulate import RunSpec, loop_body, plant_derivative, rollout

ROLLOUT = jax.jit(rollout, static_argnames=("controller",))


def flight_rollout(robot, scenario, gains, controller, realism, key, **settings):
    return rollout(robot, scenario, gains, controller, realism=realism, key=key, **settings)


FLIGHT_ROLLOUT = jax.jit(flight_rollout, static_argnames=("controller",))
#: Every stage on at neutral values (no noise, no bias, no limit, a perfect model and
#: estimate): the stages' code runs and must change nothing.
NEUTRAL_STAGES = dataclasses.replace(ideal(), stages=Stage.SENSORS | Stage.ACTUATORS | Stage.MODEL | Stage.ESTIMATE)


@pytest.fixture(scope="module")
def quiet_scenario(robot):
    """4 s without the contact sphere: the true wrench is zero, so a reading is its error."""
    return paper_scenario(robot, duration=4.0, move_duration=4.0, contact_stiffness=0.0)


@pytest.mark.parametrize("controller", ["admittance", "cartesian"])
def test_neutral_settings_run_the_papers_loop(robot, gains, short_scenario, controller):
    # Every stage on at neutral values against the paper's loop (every stage off).
    ideal_log = ROLLOUT(robot, short_scenario, gains, controller)[1]
    flight_log = FLIGHT_ROLLOUT(robot, short_scenario, gains, controller, NEUTRAL_STAGES, jax.random.PRNGKey(3))[1]
    for name, value in vars(ideal_log).items():
        if value is not None:
            np.testing.assert_allclose(getattr(flight_log, name), value, rtol=1e-12, atol=1e-12, err_msg=name)
    # Neutral values in a file are the ideal loop (the same program as no realism at all).
    neutral = make_realism({table: dict(keys) for table, keys in ideal().to_dict().items()})
    assert neutral.is_ideal(short_scenario.dt) and neutral.stages == Stage(0)
    same = jax.jit(rollout, static_argnames=("controller",))(robot, short_scenario, gains, controller, realism=neutral)[
        1
    ]
    np.testing.assert_array_equal(same.u, ideal_log.u)


@pytest.mark.slow
def test_sensor_noise_and_bias_have_the_configured_statistics(robot, gains, quiet_scenario):
    std_f, bias_f = np.array([0.05, 0.1, 0.2]), np.array([0.2, -0.1, 0.3])
    std_t, bias_t = np.array([0.002, 0.004, 0.001]), np.array([0.01, 0.0, -0.02])
    resolution, rate_std = 1e-3, 2e-3
    realism = make_realism(
        {
            "force_torque_sensor": {
                "force_noise_std": std_f.tolist(),
                "force_bias": bias_f.tolist(),
                "torque_noise_std": std_t.tolist(),
                "torque_bias": bias_t.tolist(),
            },
            "joint_sensors": {"angle_resolution_rad": resolution, "rate_noise_std_radps": rate_std},
        }
    )
    log = FLIGHT_ROLLOUT(robot, quiet_scenario, gains, "admittance", realism, jax.random.PRNGKey(7))[1]
    n = quiet_scenario.n_steps  # one reading per step (control period = dt)
    for measured, true, std, bias in (
        (log.fts_force_measured, log.fts_force, std_f, bias_f),
        (log.fts_torque_measured, log.fts_torque, std_t, bias_t),
    ):
        error = np.asarray(measured) - np.asarray(true)
        # 5 standard errors: a false alarm about once in 3 million per number.
        np.testing.assert_array_less(np.abs(error.mean(axis=0) - bias), 5 * std / np.sqrt(n))
        np.testing.assert_array_less(np.abs(error.std(axis=0) - std), 5 * std / np.sqrt(2 * n))
    rate_error = np.asarray(log.qd_measured) - np.asarray(log.qd)
    assert abs(rate_error.std() - rate_std) < 5 * rate_std / np.sqrt(2 * rate_error.size)
    angles = np.asarray(log.q_measured)
    np.testing.assert_allclose(angles / resolution, np.round(angles / resolution), atol=1e-6)  # on the encoder's grid
    assert np.max(np.abs(angles - np.asarray(log.q))) <= resolution / 2 + 1e-12
    # The key decides the noise: same key, same rollout; another key, another.
    again = FLIGHT_ROLLOUT(robot, quiet_scenario, gains, "admittance", realism, jax.random.PRNGKey(7))[1]
    other = FLIGHT_ROLLOUT(robot, quiet_scenario, gains, "admittance", realism, jax.random.PRNGKey(8))[1]
    np.testing.assert_array_equal(again.u, log.u)
    assert np.max(np.abs(np.asarray(other.u) - np.asarray(log.u))) > 1e-6
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    batch = jax.jit(
        jax.vmap(lambda key: flight_rollout(robot, quiet_scenario, gains, "admittance", realism, key)[1].u)
    )(keys)
    np.testing.assert_allclose(
        batch[1],
        FLIGHT_ROLLOUT(robot, quiet_scenario, gains, "admittance", realism, keys[1])[1].u,
        rtol=1e-10,
        atol=1e-12,
    )


@pytest.mark.slow
def test_saturation_holds_and_anti_windup_bounds_the_integrator(robot, gains, short_scenario):
    limits = [0.3] * 7  # N m, below the paper's peaks
    runs = {}
    for anti_windup in (True, False):
        realism = make_realism({"actuators": {"torque_limit_Nm": limits, "anti_windup": anti_windup}})
        final, log = FLIGHT_ROLLOUT(robot, short_scenario, gains, "admittance", realism, jax.random.PRNGKey(0))
        assert np.all(np.isfinite(np.asarray(log.u)))
        assert np.max(np.abs(np.asarray(log.u))) <= 0.3  # the run completes within the limit
        runs[anti_windup] = np.abs(np.asarray(final.controller.pid.integral))
    assert (
        np.max(np.abs(np.asarray(ROLLOUT(robot, short_scenario, gains, "admittance")[1].u))) > 1.0
    )  # it does saturate
    assert np.max(runs[True]) < 0.5 * np.max(runs[False])


@pytest.mark.slow
def test_torques_are_held_over_the_control_period_and_commands_arrive_late(robot, gains, short_scenario):
    realism = make_realism({"timing": {"control_period": 0.005, "delay_periods": 3}})
    log = FLIGHT_ROLLOUT(robot, short_scenario, gains, "cartesian", realism, jax.random.PRNGKey(0))[1]
    per_period = lambda x: np.asarray(x).reshape(-1, 5, *np.shape(x)[1:])
    u = per_period(log.u)
    np.testing.assert_array_equal(u, np.broadcast_to(u[:, :1], u.shape))  # constant within each period
    applied, computed = per_period(log.qd_des)[:, 0], per_period(log.qd_des_computed)[:, 0]
    np.testing.assert_array_equal(applied[3:], computed[:-3])  # period k applies period k - 3's command
    np.testing.assert_array_equal(applied[:3], 0.0)  # nothing has arrived yet
    assert np.max(np.abs(computed)) > 1e-4


@pytest.mark.slow
def test_the_joint_servos_run_at_their_own_period_on_their_own_readings(robot, gains, short_scenario):
    # Controller every 4 ms with one period of delay; joint PID every 2 ms on noisy rates.
    realism = make_realism(
        {
            "timing": {"control_period": 0.004, "delay_periods": 1, "servo_period": 0.002},
            "joint_sensors": {"rate_noise_std_radps": 1e-3},
        }
    )
    log = FLIGHT_ROLLOUT(robot, short_scenario, gains, "admittance", realism, jax.random.PRNGKey(5))[1]
    by = lambda x, n: np.asarray(x).reshape(-1, n, *np.shape(x)[1:])
    for name in ("qd_des", "qd_des_computed", "fts_force_measured"):  # held over the control period
        held = by(getattr(log, name), 4)
        np.testing.assert_array_equal(held, np.broadcast_to(held[:, :1], held.shape), err_msg=name)
    for name in ("u", "qd_measured"):  # held over the servo period, and not over the control period
        held = by(getattr(log, name), 2)
        np.testing.assert_array_equal(held, np.broadcast_to(held[:, :1], held.shape), err_msg=name)
        assert np.any(by(getattr(log, name), 4)[:, 2] != by(getattr(log, name), 4)[:, 0]), name
    np.testing.assert_array_equal(by(log.qd_des, 4)[1:, 0], by(log.qd_des_computed, 4)[:-1, 0])  # one period late
    # Each tick's torque is the PID of the rate error the servo read at that tick, written out
    # independently here: integral and backward difference at the servo period, t^2 ramp.
    S = 0.002
    error = by(log.qd_des, 2)[:, 0] - by(log.qd_measured, 2)[:, 0]
    t = np.arange(len(error)) * S
    integral = np.cumsum(error, axis=0) * S
    derivative = np.diff(error, axis=0, prepend=0.0) / S
    kp, ki, kd = (np.asarray(x) for x in (gains.kp, gains.ki, gains.kd))
    expected = np.minimum(t, 1.0)[:, None] ** 2 * (kp * error + ki * integral + kd * derivative)
    np.testing.assert_allclose(by(log.u, 2)[:, 0], expected, rtol=1e-9, atol=1e-12)
    # The servos read the sensors, not the truth: the readings differ from the true rates
    # by the configured noise (std 1e-3 rad/s; 1000 ticks x 7 joints, std within 10%).
    reading_error = by(log.qd_measured, 2)[:, 0] - by(log.qd, 2)[:, 0]
    assert abs(np.std(reading_error) - 1e-3) < 1e-4


@pytest.mark.slow
def test_the_controllers_model_is_its_own_and_the_plant_stays_the_plant(robot, gains, quiet_scenario):
    believing = make_realism({"controller_model": {"satellite_mass_factor": 0.3, "satellite_inertia_factor": 3.0}})
    final, log = FLIGHT_ROLLOUT(robot, quiet_scenario, gains, "cartesian", believing, jax.random.PRNGKey(0))
    # Factor 1 through the controller's own model pass: the identified result.
    identified = jax.jit(
        lambda: flight_rollout(
            robot, quiet_scenario, gains, "cartesian", ideal(), jax.random.PRNGKey(0), model_robot=robot
        )[1]
    )()
    reference = ROLLOUT(robot, quiet_scenario, gains, "cartesian")[1]
    np.testing.assert_allclose(identified.qd_des, reference.qd_des, rtol=1e-12, atol=1e-12)
    # A wrong belief changes the controller's J_dyn, hence its commands...
    assert np.max(np.abs(np.asarray(log.qd_des) - np.asarray(reference.qd_des))) > 1e-4
    # ...and not the plant: the same torques through the plant's own dynamics (checked
    # against Pinocchio in test_dynamics) give the same motion.
    u = jnp.asarray(log.u)

    def replay(state, u_k):
        derivative = lambda s, _, u: plant_derivative(robot, quiet_scenario, s, u)  # noqa: E731
        return rk4_step(lambda s: (), derivative, state, quiet_scenario.dt, u_k)[0], None

    replayed, _ = jax.jit(lambda: jax.lax.scan(replay, quiet_scenario.initial, u))()
    np.testing.assert_allclose(replayed.q, final.plant.q, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(replayed.V_base, final.plant.V_base, rtol=1e-9, atol=1e-15)


def _smooth_flight(**joint_sensors):
    """The flight preset with smooth saturation at 0.4 N m, 2 ms control with a delay, and
    joint sensors of rate noise 1e-3 rad/s plus ``joint_sensors``: the realism of the
    gradient tests below, which share one compiled gradient (its numbers are values)."""
    document = {table: dict(keys) for table, keys in FLIGHT.items()}
    document["joint_sensors"] = {"rate_noise_std_radps": 1e-3, **joint_sensors}
    document["actuators"] = {"torque_limit_Nm": [0.4] * 7, "saturation": "smooth"}
    document["timing"] = {"control_period": 0.002, "delay_periods": 1}
    return make_realism(document)


def _flight_error(kp, robot, scenario, gains, realism, key):
    log = flight_rollout(robot, scenario, dataclasses.replace(gains, kp=kp), "admittance", realism, key)[1]
    return metrics.final_position_error(log) + 0.1 * metrics.rms_position_error(log)


_flight_error_value_and_grad = jax.jit(jax.value_and_grad(_flight_error))


@pytest.fixture(scope="module")
def one_second(robot):
    return paper_scenario(robot, duration=1.0, move_duration=1.0, contact_law="smooth")


@pytest.mark.slow
def test_gradients_with_a_fixed_key_and_smooth_saturation_match_central_differences(robot, gains, one_second):
    realism = _smooth_flight()  # no encoder quantum: round() is a staircase
    key = jax.random.PRNGKey(11)
    value, gradient = _flight_error_value_and_grad(gains.kp, robot, one_second, gains, realism, key)
    assert np.isfinite(value) and np.all(np.isfinite(gradient))
    forward = jax.jit(_flight_error)
    for joint in (0, 1, 4):
        h = 1e-4 * float(gains.kp[joint])
        step = jnp.zeros(7).at[joint].set(h)
        plus = forward(gains.kp + step, robot, one_second, gains, realism, key)
        minus = forward(gains.kp - step, robot, one_second, gains, realism, key)
        np.testing.assert_allclose(gradient[joint], (plus - minus) / (2 * h), rtol=1e-4, atol=1e-12)


@pytest.mark.slow
def test_the_encoder_grid_keeps_the_position_feedback_in_the_gradient(robot, gains, one_second):
    # round() is flat between grid steps; its exact derivative would open the position loop
    # in every gradient (the error's sensitivity then grows without bound). With a 16-bit
    # encoder the gradient must stay the loop's: within 1% of the gradient without the grid.
    # The resolution is a number of the realism: the program of the test above serves both.
    def gradient(resolution):
        realism = _smooth_flight(angle_resolution_rad=resolution)  # the same noise: the same key
        return np.asarray(
            _flight_error_value_and_grad(gains.kp, robot, one_second, gains, realism, jax.random.PRNGKey(0))[1]
        )

    on_grid, exact = gradient(2 * np.pi / 2**16), gradient(0.0)
    assert np.linalg.norm(on_grid - exact) < 1e-2 * np.linalg.norm(exact)


def test_the_flight_preset_and_its_limits(robot, gains):
    preset = flight()
    assert preset.stages == Stage.SENSORS | Stage.ACTUATORS | Stage.MODEL | Stage.ESTIMATE
    with pytest.raises(AttributeError):
        Stage.SENSOR  # a misspelt stage is an error, not a test that is silently false  # noqa: B018
    assert preset.steps_per_period(1e-3) == 10 and preset.delay_periods == 1 and preset.steps_per_servo(1e-3) == 1
    scenario = paper_scenario(robot, duration=2.0, move_duration=2.0)
    log = jax.jit(rollout, static_argnames=("controller",))(
        robot, scenario, gains, "admittance", realism=preset, key=jax.random.PRNGKey(0)
    )[1]
    assert np.all(np.isfinite(np.asarray(log.u)))
    assert np.all(np.max(np.abs(np.asarray(log.u)), axis=0) <= np.asarray(preset.torque_limit_Nm))
    with pytest.raises(ValueError, match="needs a jax.random key"):
        rollout(robot, scenario, gains, "admittance", realism=preset)


def test_settings_files_are_validated_and_read_back(tmp_path):
    path = tmp_path / "realism.toml"
    path.write_text(
        "[timing]\ncontrol_period = 0.01\n[actuators]\ntorque_limit_Nm = [5.0, 5.0, 5.0, 2.0, 2.0, 1.0, inf]\n"
    )
    realism = load_realism(path)
    assert realism.control_period == 0.01 and realism.stages == Stage.ACTUATORS
    # A run record's form (config.json, campaign.json) reads back to the same settings, and so
    # does an older version's config.json.
    config = tmp_path / "config.json"
    for document in ({"record": {"realism": realism.to_dict()}}, {"realism": realism.to_dict()}):
        config.write_text(json.dumps(document))
        again = load_realism(config)
        assert again.to_dict() == realism.to_dict() and again.stages == realism.stages
    assert load_realism("flight").to_dict() == flight().to_dict()
    bad = {
        "[timing]\ncontrol_perod = 0.01\n": "unknown key timing.control_perod",
        "[sensors]\n": "unknown table",
        "[joint_sensors]\nrate_noise_std_radps = true\n": "joint_sensors.rate_noise_std_radps: expected numbers",
        '[force_torque_sensor]\nforce_bias = "0.1"\n': "force_torque_sensor.force_bias: expected numbers",
        "[actuators]\ntorque_limit_Nm = []\n": r"torque_limit_Nm: one limit a joint \(or one for all\), got none",
        "[actuators]\ntorque_limit_Nm = -1.0\n": "limits must be positive",
        '[actuators]\nsaturation = "soft"\n': "actuators.saturation",
        "[timing]\ndelay_periods = 1.5\n": "timing.delay_periods",
        "[controller_model]\nsatellite_mass_factor = 0.0\n": "satellite_mass_factor: must be between",
        "[force_torque_sensor]\nforce_noise_std = nan\n": "NaN",
        "[timing]\ncontrol_period = 0.01\nservo_period = 0.003\n": "does not divide timing.control_period",
        "[timing]\ncontrol_period = 0.01\nservo_period = 0.02\n": r"timing.servo_period: must be .* \[1e-06, control_period\]",
        "[timing]\ncontrol_period = 0.01\nservo_period = 5e-324\n": r"timing.servo_period: must be .* \[1e-06, control_period\]",
        "[timing]\ncontrol_period = 1e-7\n": r"timing.control_period: must be .* \[1e-06, 1\]",
    }
    for text, message in bad.items():
        path.write_text(text)
        with pytest.raises(RealismError, match=message):
            load_realism(path)
    with pytest.raises(RealismError, match="not a whole multiple"):
        make_realism({"timing": {"control_period": 0.0015}}).steps_per_period(1e-3)
    with pytest.raises(RealismError, match="timing.servo_period: .* not a whole multiple"):
        make_realism({"timing": {"control_period": 0.01, "servo_period": 0.0025}}).steps_per_servo(1e-3)
    with pytest.raises(RealismError, match="missing.toml: no such file"):
        load_realism(tmp_path / "missing.toml")
    with pytest.raises(RealismError, match="expected ideal, flight or a TOML file, got an empty name"):
        load_realism("")  # not the current folder


def test_torque_limits_are_one_a_joint_of_the_arm_they_run_with(robot, short_scenario):
    """A realism file's list has any length; the flight loop refuses one that is not the arm's
    number of joints before compiling. The flight preset without a robot has the paper's arm's
    seven motors; with one, the robot's own, which for the paper's arm are the same."""
    two = make_realism({"actuators": {"torque_limit_Nm": [1.0, 2.0]}})
    with pytest.raises(RealismError, match=r"2 limits for an arm of 7 joints"):
        two.check_joints(7)
    with pytest.raises(RealismError, match=r"2 limits for an arm of 7 joints"):
        loop_body(RunSpec(robot, short_scenario, "admittance", realism=two), paper_gains(), jax.random.PRNGKey(0))
    flight().check_joints(7)
    with pytest.raises(RealismError, match=r"7 limits for an arm of 6 joints.*flight\(\) without a robot has"):
        flight().check_joints(6)
    ideal().check_joints(6)  # no actuator stage: its limits are not used
    assert flight(robot).to_dict() == flight().to_dict()  # the paper's arm: the preset's own table
    ur5 = load_robot(Path(__file__).resolve().parents[1] / "configs" / "ur5_on_satellite.toml")
    flight(ur5).check_joints(6)
    assert np.asarray(flight(ur5).torque_limit_Nm).tolist() == np.asarray(ur5.joint_torque_limit).tolist()
    assert load_realism("flight", ur5).to_dict() == flight(ur5).to_dict()
