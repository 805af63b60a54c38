"""A tuning method is one class: random search, written here and never in the package, runs
through the one driver (``spacegrasp_jax.tuning.driver``) on a hand-written problem and,
once named in the registry, as a ``spacegrasp tune`` job on the simulator; interrupted, it
resumes to exactly the uninterrupted run."""

from __future__ import annotations

import dataclasses
import io
import json
from typing import ClassVar

import numpy as np
import pytest
from toy_problems import StopAfter, ToyProblem, start

from spacegrasp_jax.jobs.runfiles import write_atomically
from spacegrasp_jax.tuning import cmaes, driver
from spacegrasp_jax.tuning.protocol import Answers, Outcome, Request


@dataclasses.dataclass
class SearchState:
    rng: np.random.Generator
    mask: dict  # which entries of a point move
    best: dict  # the best point evaluated
    objective: float
    summary: dict
    step: int = -1


@dataclasses.dataclass(frozen=True)
class RandomSearchSettings:
    """Random search's settings in a tuning run (``TuneConfig.settings``)."""

    population: int = 4
    radius: float = 0.1


@dataclasses.dataclass(frozen=True)
class RandomSearch:
    """Each step: ``population`` points drawn about the best so far (normal, ``radius`` in
    log-gain units on every tuned entry), on the step's batch; the best of all is kept."""

    population: int = 4
    radius: float = 0.1
    name: ClassVar[str] = "random"
    title: ClassVar[str] = "random search"
    unit: ClassVar[str] = "step"
    point_words: ClassVar[str] = "the best point"
    settings_type: ClassVar[type] = RandomSearchSettings

    @classmethod
    def from_config(cls, config):
        return cls(config.settings.population, config.settings.radius)

    def describe(self):
        return f"by random search, {self.population} points a step"

    def init(self, point, mask, seed):
        return SearchState(np.random.default_rng(seed), mask, point, np.inf, {})

    def ask(self, state):
        if state.step < 0:
            return Request((state.best,), batch=0), state
        mask, points = state.mask, []
        for _ in range(self.population):
            points.append(
                {
                    name: np.where(mask[name], value + self.radius * state.rng.standard_normal(np.shape(value)), value)
                    for name, value in state.best.items()
                }
            )
        return Request(tuple(points), batch=state.step + 1), state

    def tell(self, state, request: Request, answers: Answers):
        which = int(np.argmin(answers.objectives))
        if answers.objectives[which] < state.objective:
            state = dataclasses.replace(
                state,
                best=request.points[which],
                objective=float(answers.objectives[which]),
                summary=answers.summaries[which],
            )
        state = dataclasses.replace(state, step=state.step + 1)
        return state, Outcome(row={"step": state.step, "loss": state.objective, **state.summary})

    def point(self, state):
        return state.best

    def best(self, state, history, best_step, best_point):
        return state.best, state.step, f"the best point after step {state.step}", state.objective

    def state_arrays(self, state):
        arrays = {f"best_{name}": np.asarray(value) for name, value in state.best.items()}
        meta = {"rng": state.rng.bit_generator.state, "objective": state.objective, "summary": state.summary}
        return arrays, meta

    def restore(self, point, mask, seed, arrays, meta, steps):
        rng = np.random.default_rng(seed)
        rng.bit_generator.state = meta["rng"]
        best = {name: arrays[f"best_{name}"] for name in point}
        return SearchState(rng, mask, best, meta["objective"], meta["summary"], steps)

    def progress(self, state, row, steps):
        return f"step {state.step}/{steps}: best {state.objective:.4f}"


def quadratic(vectors):
    losses = np.sum((vectors[:, None, :] - 0.5) ** 2, axis=-1) * np.ones((1, 2))
    return {"loss": losses, "largest_peak_torque_Nm": losses}


def test_random_search_runs_through_the_driver_and_resumes_bit_for_bit(tmp_path):
    point, mask = start(3)
    run = lambda **options: driver.optimise(
        ToyProblem(quadratic), RandomSearch(population=5, radius=0.2), point, mask, steps=30, seed=4, **options
    )
    whole = run()
    assert whole.status == "done" and whole.state.step == 30 and len(whole.state.history) == 31
    assert whole.kept["training_objective"] < 0.2 * whole.state.history[0]["loss"]  # it does search
    assert whole.state.rollouts == 2 + 30 * 5 * 2
    path = tmp_path / "checkpoint.npz"
    first = run(checkpoint_path=path, write_atomically=write_atomically, stop=StopAfter(7))
    assert first.status == "interrupted" and first.state.step == 7
    resumed = run(resume=driver.load_checkpoint(path, RandomSearch(population=5, radius=0.2), point, mask, seed=4))
    drop_wall = lambda history: [{k: v for k, v in row.items() if k != "wall_s"} for row in history]
    assert drop_wall(resumed.state.history) == drop_wall(whole.state.history)
    np.testing.assert_array_equal(resumed.point["x"], whole.point["x"])
    assert resumed.kept == whole.kept and resumed.state.rollouts == whole.state.rollouts


