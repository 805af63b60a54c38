"""A 6-joint arm (the UR5 of configs/ur5_on_satellite.toml) through the whole pipeline on a
short scenario: the command line's simulate, the tuning loss's gradient against central
differences, a few tuning steps, and a 16-sample Monte-Carlo chunk equal sample for sample to
single rollouts."""

from __future__ import annotations

import functools
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from central_differences import check_each_group
from toy_problems import descend

import spacegrasp_jax as sg
from spacegrasp_jax import cli
from spacegrasp_jax.envelope.perturbations import PerturbationRanges
from spacegrasp_jax.envelope.scenario import load_scenario
from spacegrasp_jax.jobs import experiment
from spacegrasp_jax.jobs.montecarlo import FoldedMetrics, evaluate_samples, sample_loops
from spacegrasp_jax.loop.control import load_gains
from spacegrasp_jax.loop.realism import load_realism
from spacegrasp_jax.loop.simulate import RunSpec
from spacegrasp_jax.tuning.objective import Objective, Weights
from spacegrasp_jax.tuning.parameters import GROUPS, initial_params, make_mask
from spacegrasp_jax.tuning.tune import (
    BLOCK_STEPS,
    TuneConfig,
    make_loss,
    make_value_and_grad,
    training_scenarios,
)

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
ROBOT, SCENARIO, GAINS = (
    CONFIGS / name for name in ("ur5_on_satellite.toml", "ur5_scenario.toml", "ur5_ideal_gains.json")
)
SHORT = '[trajectory]\nduration = 1.0\n[contact]\nlaw = "smooth"\n'  # contact from about 0.45 s

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def ur5():
    return sg.load_robot(ROBOT)


@pytest.fixture(scope="module")
def short(ur5, tmp_path_factory):
    """The UR5's scenario in 1 s with the smooth contact law, as a file."""
    path = tmp_path_factory.mktemp("ur5") / "short.toml"
    path.write_text(SCENARIO.read_text() + "duration = 1.0\n" + SHORT)
    return path


def test_simulate_runs_the_six_joint_arm_and_refuses_the_papers_seven_gains(ur5, short, tmp_path, capsys):
    common = ["simulate", "--controller", "admittance", "--robot", str(ROBOT), "--scenario", str(short)]
    assert cli.main([*common, "--gains", str(GAINS), "--out", str(tmp_path / "run")]) == 0
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())["admittance"]
    assert len(summary["max_abs_torque_Nm"]) == 6 and summary["max_contact_force_N"] > 0.0
    assert (tmp_path / "run" / "fig8_joint_torques.png").exists()
    capsys.readouterr()
    assert cli.main([*common, "--out", str(tmp_path / "no_gains")]) == 2
    assert "--gains: required for an arm of 6 joints" in capsys.readouterr().err
    assert not (tmp_path / "no_gains").exists()


@pytest.fixture(scope="module")
def loss_and_gradient(ur5, short):
    gains = load_gains(GAINS, "admittance", n_joints=6)
    scenario = load_scenario(ur5, short)
    config = TuneConfig(batch=1, objective="weighted", method="gradient")
    peaks = experiment.run(RunSpec(ur5, scenario, "admittance"), gains).summary["max_abs_torque_Nm"]
    objective = Objective(
        weights=Weights(contact_force=0.1),
        torque_scale_Nm=tuple(peaks),
        torque_constraint_Nm=tuple(float(x) for x in ur5.joint_torque_limit),
    )
    params = initial_params(gains, "admittance")
    mask = make_mask(gains, "admittance")
    loss = make_loss(ur5, training_scenarios(scenario, config), gains, mask, config, objective, BLOCK_STEPS)
    return loss, params, make_value_and_grad(loss, params, "reverse")


def test_the_tuning_gradient_matches_central_differences(loss_and_gradient):
    loss, params, value_and_grad = loss_and_gradient
    (_, aux), gradient = value_and_grad(params)
    assert float(aux["peak_contact_hard_N"]) > 0.0
    assert params["kp"].shape == (6,)
    check_each_group(loss, params, gradient, GROUPS["admittance"], seed=6)


