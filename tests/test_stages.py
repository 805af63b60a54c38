"""The closed loop's stages (``spacegrasp_jax.loop.stages``): each of the realism's one by one, in
milliseconds, against its definition worked by hand; and a stage written here, in the test
file, run in the loop, a campaign's samples and a tuning gradient without a change to the
package (against its own recursion, a full-log run and central differences)."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spacegrasp_jax.analysis import stability
from spacegrasp_jax.core.model import paper_robot
from spacegrasp_jax.envelope.perturbations import PerturbationRanges
from spacegrasp_jax.jobs import experiment
from spacegrasp_jax.jobs.montecarlo import FoldedMetrics, evaluate_samples, sample_loops
from spacegrasp_jax.loop import simulate, stages
from spacegrasp_jax.loop.control import paper_gains
from spacegrasp_jax.loop.realism import flight, ideal, make_realism
from spacegrasp_jax.loop.simulate import RunSpec

RNG = np.random.default_rng(8)


def _only(realism, kind):
    """The one stage of ``kind`` in ``realism``'s chain."""
    (stage,) = [s for s in stages.realism_stages(realism, 0.01) if isinstance(s, kind)]
    return stage


def test_an_ideal_realism_has_no_stage_and_flights_has_each_in_the_loops_order():
    assert stages.realism_stages(ideal(), 0.001) == ()
    chain = stages.realism_stages(flight(), 0.01)
    assert [(type(s).__name__, s.signal) for s in chain] == [
        ("WrenchSensor", "wrench"),
        ("LowPass", "wrench"),
        ("JointSensors", "joints"),
        ("JointSensors", "servo_joints"),
        ("LarEstimate", "lar"),
        ("DelayLine", "command"),
    ]


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
    sensor = _only(realism, stages.WrenchSensor)
    reading, memory = sensor.apply(sensor.init(jnp.zeros(6)), jnp.asarray(np.concatenate([force, torque])), noise)
    np.testing.assert_allclose(reading, expected, rtol=1e-15)
    assert memory == ()


def test_the_low_pass_samples_the_continuous_filters_step_response_exactly():
    """A first-order filter of cutoff f_c answers a unit step with 1 - exp(-2 pi f_c t); the
    exact discretisation at period T hits that curve at every sample."""
    cutoff, period = 7.0, 0.01
    realism = make_realism({"force_torque_sensor": {"cutoff_hz": cutoff}})
    (low_pass,) = stages.realism_stages(realism, period)
    memory, samples = low_pass.init(jnp.zeros(6)), []
    for _ in range(40):
        filtered, memory = low_pass.apply(memory, jnp.ones(6), None)
        samples.append(float(filtered[0]))
    t = period * np.arange(1, 41)
    np.testing.assert_allclose(samples, 1.0 - np.exp(-2.0 * math.pi * cutoff * t), rtol=1e-12)


def test_the_encoder_grid_and_the_rate_noise_with_a_straight_through_gradient():
    quantum = 1e-3
    realism = make_realism({"joint_sensors": {"angle_resolution_rad": quantum, "rate_noise_std_radps": 0.05}})
    chain = [s for s in stages.realism_stages(realism, 0.01) if isinstance(s, stages.JointSensors)]
    assert [s.signal for s in chain] == ["joints", "servo_joints"]
    sensors = chain[0]
    q = jnp.asarray([0.00049, 0.00051, -0.0123456, 1.0, 2.5e-4, -2.6e-4, 0.3])
    qd, noise = jnp.asarray(RNG.normal(size=7)), jnp.asarray(RNG.normal(size=7))
    (read_q, read_qd), _ = sensors.apply((), (q, qd), noise)
    np.testing.assert_allclose(read_q, [0.0, 0.001, -0.012, 1.0, 0.0, -0.0, 0.3], atol=1e-15)
    np.testing.assert_allclose(read_qd, qd + 0.05 * noise, rtol=1e-15)
    # The gradient passes the grid as if it were not there.
    gradient = jax.grad(lambda q: jnp.sum(sensors.apply((), (q, qd), noise)[0][0]))(q)
    np.testing.assert_array_equal(gradient, np.ones(7))


