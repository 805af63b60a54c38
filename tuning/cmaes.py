"""Gradient-free tuning: CMA-ES (the ``cma`` package) on the same parameters, objective and
batch as the gradient method, forward rollouts only ([`tuning.protocol`][tuning.protocol]: one
driver runs both).

The parameters are the tuned entries of the log-gains ([`spacegrasp_jax.tuning.parameters`][tuning.parameters],
frozen groups left out), one flat vector. A generation asks ``population`` candidates of
CMA-ES and evaluates them on the batch in one sharded, chunked program
([`spacegrasp_jax.jobs.batching.map_in_chunks()`][spacegrasp_jax.jobs.batching.map_in_chunks]: ``population x batch``
forward rollouts, no reverse-mode compile), tells CMA-ES their objectives, then evaluates the
distribution's new mean on the same batch: the history row of the step. The run's gains are
the best point it evaluated, or the mean after the last generation (``keep``).

Resume without pickles: CMA-ES draws its candidates from its own seeded generator, so the
checkpoint keeps each generation's candidates and objectives, and a resumed run replays the
asks and tells, which rebuilds the strategy exactly, then goes on.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, ClassVar

import jax
import numpy as np

from spacegrasp_jax.core.model import Robot
from spacegrasp_jax.jobs import batching
from spacegrasp_jax.jobs.experiment import loop_options
from spacegrasp_jax.jobs.montecarlo import SampleLoops
from spacegrasp_jax.jobs.runfiles import progress_bar
from spacegrasp_jax.loop.control.gains import Gains
from spacegrasp_jax.loop.simulate import LoopOptions
from spacegrasp_jax.tuning.objective import Objective, objective_spec, scenario_parts, tail_count
from spacegrasp_jax.tuning.parameters import gains_from_params
from spacegrasp_jax.tuning.protocol import Answers, Outcome, Request

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


def _candidate_parts(model_robot, objective: Objective, items, *, controller: str, options: LoopOptions):
    """The objective's parts of each (gains, robot, scenario, realism, key) item (vmapped;
    realism and key ``None`` in the paper's ideal loop)."""

    def one(gains, robot, scenario, realism, key):
        spec = objective_spec(robot, scenario, controller, realism=realism, model_robot=model_robot, options=options)
        return scenario_parts(spec, gains, objective, key)

    return jax.vmap(one)(*items)


#: The most rollouts one call of the population's program runs (measured on 2 cores: a
#: batch of 64 runs as fast in calls of 64 as of 32; performance page).
MAX_CHUNK = 64


def population_chunk(batch: int) -> int:
    """Rollouts per call of the population's program for a training ``batch``: the batch
    itself up to ``MAX_CHUNK`` (each candidate one call, no padding, and the mean's
    evaluation reuses the program); a larger batch, its largest divisor up to it
    where that is at least half of it, else ``MAX_CHUNK`` (the last call padded)."""
    if batch <= MAX_CHUNK:
        return batch
    divisor = max(d for d in range(1, MAX_CHUNK + 1) if batch % d == 0)
    return divisor if 2 * divisor >= MAX_CHUNK else MAX_CHUNK


def make_item_evaluator(
    robot: Robot, samples: SampleLoops, controller: str, objective: Objective, chunk: int
) -> Callable[[Gains, np.ndarray], dict]:
    """``evaluate(gains (M stacked), rows (M,)) -> parts``, every part of the objective shaped
    (M,): gain set ``k`` on sample ``rows[k]`` of ``samples`` (the flight-like loop's, or the
    ideal loop's, [`ideal_batch()`][tuning.tune.ideal_batch]); forward rollouts in one sharded,
    chunked program. The controllers believe ``samples.model_robot``, else under a realism
    ``robot``, else each sample its own robot."""
    per_sample = (samples.robots, samples.scenarios, samples.realisms, samples.keys)
    model_robot = samples.model_robot
    if model_robot is None and samples.realisms is not None:
        model_robot = robot
    function = functools.partial(_candidate_parts, controller=controller, options=loop_options(checkpoint=True))

    def evaluate(gains: Gains, rows: np.ndarray) -> dict:
        items = (gains, *batching.take(per_sample, np.asarray(rows)))
        return batching.map_in_chunks(
            "tuning.cmaes",
            function,
            (model_robot, objective),
            items,
            chunk=chunk,
            progress=None,
        )

    return evaluate


def batch_objective(losses: np.ndarray, cvar_alpha: float | None) -> np.ndarray:
    """(P,) the objective of each candidate from its (P, batch) losses: the mean, or the mean
    over the worst ``1 - cvar_alpha`` of the batch; a candidate with a non-finite loss gets
    ``inf`` (CMA-ES ranks it last)."""
    losses = np.asarray(losses, dtype=float)
    if cvar_alpha is None:
        total = losses.mean(axis=1)
    else:
        worst = tail_count(cvar_alpha, losses.shape[1])
        total = np.sort(losses, axis=1)[:, -worst:].mean(axis=1)
    return np.where(np.isfinite(total), total, np.inf)