def test_a_few_tuning_steps_run_and_keep_the_gains_finite(loss_and_gradient):
    _, params, value_and_grad = loss_and_gradient
    result = descend(value_and_grad, params, TuneConfig(steps=2, objective="weighted", method="gradient"))
    assert result.status == "done" and result.state.step == 2
    method_state = result.state.method_state
    assert np.isfinite(method_state.loss) and all(np.all(np.isfinite(v)) for v in jax.tree.leaves(method_state.params))


def test_a_monte_carlo_chunk_of_16_equals_single_rollouts(ur5, short):
    """The perturbed robots (satellite mass and inertia) and scenarios of 16 samples, batched:
    each sample's metrics equal those of its own rollout in the loop a campaign runs it in (the
    controller believing the nominal robot and the LAR where its estimate puts it)."""
    scenario = load_scenario(ur5, short)
    gains = load_gains(GAINS, "admittance", n_joints=6)
    ranges = PerturbationRanges()
    chunk = jax.jit(functools.partial(evaluate_samples, ranges=ranges))
    _, batch, _ = chunk(RunSpec(ur5, scenario, "admittance", observer=FoldedMetrics()), gains, 11, jnp.arange(16))
    assert batch["max_abs_torque_Nm"].shape == (16, 6)
    assert np.all(np.isfinite(batch["final_position_error_m"]))
    loops = sample_loops(ur5, scenario, 11, jnp.array([3, 12]), ranges)
    for k, index in enumerate([3, 12]):
        plant, perturbed, realism, key = jax.tree.map(
            lambda x: x[k], (loops.robots, loops.scenarios, loops.realisms, loops.keys)
        )
        alone = experiment.run(
            RunSpec(plant, perturbed, "admittance", realism=realism, model_robot=loops.model_robot), gains, key=key
        ).summary
        for name in ("final_position_error_m", "max_abs_torque_Nm", "max_contact_force_N"):
            np.testing.assert_allclose(batch[name][index], alone[name], rtol=1e-9, atol=1e-15, err_msg=name)


def test_a_flight_like_run_takes_a_realism_with_one_torque_limit_a_joint(short, tmp_path, capsys):
    """The flight preset takes the UR5's own six motors (its URDF's efforts); a realism file
    with six limits runs too, and its saturation holds every torque within them."""
    common = ["simulate", "--controller", "admittance", "--robot", str(ROBOT), "--scenario", str(short)]
    common += ["--gains", str(GAINS)]
    assert cli.main([*common, "--realism", "flight", "--out", str(tmp_path / "preset")]) == 0
    config = json.loads((tmp_path / "preset" / "config.json").read_text())
    assert (
        config["record"]["realism"]["actuators"]["torque_limit_Nm"]
        == np.asarray(sg.load_robot(ROBOT).joint_torque_limit).tolist()
    )
    realism = tmp_path / "ur5_flight.toml"
    realism.write_text(
        "[timing]\ncontrol_period = 0.01\nservo_period = 0.001\n"
        "[joint_sensors]\nrate_noise_std_radps = 0.001\n"
        "[actuators]\ntorque_limit_Nm = [1.0, 1.0, 1.0, 0.5, 0.5, 0.5]\n"
    )
    assert cli.main([*common, "--realism", str(realism), "--out", str(tmp_path / "run")]) == 0
    kept = load_realism(tmp_path / "run" / "realism.json")  # the run keeps the realism it ran
    assert kept.to_dict() == load_realism(realism).to_dict()
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())["admittance"]
    assert np.all(np.asarray(summary["max_abs_torque_Nm"]) <= np.array([1.0, 1.0, 1.0, 0.5, 0.5, 0.5]) + 1e-12)
    assert summary["max_contact_force_N"] > 0.0