def test_the_lar_estimate_moves_the_frame_by_its_errors_in_lar_axes():
    angle = 0.2
    realism = make_realism(
        {"target_estimate": {"position_error_m": [0.01, 0.0, 0.0], "angle_error_rad": [0.0, 0.0, angle]}}
    )
    R_lar = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # LAR x along inertial y
    estimate = _only(realism, stages.LarEstimate)
    (p, R), _ = estimate.apply((), (jnp.asarray([1.0, 2.0, 3.0]), jnp.asarray(R_lar)), None)
    np.testing.assert_allclose(p, [1.0, 2.01, 3.0], rtol=1e-15)
    Rz = np.array([[math.cos(angle), -math.sin(angle), 0.0], [math.sin(angle), math.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(R, R_lar @ Rz, atol=1e-15)


@pytest.mark.parametrize("capacity", [3, 9])
def test_the_delay_line_gives_each_value_back_after_its_length_and_zeros_before(capacity):
    """The realism's line (capacity = delay) and a longer one of the same length in use
    (the margins'), on a pytree of two arrays; a length of zero passes the value now."""
    line = stages.DelayLine(capacity, jnp.int32(3), "servo_joints")
    memory, applied = line.init((jnp.zeros(2), jnp.zeros(1))), []
    for k in range(8):
        (a, b), memory = line.apply(memory, (jnp.asarray([k + 1.0, -(k + 1.0)]), jnp.asarray([10.0 * k])), None)
        applied.append((float(a[0]), float(b[0])))
    assert applied == [(0.0, 0.0)] * 3 + [(k + 1.0, 10.0 * k) for k in range(5)]
    assert _only(make_realism({"timing": {"delay_periods": 3}}), stages.DelayLine).capacity == 3
    now = stages.DelayLine(capacity, jnp.int32(0))
    np.testing.assert_array_equal(now.apply(now.init(jnp.zeros(2)), jnp.full(2, 5.0), None)[0], 5.0)


def test_the_controllers_model_scales_the_satellites_mass_and_inertia_only():
    robot = paper_robot()
    realism = make_realism({"controller_model": {"satellite_mass_factor": 1.1, "satellite_inertia_factor": 0.9}})
    believed = stages.believed_robot(robot, realism)
    np.testing.assert_allclose(believed.satellite_mass, 1.1 * robot.satellite_mass, rtol=1e-15)
    np.testing.assert_allclose(believed.satellite_inertia, 0.9 * robot.satellite_inertia, rtol=1e-15)
    np.testing.assert_array_equal(believed.link_mass, robot.link_mass)


# ---- a stage of the user's own -------------------------------------------------------------


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ActuatorLag:
    """A first-order lag of the motors at the servo's rate: ``u += alpha (u_PID - u)``."""

    alpha: jax.Array
    signal: str = dataclasses.field(default="torque", metadata=dict(static=True))

    def init(self, value):
        return jnp.zeros_like(value)

    def apply(self, memory, value, noise):
        lagged = memory + self.alpha * (value - memory)
        return lagged, lagged


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Recorder:
    """Keeps each value that passes, in order (a row of ``rows`` a tick), and changes nothing."""

    rows: int = dataclasses.field(default=1, metadata=dict(static=True))
    signal: str = dataclasses.field(default="torque", metadata=dict(static=True))

    def init(self, value):
        return jnp.zeros((self.rows,) + value.shape, value.dtype), jnp.zeros((), jnp.int32)

    def apply(self, memory, value, noise):
        seen, count = memory
        return value, (seen.at[count].set(value), count + 1)


def lagged(torques: np.ndarray, alpha: float) -> np.ndarray:
    """The lag's recursion from rest, by hand."""
    out, previous = np.empty_like(torques), np.zeros(torques.shape[1])
    for k, value in enumerate(torques):
        previous = previous + alpha * (value - previous)
        out[k] = previous
    return out


@pytest.mark.parametrize(
    "realism",
    [None, pytest.param("flight", marks=pytest.mark.slow)],
    ids=["paper loop", "flight, 10 servo ticks a period"],
)
def test_a_stage_written_here_runs_in_the_loop_at_every_servo_tick_in_order(robot, short_scenario, realism):
    """A recorder then a lag on the PID's torques: the log's torques (those the plant gets)
    are the lag's recursion applied to what the recorder saw, tick by tick, carried across
    control periods; and the loop with a stage that changes nothing is the loop without it."""
    realism = None if realism is None else stability.quiet(flight())
    per_servo = 1 if realism is None else realism.steps_per_servo(short_scenario.dt)
    ticks = short_scenario.n_steps // per_servo
    alpha = 0.3
    spec = RunSpec(robot, short_scenario, "admittance", realism=realism)
    with_stages = dataclasses.replace(spec, stages=(Recorder(ticks), ActuatorLag(jnp.asarray(alpha))))
    run = jax.jit(simulate.closed_loop)
    key = jax.random.PRNGKey(0)
    final, log = run(with_stages, paper_gains(), key)
    seen, count = final.stages[-2]
    assert int(count) == ticks
    u = np.asarray(log.u)
    np.testing.assert_allclose(u[::per_servo], lagged(np.asarray(seen), alpha), rtol=1e-12, atol=1e-13)
    assert np.abs(u).max() > 1e-3

    _, plain = run(spec, paper_gains(), key)
    _, recorded = run(dataclasses.replace(spec, stages=(Recorder(ticks),)), paper_gains(), key)
    for name in ("u", "q", "qd", "pose_ee", "contact_force"):
        np.testing.assert_array_equal(getattr(recorded, name), getattr(plain, name))


def test_a_stage_naming_no_signal_of_the_loop_is_refused(robot, short_scenario):
    spec = RunSpec(robot, short_scenario, "admittance", stages=(ActuatorLag(jnp.asarray(0.5), "motor"),))
    with pytest.raises(ValueError, match=r"stages: ActuatorLag's signal must be one of .*got 'motor'"):
        simulate.loop_body(spec, paper_gains())


@pytest.mark.slow
def test_a_stage_written_here_runs_in_a_campaigns_samples_and_a_tuning_gradient(robot, short_scenario):
    """The lag in the campaign's batched program (each sample's metrics those of a full-log
    run of the same sample) and in the tuning gradient (against central differences)."""
    from spacegrasp_jax.tuning.gradients import central_differences, envelope_gradients
    from spacegrasp_jax.tuning.objective import Objective, Weights

    gains, ranges, lag = paper_gains(), PerturbationRanges(), (ActuatorLag(jnp.asarray(0.3)),)
    spec = RunSpec(robot, short_scenario, "admittance", realism=flight(), observer=FoldedMetrics(), stages=lag)
    indices = jnp.arange(2, dtype=jnp.uint32)
    _, sample_metrics, _ = jax.jit(lambda spec, gains: evaluate_samples(spec, gains, 3, indices, ranges=ranges))(
        spec, gains
    )
    samples = sample_loops(robot, short_scenario, 3, indices, ranges, spec.realism)
    for i in range(2):
        sample = dataclasses.replace(
            spec,
            robot=jax.tree.map(lambda x: x[i], samples.robots),
            scenario=jax.tree.map(lambda x: x[i], samples.scenarios),
            realism=jax.tree.map(lambda x: x[i], samples.realisms),
            model_robot=samples.model_robot,
            observer=simulate.FullLog(),
        )
        log = experiment.run(sample, gains, key=samples.keys[i]).log
        np.testing.assert_allclose(
            sample_metrics["largest_peak_torque_Nm"][i], np.abs(log.u).max(), rtol=1e-12, atol=1e-12
        )

    objective = Objective(Weights(), (1.0,) * 7)
    nominal = RunSpec(robot, short_scenario, "admittance", stages=lag)
    result, evaluate = envelope_gradients(nominal, gains, objective, n=1, horizons=(1.0,))
    (check,) = central_differences(result, evaluate, gains, "admittance", samples=[0])
    assert check["relative_error"] < 1e-4, check
