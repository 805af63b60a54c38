"""Gradient-free tuning: CMA-ES (the ``cma`` package) on the same parameters, objective and
batch as the gradient loop, forward rollouts only.

The parameters are the tuned entries of the log-gains ([`spacegrasp_jax.tuning.parameters`][tuning.parameters],
frozen groups left out), one flat vector. A generation asks ``population`` candidates of
CMA-ES, adds the distribution's mean, and evaluates all of them on the batch in one sharded,
chunked program ([`spacegrasp_jax.jobs.batching.map_in_chunks()`][spacegrasp_jax.jobs.batching.map_in_chunks]: ``(population + 1) x batch``
forward rollouts, no reverse-mode compile), then tells CMA-ES the candidates' objectives.
The run's gains are the mean after the last generation (the best candidate of a fixed batch
is the one most fitted to it).

Resume without pickles: CMA-ES draws its candidates from its own seeded generator, so the
checkpoint keeps each generation's candidates and objectives, and a resumed run replays the
asks and tells, which rebuilds the strategy exactly, then goes on.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import jax
import numpy as np

from spacegrasp_jax.core.model import Robot
from spacegrasp_jax.jobs import batching
from spacegrasp_jax.jobs.experiment import loop_options
from spacegrasp_jax.jobs.montecarlo import SampleLoops
from spacegrasp_jax.jobs.runfiles import StopRequest
from spacegrasp_jax.loop.control.gains import Gains
from spacegrasp_jax.loop.simulate import LoopOptions
from spacegrasp_jax.tuning.objective import (
    BATCH_MAX_PEAK_TORQUE,
    Objective,
    history_of_older_version,
    objective_spec,
    scenario_parts,
)
from spacegrasp_jax.tuning.parameters import gains_from_params

if TYPE_CHECKING:
    import cma

#: CMA-ES's default initial step in log-gain units: about +-30% on every tuned gain.
SIGMA = 0.3


def flatten(params: dict, mask: dict) -> np.ndarray:
    """The tuned entries of ``params`` (log-gains) as one vector, group by group."""
    return np.concatenate([np.asarray(params[name])[np.asarray(mask[name])] for name in params])


def unflatten(vector: np.ndarray, params: dict, mask: dict) -> dict:
    """``params`` with its tuned entries replaced by ``vector`` ([`flatten()`][tuning.cmaes.flatten]'s inverse)."""
    out, at = {}, 0
    for name, value in params.items():
        value = np.array(value)
        chosen = np.asarray(mask[name])
        count = int(chosen.sum())
        value[chosen] = vector[at : at + count]
        out[name] = value
        at += count
    return out


def gains_of(vector: np.ndarray, params: dict, base: Gains, mask: dict) -> Gains:
    """The gains a parameter vector stands for (the entries [`flatten()`][tuning.cmaes.flatten] left out keep
    ``params``' values, the frozen ones ``base``'s)."""
    return gains_from_params(unflatten(vector, params, mask), base, mask)


def _candidate_parts(
    model_robot, objective: Objective, items, *, controller: str, realism_loop: bool, options: LoopOptions
):
    """The objective's parts of each (gains, sample) item (vmapped)."""
    if realism_loop:
        gains, robot, scenario, realism, key = items
        one = lambda g, r, s, re, k: scenario_parts(
            objective_spec(r, s, controller, realism=re, model_robot=model_robot, options=options), g, objective, k
        )
        return jax.vmap(one)(gains, robot, scenario, realism, key)
    gains, scenario = items
    one = lambda g, s: scenario_parts(objective_spec(model_robot, s, controller, options=options), g, objective)
    return jax.vmap(one)(gains, scenario)


#: The most rollouts one call of the population's program runs (measured on 2 cores: a
#: batch of 64 runs as fast in calls of 64 as of 32; performance page).
MAX_CHUNK = 64


def population_chunk(batch: int) -> int:
    """Rollouts per call of the population's program for a training ``batch``: the batch
    itself up to ``MAX_CHUNK`` (each candidate one call, no padding, and the final
    mean's evaluation reuses the program); a larger batch, its largest divisor up to it
    where that is at least half of it, else ``MAX_CHUNK`` (the last call padded)."""
    if batch <= MAX_CHUNK:
        return batch
    divisor = max(d for d in range(1, MAX_CHUNK + 1) if batch % d == 0)
    return divisor if 2 * divisor >= MAX_CHUNK else MAX_CHUNK


def make_item_evaluator(
    robot: Robot, samples, base: Gains, mask: dict, params: dict, controller: str, objective: Objective, chunk: int
) -> Callable[[np.ndarray, np.ndarray], dict]:
    """``evaluate(vectors (M, n), rows (M,)) -> parts``, every part of the objective shaped
    (M,): parameter vector ``k`` on sample ``rows[k]`` of ``samples``, a ``SampleLoops`` of the
    flight-like loop (robots, scenarios, realisms, keys) or stacked scenarios of the paper's
    loop; forward rollouts in one sharded, chunked program."""
    realism_loop = isinstance(samples, SampleLoops)
    if realism_loop:
        per_sample = (samples.robots, samples.scenarios, samples.realisms, samples.keys)
        model_robot = samples.model_robot if samples.model_robot is not None else robot
    else:
        per_sample = (samples,)
        model_robot = robot
    function = functools.partial(
        _candidate_parts, controller=controller, realism_loop=realism_loop, options=loop_options(checkpoint=True)
    )

    def evaluate(vectors: np.ndarray, rows: np.ndarray) -> dict:
        unique, inverse = np.unique(np.asarray(vectors, dtype=float), axis=0, return_inverse=True)
        gains = [gains_of(v, params, base, mask) for v in unique]
        stacked = jax.tree.map(lambda *g: np.stack([np.asarray(x) for x in g])[inverse.ravel()], *gains)
        items = (stacked, *batching.take(per_sample, np.asarray(rows)))
        return batching.map_in_chunks(
            "tuning.cmaes",
            function,
            (model_robot, objective),
            items,
            chunk=chunk,
            progress=None,
        )

    return evaluate


def make_population_evaluator(
    robot: Robot, samples, base: Gains, mask: dict, params: dict, controller: str, objective: Objective, chunk: int
) -> Callable[[np.ndarray], dict]:
    """``evaluate(vectors (P, n)) -> parts`` with every part of the objective shaped
    (P, batch), for P parameter vectors on every sample of the batch ``samples``
    ([`make_item_evaluator()`][tuning.cmaes.make_item_evaluator])."""
    per_sample = (samples.robots,) if isinstance(samples, SampleLoops) else (samples,)
    batch = batching.batch_size(per_sample)
    items = make_item_evaluator(robot, samples, base, mask, params, controller, objective, chunk)

    def evaluate(vectors: np.ndarray) -> dict:
        count = len(vectors)
        parts = items(np.repeat(np.asarray(vectors), batch, axis=0), np.tile(np.arange(batch), count))
        return {name: value.reshape(count, batch) for name, value in parts.items()}

    return evaluate


def batch_objective(losses: np.ndarray, cvar_alpha: float | None) -> np.ndarray:
    """(P,) the objective of each candidate from its (P, batch) losses: the mean, or the mean
    over the worst ``1 - cvar_alpha`` of the batch; a candidate with a non-finite loss gets
    ``inf`` (CMA-ES ranks it last)."""
    losses = np.asarray(losses, dtype=float)
    if cvar_alpha is None:
        total = losses.mean(axis=1)
    else:
        worst = max(1, math.ceil((1.0 - cvar_alpha) * losses.shape[1]))
        total = np.sort(losses, axis=1)[:, -worst:].mean(axis=1)
    return np.where(np.isfinite(total), total, np.inf)


@dataclasses.dataclass
class CmaState:
    """A CMA-ES run after ``generation`` generations: the strategy, every generation's
    candidates and objectives (what a resume replays), the mean's history rows."""

    generation: int
    strategy: cma.CMAEvolutionStrategy
    asked: list
    told: list
    history: list
    #: early stopping's evaluations: ``{"generation", "objective", "mean"}`` of the mean after
    #: each generation (generation 0: ``x0``) on the validation set
    validation: list = dataclasses.field(default_factory=list)


def new_strategy(
    x0: np.ndarray, population: int | None, seed: int, step_size: float = SIGMA
) -> cma.CMAEvolutionStrategy:
    """CMA-ES from ``x0`` with initial step ``step_size`` (log-gain units), seeded (its
    ``seed`` must not be 0, which ``cma`` reads as "draw one"), silent."""
    import cma  # imported on first use: with scipy.stats, most of a second at every command's start

    options = {"seed": seed + 1, "verbose": -9, "verb_log": 0, "verb_disp": 0}
    if population is not None:
        options["popsize"] = population
    return cma.CMAEvolutionStrategy(np.asarray(x0, dtype=float), step_size, options)


def replay(strategy: cma.CMAEvolutionStrategy, asked: list, told: list) -> None:
    """Rebuild ``strategy`` by asking and telling the recorded generations again; raises
    RuntimeError if an ask does not give back the recorded candidates (another ``cma``)."""
    for candidates, objectives in zip(asked, told):
        again = np.asarray(strategy.ask())
        if not np.allclose(again, candidates, rtol=0.0, atol=1e-12):
            raise RuntimeError("the checkpoint's CMA-ES generations do not replay (was it written by another cma?)")
        strategy.tell(list(candidates), list(objectives))


def save_checkpoint(path: Path, state: CmaState, config_dict: dict, write_atomically) -> None:
    arrays = {f"asked_{k}": np.asarray(a) for k, a in enumerate(state.asked)}
    arrays |= {f"told_{k}": np.asarray(t) for k, t in enumerate(state.told)}
    meta = {"config": config_dict, "generation": state.generation, "history": state.history}
    meta["validation"] = state.validation
    arrays["meta"] = np.array(json.dumps(meta))
    write_atomically(path, lambda target: np.savez(target, **arrays))


def load_checkpoint(path: Path) -> tuple[list, list, list, list]:
    """``(asked, told, history, validation)`` of a CMA-ES checkpoint (``validation``: early
    stopping's evaluations, ``CmaState.validation``; empty without, or from an older version)."""
    with np.load(path, allow_pickle=False) as data:
        meta = json.loads(str(data["meta"]))
        count = meta["generation"]
        return (
            [data[f"asked_{k}"] for k in range(count)],
            [data[f"told_{k}"] for k in range(count)],
            history_of_older_version(meta["history"]),
            meta.get("validation", []),
        )


def optimise(
    evaluate: Callable[[np.ndarray], dict],
    x0: np.ndarray,
    *,
    generations: int,
    population: int | None,
    seed: int,
    cvar_alpha: float | None,
    step_size: float = SIGMA,
    checkpoint_path: Path | None = None,
    config_dict: dict | None = None,
    write_atomically=None,
    resume: tuple | None = None,
    on_generation: Callable[[CmaState], None] | None = None,
    stop: StopRequest | None = None,
    validate: Callable[[np.ndarray], float] | None = None,
    patience: int | None = None,
) -> tuple[CmaState, str]:
    """Run (or, from ``resume = (asked, told, history[, validation])``, continue) CMA-ES for
    ``generations``. History row k is the distribution's mean after k generations (row 0:
    ``x0``): its objective and parts (batch means), the best candidate of generation k, the
    step size and generation k's wall time. The mean after generation k is evaluated with
    generation k + 1's candidates, in the same program call; the last mean on its own.

    ``validate`` and ``patience``: early stopping. The mean after each generation (and ``x0``)
    is evaluated by ``validate`` (``CmaState.validation``); the run stops once the best of
    those has not improved for ``patience`` generations.
    Returns the state and ``"done"``, ``"stopped_early"`` or ``"interrupted"``."""
    strategy = new_strategy(x0, population, seed, step_size)
    asked, told, history = ([], [], []) if resume is None else (list(resume[0]), list(resume[1]), list(resume[2]))
    validation = list(resume[3]) if resume is not None and len(resume) > 3 else []
    if len(asked) < generations:  # a finished run given more generations: its last row comes again
        history = history[: len(asked)]
    replay(strategy, asked, told)
    state = CmaState(len(asked), strategy, asked, told, history, validation)

    def validated() -> None:  # the current mean on the validation set, once per generation
        if validate is not None and len(state.validation) == state.generation:
            mean = np.asarray(strategy.mean)
            state.validation.append(
                {"generation": state.generation, "objective": float(validate(mean)), "mean": mean.tolist()}
            )

    def stalled() -> bool:
        if validate is None or not state.validation:
            return False
        best = min(state.validation, key=lambda item: item["objective"])
        return state.generation - best["generation"] >= patience

    validated()
    wall = math.nan  # the wall time of the generation whose mean has no row yet

    def mean_row(parts, which):
        best = float(np.min(told[-1])) if told else math.nan
        return _row(
            state.generation,
            parts,
            which,
            batch_objective(parts["loss"], cvar_alpha)[which],
            best,
            strategy.sigma,
            wall,
        )

    status = "done"
    while state.generation < generations:
        if stop is not None and stop.requested:
            status = "interrupted"
            break
        if stalled():
            status = "stopped_early"
            break
        start = time.perf_counter()
        candidates = np.asarray(strategy.ask())
        parts = evaluate(np.concatenate([candidates, strategy.mean[None]]))
        history.append(mean_row(parts, -1))
        objectives = batch_objective(parts["loss"][:-1], cvar_alpha)
        strategy.tell(list(candidates), list(objectives))
        asked.append(candidates)
        told.append(objectives)
        state.generation += 1
        wall = time.perf_counter() - start
        validated()
        if checkpoint_path is not None:
            save_checkpoint(checkpoint_path, state, config_dict or {}, write_atomically)
        if on_generation is not None:
            on_generation(state)
    if len(history) == state.generation:  # the last mean, on its own
        history.append(mean_row(evaluate(strategy.mean[None]), 0))
    return state, status


def best_validated(state: CmaState) -> tuple[np.ndarray, float, int]:
    """Early stopping's choice: the mean with the least validation objective,
    ``(x, objective, generation)`` (generation 0: ``x0``)."""
    best = min(state.validation, key=lambda item: item["objective"])
    return np.asarray(best["mean"]), best["objective"], best["generation"]


def best_ever(state: CmaState) -> tuple[np.ndarray, float, int | None]:
    """The best point the run evaluated on its training batch: the candidate with the least
    objective ever told, or the final mean where it is no worse (its objective is the last
    history row's). Returns ``(x, objective, generation)``, ``generation`` the candidate's
    (1-based, as the history counts them), ``None`` for the final mean."""
    x, objective, generation = np.asarray(state.strategy.mean), float(state.history[-1]["loss"]), None
    for index, (candidates, objectives) in enumerate(zip(state.asked, state.told)):
        best = int(np.argmin(objectives))
        if float(objectives[best]) < objective:
            x, objective, generation = np.asarray(candidates[best]), float(objectives[best]), index + 1
    return x, objective, generation


def _row(generation, parts, which, objective, best, sigma, wall) -> dict:
    """A history row: the objective of candidate ``which`` (the mean) and the batch means of
    its parts, the best candidate's objective, CMA-ES's step size, the wall time (s)."""
    row = {"step": generation, "loss": float(objective)}
    row |= {name: float(np.nanmean(value[which])) for name, value in parts.items() if name != "loss"}
    row[BATCH_MAX_PEAK_TORQUE] = float(np.nanmax(parts["largest_peak_torque_Nm"][which]))
    row |= {"best_candidate_loss": best, "sigma": float(sigma), "wall_s": wall}
    return row
