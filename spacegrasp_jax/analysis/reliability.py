"""How rarely a capture fails: a failure probability below what a campaign resolves.

The failure probability ``p = P(g(z) < 0)`` of a limit state ``g`` over ``d`` independent
standard normal coordinates ``z`` (for a capture: the envelope's perturbations,
[`standard_space`][spacegrasp_jax.envelope.standard_space], and the capture's margin,
[`limit_state`][spacegrasp_jax.analysis.limit_state]) is estimated by one of ``METHODS``:

* ``"subset"``: subset simulation (Au and Beck, Probabilistic Engineering Mechanics 16(4),
  2001; OpenTURNS' ``SubsetSampling``): nested levels of conditional probability
  ``conditional_probability``, each of ``level_size`` points moved by component-wise
  random-walk Metropolis chains. No gradient. The default: the measured winner on a
  capture (documentation, How rarely it fails).
* ``"form_is"``: importance sampling at the design points. FORM (Hasofer-Lind,
  Rackwitz-Fiessler, with Abdo-Rackwitz steps: OpenTURNS' ``AbdoRackwitz``) finds the most
  probable failure point ``z*`` from ``starts`` starting points (the origin, then points drawn
  on the sphere of radius ``START_RADIUS``), on the limit state's gradient; the points are then
  drawn from the mixture of unit normals centred at the distinct design points, each weighted
  by its FORM probability ``Phi(-beta)``, and ``p`` is the importance-weighted failure rate
  (OpenTURNS' ``ProbabilitySimulationAlgorithm`` with an ``ImportanceSamplingExperiment``).
  Uses the gradient; FORM spends at most ``form_share`` of the budget.
* ``"cross_entropy"``: cross-entropy importance sampling in the standard space (Rubinstein;
  the algorithm of OpenTURNS' ``StandardSpaceCrossEntropyImportanceSampling``, written out
  here with two changes, ``_cross_entropy()``): a normal density, never narrower than the
  standard normal, adapted level by level to the ``conditional_probability`` quantile,
  ``level_size`` points a level; the last level, the one whose quantile reached failure or
  the last the budget allows, gives the estimate. No gradient.
* ``"montecarlo"``: the plain failure rate of ``budget`` points: a campaign's own samples where
  the limit state has them (``LimitState.campaign_values``), else standard normal draws; its
  95% interval is Clopper-Pearson's, an upper bound when nothing fails.

Where OpenTURNS refuses to form subset simulation's estimate (a variance that is not a
number: it has happened on a capture whose failure probability is near a level's, 1e-1), the
first level, a plain Monte-Carlo of the standard normal, gives the estimate with its
Clopper-Pearson interval, and the result says so (``details["source"]``).

The budget counts rollouts: a point 1, a gradient ``LimitState.gradient_cost``. The 95% interval
of the sampling estimators is the lognormal one of their coefficient of variation ``c``,
``p exp(+-1.96 sqrt(ln(1 + c^2)))``; with no failing point sampled there is no estimate and
no bound, and the result says so.

A limit state may be random (a flight-like loop's sensor noise): ``values(z, first)`` evaluates
point ``k`` with noise draw ``first + k``, a new draw for every point ever evaluated. Every
estimator here then estimates the probability over the perturbations and the noise together:
a sampling estimator draws the noise with the point, and a Metropolis move that proposes a new
point with a new draw of the noise is a valid move of the chain on both (the noise's proposal
is its own distribution, whose Metropolis ratio is 1). FORM's search alone holds the noise at
one draw (``fixed_values``, ``value_and_gradient``), so that it searches a deterministic
function; the importance sampling after it draws the noise again, so that only its variance,
not its mean, depends on the design points found.

Every call of the limit state is written to a journal (``journal`` folder) as it returns; a
run interrupted and started again with the same settings replays the journal (OpenTURNS'
random generator seeded by ``seed``, its state restored afterwards) and goes on from where it
stopped.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

#: The estimators (module docstring); the first is the default.
METHODS = ("subset", "form_is", "cross_entropy", "montecarlo")

#: Which use the limit state's gradient.
GRADIENT_METHODS = ("form_is",)

#: Rollouts a gradient is counted as by default: a value and its reverse-mode gradient cost
#: 3.5-3.8 forward rollouts of a capture on a CPU (documentation, Performance).
GRADIENT_COST = 4.0

#: Radius of FORM's starting points after the origin, in the standard space.
START_RADIUS = 1.0

#: Seconds between two progress lines of a stage.
PROGRESS_EVERY_S = 5.0

#: FORM's convergence: the design point's step (absolute and relative), the residual of its
#: optimality and the limit state there, each below this (the margin's scale is 1).
FORM_TOLERANCE = 1e-3

#: The quantile of a standard normal at 97.5%: the 95% intervals' half-width in sigmas.
Z_95 = 1.959963984540054


class ReliabilityError(ValueError):
    """An invalid reliability setting, or a journal that is not this run's; names the cause."""


