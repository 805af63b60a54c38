"""The worst capture in the perturbation envelope, searched for.

A Monte-Carlo campaign samples the envelope (``spacegrasp_jax.envelope.perturbations``) and can miss
its corners. This search looks for them: it raises a *measure* of the capture (the final
position error, the largest peak torque, or the largest ratio of a result to its success
criterion) over the perturbation's uniform numbers ``U`` (``perturbations.draw_units()``:
every perturbation in [-1, 1], the box of the envelope).

1. **Screening.** The first ``budget / 4`` samples of the campaign ``seed`` are run
   forward, as ``spacegrasp montecarlo`` runs them.
2. **The search** (``SearchSettings.method``), one of:

   * ``"cem"``, a cross-entropy search (the default): generations of ``budget / 8``
     samples (at least ``CEM_MIN_GENERATION``), each drawn around one of the ``elites``
     worst points found so far, ``U`` plus a normal draw of standard deviation ``spread``
     (shrunk by ``shrink`` each generation), projected on the box. A sample keeps the noise
     key of the point it was drawn around, so a lineage is a function of ``U`` alone.
     Forward rollouts only.
   * ``"ascent"``, a gradient ascent with the exact gradient of the closed loop from
     ``starts`` points: the ``starts - 1`` worst screened samples and one random corner of
     the box (every ``U`` at -1 or +1, drawn from the seed). Each takes steps of the box's
     steepest ascent, ``U + step sign(dm/dU)``, projected on the box. A step that raises
     the measure is kept and the next step grows by 1.5; one that does not is undone and
     the step halves. Where the gradient is not finite, or halving has brought the step
     below ``min_step`` (the measure is rough at the scale the gradient sees: a chaotic
     capture), the start goes on without gradients: a random sign step of size
     ``random_step``, kept only if it raises the measure. Every start keeps the noise key
     of the sample it started from.

The budget counts rollouts: a forward sample costs 1, a point of the ascent
``GRADIENT_COST`` (its reverse-mode gradient costs 3.5-3.8 forward rollouts on a CPU;
documentation, Performance). The worst capture is compared with the worst of a campaign of
the same number of rollouts and seed (``compare_with_campaign()``). Which method finds worse
captures than that campaign is measured (``benchmarks/worstcase.py``; documentation,
Margins and worst cases). A capture that runs away or diverges has the measure ``inf``: no
capture is worse, and the cross-entropy search stops there.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax.core import joint_limits
from spacegrasp_jax.core.inputs import read_document, short
from spacegrasp_jax.core.model import Robot
from spacegrasp_jax.envelope import metrics
from spacegrasp_jax.envelope.criteria import CaptureCriteria
from spacegrasp_jax.envelope.perturbations import (
    LATER_FIELDS,
    Perturbation,
    PerturbationError,
    PerturbationRanges,
    draw_units,
    from_units,
    project_units,
    sample_keys,
)
from spacegrasp_jax.envelope.scenario import Scenario
from spacegrasp_jax.jobs import anatomy, batching, compilation
from spacegrasp_jax.jobs.campaign import (
    CampaignConfig,
    CampaignError,
    Variant,
    compiled_chunk,
    evaluate_indices,
    variant_spec,
)
from spacegrasp_jax.jobs.experiment import loop_options
from spacegrasp_jax.jobs.montecarlo import NOISE_STREAM, lost, perturbed_run
from spacegrasp_jax.loop.control.gains import Gains
from spacegrasp_jax.loop.control.registry import law_named
from spacegrasp_jax.loop.simulate import FullLog, RunSpec, closed_loop, largest_divisor

#: The measures a search can climb: name -> (unit, meaning).
MEASURES = {
    "final_error": ("m", "the EE's final position error in the LAR frame"),
    "peak_torque": ("N m", "the largest peak |u_i| over the joints"),
    "criteria": (
        "",
        "the largest of final position error / tolerance, final orientation error / tolerance, "
        "largest peak torque / torque limit, for a robot with joint ranges their margin "
        "(exp(furthest excess beyond a range / 0.05 rad)) and, where rate limits are criteria, "
        "the largest peak joint rate / its limit: above 1, the capture fails",
    ),
}

#: How the console shows each measure: a scale from its SI unit, and the unit shown
#: (millimetres for a position, as every other console line).
SHOWN = {"final_error": (1e3, "mm"), "peak_torque": (1.0, "N m"), "criteria": (1.0, "")}


def shown(measure: str, value: float) -> str:
    """``value`` of ``measure`` (in ``MEASURES``' unit) as the console writes it: ``4.888 mm``."""
    scale, unit = SHOWN[measure]
    return f"{scale * value:.4g} {unit}".rstrip()


#: Rollouts one point of the ascent is counted as: its value and reverse-mode gradient.
GRADIENT_COST = 4

#: The fewest samples of a generation of the cross-entropy search.
CEM_MIN_GENERATION = 8


class WorstCaseError(ValueError):
    """An invalid worst-case setting; names the cause."""


#: How a search spends its budget after the screening (module docstring): ``"cem"``, the
#: cross-entropy search, forward rollouts only; ``"ascent"``, the gradient ascent.
METHODS = ("cem", "ascent")


@dataclasses.dataclass(frozen=True)
class SearchSettings:
    """How the worst case is searched (module docstring).

    Attributes:
        budget: rollouts in all (screening samples and the cross-entropy search's samples
            count 1, ascent points ``GRADIENT_COST``).
        measure: one of ``MEASURES``.
        method: one of ``METHODS``.
        starts: the ascent's starts, run side by side (the screening's ``starts - 1`` worst
            and a corner).
        first_step: the ascent's first step in ``U``, the box being [-1, 1].
        min_step: below this the ascent's step gives way to random steps.
        random_step: the size of the ascent's random step.
        elites: the cross-entropy search's parents: the worst points found so far.
        spread: the standard deviation in ``U`` of its first generation's draws around them.
        shrink: the spread's factor from one generation to the next.
    """

    budget: int = 512
    measure: str = "final_error"
    method: str = "cem"
    starts: int = 4
    first_step: float = 0.25
    min_step: float = 1.0 / 64.0
    random_step: float = 0.1
    elites: int = 4
    spread: float = 0.3
    shrink: float = 0.8

    def __post_init__(self):
        if self.measure not in MEASURES:
            raise WorstCaseError(f"measure: expected one of {', '.join(MEASURES)}, got {self.measure!r}")
        if self.method not in METHODS:
            raise WorstCaseError(f"method: expected one of {', '.join(METHODS)}, got {self.method!r}")
        for name in ("starts", "elites"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise WorstCaseError(f"{name}: must be a positive integer, got {value!r}")
        if isinstance(self.budget, bool) or not isinstance(self.budget, int) or self.budget < self.minimum_budget:
            spent = (
                f"screening {self.starts} samples and one ascent step of {self.starts} starts at {GRADIENT_COST} "
                "rollouts each"
                if self.method == "ascent"
                else f"screening {self.elites} samples and one generation of {CEM_MIN_GENERATION}"
            )
            raise WorstCaseError(
                f"budget: must be an integer of at least {self.minimum_budget} rollouts ({spent}), got {self.budget!r}"
            )
        for name in ("first_step", "min_step", "random_step", "spread"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and 0.0 < value <= 2.0):
                raise WorstCaseError(f"{name}: must be in (0, 2], got {value!r}")
        if not (isinstance(self.shrink, (int, float)) and 0.0 < self.shrink <= 1.0):
            raise WorstCaseError(f"shrink: must be in (0, 1], got {self.shrink!r}")

    @property
    def minimum_budget(self) -> int:
        if self.method == "cem":
            return self.elites + CEM_MIN_GENERATION
        return self.starts + GRADIENT_COST * self.starts

    @property
    def screening(self) -> int:
        """Samples run forward before the ascent or the cross-entropy search."""
        return max(self.elites if self.method == "cem" else self.starts, self.budget // 4)

    @property
    def generation(self) -> int:
        """The cross-entropy search's samples per generation: an eighth of the budget, at
        least ``CEM_MIN_GENERATION``."""
        return max(CEM_MIN_GENERATION, self.budget // 8)

    @property
    def generations(self) -> int:
        """The cross-entropy search's generations (the last may be smaller)."""
        return math.ceil((self.budget - self.screening) / self.generation)

    @property
    def campaign_chunk(self) -> int:
        """Samples per call of the forward program, the screening's and the comparison's."""
        return batching.chunk_size(min(64, self.screening), self.screening)

    @property
    def ascent_steps(self) -> int:
        """Batched points of the ascent the budget leaves."""
        return (self.budget - self.screening) // (GRADIENT_COST * self.starts)


# ---- the measure -------------------------------------------------------------------------


def measure_of_metrics(sample_metrics: dict, measure: str, config: CampaignConfig) -> np.ndarray:
    """(n,) the measure of samples from a campaign's metrics; ``inf`` where a sample ran
    away or diverged (NumPy)."""
    if measure == "final_error":
        values = np.asarray(sample_metrics["final_position_error_m"], dtype=float)
    elif measure == "peak_torque":
        values = np.asarray(sample_metrics["largest_peak_torque_Nm"], dtype=float)
    else:
        margins = anatomy.failure_classes(sample_metrics, config.criteria)
        parts = [margins["position_margin"], margins["orientation_margin"]]
        if config.criteria.torque_threshold_Nm is not None:
            parts.append(margins["torque_margin"])
        excess = margins["range_excess_rad"]
        if np.isfinite(excess).any():  # a robot with joint ranges
            with np.errstate(over="ignore"):
                parts.append(np.exp(excess / joint_limits.RANGE_MARGIN_SCALE_RAD))
        if config.criteria.joint_rate_limits_radps is not None:
            parts.append(margins["joint_rate_margin"])
        values = np.max(np.stack(parts), axis=0)
    return np.where(lost(sample_metrics) | ~np.isfinite(values), np.inf, values)


def _measure_of_log(log, measure: str, criteria: CaptureCriteria, ranges: tuple) -> jax.Array:
    if measure == "final_error":
        return metrics.final_position_error(log)
    peak = jnp.max(jnp.abs(log.u))
    if measure == "peak_torque":
        return peak
    ratios = [
        metrics.final_position_error(log) / criteria.position_tolerance_m,
        metrics.final_orientation_error(log) / criteria.orientation_tolerance_rad,
    ]
    if criteria.torque_threshold_Nm is not None:
        ratios.append(peak / criteria.torque_threshold_Nm)
    if ranges:  # the hard excess, as the campaign's criterion: exp(excess / scale), 1 at a limit
        excess = jnp.max(joint_limits.range_excess(log.q, ranges))
        ratios.append(jnp.exp(jnp.minimum(excess / joint_limits.RANGE_MARGIN_SCALE_RAD, 50.0)))
    if criteria.joint_rate_limits_radps is not None:
        ratios.append(jnp.max(jnp.abs(log.qd) / jnp.asarray(criteria.joint_rate_limits_radps)))
    return jnp.max(jnp.stack(ratios))


def gradient_spec(robot: Robot, scenario: Scenario, controller, realism=None) -> RunSpec:
    """The nominal run whose perturbations the search differentiates: the whole log kept in
    inner scans of two steps, each control period checkpointed for reverse mode (the
    options this process compiles best: [`experiment.loop_options()`][spacegrasp_jax.jobs.experiment.loop_options])."""
    return RunSpec(
        robot,
        scenario,
        controller,
        realism=realism,
        observer=FullLog(largest_divisor(scenario.n_steps, 2)),
        options=loop_options(checkpoint=True),
    )


def _value_and_gradient(spec, gains, ranges, block, *, measure, criteria, joint_ranges, identified):
    """The measure and its gradient in ``U`` for a block ``(units, keys)`` of points of the
    nominal run ``spec`` (its whole log kept, checkpointed: [`gradient_spec()`][spacegrasp_jax.analysis.worstcase.gradient_spec]), one
    point after another (``compilation.map_one_at_a_time``): the program then holds the gradient of one rollout,
    not of a batch, and compiles sooner than a ``vmap`` (measured: documentation, Changelog)."""

    def value(units, key):
        sample = perturbed_run(spec, from_units(units, ranges), ranges, identified)
        _, log = closed_loop(sample, gains, key)
        return _measure_of_log(log, measure, criteria, joint_ranges)

    return compilation.map_one_at_a_time(lambda point: jax.value_and_grad(value)(*point), block)


# ---- the search -------------------------------------------------------------------------------


def units_of_samples(seed: int, indices, dtype=jnp.float64, n_joints: int = 7) -> Perturbation:
    """The uniform numbers of the campaign's samples ``indices`` (leading axis n; NumPy), for
    an arm of ``n_joints`` joints (the paper's 7)."""
    units = jax.jit(jax.vmap(lambda key: draw_units(key, dtype, n_joints)))(sample_keys(seed, indices))
    return jax.tree.map(np.asarray, units)


def noise_keys(seed: int, indices) -> np.ndarray:
    """(n, 2) the sensor noise keys of the campaign's samples ``indices`` (as a campaign's)."""
    keys = jax.vmap(lambda k: jax.random.fold_in(k, NOISE_STREAM))(sample_keys(seed, indices))
    return np.asarray(keys)


def random_corner(seed: int, like: Perturbation) -> Perturbation:
    """A corner of the box (every ``U`` at -1 or +1; the ball's part on its surface), drawn
    from ``seed`` (one point, shaped as ``like``'s first item)."""
    rng = np.random.default_rng(seed)
    corner = jax.tree.map(lambda x: rng.choice([-1.0, 1.0], size=np.shape(x)[1:]), like)
    offset = corner.target_com_offset
    return dataclasses.replace(corner, target_com_offset=offset / np.linalg.norm(offset))


@dataclasses.dataclass
class SearchResult:
    """What ``search()`` returns.

    Attributes:
        value: the worst measure found. units: its point (a ``Perturbation`` of units).
        key: (2,) its sensor noise key. start: which start found it (-1: the screening).
        screening: the screening samples' measures (n,). history: per ascent step, each
            start's best measure so far and mode (``"gradient"`` or ``"random"``).
        rollouts: rollouts spent. compile_s: the programs' compile time (s). search_s:
            the screening's and the ascent's run time (s).
        start_samples: the campaign sample each start began at (``None``: the corner);
            the cross-entropy search has one start, the sample its worst descends from.
        found_by: how the worst was found, in words.
    """

    value: float
    units: Perturbation
    key: np.ndarray
    start: int
    screening: np.ndarray
    history: list
    rollouts: int
    compile_s: float
    search_s: float
    start_samples: list
    found_by: str = ""


def search(
    robot: Robot,
    scenario: Scenario,
    gains: Gains,
    controller: str,
    config: CampaignConfig,
    settings: SearchSettings = SearchSettings(),
    progress: Callable[[str], None] | None = None,
) -> SearchResult:
    """The worst capture of the envelope ``config.ranges`` (module docstring).

    Args:
        robot, scenario, gains, controller: the nominal loop.
        config: the envelope and campaign seed, the realism, the criteria (for the
            ``criteria`` measure) and whether the controller is told each plant
            (``identified``); its ``n`` and ``chunk`` are not used.
        settings: the budget, the measure, the method and its steps.
        progress: called with one line after the screening and one per generation or
            ascent step (``None``: silent).
    """
    started = time.perf_counter()
    say = progress or (lambda line: None)
    chunk = settings.campaign_chunk
    screening = chunk * math.ceil(settings.screening / chunk)
    values, compile_s = campaign_measures(
        robot, scenario, gains, controller, config, settings.measure, 0, screening, chunk
    )
    say(f"screening: {screening} samples, worst {settings.measure} {shown(settings.measure, np.max(values))}")
    if settings.method == "cem":
        return _cross_entropy(robot, scenario, gains, controller, config, settings, values, compile_s, started, say)
    return _ascent(robot, scenario, gains, controller, config, settings, values, compile_s, started, say)


def _ascent(robot, scenario, gains, controller, config, settings, values, compile_s, started, say) -> SearchResult:
    """The gradient ascent of the module docstring after the screening ``values``."""
    screening = len(values)
    worst_samples = [int(i) for i in np.argsort(-values, kind="stable")[: settings.starts - 1]]
    joints = scenario.initial.q.shape[-1]
    units = units_of_samples(config.seed, worst_samples, n_joints=joints)
    corner = random_corner(config.seed, units_of_samples(config.seed, [0], n_joints=joints))
    units = jax.tree.map(lambda many, one: np.concatenate([many, np.asarray(one)[None]]), units, corner)
    keys = np.concatenate([noise_keys(config.seed, worst_samples), noise_keys(config.seed, [screening])])
    starts = settings.starts
    batch = batching.chunk_size(starts, starts)
    pad = lambda x: np.concatenate([x, np.repeat(x[-1:], batch - starts, axis=0)])

    function = functools.partial(
        _value_and_gradient,
        measure=settings.measure,
        criteria=config.criteria,
        joint_ranges=joint_limits.finite_ranges(robot),
        identified=config.identified,
    )
    spec = gradient_spec(robot, scenario, law_named(controller, config.pinv_damping), config.realism)
    replicated = (spec, gains, config.ranges)
    try:
        executable, gradient_compile_s = batching.compile_chunk(
            f"worst-case gradient, {controller}",
            function,
            replicated,
            jax.tree.map(pad, (units, keys)),
            device_batch=1,
        )
    except batching.BatchingError as error:
        raise CampaignError(str(error)) from None
    compile_s += gradient_compile_s

    def evaluate(points):
        block = jax.tree.map(pad, (points, keys))
        values, gradients = batching.run_chunk(executable, replicated, block)
        return values[:starts], jax.tree.map(lambda x: x[:starts], gradients)

    best_values, best_units, history = ascend(
        evaluate, units, settings, np.random.default_rng([config.seed, 1]), screening, say
    )
    rollouts = history[-1]["rollouts"]

    best_start = int(np.argmax(best_values))
    screening_worst = int(np.argmax(values))
    if values[screening_worst] > best_values[best_start]:
        value, start = float(values[screening_worst]), -1
        found_units = jax.tree.map(lambda x: x[0], units_of_samples(config.seed, [screening_worst], n_joints=joints))
        found_key = noise_keys(config.seed, [screening_worst])[0]
    else:
        value, start = float(best_values[best_start]), best_start
        found_units = jax.tree.map(lambda x: np.asarray(x[best_start]), best_units)
        found_key = keys[best_start]
    return SearchResult(
        value=value,
        units=found_units,
        key=np.asarray(found_key),
        start=start,
        screening=values,
        history=history,
        rollouts=rollouts,
        compile_s=compile_s,
        search_s=time.perf_counter() - started - compile_s,
        start_samples=worst_samples + [None],
        found_by="a screened sample" if start < 0 else f"the ascent from start {start}",
    )


def _cross_entropy(robot, scenario, gains, controller, config, settings, values, compile_s, started, say):
    """The cross-entropy search of the module docstring after the screening ``values``."""
    screened = len(values)
    joints = scenario.initial.q.shape[-1]
    population = Population(
        points=units_of_samples(config.seed, range(screened), n_joints=joints),
        values=np.where(np.isfinite(values), values, np.inf),
        keys=noise_keys(config.seed, range(screened)),
        origins=np.arange(screened),
        born=np.zeros(screened, dtype=int),
    )
    size = batching.chunk_size(settings.generation, settings.generation)
    metrics_at, samples_compile_s = units_evaluator(
        robot, scenario, gains, controller, config, size, f"worst-case samples, {controller}"
    )
    compile_s += samples_compile_s

    def evaluate(points, keys):
        return measure_of_metrics(metrics_at(points, keys), settings.measure, config)

    population, history = cross_entropy(evaluate, population, settings, np.random.default_rng([config.seed, 2]), say)
    worst = int(np.argmax(population.values))
    born, origin = int(population.born[worst]), int(population.origins[worst])
    return SearchResult(
        value=float(population.values[worst]),
        units=jax.tree.map(lambda x: np.asarray(x[worst]), population.points),
        key=np.asarray(population.keys[worst]),
        start=-1 if born == 0 else 0,
        screening=np.asarray(population.values[:screened]),
        history=history,
        rollouts=history[-1]["rollouts"],
        compile_s=compile_s,
        search_s=time.perf_counter() - started - compile_s,
        start_samples=[origin],
        found_by=(
            f"screened sample {worst}"
            if born == 0
            else f"generation {born} of the cross-entropy search, descended from sample {origin}"
        ),
    )


@dataclasses.dataclass(frozen=True)
class Population:
    """The points a cross-entropy search has measured, in the order it measured them.

    Attributes:
        points: a ``Perturbation`` of units, leading axis n.
        values: (n,) their measures (``inf``: a capture that ran away or diverged).
        keys: (n, 2) their noise keys.
        origins: (n,) the screened point each descends from (its index).
        born: (n,) the generation that drew it (0: the screening).
    """

    points: Perturbation
    values: np.ndarray
    keys: np.ndarray
    origins: np.ndarray
    born: np.ndarray


def cross_entropy(evaluate, population: Population, settings: SearchSettings, rng, say=None):
    """The cross-entropy search of the module docstring from the screened ``population``,
    until ``settings.budget`` rollouts are spent (the screening counted) or a measure is
    ``inf``.

    Args:
        evaluate: ``(points, keys) -> values (n,)``, the measure at a batch of points (a
            ``Perturbation`` of units with leading axis n, and their noise keys).
        population: the screened points (``born`` 0).
        settings: the budget, ``elites``, ``spread``, ``shrink`` and the generation's size.
        rng: a NumPy generator, for the parents and the draws.
        say: called with one line per generation (``None``: silent).

    Returns:
        ``(population, history)``: every point measured, the screening's first; and per
        generation (the screening first) the rollouts spent so far and the worst measure.
    """
    spread, rollouts = settings.spread, len(population.values)
    history = [{"rollouts": rollouts, "best": [float(np.max(population.values))], "modes": ["screening"]}]
    for generation in range(1, settings.generations + 1):
        if np.isinf(np.max(population.values)):  # a capture ran away or diverged: none is worse
            break
        count = min(settings.generation, settings.budget - rollouts)
        if count < 1:  # the screening, a whole number of chunks, took more than its share
            break
        parents = rng.choice(np.argsort(-population.values, kind="stable")[: settings.elites], size=count)
        drawn = jax.tree.map(lambda x: x[parents] + spread * rng.standard_normal(x[parents].shape), population.points)
        children = jax.tree.map(np.asarray, jax.vmap(project_units)(drawn))
        measured = np.asarray(evaluate(children, population.keys[parents]), dtype=float)
        population = Population(
            points=jax.tree.map(lambda a, b: np.concatenate([a, b]), population.points, children),
            values=np.concatenate([population.values, np.where(np.isnan(measured), np.inf, measured)]),
            keys=np.concatenate([population.keys, population.keys[parents]]),
            origins=np.concatenate([population.origins, population.origins[parents]]),
            born=np.concatenate([population.born, np.full(count, generation)]),
        )
        rollouts += count
        spread *= settings.shrink
        history.append({"rollouts": rollouts, "best": [float(np.max(population.values))], "modes": ["sample"]})
        if say is not None:
            say(
                f"generation {generation}/{settings.generations}: worst {settings.measure} "
                f"{shown(settings.measure, np.max(population.values))}"
            )
    return population, history


def units_evaluator(
    robot: Robot, scenario: Scenario, gains: Gains, controller: str, config: CampaignConfig, size: int, name: str
) -> tuple[Callable, float]:
    """``(metrics_at, compile_s)``: ``metrics_at(units, keys)`` runs up to ``size`` points (a
    ``Perturbation`` of units with a leading axis, and (n, 2) noise keys) as the campaign of
    ``config`` runs a sample of those units and key, and returns their campaign metrics
    (leading axis n); one program of ``size`` points (a shorter block padded), compiled now
    (``compile_s``, the job's line named ``name``)."""
    variant = Variant(controller, gains)
    spec = variant_spec(robot, scenario, variant, dataclasses.replace(config, timeseries_every=None))
    replicated = (spec, gains, config.ranges)
    function = functools.partial(_metrics_at, identified=config.identified)
    joints = scenario.initial.q.shape[-1]
    like = (units_of_samples(config.seed, range(1), n_joints=joints), noise_keys(config.seed, range(1)))
    example = jax.tree.map(lambda x: np.repeat(np.asarray(x)[:1], size, axis=0), like)
    try:
        executable, compile_s = batching.compile_chunk(
            name, function, replicated, example, device_batch=config.device_batch
        )
    except batching.BatchingError as error:
        raise CampaignError(str(error)) from None

    def metrics_at(points, keys) -> dict:
        count = len(keys)
        block = jax.tree.map(lambda x: np.concatenate([x, np.repeat(x[-1:], size - count, axis=0)]), (points, keys))
        outputs = batching.run_chunk(executable, replicated, block)
        return {name: value[:count] for name, value in outputs.items()}

    return metrics_at, compile_s


def _metrics_at(spec, gains, ranges, block, *, identified):
    """The campaign metrics (``spec``'s observer, a ``FoldedMetrics``) of a block ``(units,
    keys)`` of points of the nominal run ``spec``, each run as a campaign runs the sample of
    those units and noise key."""

    def one(units, key):
        sample = perturbed_run(spec, from_units(units, ranges), ranges, identified)
        return closed_loop(sample, gains, key)[1][0]

    return jax.vmap(one)(*block)


def ascend(evaluate, units: Perturbation, settings: SearchSettings, rng, rollouts_before: int = 0, say=None):
    """The ascent of the module docstring from the batch of points ``units`` (leading axis:
    the starts), for ``settings.ascent_steps`` evaluations.

    Args:
        evaluate: ``points -> (values (n,), gradients)``, the measure and its gradient in
            ``U`` at a batch of points (gradients shaped as the points).
        units: the starts, a ``Perturbation`` of units with leading axis n.
        settings: the steps (``first_step``, ``min_step``, ``random_step``) and their number.
        rng: a NumPy generator, for the random steps.
        rollouts_before: rollouts spent before the ascent (for ``history``).
        say: called with one line per step (``None``: silent).

    Returns:
        ``(values, units, history)``: each start's best measure (``inf``: a capture that
        ran away) and its point, and per evaluation the rollouts spent so far, each start's
        best measure and its mode (``"gradient"`` or ``"random"``).
    """
    starts = len(jax.tree.leaves(units)[0])
    best_values, best_gradients = evaluate(units)
    best_values = np.where(np.isfinite(best_values), best_values, np.inf)
    best_units = units
    steps = np.full(starts, settings.first_step)
    modes = ["gradient"] * starts
    rollouts = rollouts_before + GRADIENT_COST * starts
    history = [{"rollouts": rollouts, "best": best_values.tolist(), "modes": list(modes)}]
    for step_number in range(settings.ascent_steps - 1):
        finite_gradient = [
            all(np.all(np.isfinite(leaf[i])) for leaf in jax.tree.leaves(best_gradients)) for i in range(starts)
        ]
        for i in range(starts):
            if modes[i] == "gradient" and (not finite_gradient[i] or steps[i] < settings.min_step):
                modes[i], steps[i] = "random", settings.random_step

        def proposal(u, g, i):
            direction = np.sign(g) if modes[i] == "gradient" else rng.choice([-1.0, 1.0], size=np.shape(u))
            return u + steps[i] * direction

        proposals = jax.tree.map(
            lambda u, g: np.stack([proposal(u[i], g[i], i) for i in range(starts)]), best_units, best_gradients
        )
        proposals = jax.tree.map(np.asarray, jax.vmap(project_units)(proposals))
        values_now, gradients_now = evaluate(proposals)
        values_now = np.where(np.isfinite(values_now), values_now, np.inf)
        rollouts += GRADIENT_COST * starts
        for i in range(starts):
            if np.isfinite(best_values[i]) and values_now[i] > best_values[i]:
                best_values[i] = values_now[i]
                take = lambda best, new, i=i: _set_row(best, i, new[i])
                best_units = jax.tree.map(take, best_units, proposals)
                best_gradients = jax.tree.map(take, best_gradients, gradients_now)
                if modes[i] == "gradient":
                    steps[i] = min(1.0, 1.5 * steps[i])
            elif modes[i] == "gradient":
                steps[i] *= 0.5
        history.append({"rollouts": rollouts, "best": best_values.tolist(), "modes": list(modes)})
        if say is not None:
            say(
                f"ascent step {step_number + 2}/{settings.ascent_steps}: best {settings.measure} "
                + ", ".join(f"{shown(settings.measure, v)} ({m[0]})" for v, m in zip(best_values, modes))
            )
    return best_values, best_units, history


def _set_row(array, i, row):
    array = np.array(array, copy=True)
    array[i] = row
    return array


def campaign_measures(
    robot: Robot,
    scenario: Scenario,
    gains: Gains,
    controller: str,
    config: CampaignConfig,
    measure: str,
    first: int,
    stop: int,
    chunk: int,
) -> tuple[np.ndarray, float]:
    """The measures of the campaign's samples ``first .. stop - 1`` (``stop - first`` a
    multiple of ``chunk``), run ``chunk`` at a time as ``spacegrasp montecarlo`` runs them,
    and the compile time of their program (s)."""
    campaign_config = dataclasses.replace(config, n=stop, chunk=chunk)
    variant = Variant(controller, gains)
    _, compile_s = compiled_chunk(robot, scenario, variant, campaign_config)
    pieces = [
        evaluate_indices(robot, scenario, variant, campaign_config, np.arange(start, start + chunk))
        for start in range(first, stop, chunk)
    ]
    sample_metrics = {name: np.concatenate([piece[name] for piece in pieces]) for name in pieces[0]}
    return measure_of_metrics(sample_metrics, measure, config), compile_s


def compare_with_campaign(
    robot: Robot,
    scenario: Scenario,
    gains: Gains,
    controller: str,
    config: CampaignConfig,
    n: int,
    measure: str,
    chunk: int = 64,
    screened: np.ndarray | None = None,
) -> dict:
    """The worst of a campaign of ``n`` samples (seed ``config.seed``), run ``chunk`` at a
    time (the screening's ``SearchSettings.campaign_chunk`` shares its program): ``value``,
    ``sample`` (its index), and every sample's measure (``values``). ``screened``: the
    measures of its first samples, already run (``SearchResult.screening``): not run again."""
    known = np.zeros(0) if screened is None else np.asarray(screened, dtype=float)[:n]
    if len(known) % chunk:
        raise WorstCaseError(f"screened: {len(known)} samples is not a whole number of chunks of {chunk}")
    rest = np.zeros(0)
    if len(known) < n:
        stop = len(known) + chunk * math.ceil((n - len(known)) / chunk)
        rest, _ = campaign_measures(robot, scenario, gains, controller, config, measure, len(known), stop, chunk)
    values = np.concatenate([known, rest])[:n]
    worst = int(np.argmax(values))
    return {"value": float(values[worst]), "sample": worst, "values": values}


def units_to_dict(units: Perturbation) -> dict[str, list[float]]:
    """The units as plain lists (JSON)."""
    return {name: np.ravel(np.asarray(value, dtype=float)).tolist() for name, value in vars(units).items()}


def units_from_dict(document: dict, dtype=np.float64) -> Perturbation:
    """``units_to_dict()``'s inverse; every field required (but those added later,
    ``LATER_FIELDS``, nominal where missing), each of its shape, in the box (the arm's number
    of joints is ``dq_init``'s length)."""
    angles = document.get("dq_init")
    joints = len(angles) if isinstance(angles, list) and angles else 7  # else refused below as for the paper's arm
    like = jax.tree.map(np.asarray, draw_units(jax.random.PRNGKey(0), dtype, joints))
    fields = {}
    for name, reference in vars(like).items():
        if name not in document and name in LATER_FIELDS:  # a file of a version before the field
            fields[name] = np.zeros_like(reference)
            continue
        if name not in document:
            raise WorstCaseError(f"units: {name} is missing")
        try:
            value = np.asarray(document[name], dtype=dtype)
        except (TypeError, ValueError):
            raise WorstCaseError(f"units.{name}: expected numbers, got {short(document[name])}") from None
        if value.size != reference.size or not np.all(np.isfinite(value)):
            raise WorstCaseError(f"units.{name}: expected {reference.size} finite numbers, got {document[name]!r}")
        if np.any(np.abs(value) > 1.0 + 1e-12):
            raise WorstCaseError(f"units.{name}: outside the box [-1, 1]: {value.tolist()}")
        if name == "target_com_offset" and np.linalg.norm(value) > 1.0 + 1e-12:
            raise WorstCaseError(f"units.{name}: outside the unit ball: {value.tolist()}")
        fields[name] = value.reshape(reference.shape)
    unknown = set(document) - set(fields)
    if unknown:
        raise WorstCaseError(f"units: unknown field(s) {', '.join(sorted(unknown))}")
    return Perturbation(**fields)


def perturbation_document(units: Perturbation, ranges, key, identified: bool) -> dict:
    """A perturbation file's content (``spacegrasp simulate --perturbation``): the units,
    the half-widths they scale, the sensor noise key and whether the controller is told
    the perturbed satellite."""
    return {
        "units": units_to_dict(units),
        "ranges": ranges.to_dict(),
        "noise_key": [int(x) for x in np.asarray(key, dtype=np.uint32).ravel()],
        "identified": bool(identified),
    }


def load_perturbation(path) -> tuple[Perturbation, PerturbationRanges, np.ndarray, bool]:
    """A perturbation file (``perturbation_document()``): ``(units, ranges, key, identified)``."""
    document = read_document(Path(path), WorstCaseError)
    if not isinstance(document, dict):
        raise WorstCaseError(f"{path}: expected a table with units, ranges, noise_key and identified")
    for name in ("units", "ranges", "noise_key", "identified"):
        if name not in document:
            raise WorstCaseError(f"{path}: {name} is missing")
    if not isinstance(document["units"], dict):
        raise WorstCaseError(f"{path}: units: expected a table of fields")
    if not isinstance(document["ranges"], dict):
        raise WorstCaseError(f"{path}: ranges: expected a table of half-widths")
    key = document["noise_key"]
    if not (
        isinstance(key, list)
        and len(key) == 2
        and all(isinstance(x, int) and not isinstance(x, bool) and 0 <= x < 2**32 for x in key)
    ):
        raise WorstCaseError(f"{path}: noise_key: expected two integers in [0, 2^32), got {short(key)}")
    if not isinstance(document["identified"], bool):
        raise WorstCaseError(f"{path}: identified: expected true or false, got {short(document['identified'])}")
    try:
        units = units_from_dict(document["units"])
        ranges = PerturbationRanges.from_mapping(document["ranges"], base=PerturbationRanges.nominal())
    except (WorstCaseError, PerturbationError) as error:
        raise WorstCaseError(f"{path}: {error}") from None
    return units, ranges, np.asarray(key, dtype=np.uint32), document["identified"]


def perturbed_spec(spec: RunSpec, path) -> tuple[RunSpec, jax.Array]:
    """The nominal run ``spec`` perturbed as the perturbation file ``path`` says, as a campaign
    runs that sample ([`montecarlo.perturbed_loop()`][spacegrasp_jax.jobs.montecarlo.perturbed_loop]: the perturbed plant and scenario,
    the sample's realism, the robot the controller believes), and the sample's noise key
    (2,) uint32.

    Raises:
        WorstCaseError: the file is not a perturbation file (names the field).
    """
    units, ranges, noise_key, identified = load_perturbation(path)
    perturbation = from_units(jax.tree.map(jnp.asarray, units), ranges)
    return perturbed_run(spec, perturbation, ranges, identified), jnp.asarray(noise_key, dtype=jnp.uint32)


__all__ = [
    "gradient_spec",
    "perturbed_spec",
    "GRADIENT_COST",
    "MEASURES",
    "SHOWN",
    "shown",
    "SearchResult",
    "SearchSettings",
    "WorstCaseError",
    "ascend",
    "campaign_measures",
    "compare_with_campaign",
    "load_perturbation",
    "perturbation_document",
    "measure_of_metrics",
    "noise_keys",
    "random_corner",
    "search",
    "units_from_dict",
    "units_of_samples",
    "units_to_dict",
]
