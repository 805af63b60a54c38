"""Tuning over a batch of scenarios: the batch's loss and gradient are the mean of each
scenario's, whether the batch runs one scenario after another or vmapped (its own file: with
tests/test_tuning.py in one, that file bounded how well two test workers balance)."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from spacegrasp_jax.envelope.scenario import paper_scenario
from spacegrasp_jax.jobs import compilation, paper
from spacegrasp_jax.tuning import tune
from spacegrasp_jax.tuning.objective import Objective, Weights
from spacegrasp_jax.tuning.parameters import initial_params, make_mask
from spacegrasp_jax.tuning.tune import TuneConfig, make_loss, make_value_and_grad, training_scenarios

pytestmark = pytest.mark.slow  # three reverse-mode gradient programs


@pytest.fixture(scope="module")
def batch_problem(robot, gains):
    """A batch of 2 short scenarios (Cartesian law), and the mean of the one-scenario losses
    and gradients, each built from its scenario alone."""
    nominal = paper_scenario(robot, contact_law="smooth", duration=0.1, move_duration=1.0)
    config = TuneConfig(controller="cartesian", batch=2, objective="weighted", method="gradient")
    scenarios = training_scenarios(nominal, config)
    scale = tuple(paper.MAX_ABS_TORQUE_NM["cartesian"])  # any positive scale: Table 5's peaks
    objective = Objective(weights=Weights(contact_force=0.1), torque_scale_Nm=scale)
    mask, params = make_mask(gains, "cartesian"), initial_params(gains, "cartesian")
    single = TuneConfig(controller="cartesian", batch=1, objective="weighted", method="gradient")
    segment = tune.block_steps(nominal.n_steps)

    # One program for both scenarios: the scenario is an argument, not a constant of the loss.
    @compilation.jit
    def one_scenario(scenario):
        loss = make_loss(robot, scenario, gains, mask, single, objective, segment)
        return jax.value_and_grad(loss, has_aux=True)(params)

    values, gradients = [], []
    for i in range(config.batch):
        (value, _), gradient = one_scenario(jax.tree.map(lambda leaf: leaf[i : i + 1], scenarios))
        values.append(float(value))
        gradients.append(gradient)
    mean_gradient = {group: np.mean([g[group] for g in gradients], axis=0) for group in params}
    return dict(
        scenarios=scenarios,
        config=config,
        objective=objective,
        mask=mask,
        params=params,
        one_scenario_segment=segment,
        mean_value=float(np.mean(values)),
        mean_gradient=mean_gradient,
    )


@pytest.mark.parametrize("in_sequence", [True, False], ids=["one-after-another", "vmapped"])
def test_batch_gradient_is_the_mean_of_the_scenarios_gradients(robot, gains, batch_problem, monkeypatch, in_sequence):
    # Both ways of running a batch (lax.map on a CPU up to SEQUENTIAL_BATCH, else vmap).
    monkeypatch.setattr(tune, "SEQUENTIAL_BATCH", 8 if in_sequence else 1)
    b = batch_problem
    assert tune.batch_in_sequence(2) == in_sequence
    segment = tune.block_steps(b["scenarios"].n_steps, 2)
    assert segment == (b["one_scenario_segment"] if in_sequence else 1)
    loss = make_loss(robot, b["scenarios"], gains, b["mask"], b["config"], b["objective"], segment)
    (value, _), gradient = make_value_and_grad(loss, b["params"], "reverse")(b["params"])
    assert float(value) == pytest.approx(b["mean_value"], rel=1e-10)
    for group in b["params"]:
        np.testing.assert_allclose(gradient[group], b["mean_gradient"][group], rtol=1e-8, atol=1e-12, err_msg=group)