def new_strategy(
    x0: np.ndarray, population: int | None, seed: int, step_size: float = SIGMA, separable: bool = False
) -> cma.CMAEvolutionStrategy:
    """CMA-ES from ``x0`` with initial step ``step_size`` (log-gain units), seeded (its
    ``seed`` must not be 0, which ``cma`` reads as "draw one"), silent; ``separable``: a
    diagonal covariance throughout (sep-CMA-ES, pycma's ``CMA_diagonal``)."""
    import cma  # imported on first use: with scipy.stats, most of a second at every command's start

    options = {"seed": seed + 1, "verbose": -9, "verb_log": 0, "verb_disp": 0}
    if population is not None:
        options["popsize"] = population
    if separable:
        options["CMA_diagonal"] = True
    return cma.CMAEvolutionStrategy(np.asarray(x0, dtype=float), step_size, options)


def reevaluated(population: int, objectives: np.ndarray, seed: int, generation: int) -> np.ndarray:
    """The candidates of a generation that the noise measurement evaluates again (UH-CMA-ES,
    Hansen et al., IEEE TEC 2009, as ``cma.NoiseHandler.indices``): ``2 + population / 20``
    of them (the fraction drawn), the first half in the order asked, the rest the best of the
    others. Drawn from a generator of ``(seed, generation)``, so a resumed run chooses alike."""
    wanted = 2.0 + population / 20.0
    draw = np.random.default_rng([seed, generation]).random()
    count = min(population, int(wanted) + int(wanted % 1 > draw))
    first = count - count // 2
    rest = np.argsort(np.asarray(objectives)[first:], kind="stable") + first
    return np.concatenate([np.arange(first), rest[: count - first]]).astype(int)


def new_noise_handler(dimension: int):
    """pycma's noise measurement and treatment for ``dimension`` numbers, each objective one
    batch (``maxevals=1``): where the re-evaluated candidates' ranks move more than chance
    allows, the step size grows (``treat()``)."""
    import cma

    return cma.NoiseHandler(dimension, maxevals=1, epsilon=0.0)


def measure_noise(handler, objectives: np.ndarray, indices: np.ndarray, again: np.ndarray) -> float:
    """Feed ``handler`` a generation's objectives and the re-evaluations ``again`` of the
    candidates ``indices``; the factor the step size is multiplied by."""
    handler.fit = [float(x) for x in objectives]
    handler.fitre = list(handler.fit)
    for index, value in zip(indices, again, strict=True):
        handler.fitre[int(index)] = float(value)
    handler.idx = np.asarray(indices, dtype=int)
    handler.update_measure()
    return float(handler.treat())


def replay(strategy: cma.CMAEvolutionStrategy, asked: list, told: list, noise=None) -> None:
    """Rebuild ``strategy`` by asking and telling the recorded generations again (with
    ``noise = (handler, [(indices, again), ...])``, the noise treatment after each generation
    whose re-evaluations are recorded); raises RuntimeError if an ask does not give back the
    recorded candidates (another ``cma``)."""
    for generation, (candidates, objectives) in enumerate(zip(asked, told)):
        again = np.asarray(strategy.ask())
        if not np.allclose(again, candidates, rtol=0.0, atol=1e-12):
            raise RuntimeError("the checkpoint's CMA-ES generations do not replay (was it written by another cma?)")
        strategy.tell(list(candidates), list(objectives))
        if noise is not None and generation < len(noise[1]):
            indices, values = noise[1][generation]
            strategy.sigma *= measure_noise(noise[0], objectives, indices, values)


@dataclasses.dataclass(frozen=True)
class CMAESSettings:
    """CMA-ES's settings in a tuning run (``TuneConfig.settings`` with ``method="cmaes"``).

    Attributes:
        population: candidates per generation (``None``: pycma's default, ``4 + 3 ln n`` for n
            tuned numbers).
        step_size: the initial step in log-gain units (0.3: about +-30% on every gain; smaller
            to refine gains already tuned).
        separable: a diagonal covariance (sep-CMA-ES; [`CMAES`][tuning.cmaes.CMAES]).
        noise_handling: pycma's noise handling (UH-CMA-ES; needs the run's ``fresh_batches``): a
            few candidates of each generation evaluated again on the next batch, the step size
            raised where their ranks move more than chance allows.

    Raises:
        ValueError: a setting out of its range, naming it.
    """

    population: int | None = None
    step_size: float = SIGMA
    separable: bool = False
    noise_handling: bool = False

    def __post_init__(self):
        population = self.population
        if population is not None and not (
            isinstance(population, int) and not isinstance(population, bool) and 2 <= population <= 10_000
        ):
            raise ValueError(f"population: must be a whole number from 2 to 10000, got {population!r}")
        if not (isinstance(self.step_size, (int, float)) and self.step_size > 0.0 and math.isfinite(self.step_size)):
            raise ValueError(f"step_size: must be positive and finite, got {self.step_size}")
        for name in ("separable", "noise_handling"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name}: must be true or false, got {getattr(self, name)!r}")