def test_a_checkpoint_of_one_method_is_not_resumed_by_another(tmp_path):
    point, mask = start(3)
    path = tmp_path / "checkpoint.npz"
    driver.optimise(
        ToyProblem(quadratic),
        RandomSearch(),
        point,
        mask,
        steps=2,
        seed=0,
        checkpoint_path=path,
        write_atomically=write_atomically,
    )
    with pytest.raises(ValueError, match="a checkpoint of the random method, not of cmaes"):
        driver.load_checkpoint(path, cmaes.CMAES(), point, mask, seed=0)


@pytest.mark.slow
def test_a_method_named_in_the_registry_runs_as_a_tuning_job_and_resumes_bit_for_bit(tmp_path, monkeypatch):
    """The registry entry is all ``tune`` needs: a run of random search on the simulator (the
    paper's loop, 1 s, a batch of 2) stopped after step 2 and resumed gives the uninterrupted
    run's history, gains and held-out parts bit for bit."""
    from spacegrasp_jax.tuning import tune as tune_module
    from spacegrasp_jax.tuning.run import tune
    from spacegrasp_jax.tuning.tune import TuneConfig

    monkeypatch.setitem(tune_module.METHODS, "random", RandomSearch)
    scenario = tmp_path / "short.toml"
    scenario.write_text("duration = 1.0\n[trajectory]\nduration = 1.0\n")
    config = TuneConfig(
        method="random", steps=4, batch=2, settings=RandomSearchSettings(population=3, radius=0.2), seed=2
    )
    common = dict(scenario_file=str(scenario), holdout=2, progress=io.StringIO())
    whole = tune(tmp_path / "whole", config=config, **common)
    assert whole.status == "done" and len(whole.history) == 5
    first = tune(tmp_path / "parts", config=config, stop=StopAfter(2), **common)
    assert first.status == "interrupted" and len(first.history) == 3
    resumed = tune(tmp_path / "parts", config=config, resume=True, **common)
    assert resumed.status == "done"
    for name in ("history.csv", "gains.json"):
        whole_text, resumed_text = ((tmp_path / run / name).read_text() for run in ("whole", "parts"))
        if name == "history.csv":  # the wall times differ
            whole_text, resumed_text = (
                [line.rsplit(",", 1)[0] for line in text.splitlines()] for text in (whole_text, resumed_text)
            )
        assert whole_text == resumed_text, name
    summaries = [json.loads((tmp_path / run / "summary.json").read_text()) for run in ("whole", "parts")]
    assert summaries[0]["kept"] == summaries[1]["kept"] and summaries[0]["holdout"] == summaries[1]["holdout"]
    with np.load(tmp_path / "whole" / "holdout.npz") as a, np.load(tmp_path / "parts" / "holdout.npz") as b:
        for part in a.files:
            np.testing.assert_array_equal(a[part], b[part])


def _older_layout(path, method):
    """Rewrite a checkpoint as the version before the driver wrote it: CMA-ES's own layout
    (its generations, the rows before the last mean's, the validations) or the gradient
    method's (its leaves, the rest in ``meta``)."""
    arrays, meta = driver.read_checkpoint(path)
    arrays = {name: value for name, value in arrays.items() if method == "gradient" or not name.startswith("best_")}
    if method == "cmaes":
        history = [{k: v for k, v in row.items() if k != "validation_loss"} for row in meta["history"]]
        older = {"config": meta["config"], "generation": meta["method_state"]["generation"], "history": history[:-1]}
        older["validation"] = []
    else:
        older = {"config": meta["config"], "step": meta["step"], "best_step": meta["best_step"]}
        older |= {"history": meta["history"], "events": meta["events"]}
        older |= {key: meta["method_state"][key] for key in ("scale", "loss", "aux")}
    np.savez(path, **arrays, meta=np.array(json.dumps(older)))


@pytest.mark.parametrize("method", ["cmaes", "gradient"])
def test_a_checkpoint_of_the_older_layout_resumes_to_the_uninterrupted_run(tmp_path, method):
    import jax.numpy as jnp

    from spacegrasp_jax.tuning.tune import TuneConfig, make_method

    point, mask = start(3)
    if method == "cmaes":
        problem = lambda: ToyProblem(quadratic)
        tuner = cmaes.CMAES(population=5)
    else:
        problem = lambda: ToyProblem(
            value_and_grad=lambda p: (
                (jnp.sum((p["x"] - 0.5) ** 2), {"max_largest_peak_torque_Nm": jnp.asarray(1.0)}),
                {"x": 2.0 * (p["x"] - 0.5)},
            )
        )
        tuner = make_method(TuneConfig.of(method="gradient", steps=9, optimizer="sgd", learning_rate=0.1))
    run = lambda **options: driver.optimise(problem(), tuner, point, mask, steps=9, seed=1, **options)
    whole = run()
    path = tmp_path / "checkpoint.npz"
    assert run(checkpoint_path=path, write_atomically=write_atomically, stop=StopAfter(4)).status == "interrupted"
    _older_layout(path, method)
    resumed = run(resume=driver.load_checkpoint(path, tuner, point, mask, seed=1))
    drop_wall = lambda history: [{k: v for k, v in row.items() if k != "wall_s"} for row in history]
    np.testing.assert_equal(drop_wall(resumed.state.history), drop_wall(whole.state.history))
    np.testing.assert_array_equal(resumed.point["x"], whole.point["x"])
