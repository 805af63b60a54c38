"""CMA-ES on problems with a known optimum, run by the tuning driver; its resume by replay;
the parameter vector's round trip through the log-gains."""

from __future__ import annotations

import numpy as np
import pytest
from toy_problems import StopAfter, ToyProblem, start

from spacegrasp_jax.jobs.runfiles import write_atomically
from spacegrasp_jax.loop.control import paper_gains
from spacegrasp_jax.tuning import cmaes, driver
from spacegrasp_jax.tuning.parameters import initial_params, make_mask

OPTIMUM = np.array([0.7, -1.3, 0.2, 2.0, -0.4])


def quadratic_batch(vectors: np.ndarray) -> dict:
    """A batch of 4 'scenarios' per candidate, each a shifted quadratic whose batch mean
    is least at ``OPTIMUM``: the shape of the tuning evaluator's output."""
    shifts = np.array([-0.1, 0.1, -0.05, 0.05])[None, :, None]
    losses = np.sum((vectors[:, None, :] - OPTIMUM - shifts) ** 2, axis=-1)
    peak = np.abs(vectors).max(axis=1, keepdims=True) * np.ones((1, 4))
    return {"loss": losses, "final_position_error_m": losses * 1e-3, "largest_peak_torque_Nm": peak}


def run_cmaes(batch_parts, x0, generations, population, seed, **options):
    point, mask = start(len(x0))
    point["x"] = np.asarray(x0, dtype=float)
    method = cmaes.CMAES(population=population)
    return driver.optimise(ToyProblem(batch_parts), method, point, mask, steps=generations, seed=seed, **options)


def test_cmaes_finds_the_optimum_of_a_quadratic():
    result = run_cmaes(quadratic_batch, np.zeros(5), generations=120, population=10, seed=3)
    state = result.state
    assert result.status == "done"
    np.testing.assert_allclose(state.method_state.strategy.mean, OPTIMUM, atol=1e-4)
    # At the optimum each scenario still costs its shift: 5 mean(s^2) = 0.03125.
    assert state.history[-1]["loss"] == pytest.approx(5 * np.mean(np.array([0.1, 0.1, 0.05, 0.05]) ** 2), abs=1e-8)
    assert state.history[0]["step"] == 0 and state.history[-1]["step"] == 120 == len(state.history) - 1
    # a generation's candidates and its mean: population + 1 points a step, 4 samples each
    assert state.rollouts == 4 + 120 * (10 + 1) * 4


def test_cmaes_on_a_rosenbrock_valley():
    def rosenbrock(vectors):
        x, y = vectors[:, 0], vectors[:, 1]
        loss = (1 - x) ** 2 + 100 * (y - x**2) ** 2
        return {"loss": loss[:, None], "largest_peak_torque_Nm": np.zeros((len(vectors), 1))}

    result = run_cmaes(rosenbrock, np.array([-1.0, 1.5]), generations=250, population=8, seed=0)
    np.testing.assert_allclose(result.state.method_state.strategy.mean, [1.0, 1.0], atol=1e-3)


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
    whole = run_cmaes(quadratic_batch, np.zeros(5), generations=12, population=6, seed=1)
    checkpointed = dict(checkpoint_path=path, write_atomically=write_atomically)
    first = run_cmaes(quadratic_batch, np.zeros(5), 12, 6, 1, stop=StopAfter(5), **checkpointed)
    assert first.status == "interrupted" and first.state.step == 5 == first.state.method_state.generation
    point, mask = start(5)
    resume = driver.load_checkpoint(path, cmaes.CMAES(population=6), point, mask, seed=1)
    resumed = run_cmaes(quadratic_batch, np.zeros(5), 12, 6, 1, resume=resume)
    assert resumed.status == "done"
    np.testing.assert_array_equal(resumed.state.method_state.strategy.mean, whole.state.method_state.strategy.mean)
    drop_wall = lambda history: [{k: v for k, v in row.items() if k != "wall_s"} for row in history]
    np.testing.assert_equal(drop_wall(resumed.state.history), drop_wall(whole.state.history))  # NaN as NaN
    np.testing.assert_array_equal(resumed.point["x"], whole.point["x"])
    assert resumed.kept == whole.kept and resumed.state.rollouts == whole.state.rollouts


def test_a_checkpoint_of_another_run_does_not_replay(tmp_path):
    path = tmp_path / "checkpoint.npz"
    run_cmaes(quadratic_batch, np.zeros(5), 2, 6, 1, checkpoint_path=path, write_atomically=write_atomically)
    point, mask = start(5)
    with pytest.raises(RuntimeError, match="do not replay"):
        driver.load_checkpoint(path, cmaes.CMAES(population=6), point, mask, seed=2)


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


def _candidate_correlation(strategy, count=4000) -> float:
    """The correlation of the first two numbers over ``count`` candidates drawn now."""
    candidates = np.asarray(strategy.ask(count))
    return float(np.corrcoef(candidates[:, 0], candidates[:, 1])[0, 1])