@dataclasses.dataclass
class CMAESState:
    """A CMA-ES run after ``generation`` generations: the strategy, every generation's
    candidates and objectives (what a checkpoint keeps and a resume replays), the start
    (``params``: the point whose tuned entries the vectors are, ``mask``: which they are) and
    what the next ask asks: ``"mean"`` (the distribution's mean, whose row completes a step)
    or ``"candidates"`` (a generation). Under noise handling, ``noise`` is pycma's
    ``NoiseHandler`` and ``reevaluations`` each generation's re-evaluated candidates
    ``(indices, objectives)``; ``seed`` chooses them."""

    strategy: cma.CMAEvolutionStrategy
    params: dict
    mask: dict
    asked: list = dataclasses.field(default_factory=list)
    told: list = dataclasses.field(default_factory=list)
    generation: int = 0
    phase: str = "mean"
    seed: int = 0
    noise: object = None
    reevaluations: list = dataclasses.field(default_factory=list)

    def point_of(self, vector: np.ndarray) -> dict:
        """The point whose tuned entries are ``vector``."""
        return unflatten(np.asarray(vector, dtype=float), self.params, self.mask)

    def to_reevaluate(self) -> np.ndarray:
        """The last generation's candidates the noise measurement evaluates again (none before
        the first generation or without noise handling)."""
        if self.noise is None or not self.told:
            return np.zeros(0, dtype=int)
        return reevaluated(len(self.told[-1]), self.told[-1], self.seed, self.generation)