class _BudgetSpent(Exception):
    """A call that the budget does not leave room for."""


@dataclasses.dataclass(frozen=True)
class LimitState:
    """A limit state over ``dimension`` standard normal coordinates: failure where ``g < 0``.

    Each function returns a dict of arrays: ``"g"`` and, where it has them, extras a run keeps
    with each point (a failed criterion's name, a noise key), each with the points' leading
    axis.

    Attributes:
        dimension: d.
        values: ``(z (n, d), first) -> {"g": (n,), ...}``: point ``k`` evaluated with noise
            draw ``first + k`` (a deterministic limit state ignores ``first``).
        value_and_gradient: ``z (d,) -> {"g": (), "gradient": (d,), ...}`` at the fixed
            noise draw (``None``: no gradient; the gradient methods refuse it).
        fixed_values: ``z (n, d) -> {"g": (n,), ...}`` at the fixed noise draw (``None``:
            ``values`` with draw 0 for every point).
        campaign_values: ``(start, stop) -> {"g": (stop - start,), "z": (n, d), ...}``: the
            campaign's own samples ``start, ..., stop - 1`` (``None``: Monte-Carlo draws ``z``).
        gradient_cost: rollouts a gradient counts.
        names: (d,) the coordinates' names (``None``: ``z[0]``, ``z[1]``, ...).
    """

    dimension: int
    values: Callable
    value_and_gradient: Callable | None = None
    fixed_values: Callable | None = None
    campaign_values: Callable | None = None
    gradient_cost: float = GRADIENT_COST
    names: tuple[str, ...] | None = None

    def coordinate_names(self) -> tuple[str, ...]:
        return self.names if self.names is not None else tuple(f"z[{i}]" for i in range(self.dimension))