def test_separable_cmaes_learns_no_correlation_where_full_cmaes_does():
    # A valley along x0 = x1 (condition 100): full CMA-ES learns the correlation of its two
    # numbers; sep-CMA-ES (Ros and Hansen 2008) has a diagonal covariance and cannot.
    def valley(vectors):
        x, y = vectors[:, 0], vectors[:, 1]
        loss = 100.0 * (x - y) ** 2 + (x + y - 1.0) ** 2 + np.sum(vectors[:, 2:] ** 2, axis=1)
        return {"loss": loss[:, None], "largest_peak_torque_Nm": np.zeros((len(vectors), 1))}

    point, mask = start(4)
    runs = {}
    for separable in (False, True):
        method = cmaes.CMAES(population=10, separable=separable)
        runs[separable] = driver.optimise(ToyProblem(valley), method, point, mask, steps=25, seed=4)
    assert _candidate_correlation(runs[False].state.method_state.strategy) > 0.9
    assert abs(_candidate_correlation(runs[True].state.method_state.strategy)) < 0.1
    # so on this rotated valley it learns more slowly (the price of its n variances)
    final = {separable: run.state.history[-1]["loss"] for separable, run in runs.items()}
    assert final[False] < final[True] < runs[True].state.history[0]["loss"]


class FreshBatches(ToyProblem):
    """A quadratic whose every batch is drawn anew (``request.batch`` seeds it): each
    sample's optimum is ``OPTIMUM`` moved by noise of standard deviation ``noise``."""

    def __init__(self, noise: float):
        super().__init__(self.parts)
        self.noise, self.batch = noise, 0

    def evaluate(self, request):
        self.batch = request.batch
        return super().evaluate(request)

    def parts(self, vectors):
        shifts = self.noise * np.random.default_rng(self.batch).standard_normal((1, 4, OPTIMUM.size))
        losses = np.sum((vectors[:, None, :] - OPTIMUM - shifts) ** 2, axis=-1)
        return {"loss": losses, "largest_peak_torque_Nm": np.zeros_like(losses)}


def run_noise_handled(noise: float, noise_handling: bool, generations: int = 30, **options):
    point, mask = start(OPTIMUM.size)
    method = cmaes.CMAES(population=12, noise_handling=noise_handling, fresh=True)
    return driver.optimise(FreshBatches(noise), method, point, mask, steps=generations, seed=2, **options)


def test_noise_handling_finds_no_noise_in_a_noise_free_problem_and_changes_nothing():
    # Every candidate evaluated again gives its value again: no rank moves, the noise
    # measure falls below zero and the step size is never raised (UH-CMA-ES, Hansen et al. 2009).
    plain, handled = run_noise_handled(0.0, False), run_noise_handled(0.0, True)
    rows = handled.state.history
    assert all(row["noise_measure"] <= 0.0 for row in rows[1:])
    np.testing.assert_array_equal(handled.state.method_state.strategy.mean, plain.state.method_state.strategy.mean)
    # 2 + 12/20 candidates a generation again: 2 or 3 (the fraction drawn), with the mean
    again = [len(indices) for indices, _ in handled.state.method_state.reevaluations]
    assert set(again) <= {2, 3} and len(again) == 30
    assert handled.state.rollouts == plain.state.rollouts + 4 * sum(again)


def test_noise_handling_raises_the_step_size_where_noise_drowns_the_ranking():
    # Near the optimum, noise of 0.5 per number swamps the differences between candidates:
    # the re-evaluated ranks move, the measure turns positive, the step size grows against
    # the plain run's.
    plain, handled = run_noise_handled(0.5, False, 40), run_noise_handled(0.5, True, 40)
    assert max(row["noise_measure"] for row in handled.state.history[1:]) > 0.0
    assert handled.state.history[-1]["sigma"] > 1.5 * plain.state.history[-1]["sigma"]


def test_under_fresh_batches_cmaes_keeps_its_final_mean():
    # Candidates of different batches are not compared: the run keeps the distribution's
    # mean (pycma's xfavorite), never a candidate that drew an easy batch.
    result = run_noise_handled(0.5, False, 10)
    np.testing.assert_array_equal(result.point["x"], result.state.method_state.strategy.mean)
    assert result.kept["what"] == "the mean after generation 10"


def test_a_noise_handled_run_resumes_bit_for_bit(tmp_path):
    path = tmp_path / "checkpoint.npz"
    whole = run_noise_handled(0.5, True, 12)
    first = run_noise_handled(0.5, True, 12, stop=StopAfter(5), checkpoint_path=path, write_atomically=write_atomically)
    assert first.status == "interrupted"
    point, mask = start(OPTIMUM.size)
    method = cmaes.CMAES(population=12, noise_handling=True, fresh=True)
    resumed = run_noise_handled(0.5, True, 12, resume=driver.load_checkpoint(path, method, point, mask, seed=2))
    np.testing.assert_array_equal(resumed.state.method_state.strategy.mean, whole.state.method_state.strategy.mean)
    assert resumed.state.method_state.strategy.sigma == whole.state.method_state.strategy.sigma
    drop_wall = lambda history: [{k: v for k, v in row.items() if k != "wall_s"} for row in history]
    np.testing.assert_equal(drop_wall(resumed.state.history), drop_wall(whole.state.history))