@dataclasses.dataclass(frozen=True)
class CMAES:
    """CMA-ES ([`tuning.protocol.TuningMethod`][tuning.protocol.TuningMethod]): a step is a
    generation of ``population`` candidates (``None``: pycma's default, ``4 + 3 ln n`` for n
    tuned numbers) on the step's batch, then the new mean on the next step's batch (the same
    one without fresh batches).

    Attributes:
        population: candidates per generation.
        step_size: the initial step in log-gain units.
        separable: a diagonal covariance (sep-CMA-ES, Ros and Hansen, PPSN 2008): ``n``
            variances learnt instead of ``n (n + 1) / 2`` covariances, so faster learning
            on hundreds of numbers.
        noise_handling: UH-CMA-ES (Hansen et al., IEEE TEC 2009; ``cma.NoiseHandler``): after
            every generation ``2 + population / 20`` candidates are evaluated again on the
            next batch (with the mean), and where their ranks move more than chance allows
            the step size grows. Needs fresh batches.
        fresh: the problem draws a new batch every generation: the candidates of different
            generations were ranked on different batches, so ``best()`` hands back the final
            mean (pycma's ``xfavorite``), never a lucky candidate.
    """

    population: int | None = None
    step_size: float = SIGMA
    separable: bool = False
    noise_handling: bool = False
    fresh: bool = False
    name: ClassVar[str] = "cmaes"
    title: ClassVar[str] = "CMA-ES"
    unit: ClassVar[str] = "generation"
    point_words: ClassVar[str] = "the mean"
    #: its settings in a ``TuneConfig`` (``TuneConfig.settings``)
    settings_type: ClassVar[type] = CMAESSettings

    @classmethod
    def from_config(cls, config) -> CMAES:
        s = config.settings
        return cls(s.population, s.step_size, s.separable, s.noise_handling, config.fresh_batches)

    @classmethod
    def check(cls, config) -> None:
        """What CMA-ES's settings need of the rest of a ``TuneConfig``."""
        if config.settings.noise_handling and not config.fresh_batches:
            raise ValueError(
                "noise_handling: measures the noise by evaluating candidates again on a new batch (choose --fresh-batches)"
            )

    def describe(self) -> str:
        variant = ["separable"] if self.separable else []
        variant += ["noise handling (UH-CMA-ES)"] if self.noise_handling else []
        return "forward rollouts only" + (f", {' and '.join(variant)}" if variant else "")

    def init(self, point, mask, seed: int) -> CMAESState:
        params = {name: np.asarray(value) for name, value in point.items()}
        x0 = flatten(params, mask)
        strategy = new_strategy(x0, self.population, seed, self.step_size, self.separable)
        noise = new_noise_handler(x0.size) if self.noise_handling else None
        return CMAESState(strategy, params, mask, seed=seed, noise=noise)

    def ask(self, state: CMAESState) -> tuple[Request, CMAESState]:
        if state.phase == "mean":
            again = tuple(state.point_of(state.asked[-1][i]) for i in state.to_reevaluate())
            return Request((state.point_of(state.strategy.mean), *again), batch=state.generation), state
        candidates = np.asarray(state.strategy.ask())
        state = dataclasses.replace(state, asked=[*state.asked, candidates])
        return Request(tuple(state.point_of(x) for x in candidates), batch=state.generation), state

    def tell(self, state: CMAESState, request: Request, answers: Answers) -> tuple[CMAESState, Outcome]:
        if state.phase == "mean":
            indices = state.to_reevaluate()
            if indices.size:
                again = np.asarray(answers.objectives[1:], dtype=float)
                state.strategy.sigma *= measure_noise(state.noise, state.told[-1], indices, again)
                state = dataclasses.replace(state, reevaluations=[*state.reevaluations, (indices, again)])
            best = float(np.min(state.told[-1])) if state.told else math.nan
            row = {"step": state.generation, "loss": float(answers.objectives[0]), **answers.summaries[0]}
            row |= {"best_candidate_loss": best, "sigma": float(state.strategy.sigma)}
            if state.noise is not None:
                row["noise_measure"] = float(state.noise.noiseS)
            return dataclasses.replace(state, phase="candidates"), Outcome(row=row)
        objectives = np.asarray(answers.objectives)
        state.strategy.tell(list(state.asked[-1]), list(objectives))
        state = dataclasses.replace(
            state, told=[*state.told, objectives], generation=state.generation + 1, phase="mean"
        )
        return state, Outcome()

    def point(self, state: CMAESState) -> dict:
        return state.point_of(state.strategy.mean)

    def point_of_vector(self, state: CMAESState, vector: np.ndarray) -> dict:
        """The point whose tuned entries are ``vector`` (an older checkpoint's validated mean)."""
        return state.point_of(vector)

    def best(self, state: CMAESState, history: list[dict], best_step: int, best_point):
        """The candidate with the least objective ever told, or the final mean where it is no
        worse (its objective the last history row's); under fresh batches, the final mean."""
        x, objective, generation = np.asarray(state.strategy.mean), float(history[-1]["loss"]), None
        for index, (candidates, objectives) in enumerate(zip(state.asked, state.told)):
            which = int(np.argmin(objectives))
            if not self.fresh and float(objectives[which]) < objective:
                x, objective, generation = np.asarray(candidates[which]), float(objectives[which]), index + 1
        if generation is None:
            return state.point_of(x), len(history) - 1, f"the mean after generation {len(history) - 1}", objective
        return state.point_of(x), None, f"the best candidate of generation {generation}", objective

    def state_arrays(self, state: CMAESState) -> tuple[dict, dict]:
        arrays = {f"asked_{k}": np.asarray(a) for k, a in enumerate(state.asked)}
        arrays |= {f"told_{k}": np.asarray(t) for k, t in enumerate(state.told)}
        for k, (indices, again) in enumerate(state.reevaluations):
            arrays |= {f"reevaluated_{k}": np.asarray(indices), f"again_{k}": np.asarray(again)}
        return arrays, {"generation": state.generation, "phase": state.phase}

    def restore(self, point, mask, seed: int, arrays: dict, meta: dict, steps: int) -> CMAESState:
        state = self.init(point, mask, seed)
        count = meta["generation"]
        asked = [arrays[f"asked_{k}"] for k in range(count)]
        told = [arrays[f"told_{k}"] for k in range(count)]
        reevaluations = [
            (arrays[f"reevaluated_{k}"], arrays[f"again_{k}"]) for k in range(count) if f"reevaluated_{k}" in arrays
        ]
        noise = None if state.noise is None else (state.noise, reevaluations)
        replay(state.strategy, asked, told, noise)
        return dataclasses.replace(
            state, asked=asked, told=told, generation=count, phase=meta["phase"], reevaluations=reevaluations
        )

    def progress(self, state: CMAESState, row: dict, steps: int) -> str:
        candidates = (
            "no candidates yet" if state.generation == 0 else f"best candidate {row['best_candidate_loss']:.4f}"
        )
        mean = "the start" if state.generation == 0 else "the mean after it"
        return progress_bar(
            state.generation,
            steps,
            f"generation {state.generation}/{steps}: {candidates} | "
            f"{mean} {row['loss']:.4f}, final pos {1e3 * row['final_position_error_m']:.3f} mm | "
            f"step size {state.strategy.sigma:.3f}",
        )