@dataclasses.dataclass(frozen=True)
class Settings:
    """How a failure probability is estimated (module docstring).

    Attributes:
        method: one of ``METHODS``.
        budget: rollouts in all (a gradient counts the limit state's ``gradient_cost``).
        seed: seed of the estimator's draws (OpenTURNS' generator, FORM's starts, the
            Monte-Carlo draws); a campaign's samples are those of the limit state's own seed.
        conditional_probability: subset simulation's and cross-entropy's level probability.
        smallest_probability: the smallest probability the levels are sized for: each level
            has ``level_size = budget // levels`` points, ``levels`` those that reach it.
        block: points per call of the limit state.
        starts: FORM's starting points (``form_is``).
        form_share: the share of the budget FORM may spend (``form_is``).
        target_cv: stop sampling once the estimator's coefficient of variation is below it
            (``form_is``, ``montecarlo``; 0: spend the budget).
        design_points: the most probable failure points kept.
    """

    method: str = METHODS[0]
    budget: int = 5000
    seed: int = 0
    conditional_probability: float = 0.1
    smallest_probability: float = 1e-6
    block: int = 100
    starts: int = 4
    form_share: float = 0.25
    target_cv: float = 0.0
    design_points: int = 5

    def __post_init__(self):
        if self.method not in METHODS:
            raise ReliabilityError(f"method: expected one of {', '.join(METHODS)}, got {self.method!r}")
        for name in ("budget", "block", "starts", "design_points"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ReliabilityError(f"{name}: must be a positive integer, got {value!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or not 0 <= self.seed < 2**31:
            raise ReliabilityError(f"seed: must be an integer in [0, 2^31), got {self.seed!r}")
        for name, low, high in (
            ("conditional_probability", 0.0, 0.5),
            ("smallest_probability", 0.0, 0.5),
            ("form_share", 0.0, 1.0),
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not low < value < high:
                raise ReliabilityError(f"{name}: must be in ({low:g}, {high:g}), got {value!r}")
        if (
            isinstance(self.target_cv, bool)
            or not isinstance(self.target_cv, (int, float))
            or not (0.0 <= self.target_cv < math.inf)
        ):
            raise ReliabilityError(f"target_cv: must be a number >= 0, got {self.target_cv!r}")
        if self.method in ("subset", "cross_entropy") and self.level_size < self.block:
            raise ReliabilityError(
                f"budget: {self.budget} rollouts give levels of {self.budget // self.levels} points, fewer than a "
                f"block of {self.block}, over the {self.levels} levels down to {self.smallest_probability:g}: raise "
                "the budget, or lower the block or the smallest probability"
            )

    @property
    def levels(self) -> int:
        """Levels of ``conditional_probability`` down to ``smallest_probability``."""
        return max(1, math.ceil(math.log(self.smallest_probability) / math.log(self.conditional_probability) - 1e-9))

    @property
    def level_size(self) -> int:
        """Points a level (subset simulation, cross-entropy): a whole number of blocks."""
        return self.block * (self.budget // self.levels // self.block)


@dataclasses.dataclass
class Estimate:
    """A failure probability and how it was obtained.

    Attributes:
        method: the estimator.
        probability: the estimate (NaN where no failing point was sampled: no estimate).
        low, high: its 95% interval (``low`` 0 and ``high`` an upper bound when a
            Monte-Carlo sees no failure; NaN where there is no estimate).
        coefficient_of_variation: the estimator's (NaN where unknown).
        rollouts: rollouts spent (a gradient counted ``gradient_cost``).
        points, gradients: limit state values and gradients evaluated.
        failing: failing points evaluated (any stage).
        wall_s: seconds of the estimate, the replayed journal's included as it was recorded.
        design_points: the most probable failing points, most probable first: each
            ``{"z", "g", "distance", "importance", ...extras}``, ``importance`` the
            coordinates' shares of ``|z|^2``, the largest first.
        attribution: what the failures have in common (``attribution()``): coordinate name ->
            its share, the largest first (empty without failing points).
        details: the method's own: FORM's design points and reliability indices, the levels'
            thresholds, ...
        complete: False where the budget ran out before the method finished (no estimate).
    """

    method: str
    probability: float
    low: float
    high: float
    coefficient_of_variation: float
    rollouts: float
    points: int
    gradients: int
    failing: int
    wall_s: float
    design_points: list
    attribution: dict
    details: dict
    complete: bool = True

    def to_dict(self) -> dict:
        return {name: _plain(value) for name, value in dataclasses.asdict(self).items()}

    def summary(self) -> str:
        """One line: ``p = 2.1e-05 [1.3e-05, 3.4e-05], c.o.v. 0.24, 4,980 rollouts``."""
        if not self.complete:
            why = self.details.get("error", "the budget ran out")
            return f"no estimate: {why}, after {self.rollouts:,.0f} rollouts"
        if not math.isfinite(self.probability) and "below" in self.details:
            return (
                f"no estimate: the levels reached {self.details['below']:.3g} without a failing capture, "
                f"after {self.rollouts:,.0f} rollouts"
            )
        if not math.isfinite(self.probability):
            return f"no failing point sampled in {self.rollouts:,.0f} rollouts: no estimate"
        cv = (
            f"c.o.v. {self.coefficient_of_variation:.2f}"
            if math.isfinite(self.coefficient_of_variation)
            else "c.o.v. -"
        )
        line = f"p = {self.probability:.3g} [{self.low:.3g}, {self.high:.3g}], {cv}, {self.rollouts:,.0f} rollouts"
        if self.details.get("source") == "the first level's Monte-Carlo":
            line += (
                f" (the first level's Monte-Carlo, {self.details['failures']:,} failures in "
                f"{self.details['samples']:,}: OpenTURNS refused its estimate, {self.details['error']})"
            )
        return line


def _plain(value):
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, (np.floating, float)):
        return float(value)
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.str_):
        return str(value)
    return value


def lognormal_interval(probability: float, cv: float) -> tuple[float, float]:
    """The 95% interval ``p exp(+-1.96 s)``, ``s = sqrt(ln(1 + cv^2))``, of an estimate with
    coefficient of variation ``cv``."""
    if not (math.isfinite(probability) and probability > 0.0 and math.isfinite(cv)):
        return math.nan, math.nan
    spread = math.sqrt(math.log1p(cv * cv))
    return probability * math.exp(-Z_95 * spread), probability * math.exp(Z_95 * spread)


def binomial_interval(failures: int, samples: int) -> tuple[float, float]:
    """The 95% Clopper-Pearson interval of ``failures`` in ``samples`` (``low`` 0 when none)."""
    from scipy import stats

    interval = stats.binomtest(int(failures), int(samples)).proportion_ci(confidence_level=0.95, method="exact")
    return float(interval.low), float(interval.high)


# ---- the journal of calls ---------------------------------------------------------------


class _Calls:
    """The limit state as the estimators call it: counted, journaled, replayed, reported."""

    def __init__(self, limit_state: LimitState, settings: Settings, journal: Path | None, say):
        self.limit_state = limit_state
        self.settings = settings
        self.journal = journal
        self.say = say
        self.fresh = 0  # points evaluated with a new noise draw
        self.points = 0
        self.gradients = 0
        self.rollouts = 0.0
        self.recorded_s = 0.0  # seconds the calls took, as recorded
        self.position = 0
        self.failing: list[dict] = []
        self.fresh_g: list[np.ndarray] = []  # g of each call with new noise draws, in order
        self.raised: BaseException | None = None  # what the limit state raised (an interrupt, an error)
        self.stage, self.reported_at = "", -math.inf  # the last progress line's
        self.entries = sorted(journal.glob("*.npz")) if journal is not None and journal.exists() else []
        if journal is not None:
            journal.mkdir(parents=True, exist_ok=True)

    @property
    def replaying(self) -> bool:
        return self.position < len(self.entries)

    def _spend(self, rollouts: float) -> None:
        """Counts ``rollouts``; raises ``_BudgetSpent`` where they would pass the budget."""
        if self.rollouts + rollouts > self.settings.budget:
            self.raised = _BudgetSpent()
            raise self.raised
        self.rollouts += rollouts

    def _call(self, kind: str, z: np.ndarray, compute: Callable[[], dict]) -> dict:
        if self.position < len(self.entries):
            path = self.entries[self.position]
            with np.load(path) as entry:
                stored_kind, stored_z = str(entry["kind"]), entry["z"]
                outputs = {name[4:]: entry[name] for name in entry.files if name.startswith("out.")}
                seconds = float(entry["seconds"])
            if stored_kind != kind or stored_z.shape != z.shape or not np.array_equal(stored_z, z):
                self.raised = ReliabilityError(
                    f"{path}: the journal's call {self.position} was {stored_kind} of {stored_z.shape[0]} point(s), "
                    f"this run's is {kind} of {z.shape[0]}: not this run's journal (other settings or limit state)"
                )
                raise self.raised
        else:
            started = time.perf_counter()
            try:
                outputs = {name: np.asarray(value) for name, value in compute().items()}
            except BaseException as error:  # OpenTURNS would turn it into its own error: kept to raise as it was
                self.raised = error
                raise
            seconds = time.perf_counter() - started
            if self.journal is not None:
                _write_entry(self.journal / f"{self.position:06d}.npz", kind, z, outputs, seconds)
        self.position += 1
        self.recorded_s += seconds
        return outputs

    def _keep_failing(self, z: np.ndarray, outputs: dict, stage: str) -> None:
        g = np.atleast_1d(outputs["g"])
        for k in np.flatnonzero(g < 0.0):
            extras = {name: value[k] for name, value in outputs.items() if name not in ("g", "gradient", "z")}
            self.failing.append({"z": z[k], "g": float(g[k]), "stage": stage} | extras)

    def values(self, z: np.ndarray, stage: str) -> np.ndarray:
        """(n,) g at points z (n, d), each with a new noise draw."""
        z = np.ascontiguousarray(z, dtype=np.float64)
        first = self.fresh
        self._spend(len(z))
        outputs = self._call("values", z, lambda: self.limit_state.values(z, first))
        self.fresh += len(z)
        self.fresh_g.append(np.atleast_1d(np.asarray(outputs["g"], dtype=np.float64)))
        self.points += len(z)
        self._keep_failing(z, outputs, stage)
        self._report(stage)
        return np.asarray(outputs["g"], dtype=np.float64)

    def fixed_values(self, z: np.ndarray, stage: str) -> np.ndarray:
        """(n,) g at points z (n, d) at the fixed noise draw."""
        z = np.ascontiguousarray(z, dtype=np.float64)
        fixed = self.limit_state.fixed_values or (lambda points: self.limit_state.values(points, 0))
        self._spend(len(z))
        outputs = self._call("fixed", z, lambda: fixed(z))
        self.points += len(z)
        self._keep_failing(z, outputs, stage)
        self._report(stage)
        return np.asarray(outputs["g"], dtype=np.float64)

    def value_and_gradient(self, z: np.ndarray, stage: str) -> tuple[float, np.ndarray]:
        z = np.ascontiguousarray(z, dtype=np.float64)
        self._spend(self.limit_state.gradient_cost)
        outputs = self._call("gradient", z[None], lambda: _with_leading_axis(self.limit_state.value_and_gradient(z)))
        self.points += 1
        self.gradients += 1
        self._keep_failing(z[None], outputs, stage)
        self._report(stage)
        return float(outputs["g"][0]), np.asarray(outputs["gradient"][0], dtype=np.float64)

    def campaign_values(self, start: int, stop: int, stage: str) -> np.ndarray:
        indices = np.arange(start, stop, dtype=np.float64)[:, None]
        self._spend(stop - start)
        outputs = self._call("campaign", indices, lambda: self.limit_state.campaign_values(start, stop))
        self.points += stop - start
        self._keep_failing(np.asarray(outputs["z"], dtype=np.float64), outputs, stage)
        self._report(stage)
        return np.asarray(outputs["g"], dtype=np.float64)

    def _report(self, stage: str) -> None:
        """A progress line: at a new stage, then at most every ``PROGRESS_EVERY_S``."""
        if self.say is None or self.replaying:
            return
        now = time.perf_counter()
        if stage != self.stage or now - self.reported_at >= PROGRESS_EVERY_S:
            self.stage, self.reported_at = stage, now
            self.say(
                f"{stage}: {self.rollouts:,.0f} of {self.settings.budget:,} rollouts, "
                f"{len(self.failing):,} failing point(s), {self.recorded_s:.0f} s"
            )


def _with_leading_axis(outputs: dict) -> dict:
    return {name: np.asarray(value)[None] for name, value in outputs.items()}


def _write_entry(path: Path, kind: str, z: np.ndarray, outputs: dict, seconds: float) -> None:
    arrays = {"kind": np.asarray(kind), "z": z, "seconds": np.asarray(seconds)}
    arrays |= {f"out.{name}": value for name, value in outputs.items()}
    handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".npz.tmp")
    try:
        with os.fdopen(handle, "wb") as stream:
            np.savez(stream, **arrays)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def _openturns_seeded(seed: int):
    """OpenTURNS' global random generator seeded with ``seed``, its state restored after."""
    import openturns as ot

    state = ot.RandomGenerator.GetState()
    ot.RandomGenerator.SetSeed(seed)
    try:
        yield ot
    finally:
        ot.RandomGenerator.SetState(state)


def _openturns():
    try:
        import openturns
    except ImportError:
        raise ReliabilityError(
            "the reliability methods need OpenTURNS: pip install 'spacegrasp-jax[reliability]'"
        ) from None
    return openturns


def _event(ot, dimension: int, batch: Callable, single: Callable | None = None, gradient: Callable | None = None):
    """The event ``g(Z) < 0``, ``Z`` standard normal in ``dimension`` dimensions, of a limit
    state called in batches (``batch``: (n, d) -> (n,))."""
    single = single or (lambda x: batch(np.asarray(x, dtype=np.float64)[None])[:1])
    kwargs = {} if gradient is None else {"gradient": lambda x: np.asarray(gradient(np.asarray(x)))[:, None].tolist()}
    function = ot.PythonFunction(
        dimension,
        1,
        func=lambda x: [float(single(x)[0])],
        func_sample=lambda xs: np.asarray(batch(np.asarray(xs, dtype=np.float64)), dtype=np.float64)[:, None],
        **kwargs,
    )
    vector = ot.CompositeRandomVector(function, ot.RandomVector(ot.Normal(dimension)))
    return ot.ThresholdEvent(vector, ot.Less(), 0.0)


# ---- the estimators ---------------------------------------------------------------------


def estimate(limit_state: LimitState, settings: Settings, *, journal=None, say=None) -> Estimate:
    """The failure probability of ``limit_state`` by ``settings.method`` (module docstring).

    Args:
        limit_state: the limit state.
        settings: the method, budget and seed.
        journal: a folder for the journal of calls (``None``: none, no resume); a run with
            the same settings and limit state replays what it holds.
        say: called with a progress line after each call (``None``: silent).

    Raises:
        ReliabilityError: a gradient method on a limit state without a gradient, or a journal
            of another run.
    """
    if settings.method in GRADIENT_METHODS and limit_state.value_and_gradient is None:
        raise ReliabilityError(f"method {settings.method}: needs the limit state's gradient, which this one has not")
    calls = _Calls(limit_state, settings, None if journal is None else Path(journal), say)
    if settings.method == "montecarlo":
        result = _montecarlo(calls, settings)
    elif settings.method == "cross_entropy":
        result = _cross_entropy(calls, settings)
    else:
        ot = _openturns()
        method = {"form_is": _form_is, "subset": _subset}[settings.method]
        with _openturns_seeded(settings.seed):
            try:
                result = method(ot, calls, settings)
            except Exception as error:  # OpenTURNS' error, or what a call raised, which it wraps
                if isinstance(calls.raised, _BudgetSpent):
                    result = math.nan, math.nan, {"error": "the budget ran out"}, False
                elif calls.raised is not None:
                    raise calls.raised from None
                elif _openturns_refusal(error):  # a result OpenTURNS cannot form
                    result = _first_level(calls, settings, str(error).splitlines()[0][:300])
                else:
                    raise
    probability, cv, details, complete = result
    if complete and "samples" in details:  # a Monte-Carlo's failure rate
        low, high = binomial_interval(details["failures"], details["samples"])
    elif complete and probability > 0.0:
        low, high = lognormal_interval(probability, cv)
    else:
        probability, low, high, cv = math.nan, math.nan, math.nan, math.nan
    return Estimate(
        method=settings.method,
        probability=float(probability),
        low=float(low),
        high=float(high),
        coefficient_of_variation=float(cv),
        rollouts=float(calls.rollouts),
        points=calls.points,
        gradients=calls.gradients,
        failing=len(calls.failing),
        wall_s=calls.recorded_s,
        design_points=most_probable(calls.failing, settings.design_points, limit_state.coordinate_names()),
        attribution=attribution(calls.failing, limit_state.coordinate_names()),
        details=details,
        complete=complete,
    )


def journal_points(journal) -> dict[str, np.ndarray]:
    """Every point a run's journal holds, in the order evaluated: ``distance`` (n,) ``|z|``,
    ``g`` (n,) and ``kind`` (n,) the call (``values``, ``fixed``, ``gradient``, ``campaign``)."""
    distance, g, kind = [], [], []
    for path in sorted(Path(journal).glob("*.npz")):
        with np.load(path) as entry:
            z = entry["out.z"] if str(entry["kind"]) == "campaign" else entry["z"]
            distance.append(np.linalg.norm(z, axis=1))
            g.append(np.atleast_1d(entry["out.g"]))
            kind += [str(entry["kind"])] * len(z)
    if not g:
        return {"distance": np.zeros(0), "g": np.zeros(0), "kind": np.zeros(0, dtype=str)}
    return {"distance": np.concatenate(distance), "g": np.concatenate(g), "kind": np.asarray(kind)}


def attribution(failing: list[dict], names, shown: int = 8) -> dict[str, float]:
    """Which coordinates the failing points have in common: each coordinate's excess second
    moment over the failing points, ``max(mean(z_i^2) - 1, 0)`` (a standard normal's is 1: a
    coordinate that does not matter keeps it, one that carries the failures, in either
    direction, exceeds it), as shares of their sum, the ``shown`` largest. Over the failing
    points found, unweighted: the failure domain's conditional distribution for Monte-Carlo
    and the last level of subset simulation, an approximation of it for importance sampling."""
    if not failing:
        return {}
    z = np.stack([np.asarray(p["z"], dtype=np.float64) for p in failing])
    excess = np.maximum(np.mean(z * z, axis=0) - 1.0, 0.0)
    total = float(np.sum(excess))
    if total == 0.0:
        return {}
    order = np.argsort(-excess)[:shown]
    return {names[i]: float(excess[i] / total) for i in order if excess[i] > 0.0}


def most_probable(failing: list[dict], count: int, names) -> list[dict]:
    """The ``count`` failing points nearest the origin (the most probable; one of points
    closer than 1e-9 to each other), each with its distance and the coordinates' shares of
    ``|z|^2``, the largest first."""
    kept: list[dict] = []
    for point in sorted(failing, key=lambda p: float(np.sum(np.square(p["z"])))):
        z = np.asarray(point["z"], dtype=np.float64)
        if any(np.linalg.norm(z - np.asarray(k["z"])) < 1e-9 for k in kept):
            continue
        squared = np.square(z)
        total = float(np.sum(squared))
        order = np.argsort(-squared)
        importance = {names[i]: float(squared[i] / total) if total > 0 else 0.0 for i in order[: min(8, len(order))]}
        kept.append(point | {"z": z, "distance": math.sqrt(total), "importance": importance})
        if len(kept) == count:
            break
    return kept


def _montecarlo(calls: _Calls, settings: Settings):
    n, block = settings.budget, settings.block
    rng = np.random.default_rng(settings.seed)
    failures = samples = 0
    for start in range(0, n, block):
        stop = min(n, start + block)
        if calls.limit_state.campaign_values is not None:
            g = calls.campaign_values(start, stop, "montecarlo")
        else:
            g = calls.values(rng.standard_normal((stop - start, calls.limit_state.dimension)), "montecarlo")
        failures += int(np.sum(g < 0.0))
        samples += len(g)
        if settings.target_cv and failures and _binomial_cv(failures, samples) <= settings.target_cv:
            break
    p = failures / samples
    source = "campaign" if calls.limit_state.campaign_values is not None else "standard normal draws"
    return p, _binomial_cv(failures, samples), {"failures": failures, "samples": samples, "source": source}, True


def _first_level(calls: _Calls, settings: Settings, error: str):
    """The failure rate of subset simulation's first level, whose points are a plain
    Monte-Carlo of the standard normal, where OpenTURNS refused to form its estimate; no
    estimate where the first level did not complete (or for FORM-IS)."""
    n = (settings.level_size // settings.block) * settings.block
    g = np.concatenate(calls.fresh_g) if calls.fresh_g else np.zeros(0)
    if settings.method != "subset" or len(g) < n:
        return math.nan, math.nan, {"error": error}, False
    failures = int(np.sum(g[:n] < 0.0))
    details = {"failures": failures, "samples": n, "source": "the first level's Monte-Carlo", "error": error}
    return failures / n, _binomial_cv(failures, n), details, True


def _binomial_cv(failures: int, samples: int) -> float:
    """The coefficient of variation of a failure rate (NaN without a failure)."""
    p = failures / samples
    return math.sqrt((1.0 - p) / (samples * p)) if failures else math.nan


def _openturns_refusal(error: Exception) -> bool:
    """Whether ``error`` is OpenTURNS' own (``InvalidArgumentException : ...``, raised as a
    ``RuntimeError`` or a ``TypeError``), not a defect of the caller."""
    name, separator, _ = str(error).partition(" : ")
    return bool(separator) and name.endswith("Exception") and " " not in name


def _tail(beta: float) -> float:
    """``Phi(-beta)``."""
    return 0.5 * math.erfc(beta / math.sqrt(2.0))


def _spent_past(calls: _Calls, rollouts: float) -> bool:
    return calls.rollouts >= rollouts


def _subset(ot, calls: _Calls, settings: Settings):
    event = _event(ot, calls.limit_state.dimension, lambda z: calls.values(z, "subset"))
    algorithm = ot.SubsetSampling(event)
    algorithm.setConditionalProbability(settings.conditional_probability)
    algorithm.setBlockSize(settings.block)
    algorithm.setMaximumOuterSampling(settings.level_size // settings.block)
    # The levels are sized for the smallest probability; a smaller one goes on until the
    # budget runs out (then no estimate).
    algorithm.setMinimumProbability(settings.smallest_probability * 1e-6)
    algorithm.run()
    result = algorithm.getResult()
    thresholds = [float(t) for t in algorithm.getThresholdPerStep()]
    reached = bool(thresholds) and thresholds[-1] <= 0.0
    details = {
        "level_size": settings.level_size,
        "thresholds": thresholds,
        "level_probabilities": [float(p) for p in algorithm.getProbabilityEstimatePerStep()],
        "reached_failure": reached,
    }
    if not reached:  # the levels stopped at the smallest probability: only a bound
        details["below"] = float(result.getProbabilityEstimate())
        return 0.0, math.nan, details, True
    return float(result.getProbabilityEstimate()), float(result.getCoefficientOfVariation()), details, True


def _cross_entropy(calls: _Calls, settings: Settings):
    """Cross-entropy importance sampling in the standard space: the algorithm of OpenTURNS'
    ``StandardSpaceCrossEntropyImportanceSampling`` (independent normal densities, each
    level's mean and standard deviations the likelihood-ratio-weighted moments of the points
    below the level's ``conditional_probability`` quantile of ``g``; the estimate the
    importance-weighted failure rate of the last level, with OpenTURNS' variance), with two
    changes. A level's standard deviations are never below 1: a density narrower than the
    standard normal in a coordinate gives weights ``phi / q`` that grow without bound in that
    coordinate's tails, and an estimate of unbounded variance whose typical value lies below
    the truth. And the levels end where the budget does: where the next level would pass it,
    the last level drawn gives the estimate, as one whose quantile reached 0 does (OpenTURNS'
    draws levels until the quantile reaches 0, and one that stalls above it, as a capture
    whose failures need a perturbation at the edge of its bounded range and unlucky sensor
    noise can, ends with the budget and no estimate). The draws are NumPy's, seeded by
    ``settings.seed``."""
    d, n, block = calls.limit_state.dimension, settings.level_size, settings.block
    rng = np.random.default_rng(settings.seed)
    mean, std = np.zeros(d), np.ones(d)
    thresholds = []
    while True:
        z = mean + std * rng.standard_normal((n, d))
        g = np.concatenate([calls.values(z[start : start + block], "cross_entropy") for start in range(0, n, block)])
        # log(standard normal density / the level's density) at each point
        log_ratio = np.sum(-0.5 * z**2 + 0.5 * ((z - mean) / std) ** 2 + np.log(std), axis=1)
        quantile = float(np.quantile(g, settings.conditional_probability))
        thresholds.append(quantile)
        if quantile < 0.0 or calls.rollouts + n > settings.budget:
            break
        critic = g < quantile
        if not np.any(critic):  # every point at or above the quantile (values tied there)
            critic = g <= quantile
        weights = np.exp(log_ratio[critic] - np.max(log_ratio[critic]))
        mean = weights @ z[critic] / np.sum(weights)
        # Never narrower than the standard normal: where a level's density is narrower in a
        # coordinate, phi / q grows without bound in that coordinate's tails and the
        # estimate's variance with it (OpenTURNS' follows the points there).
        std = np.maximum(np.sqrt(weights @ (z[critic] - mean) ** 2 / np.sum(weights)), 1.0)
    failing = g < 0.0
    details = {
        "level_size": n,
        "thresholds": thresholds,
        "reached_failure": thresholds[-1] < 0.0,
        "failures_last_level": int(np.sum(failing)),
    }
    if not np.any(failing):
        return 0.0, math.nan, details, True
    ratios = np.exp(log_ratio[failing])
    probability = float(np.sum(ratios) / n)
    variance = (np.sum((ratios - probability) ** 2) + (n - ratios.size) * probability**2) / (n - 1) / n
    return probability, math.sqrt(variance) / probability, details, True


def _form_is(ot, calls: _Calls, settings: Settings):
    d = calls.limit_state.dimension
    form_budget = settings.form_share * settings.budget
    event = _event(
        ot,
        d,
        lambda z: calls.fixed_values(z, "form"),
        gradient=lambda z: calls.value_and_gradient(np.asarray(z, dtype=np.float64), "form")[1],
    )
    rng = np.random.default_rng(settings.seed)
    starts = [np.zeros(d)]
    for _ in range(settings.starts - 1):
        direction = rng.standard_normal(d)
        starts.append(START_RADIUS * direction / np.linalg.norm(direction))
    found = []
    for k, start in enumerate(starts):
        spent = calls.rollouts
        share = (form_budget - spent) / (len(starts) - k)
        if share < 1.0 + calls.limit_state.gradient_cost:
            break
        optimiser = ot.AbdoRackwitz()
        optimiser.setStartingPoint(ot.Point(start))
        for set_tolerance in (
            optimiser.setMaximumAbsoluteError,
            optimiser.setMaximumRelativeError,
            optimiser.setMaximumResidualError,
            optimiser.setMaximumConstraintError,
        ):
            set_tolerance(FORM_TOLERANCE)
        failing_before = len(calls.failing)
        # OpenTURNS keeps the callback without a reference of its own: it must outlive the run.
        stop = functools.partial(_spent_past, calls, spent + share)
        optimiser.setStopCallback(stop)
        form = ot.FORM(optimiser, event)
        try:
            form.run()
        except RuntimeError as error:  # a zero gradient at the start, a failed line search
            if calls.raised is not None and not isinstance(calls.raised, _BudgetSpent):
                raise calls.raised from None  # an interrupt, the limit state's own error
            calls.raised = None
            stopped = {"start": start, "error": str(error).splitlines()[0][:200]}
            # Stopped before it converged: the nearest failing point it met, if any, is a centre.
            met = [p for p in calls.failing[failing_before:] if p["stage"] == "form"]
            if met:
                nearest = min(met, key=lambda p: float(np.sum(np.square(p["z"]))))
                beta = float(np.linalg.norm(nearest["z"]))
                stopped |= {"design_point": np.asarray(nearest["z"]), "beta": beta, "probability": _tail(beta)}
            found.append(stopped)
            continue
        result = form.getResult()
        found.append(
            {
                "start": start,
                "design_point": np.asarray(result.getStandardSpaceDesignPoint(), dtype=np.float64),
                "beta": float(result.getHasoferReliabilityIndex()),
                "probability": float(result.getEventProbability()),
                "origin_fails": bool(result.getIsStandardPointOriginInFailureSpace()),
            }
        )
    centres, weights = [], []
    for point in found:
        if "design_point" not in point:
            continue
        centre = point["design_point"]
        if all(np.linalg.norm(centre - c) > 0.1 * max(1.0, np.linalg.norm(centre)) for c in centres):
            centres.append(centre)
            weights.append(max(point["probability"], 1e-300))
    details = {
        "form": found,
        "centres": centres,
        "centre_weights": list(np.asarray(weights) / np.sum(weights)) if weights else [],
        "form_rollouts": calls.rollouts,
    }
    if centres:
        components = [ot.Normal(ot.Point(c), ot.Point(d, 1.0), ot.CorrelationMatrix(d)) for c in centres]
        instrumental = components[0] if len(components) == 1 else ot.Mixture(components, weights)
        experiment = ot.ImportanceSamplingExperiment(instrumental)
    else:  # no design point: plain sampling
        experiment = ot.MonteCarloExperiment()
    sampling_event = _event(ot, d, lambda z: calls.values(z, "importance sampling"))
    algorithm = ot.ProbabilitySimulationAlgorithm(sampling_event, experiment)
    remaining = settings.budget - calls.rollouts
    algorithm.setBlockSize(settings.block)
    algorithm.setMaximumOuterSampling(max(1, int(remaining // settings.block)))
    algorithm.setMaximumCoefficientOfVariation(settings.target_cv)
    algorithm.setMaximumStandardDeviation(0.0)
    algorithm.run()
    result = algorithm.getResult()
    details["sampled"] = int(result.getOuterSampling() * result.getBlockSize())
    return float(result.getProbabilityEstimate()), float(result.getCoefficientOfVariation()), details, True


__all__ = [
    "GRADIENT_COST",
    "GRADIENT_METHODS",
    "METHODS",
    "Estimate",
    "LimitState",
    "ReliabilityError",
    "Settings",
    "attribution",
    "binomial_interval",
    "estimate",
    "journal_points",
    "lognormal_interval",
    "most_probable",
]
