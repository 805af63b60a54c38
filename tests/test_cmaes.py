"""CMA-ES on problems with a known optimum, its resume by replay, and the parameter vector's
round trip through the log-gains."""

from __future__ import annotations

import numpy as np
import pytest

from spacegrasp_jax.jobs.runfiles import write_atomically
from spacegrasp_jax.loop.control import paper_gains
from spacegrasp_jax.tuning import cmaes
from spacegrasp_jax.tuning.parameters import initial_params, make_mask

OPTIMUM = np.array([0.7, -1.3, 0.2, 2.0, -0.4])


def quadratic_batch(vectors: np.ndarray) -> dict:
    """A batch of 4 'scenarios' per candidate, each a shifted quadratic whose batch mean
    is least at ``OPTIMUM``: the shape of the tuning evaluator's output."""
    shifts = np.array([-0.1, 0.1, -0.05, 0.05])[None, :, None]
    losses = np.sum((vectors[:, None, :] - OPTIMUM - shifts) ** 2, axis=-1)
    peak = np.abs(vectors).max(axis=1, keepdims=True) * np.ones((1, 4))
    return {"loss": losses, "final_position_m": losses * 1e-3, "largest_peak_torque_Nm": peak}


def test_cmaes_finds_the_optimum_of_a_quadratic():
    state, status = cmaes.optimise(
        quadratic_batch, np.zeros(5), generations=120, population=10, seed=3, cvar_alpha=None
    )
    assert status == "done"
    np.testing.assert_allclose(state.strategy.mean, OPTIMUM, atol=1e-4)
    # At the optimum each scenario still costs its shift: 5 mean(s^2) = 0.03125.
    assert state.history[-1]["loss"] == pytest.approx(5 * np.mean(np.array([0.1, 0.1, 0.05, 0.05]) ** 2), abs=1e-8)
    assert state.history[0]["step"] == 0 and state.history[-1]["step"] == 120


def test_cmaes_on_a_rosenbrock_valley():
    def rosenbrock(vectors):
        x, y = vectors[:, 0], vectors[:, 1]
        loss = (1 - x) ** 2 + 100 * (y - x**2) ** 2
        return {"loss": loss[:, None], "largest_peak_torque_Nm": np.zeros((len(vectors), 1))}

    state, _ = cmaes.optimise(rosenbrock, np.array([-1.0, 1.5]), generations=250, population=8, seed=0, cvar_alpha=None)
    np.testing.assert_allclose(state.strategy.mean, [1.0, 1.0], atol=1e-3)


def test_the_initial_step_size_sets_the_first_generations_spread():
    # The first generation is drawn from N(x0, step^2 I): its spread about x0 is the step.
    for step in (0.3, 0.05):
        strategy = cmaes.new_strategy(np.zeros(40), 200, seed=1, step_size=step)
        candidates = np.asarray(strategy.ask())
        assert np.std(candidates) == pytest.approx(step, rel=0.05)


def test_a_non_finite_candidate_is_ranked_last():
    objective = cmaes.batch_objective(np.array([[1.0, 2.0], [np.nan, 0.0], [0.5, 0.5]]), None)
    assert objective[1] == np.inf and objective[2] == 0.5
    worst = cmaes.batch_objective(np.array([[1.0, 2.0, 3.0, 4.0]]), 0.5)
    assert worst[0] == 3.5


def test_resume_replays_to_the_same_run(tmp_path):
    path = tmp_path / "checkpoint.npz"
    whole, _ = cmaes.optimise(quadratic_batch, np.zeros(5), generations=12, population=6, seed=1, cvar_alpha=None)

    class StopAfter:
        def __init__(self, count):
            self.count = count

        @property
        def requested(self):
            self.count -= 1
            return self.count < 0

    first, status = cmaes.optimise(
        quadratic_batch,
        np.zeros(5),
        generations=12,
        population=6,
        seed=1,
        cvar_alpha=None,
        checkpoint_path=path,
        write_atomically=write_atomically,
        stop=StopAfter(5),
    )
    assert status == "interrupted" and first.generation == 5
    resumed, status = cmaes.optimise(
        quadratic_batch,
        np.zeros(5),
        generations=12,
        population=6,
        seed=1,
        cvar_alpha=None,
        resume=cmaes.load_checkpoint(path),
    )
    assert status == "done"
    np.testing.assert_array_equal(resumed.strategy.mean, whole.strategy.mean)
    assert [row["loss"] for row in resumed.history] == [row["loss"] for row in whole.history]


def test_a_checkpoint_of_another_run_does_not_replay(tmp_path):
    path = tmp_path / "checkpoint.npz"
    cmaes.optimise(
        quadratic_batch,
        np.zeros(5),
        generations=2,
        population=6,
        seed=1,
        cvar_alpha=None,
        checkpoint_path=path,
        write_atomically=write_atomically,
    )
    with pytest.raises(RuntimeError, match="do not replay"):
        cmaes.optimise(
            quadratic_batch,
            np.zeros(5),
            generations=3,
            population=6,
            seed=2,
            cvar_alpha=None,
            resume=cmaes.load_checkpoint(path),
        )


def test_the_vector_round_trip_leaves_frozen_and_zero_gains_alone():
    gains = paper_gains()
    params = {name: np.asarray(value) for name, value in initial_params(gains, "admittance").items()}
    mask = make_mask(gains, "admittance", frozen=("kd",))
    vector = cmaes.flatten(params, mask)
    assert vector.size == 6 * 3 + 7 * 2 + 1  # kd frozen; the damping tuned from its start
    np.testing.assert_allclose(np.exp(params["pinv_damping"]), 1e-3)
    moved = cmaes.unflatten(vector + 1.0, params, mask)
    np.testing.assert_array_equal(moved["kd"], params["kd"])
    np.testing.assert_allclose(moved["kp"], params["kp"] + 1.0)
    np.testing.assert_array_equal(cmaes.flatten(cmaes.unflatten(vector, params, mask), mask), vector)
