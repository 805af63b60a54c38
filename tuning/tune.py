"""The settings of a tuning run ([`TuneConfig`][tuning.tune.TuneConfig]), its problem
([`make_problem()`][tuning.tune.make_problem]: the loss over a batch of scenarios and its
gradient programs), the gradient method ([`GradientMethod`][tuning.tune.GradientMethod]: an
optax transformation with a divergence guard) and the methods' registry (``METHODS``).

One gradient step: ``updates = optimiser(gradient)``; the candidate ``params + scale * updates`` is
evaluated (loss and gradient together); if its rollout diverged (non-finite values, or a peak
torque above ``torque_guard_Nm``, or a loss above ``loss_guard`` times the starting loss) it is
rejected, ``scale`` is halved and the event logged, else it is accepted together with the
optimiser's new state. The driver ([`tuning.driver`][tuning.driver]) writes the whole run
state atomically to ``checkpoint.npz`` after every accepted step, so an interrupted run
resumes from its last completed step and ends exactly where an uninterrupted one would.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import math
import warnings
from collections.abc import Callable
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.flatten_util import ravel_pytree

from spacegrasp_jax.core import joint_limits
from spacegrasp_jax.core.model import Robot
from spacegrasp_jax.envelope.criteria import CaptureCriteria
from spacegrasp_jax.envelope.perturbations import PerturbationRanges, check_for_scenario, sample_scenarios
from spacegrasp_jax.envelope.scenario import Scenario
from spacegrasp_jax.jobs import batching, compilation
from spacegrasp_jax.jobs.experiment import loop_options
from spacegrasp_jax.jobs.montecarlo import SampleLoops, sample_loops
from spacegrasp_jax.jobs.runfiles import progress_bar
from spacegrasp_jax.loop.control.gains import Gains
from spacegrasp_jax.loop.control.registry import CONTROLLERS
from spacegrasp_jax.loop.control.schedule import VARIABLES
from spacegrasp_jax.loop.realism import Realism, ideal, make_realism
from spacegrasp_jax.loop.simulate import LoopOptions, gradient_cut, largest_divisor
from spacegrasp_jax.tuning import cmaes, estimators
from spacegrasp_jax.tuning.objective import (
    BATCH_MAX_PEAK_TORQUE,
    OBJECTIVES,
    Objective,
    Weights,
    objective_spec,
    scenario_parts,
    tail_count,
)
from spacegrasp_jax.tuning.parameters import GROUPS, gains_from_params, initial_params, make_mask
from spacegrasp_jax.tuning.problem import TuningProblem
from spacegrasp_jax.tuning.protocol import Answers, Outcome, Request

CHECKPOINT = "checkpoint.npz"


#: What ``spacegrasp tune`` runs when ``--method`` is not given, by problem: the recipe that
#: won the race at equal wall time on that problem (documentation, Tuning the gains, "Which
#: method"). In a flight-like loop (a realism other than the ideal one), on constant gains and
#: on gain schedules, the gradient method on a fresh batch of 32 captures every step, combined
#: as the median of four group means, for 75 steps (14-21 minutes on 2-core VMs). The ideal
#: loop was not raced: CMA-ES, the earlier default, stays its default.
RECIPES = {
    "ideal": {"method": "cmaes"},
    "flight_like": {
        "method": "gradient",
        "fresh_batches": True,
        "aggregate": "median_of_means",
        "batch": 32,
        "steps": 75,
        "keep": "last",  # the races held out each run's last step, not its best on its own batch
    },
}


def default_recipe(realism: dict | None) -> dict:
    """The TuneConfig fields ``spacegrasp tune`` fills when ``--method`` is not given, for a
    run under ``realism`` (``Realism.to_dict()``; ``None`` or the ideal realism's: the
    paper's loop). An option given explicitly overrides its field."""
    return dict(RECIPES["ideal" if realism is None or realism == ideal().to_dict() else "flight_like"])


#: The robust batch's perturbations: initial joint angles, LAR pose and contact stiffness,
#: the model and the initial velocities left nominal (the Monte-Carlo defaults vary those too).
TUNING_RANGES = PerturbationRanges(
    lar_estimate_position_m=0.0,
    lar_estimate_angle_rad=0.0,
    q_init_rad=0.01,
    lar_position_m=0.003,
    lar_angle_rad=0.005,
    stiffness_factor=2.0,
    base_speed_mps=0.0,
    base_rate_radps=0.0,
    joint_rate_radps=0.0,
    radius_fraction=0.0,
    satellite_mass_fraction=0.0,
    satellite_inertia_fraction=0.0,
)


@dataclasses.dataclass(frozen=True)
class GradientSettings:
    """The gradient method's settings in a tuning run (``TuneConfig.settings`` with
    ``method="gradient"``; [`GradientMethod`][tuning.tune.GradientMethod]).

    Attributes:
        learning_rate: initial step size in log-gain space (0.15: about 15% per step at most,
            before Adam's normalisation), decayed by a cosine schedule to a tenth.
        optimizer: any optax optimiser taking a learning rate (``adam``, ``sgd``, ...).
        clip_norm: global-norm clipping of the gradient.
        gradient: ``"reverse"`` (checkpointed; the faster) or ``"forward"``.
        torque_guard_Nm: a candidate whose peak torque exceeds this is rejected.
        loss_guard: a candidate whose loss exceeds this many times the starting loss is
            rejected too.
        aggregate: how the batch's gradients combine: ``"mean"`` (the gradient of the mean
            or CVaR); ``"clip"``: each sample's gradient clipped to ``CLIP_FACTOR``
            times the batch's median gradient norm before the mean (one chaotic sample
            cannot steer the step); ``"trimmed"`` or ``"median_of_means"``
            ([`estimators.aggregate()`][tuning.estimators.aggregate]: per gain, the mean
            without the extreme tenths, or the median of four group means, of fewer in a
            batch of fewer than four).
        gradient_from_s: truncated backpropagation (s; ``None``: the whole capture): each
            capture is differentiated from this time on only, the state there held
            ([`LoopOptions`][spacegrasp_jax.loop.simulate.LoopOptions]' ``gradient_from_s``):
            the loss is the same, the gradient cheaper and biased (documentation, Tuning).

    Raises:
        ValueError: a setting out of its range, naming it.
    """

    learning_rate: float = 0.15
    optimizer: str = "adam"
    clip_norm: float = 1.0
    gradient: str = "reverse"
    torque_guard_Nm: float = 100.0
    loss_guard: float = 10.0
    aggregate: str = "mean"
    gradient_from_s: float | None = None

    def __post_init__(self):
        for name in ("learning_rate", "clip_norm", "torque_guard_Nm", "loss_guard"):
            value = getattr(self, name)
            if not (value > 0.0 and math.isfinite(value)):
                raise ValueError(f"{name}: must be positive and finite, got {value}")
        if self.gradient not in ("reverse", "forward"):
            raise ValueError(f"gradient: expected reverse or forward, got {self.gradient!r}")
        if self.aggregate not in estimators.AGGREGATES:
            raise ValueError(f"aggregate: expected one of {', '.join(estimators.AGGREGATES)}, got {self.aggregate!r}")
        if not is_optimizer(self.optimizer):
            raise ValueError(
                f"optimizer: {self.optimizer!r} is not an optax optimiser taking a learning rate (e.g. adam, sgd, lamb)"
            )
        if self.gradient_from_s is not None and not (
            isinstance(self.gradient_from_s, int | float) and 0.0 <= self.gradient_from_s < math.inf
        ):
            raise ValueError(f"gradient_from_s: must be a time of 0 s or more, got {self.gradient_from_s!r}")


@dataclasses.dataclass(frozen=True)
class TuneConfig:
    """Everything that defines a tuning run (saved with its checkpoint): the problem (the
    objective and its criteria, the envelope, the loop, the batch), the run (steps, stopping,
    what it hands back) and the method with its own settings.

    ``to_dict()`` writes the method's settings beside the other fields, one flat table, as the
    command line names them; ``of()`` and ``from_dict()`` read such a table (and the records of
    older versions, which held every method's settings).

    Attributes:
        controller: a law's name (``control.CONTROLLERS``).
        steps: optimiser steps.
        weights: objective weights.
        temperature: smooth-max temperature of the objective.
        batch: scenarios per step: the nominal one plus ``batch - 1`` perturbed ones.
        cvar_alpha: None for the batch mean; else the mean over the worst ``1 - alpha``
            fraction of the batch (conditional value at risk).
        seed: seed of the training perturbations.
        frozen: gain groups kept at their initial values.
        ranges: perturbation half-widths for the robust batch (``TUNING_RANGES``).
        realism: the tables of a [`Realism`][spacegrasp_jax.loop.realism.Realism] to train under
            (``None``: the paper's loop). Then every sample of the batch draws its noise key
            and a perturbed satellite (10% mass and inertia unless ``ranges`` sets them) that
            the controller does not know: it believes the nominal robot.
        objective: ``"capture"`` (the default) or ``"weighted"``
            ([`spacegrasp_jax.tuning.objective`][tuning.objective]); ``weights`` apply to the weighted one.
        method: a name in ``METHODS``: ``"cmaes"`` (the default; [`CMAES`][tuning.cmaes.CMAES]:
            ``steps`` generations of candidates, forward rollouts only) or ``"gradient"``
            ([`GradientMethod`][tuning.tune.GradientMethod]: optax on the reverse- or
            forward-mode gradient), each run by the one driver
            ([`tuning.driver.optimise()`][tuning.driver.optimise]). ``spacegrasp tune`` without
            ``--method`` runs the problem's measured winner ([`default_recipe()`][tuning.tune.default_recipe]).
        settings: the method's own settings, an instance of its ``settings_type``
            ([`GradientSettings`][tuning.tune.GradientSettings],
            [`CMAESSettings`][tuning.cmaes.CMAESSettings]; ``None``: its defaults).
        torque_fraction: the capture objective's torque constraint, as a fraction of the
            motors' limits (the robot's ``joint_torque_limit``; 1: the limits themselves).
        torque_cap_Nm: a torque budget in N m for every joint (``None``: none): the
            constraint of joint ``i`` is ``min(torque_fraction * limit_i, torque_cap_Nm)``.
            A budget in N m matches a requirement on the largest peak over the joints,
            which a fraction of unequal limits does not (at 40% of the paper's arm's limits
            the wrist's constraint is 0.8 N m, about the paper's own median wrist peak).
        fresh_batches: a run under a realism draws a new batch of the envelope for every
            step (step k's seed ``seed + FRESH_SEED_STRIDE * k``; step 0 and the held-out
            evaluation as without): the gradient method becomes stochastic gradient descent
            on the envelope rather than on one batch of it; CMA-ES ranks each generation's
            candidates, and evaluates the mean after it, on a new batch (generation k + 1's
            candidates and the mean after generation k share step k's batch). Each step's
            objective is then on its own batch.
        keep: which gains the run hands back: ``"best"``, those with the least training
            objective it evaluated (CMA-ES: the best candidate ever told, or the final mean
            where no worse, and under fresh batches the final mean, pycma's ``xfavorite``; gradient descent: its best step, the start included; with fresh
            batches each step's objective is on its own batch), or ``"last"`` (the final
            mean, the final step). Either way the held-out evaluation then compares them
            with the starting gains, and ``gains.json`` holds the better
            ([`tune()`][tuning.run.tune]).
        patience: early stopping (``None``: off). After every step (generation) the current
            gains (CMA-ES: the mean) are evaluated on a validation set of
            ``validation_size`` captures of their own (seed ``seed + VALIDATION_SEED_OFFSET``,
            exact contact law, as the held-out set), and the run stops once that objective
            has not improved for ``patience`` steps; ``keep="best"`` then hands back the
            gains of the best validation objective instead of the best training one.
        validation_size: the validation set's captures (with ``patience`` only).
        joint_rate_limits_radps: (N,) rad/s, each joint's rate limit as a success criterion:
            a margin of the capture objective and a criterion of the held-out verdict
            (``None``, the default: none, as for the paper's arm, whose limits are assumed;
            ``spacegrasp tune`` sets it to a robot file's own limits).
        schedule_variable: tune a gain schedule on this variable
            (``control.schedule.VARIABLES``):
            every tuned group but the pseudoinverse's damping gets the knots
            ``schedule_knots``, each starting at the starting gains; the parameters are the
            log-gains at every knot (``None``: constant gains, or the starting file's
            schedule as it is).
        schedule_knots: the knots (increasing, at least two) on ``schedule_variable``.
    """

    controller: str = "admittance"
    steps: int = 60
    weights: Weights = Weights()
    temperature: float = 0.02
    batch: int = 4
    cvar_alpha: float | None = None
    seed: int = 0
    frozen: tuple[str, ...] = ()
    ranges: PerturbationRanges = TUNING_RANGES
    realism: dict | None = None
    objective: str = "capture"
    method: str = "cmaes"
    settings: object = None
    torque_fraction: float = 1.0
    torque_cap_Nm: float | None = None
    fresh_batches: bool = False
    keep: str = "best"
    patience: int | None = None
    validation_size: int = 32
    joint_rate_limits_radps: tuple[float, ...] | None = None
    schedule_variable: str | None = None
    schedule_knots: tuple[float, ...] = ()

    def __post_init__(self):
        if self.controller not in CONTROLLERS:
            raise ValueError(f"controller: expected one of {', '.join(CONTROLLERS)}, got {self.controller!r}")
        self._check_schedule()
        if self.steps < 1 or self.batch < 1:
            raise ValueError("steps and batch must be at least 1")
        for name in ("temperature", "torque_fraction"):
            value = getattr(self, name)
            if not (value > 0.0 and math.isfinite(value)):
                raise ValueError(f"{name}: must be positive and finite, got {value}")
        if self.cvar_alpha is not None and not 0.0 <= self.cvar_alpha < 1.0:
            raise ValueError(f"cvar_alpha: must be in [0, 1), got {self.cvar_alpha}")
        if self.objective not in OBJECTIVES:
            raise ValueError(f"objective: expected one of {', '.join(OBJECTIVES)}, got {self.objective!r}")
        if self.objective != "weighted" and self.weights != Weights():
            raise ValueError("weights: they weigh the weighted objective's parts; choose it (--objective weighted)")
        if self.objective == "weighted" and self.torque_fraction != 1.0:
            raise ValueError(
                "torque_fraction: the capture objective's torque constraint; the weighted objective has none"
            )
        if self.torque_cap_Nm is not None:
            if not (self.torque_cap_Nm > 0.0 and math.isfinite(self.torque_cap_Nm)):
                raise ValueError(f"torque_cap_Nm: must be positive and finite, got {self.torque_cap_Nm}")
            if self.objective == "weighted":
                raise ValueError(
                    "torque_cap_Nm: the capture objective's torque constraint; the weighted objective has none"
                )
        if self.method not in METHODS:
            raise ValueError(f"method: expected one of {', '.join(METHODS)}, got {self.method!r}")
        method = METHODS[self.method]
        if self.settings is None:
            object.__setattr__(self, "settings", method.settings_type())
        elif not isinstance(self.settings, method.settings_type):
            raise ValueError(
                f"settings: {method.title}'s are a {method.settings_type.__name__}, got {type(self.settings).__name__}"
            )
        # Made (and so checked) now, before anything compiles, and once: ``loop_realism``.
        loop = None if self.realism is None else make_realism(self.realism, source="realism")
        object.__setattr__(self, "_loop_realism", loop)
        unknown = sorted(set(self.frozen) - set(GROUPS[self.controller]))
        if unknown:
            raise ValueError(
                f"frozen: {', '.join(unknown)} not a gain group of the {self.controller} law; "
                f"expected some of {', '.join(GROUPS[self.controller])}"
            )
        if set(self.frozen) == set(GROUPS[self.controller]):
            raise ValueError(f"frozen: every gain group of the {self.controller} law frozen leaves nothing to tune")
        if self.patience is not None and self.patience < 1:
            raise ValueError(f"patience: must be at least 1 step, got {self.patience}")
        if self.validation_size < 1:
            raise ValueError(f"validation_size: must be at least 1 capture, got {self.validation_size}")
        if self.patience is None and self.validation_size != 32:
            raise ValueError("validation_size: the validation set of early stopping (choose --patience)")
        try:
            object.__setattr__(
                self, "joint_rate_limits_radps", joint_limits.rate_criterion(self.joint_rate_limits_radps)
            )
        except ValueError as error:
            raise ValueError(f"joint_rate_limits_radps: {error}") from None
        if self.keep not in KEEPS:
            raise ValueError(f"keep: expected one of {', '.join(KEEPS)}, got {self.keep!r}")
        if self.fresh_batches and self.realism is None:
            raise ValueError("fresh_batches: draws each step's samples of a run under a realism (choose --realism)")
        check = getattr(method, "check", None)
        if check is not None:
            check(self)

    def _check_schedule(self) -> None:
        object.__setattr__(self, "schedule_knots", tuple(float(x) for x in self.schedule_knots))
        if self.schedule_variable is None:
            if self.schedule_knots:
                raise ValueError("schedule_knots: given without a schedule_variable")
            return
        if self.schedule_variable not in VARIABLES:
            raise ValueError(
                f"schedule_variable: expected one of {', '.join(VARIABLES)}, got {self.schedule_variable!r}"
            )
        knots = np.asarray(self.schedule_knots)
        if knots.size < 2 or not np.all(np.isfinite(knots)) or np.any(np.diff(knots) <= 0.0):
            raise ValueError(f"schedule_knots: need two or more finite values, increasing; got {knots.tolist()}")

    @property
    def loop_realism(self) -> Realism | None:
        """The loop's [`Realism`][spacegrasp_jax.loop.realism.Realism] made from ``realism``
        when the settings were made (``None``: the paper's ideal loop)."""
        return self._loop_realism

    @property
    def gradient_settings(self) -> GradientSettings:
        """How the problem takes a gradient where a method asks for one: the gradient
        method's settings, or their defaults under another method."""
        return self.settings if isinstance(self.settings, GradientSettings) else GradientSettings()

    def to_dict(self) -> dict:
        """The settings as one flat table (the run's files): every field but ``settings``,
        and the method's settings beside them by name."""
        document = dataclasses.asdict(self)
        document |= document.pop("settings")
        document["frozen"] = list(self.frozen)
        document["schedule_knots"] = list(self.schedule_knots)
        return document

    @classmethod
    def of(cls, **fields) -> TuneConfig:
        """The settings of flat ``fields`` (the command line's, a run's files'): the problem's
        and the run's, and the method's settings by name. A setting of another method must
        keep its default (older records held every method's).

        Raises:
            ValueError: a setting of another method given, or a name no method knows.
        """
        own = {field.name for field in dataclasses.fields(cls)} - {"settings"}
        name = fields.get("method", cls.method)
        if name not in METHODS:
            raise ValueError(f"method: expected one of {', '.join(METHODS)}, got {name!r}")
        method = METHODS[name]
        mine = {field.name for field in dataclasses.fields(method.settings_type)}
        chosen, settings = {}, {}
        for field, value in fields.items():
            if field in own:
                chosen[field] = value
            elif field in mine:
                settings[field] = value
            else:
                owners = [m for m in METHODS.values() if field in {f.name for f in dataclasses.fields(m.settings_type)}]
                if not owners:
                    raise ValueError(f"{field}: not a setting of a tuning run")
                default = {f.name: f.default for f in dataclasses.fields(owners[0].settings_type)}[field]
                if value == default:
                    continue
                owners[0].settings_type(**{field: value})  # a bad value is named as such first
                raise ValueError(
                    f"{field}: a setting of {' and '.join(m.title for m in owners)}; "
                    f"{method.title} does not use it (choose --method {owners[0].name})"
                )
        return cls(**chosen, settings=method.settings_type(**settings))

    @classmethod
    def from_dict(cls, document: dict) -> TuneConfig:
        """``to_dict()``'s table (or an older version's) read back."""
        document = dict(document)
        if document.get("method") == "cmaes":  # older records wrote clip, which CMA-ES never read
            document["aggregate"] = "mean"
        document["weights"] = Weights(**document["weights"])
        document["ranges"] = PerturbationRanges.from_mapping(document["ranges"], base=TUNING_RANGES)
        document["frozen"] = tuple(document["frozen"])
        document["schedule_knots"] = tuple(document.get("schedule_knots", ()))
        return cls.of(**document)


#: Validation captures (early stopping, ``TuneConfig.patience``) are drawn with seed ``seed +``
#: this: never the training batch's (``seed``, or ``seed + FRESH_SEED_STRIDE * k``), never the
#: held-out set's (``seed + HOLDOUT_SEED_OFFSET``).
VALIDATION_SEED_OFFSET = 2_000_003

#: The gains a tuning run can hand back (``TuneConfig.keep``).
KEEPS = ("best", "last")


def is_optimizer(name: str) -> bool:
    """Whether ``optax.<name>`` is an optimiser: a function whose first parameter is
    ``learning_rate`` and which returns a gradient transformation."""
    factory = getattr(optax, name, None) if name.isidentifier() and not name.startswith("_") else None
    if not callable(factory) or isinstance(factory, type):
        return False
    try:
        parameters = list(inspect.signature(factory).parameters)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            transformation = factory(learning_rate=1e-3) if parameters[:1] == ["learning_rate"] else None
    except (TypeError, ValueError):
        return False
    return isinstance(transformation, optax.GradientTransformation)


def make_optimizer(settings: GradientSettings, steps: int):
    """``chain(clip_by_global_norm, <optimizer>(cosine schedule over steps))`` and its schedule."""
    schedule = optax.cosine_decay_schedule(settings.learning_rate, decay_steps=steps, alpha=0.1)
    return optax.chain(
        optax.clip_by_global_norm(settings.clip_norm), getattr(optax, settings.optimizer)(schedule)
    ), schedule


#: Steps per inner scan of a one-scenario reverse-mode gradient (``simulate.rollout``'s
#: ``block_steps``). The tape holds each step's state and RK4's stage rates, (3, N)
#: numbers a field per step. With loops compiled whole (``spacegrasp_jax.jobs.compilation``) the
#: length does not matter; where XLA runs loops kernel by kernel, 2 steps keep the inner
#: loops within 64 numbers an array, in XLA's faster sequential mode (documentation,
#: changelog).
BLOCK_STEPS = 2


#: The largest batch whose scenarios a gradient on a CPU runs one after another
#: (``compilation.map_one_at_a_time``) instead of vmapping them: up to this size the two run
#: about as fast and the sequential program compiles faster (documentation, changelog).
SEQUENTIAL_BATCH = 8


def batch_in_sequence(batch: int) -> bool:
    """Whether the loss runs its ``batch`` scenarios one after another rather than vmapped:
    one scenario, or up to ``SEQUENTIAL_BATCH`` on a CPU (a GPU always vmaps)."""
    return batch == 1 or (batch <= SEQUENTIAL_BATCH and jax.default_backend() == "cpu")


def block_steps(n_steps: int, batch: int = 1) -> int:
    """Steps per inner scan for a gradient over ``batch`` scenarios: the largest divisor of
    ``n_steps`` up to ``BLOCK_STEPS`` when the scenarios run one after another
    ([`batch_in_sequence()`][tuning.tune.batch_in_sequence]); 1 for a vmapped batch, whose arrays are too large for XLA's
    sequential mode anyway."""
    if not batch_in_sequence(batch):
        return 1
    return largest_divisor(n_steps, BLOCK_STEPS)


def training_scenarios(nominal: Scenario, config: TuneConfig) -> Scenario:
    """The nominal scenario followed by ``batch - 1`` perturbed ones, stacked."""
    stacked = jax.tree.map(lambda leaf: jnp.asarray(leaf)[None], nominal)
    if config.batch == 1:
        return stacked
    perturbed = sample_scenarios(nominal, config.seed, range(1, config.batch), config.ranges)
    return jax.tree.map(lambda a, b: jnp.concatenate([a, b]), stacked, perturbed)


def batch_loss(
    params,
    values,
    *,
    controller: str,
    cvar_alpha: float | None,
    segment: int | None,
    in_sequence: bool = False,
    options: LoopOptions = LoopOptions(checkpoint=True),
):
    """``(loss, aux)`` at the log-gains ``params``: the batch mean (or CVaR) of the objective,
    and the batch-mean parts plus the worst hard peak torque (N m) for the divergence guard.
    ``values = (robot, scenarios, base, mask, objective)``, every number an argument of the
    program (other scenarios, gains or weights reuse it); the keywords shape it. The
    scenarios run one after another with ``in_sequence``
    ([`batch_in_sequence()`][tuning.tune.batch_in_sequence], asked by the host), else vmapped."""
    robot, scenarios, base, mask, objective = values
    gains = gains_from_params(params, base, mask)

    def one(scenario):
        return scenario_parts(objective_spec(robot, scenario, controller, segment, options=options), gains, objective)

    count = jax.tree.leaves(scenarios)[0].shape[0]
    if count == 1:  # one scenario: the unbatched program
        parts = jax.tree.map(lambda x: x[None], one(jax.tree.map(lambda x: x[0], scenarios)))
    elif in_sequence:
        parts = compilation.map_one_at_a_time(one, scenarios)
    else:
        parts = jax.vmap(one)(scenarios)
    losses = parts["loss"]
    if cvar_alpha is None:
        total = jnp.mean(losses)
    else:
        worst = tail_count(cvar_alpha, losses.shape[0])
        total = jnp.mean(jnp.sort(losses)[-worst:])
    aux = {name: jnp.mean(value) for name, value in parts.items()}
    aux[BATCH_MAX_PEAK_TORQUE] = jnp.max(parts["largest_peak_torque_Nm"])
    return total, aux


@dataclasses.dataclass(frozen=True)
class BoundLoss:
    """``loss(params) -> (loss, aux)`` ([`batch_loss()`][tuning.tune.batch_loss]) with its values bound:
    ``function(params, values)`` is what is compiled, ``values`` what it is called with."""

    function: Callable
    values: tuple

    def __call__(self, params):
        return self.function(params, self.values)


def tuning_loop_options(config: TuneConfig) -> LoopOptions:
    """The loop options of a tuning run's gradient programs: checkpointed as this process
    compiles best ([`experiment.loop_options()`][spacegrasp_jax.jobs.experiment.loop_options]),
    truncated at the gradient settings' ``gradient_from_s``."""
    return dataclasses.replace(loop_options(checkpoint=True), gradient_from_s=config.gradient_settings.gradient_from_s)


def check_gradient_cut(config: TuneConfig, scenario: Scenario) -> None:
    """Refuse a ``gradient_from_s`` that leaves nothing of ``scenario`` to differentiate,
    before anything compiles (``ValueError`` naming the field)."""
    cut = config.gradient_settings.gradient_from_s
    if cut is None:
        return
    realism = config.loop_realism
    steps = 1 if realism is None else realism.steps_per_period(scenario.dt)
    gradient_cut(cut, steps * scenario.dt, 1, scenario.n_steps // steps)


def make_loss(
    robot: Robot, scenarios: Scenario, base: Gains, mask, config: TuneConfig, objective: Objective, segment: int | None
) -> BoundLoss:
    """The tuning loss over ``scenarios`` (stacked), [`batch_loss()`][tuning.tune.batch_loss] with these values."""
    in_sequence = batch_in_sequence(jax.tree.leaves(scenarios)[0].shape[0])
    options = tuning_loop_options(config)
    function = _batch_loss_function(config.controller, config.cvar_alpha, segment, in_sequence, options)
    return BoundLoss(function, (robot, scenarios, base, mask, objective))


@functools.cache
def _batch_loss_function(
    controller: str, cvar_alpha: float | None, segment: int | None, in_sequence: bool, options: LoopOptions
) -> Callable:
    return functools.partial(
        batch_loss,
        controller=controller,
        cvar_alpha=cvar_alpha,
        segment=segment,
        in_sequence=in_sequence,
        options=options,
    )


@dataclasses.dataclass(frozen=True)
class BoundProgram:
    """A jitted ``program(params, values)`` called as ``program(params)``: the values are
    arguments of the compiled program, not constants in it, so a loss over other scenarios,
    gains or weights of the same shapes runs the same program (compiled once per process by
    [`compile_once()`][spacegrasp_jax.jobs.compilation.compile_once], which announces it, and loaded
    from the persistent cache by later processes).

    Attributes:
        program: the jitted function.
        values: its second argument.
        settings: what shapes the program besides its arguments' shapes (its name and the
            loss's static settings); with [`argument_signature()`][spacegrasp_jax.jobs.compilation.argument_signature]
            of the arguments, the program's key. No default: two programs given the same
            settings would share one executable.
        label: the program's name for people (the compile line).
    """

    program: Callable
    values: tuple
    settings: tuple
    label: str

    def __call__(self, params):
        arguments = (params, self.values)
        key = (*self.settings, compilation.argument_signature(arguments))
        executable, _ = compilation.compile_once(key, lambda: self.program.lower(*arguments), label=self.label)
        return executable(*arguments)

    def lower(self, params):
        """The program's ``jax.stages.Lowered`` for these ``params`` and values."""
        return self.program.lower(params, self.values)


@functools.cache
def _gradient_program(function: Callable, mode: str, structure) -> Callable:
    """The jitted gradient of ``function(params, values)`` with respect to ``params``, one
    per loss function, mode and parameter structure (``structure``: their tree)."""
    if mode == "reverse":
        return compilation.jit(jax.value_and_grad(function, has_aux=True))

    def forward(params, values):
        flat, unravel = ravel_pytree(params)

        def flat_loss(x):
            value, aux = function(unravel(x), values)
            return value, (value, aux)

        gradient, (value, aux) = jax.jacfwd(flat_loss, has_aux=True)(flat)
        return (value, aux), unravel(gradient)

    return compilation.jit(forward)


def make_value_and_grad(loss: BoundLoss, params, mode: str) -> BoundProgram:
    """``params -> ((loss, aux), gradient)`` by reverse or forward mode, for a loss of
    [`make_loss()`][tuning.tune.make_loss]: the compiled program takes the loss's values as arguments and is shared
    by every loss of the same settings and shapes."""
    static = loss.function.keywords  # the loss's static settings: controller, cvar_alpha, segment
    return BoundProgram(
        _gradient_program(loss.function, mode, jax.tree.structure(params)),
        loss.values,
        settings=("tuning.gradient", mode, batching.program_settings(loss.function)),
        label=f"the {mode}-mode gradient of the {static['controller']} law's tuning loss",
    )


#: Under ``aggregate="clip"``, a sample's gradient is clipped to this many times the batch's
#: median gradient norm.
CLIP_FACTOR = estimators.CLIP_FACTOR


def flight_batch(robot: Robot, nominal: Scenario, config: TuneConfig, seed: int, count: int) -> SampleLoops:
    """``count`` samples of seed ``seed`` for a run under ``config.realism``: perturbed
    scenarios and satellites, each with its noise key; the controller believes ``robot``."""
    ranges = config.ranges
    if ranges.satellite_mass_fraction == 0.0 and ranges.satellite_inertia_fraction == 0.0:
        ranges = dataclasses.replace(ranges, satellite_mass_fraction=0.1, satellite_inertia_fraction=0.1)
    return sample_loops(robot, nominal, seed, range(count), ranges, config.loop_realism)


def aggregate_gradients(losses, gradients, config: TuneConfig):
    """``(total, gradient, clipped)``: the batch's objective (mean, or CVaR), its gradient
    from the per-sample ``gradients`` (a pytree with a leading batch axis) as
    the gradient settings' ``aggregate`` combines them (clipped per sample under ``"clip"``),
    and how many samples were clipped."""
    count = losses.shape[0]
    aggregate = config.gradient_settings.aggregate
    if aggregate in ("trimmed", "median_of_means"):  # the batch mean's gradient, estimated robustly
        leaves, structure = jax.tree.flatten(gradients)
        flat = np.concatenate([np.asarray(leaf).reshape(count, -1) for leaf in leaves], axis=1)
        combined = estimators.aggregate(flat, aggregate, groups=min(estimators.GROUPS, count))
        estimate = np.split(combined, np.cumsum([leaf[0].size for leaf in leaves])[:-1])
        gradient = jax.tree.unflatten(
            structure,
            [jnp.asarray(piece.reshape(leaf.shape[1:])) for piece, leaf in zip(estimate, leaves, strict=True)],
        )
        return jnp.mean(losses), gradient, jnp.asarray(0)
    norms = jnp.sqrt(sum(jnp.sum(g.reshape(count, -1) ** 2, axis=1) for g in jax.tree.leaves(gradients)))
    if aggregate == "clip":
        ceiling = CLIP_FACTOR * jnp.median(norms)
        scale = jnp.where(norms > ceiling, ceiling / jnp.where(norms > 0.0, norms, 1.0), 1.0)
    else:
        scale = jnp.ones_like(norms)
    if config.cvar_alpha is None:
        weights = jnp.full(count, 1.0 / count)
    else:
        worst = tail_count(config.cvar_alpha, count)
        weights = jnp.zeros(count).at[jnp.argsort(losses)[-worst:]].set(1.0 / worst)
    total = jnp.sum(weights * losses)
    gradient = jax.tree.map(lambda g: jnp.tensordot(weights * scale, g, axes=1), gradients)
    return total, gradient, jnp.sum(scale < 1.0)


def _per_sample_gradients(
    params, base, mask, model_robot, objective: Objective, samples, *, controller: str, options: LoopOptions
):
    """``(losses, parts, gradients)``, each with the samples' leading axis: each sample's
    objective and its reverse-mode gradient (one control period a checkpoint), one sample
    after another (``compilation.map_one_at_a_time``: the tape of one rollout at a time)."""

    def one(sample):
        r, scenario, realism, key = sample

        def sample_loss(params):
            gains = gains_from_params(params, base, mask)
            spec = objective_spec(r, scenario, controller, 1, realism, model_robot, options)
            parts = scenario_parts(spec, gains, objective, key)
            return parts["loss"], parts

        (loss, parts), gradient = jax.value_and_grad(sample_loss, has_aux=True)(params)
        return loss, parts, gradient

    return compilation.map_one_at_a_time(one, samples)


def make_flight_value_and_grad(
    robot: Robot,
    batch: SampleLoops,
    base: Gains,
    mask,
    config: TuneConfig,
    objective: Objective,
    fresh: Callable[[int], SampleLoops] | None = None,
):
    """``(params, step=0) -> ((loss, aux), gradient)`` under ``config.realism``: the samples'
    gradients (``_per_sample_gradients()``) as one program sharded over every device
    ([`spacegrasp_jax.jobs.batching.map_in_chunks()`][spacegrasp_jax.jobs.batching.map_in_chunks]: a share of the batch per core or GPU),
    then [`aggregate_gradients()`][tuning.tune.aggregate_gradients] on the host. ``aux`` has the batch-mean parts, the worst
    hard peak torque and ``clipped_samples``. The samples are ``batch``, or at a step above
    0 ``fresh(step)`` where given (``config.fresh_batches``: the same program, other samples)."""
    function = functools.partial(
        _per_sample_gradients, controller=config.controller, options=tuning_loop_options(config)
    )
    count = int(batch.keys.shape[0])

    def value_and_grad(params, step: int = 0):
        drawn = fresh(step) if fresh is not None and step > 0 else batch
        losses, parts, gradients = batching.map_in_chunks(
            "tuning.flight_gradient",
            function,
            (params, base, mask, drawn.model_robot, objective),
            (drawn.robots, drawn.scenarios, drawn.realisms, drawn.keys),
            chunk=count,
            progress=None,
        )
        losses, gradients = jnp.asarray(losses), jax.tree.map(jnp.asarray, gradients)
        total, gradient, clipped = aggregate_gradients(losses, gradients, config)
        aux = {name: jnp.mean(value) for name, value in parts.items()}
        aux[BATCH_MAX_PEAK_TORQUE] = jnp.max(parts["largest_peak_torque_Nm"])
        aux["clipped_samples"] = clipped.astype(losses.dtype)
        return (total, aux), gradient

    return value_and_grad


#: Under ``fresh_batches``, step k's batch is drawn with seed ``seed + FRESH_SEED_STRIDE * k``:
#: apart from every other seed a run uses (its batch's, the held-out's ``seed + 1,000,003``).
FRESH_SEED_STRIDE = 7_919


@dataclasses.dataclass
class GradientState:
    """The gradient method's state after ``step`` accepted steps (``-1``: the start not yet
    evaluated): the point, the optimiser's state, the point's objective, batch statistics
    and gradient, the step-size factor the divergence guard has left (``scale``), and, inside
    a step, the optimiser's pending update and the candidates rejected so far."""

    step: int
    scale: float
    params: dict
    opt_state: object
    loss: float = math.nan
    aux: dict = dataclasses.field(default_factory=dict)
    gradient: dict | None = None
    start_loss: float = math.nan  #: the starting point's objective (the loss guard's reference)
    pending: tuple | None = None  #: ``(updates, new_opt_state)`` of the step under way
    rejected: int = 0  #: candidates of the step under way rejected so far


def _is_acceptable(loss, aux, gradient, guard_Nm: float, loss_ceiling: float = math.inf) -> bool:
    finite = math.isfinite(float(loss)) and all(bool(np.all(np.isfinite(g))) for g in jax.tree.leaves(gradient))
    return finite and float(aux[BATCH_MAX_PEAK_TORQUE]) <= guard_Nm and float(loss) <= loss_ceiling


def history_row(step: int, loss: float, aux: dict, gradient, step_size: float, rejected: int) -> dict:
    """A gradient step's history row (the driver adds its wall time)."""
    flat, _ = ravel_pytree(gradient)
    return {
        "step": step,
        "loss": float(loss),
        **{name: float(value) for name, value in aux.items()},
        "gradient_norm": float(jnp.linalg.norm(flat)),
        "step_size": step_size,
        "rejected_candidates": rejected,
    }


def progress_line(step: int, loss: float, aux: dict, total: int) -> str:
    """The progress line after step ``step`` of ``total``: its objective and batch statistics."""
    return progress_bar(
        step,
        total,
        f"step {step}/{total} loss {loss:.4f} | "
        f"final pos {1e3 * aux['final_position_error_m']:.3f} mm | peak torque / constraint {aux['peak_torque_smooth']:.3f} "
        f"(hard {aux['peak_torque_hard']:.3f}, gap {aux['peak_torque_gap']:.3f}) | rms {1e3 * aux['rms_tracking_m']:.2f} mm "
        f"(batch means) | largest peak {aux[BATCH_MAX_PEAK_TORQUE]:.2f} N m (batch max)",
    )


@dataclasses.dataclass(frozen=True)
class GradientMethod:
    """Gradient descent by an optax transformation on the batch objective's gradient, with a
    divergence guard ([`tuning.protocol.TuningMethod`][tuning.protocol.TuningMethod]).

    A step: ``updates = optimiser(gradient)``; the candidate ``params + scale * updates`` is
    evaluated (objective and gradient together, on the step's batch); if it diverged
    (non-finite, a peak torque above ``torque_guard_Nm``, or an objective above ``loss_guard``
    times the start's) it is rejected, ``scale`` halved and the event logged, else accepted
    with the optimiser's new state. Below ``1e-6`` of the step size the run ends ``"diverged"``.

    Attributes:
        optimizer: the optax transformation ([`make_optimizer()`][tuning.tune.make_optimizer]).
        schedule: its learning rate by step (the history's ``step_size``).
        torque_guard_Nm: a candidate whose batch's largest peak torque exceeds this is rejected.
        loss_guard: a candidate whose objective exceeds this many times the start's is rejected.
        mode: ``"reverse"`` or ``"forward"`` (for the start line).
    """

    optimizer: optax.GradientTransformation
    schedule: Callable
    torque_guard_Nm: float = 100.0
    loss_guard: float = 10.0
    mode: str = "reverse"
    name: ClassVar[str] = "gradient"
    title: ClassVar[str] = "the gradient method"
    unit: ClassVar[str] = "step"
    point_words: ClassVar[str] = "the gains"
    #: its settings in a ``TuneConfig`` (``TuneConfig.settings``)
    settings_type: ClassVar[type] = GradientSettings

    @classmethod
    def from_config(cls, config: TuneConfig) -> GradientMethod:
        s = config.settings
        optimizer, schedule = make_optimizer(s, config.steps)
        return cls(optimizer, schedule, s.torque_guard_Nm, s.loss_guard, s.gradient)

    @classmethod
    def check(cls, config: TuneConfig) -> None:
        """What the gradient method's settings need of the rest of a ``TuneConfig``."""
        s = config.settings
        if s.aggregate in ("trimmed", "median_of_means") and config.cvar_alpha is not None:
            raise ValueError(
                f"aggregate: {s.aggregate} estimates the batch mean's gradient; CVaR weighs the worst samples"
            )
        if config.realism is None and s.aggregate != "mean":
            raise ValueError(
                f"aggregate: {s.aggregate} combines the samples' separate gradients of a run under a realism; "
                "the ideal loop's batch has one gradient of the mean (choose --realism, or mean)"
            )
        if config.realism is not None and s.gradient != "reverse":
            raise ValueError(
                "gradient: tuning under a realism takes each sample's reverse-mode gradient; forward mode runs the ideal loop only"
            )

    def describe(self) -> str:
        return f"by its {self.mode}-mode gradient"

    def init(self, point, mask, seed: int) -> GradientState:
        return GradientState(-1, 1.0, point, self.optimizer.init(point))

    def ask(self, state: GradientState) -> tuple[Request, GradientState]:
        if state.step < 0:
            return Request((state.params,), gradient=True, batch=0), state
        if state.pending is None:
            pending = self.optimizer.update(state.gradient, state.opt_state, state.params)
            state = dataclasses.replace(state, pending=pending)
        updates = state.pending[0]
        candidate = jax.tree.map(lambda p, u: p + state.scale * u, state.params, updates)
        return Request((candidate,), gradient=True, batch=state.step + 1), state

    def tell(self, state: GradientState, request: Request, answers: Answers) -> tuple[GradientState, Outcome]:
        (point,), (aux,), (gradient,) = request.points, answers.summaries, answers.gradients
        loss = answers.objectives[0]
        if state.step < 0:
            if not _is_acceptable(loss, aux, gradient, self.torque_guard_Nm):
                raise RuntimeError(f"the initial gains already diverge or exceed the torque guard (loss {float(loss)})")
            state = dataclasses.replace(
                state, step=0, loss=float(loss), aux=aux, gradient=gradient, start_loss=float(loss)
            )
            return state, Outcome(row=history_row(0, loss, aux, gradient, 0.0, 0))
        # With saturating motors an unstable candidate need not raise the torque: the EE
        # drifts away instead, which the loss sees.
        if not _is_acceptable(loss, aux, gradient, self.torque_guard_Nm, self.loss_guard * state.start_loss):
            event = {
                "step": state.step + 1,
                "event": "rejected",
                "loss": float(loss),
                BATCH_MAX_PEAK_TORQUE: float(aux[BATCH_MAX_PEAK_TORQUE]),
                "new_scale": state.scale / 2,
            }
            state = dataclasses.replace(state, scale=state.scale / 2.0, rejected=state.rejected + 1)
            return state, Outcome(events=(event,), status="diverged" if state.scale < 1e-6 else None)
        step_size = float(self.schedule(state.step)) * state.scale
        row = history_row(state.step + 1, loss, aux, gradient, step_size, state.rejected)
        state = dataclasses.replace(
            state,
            step=state.step + 1,
            params=point,
            opt_state=state.pending[1],
            loss=float(loss),
            aux=aux,
            gradient=gradient,
            pending=None,
            rejected=0,
        )
        return state, Outcome(row=row)

    def point(self, state: GradientState):
        return state.params

    def best(self, state: GradientState, history: list[dict], best_step: int, best_point):
        return best_point, best_step, f"the gains after step {best_step}", history[best_step]["loss"]

    def state_arrays(self, state: GradientState) -> tuple[dict, dict]:
        leaves = {
            "params": jax.tree.leaves(state.params),
            "opt_state": jax.tree.leaves(state.opt_state),
            "gradient": jax.tree.leaves(state.gradient),
        }
        arrays = {f"{group}_{i}": np.asarray(leaf) for group, values in leaves.items() for i, leaf in enumerate(values)}
        meta = {
            "scale": state.scale,
            "loss": state.loss,
            "aux": {name: float(value) for name, value in state.aux.items()},
            "start_loss": state.start_loss,
        }
        return arrays, meta

    def restore(self, point, mask, seed: int, arrays: dict, meta: dict, steps: int) -> GradientState:
        def restored(group, template):
            leaves = [jnp.asarray(arrays[f"{group}_{i}"]) for i in range(len(jax.tree.leaves(template)))]
            return jax.tree.unflatten(jax.tree.structure(template), leaves)

        return GradientState(
            step=steps,
            scale=meta["scale"],
            params=restored("params", point),
            opt_state=restored("opt_state", self.optimizer.init(point)),
            loss=meta["loss"],
            aux=meta["aux"],
            gradient=restored("gradient", point),
            start_loss=meta["start_loss"],
        )

    def progress(self, state: GradientState, row: dict, steps: int) -> str:
        return progress_line(state.step, state.loss, state.aux, steps)


#: The tuning methods ``--method`` names: each a class of the tuning interface
#: ([`tuning.protocol.TuningMethod`][tuning.protocol.TuningMethod]) with its ``settings_type``
#: and ``from_config(TuneConfig)``.
METHODS = {"gradient": GradientMethod, "cmaes": cmaes.CMAES}


def make_method(config: TuneConfig):
    """The tuning method ``config.method`` names, with ``config``'s settings for it."""
    return METHODS[config.method].from_config(config)


def make_objective(robot: Robot, config: TuneConfig, torque_scale_Nm) -> Objective:
    """The run's objective: ``config.objective`` with the ``weighted`` one's torque scale,
    the robot's motor limits and joint ranges, and the rate limits of ``config``."""
    return Objective(
        weights=config.weights,
        torque_scale_Nm=tuple(float(x) for x in torque_scale_Nm),
        temperature=config.temperature,
        kind=config.objective,
        torque_constraint_Nm=torque_constraint_Nm(robot, config),
        criteria=CaptureCriteria(joint_rate_limits_radps=config.joint_rate_limits_radps),
        joint_ranges=joint_limits.finite_ranges(robot),
    )


def torque_constraint_Nm(robot: Robot, config: TuneConfig) -> tuple[float, ...]:
    """(N,) the capture objective's torque constraint per joint (N m):
    ``min(torque_fraction * joint_torque_limit_i, torque_cap_Nm)``."""
    cap = math.inf if config.torque_cap_Nm is None else config.torque_cap_Nm
    return tuple(min(config.torque_fraction * float(x), cap) for x in robot.joint_torque_limit)


def ideal_batch(robot: Robot, scenarios: Scenario) -> SampleLoops:
    """Stacked scenarios of the paper's ideal loop as a batch of samples (the one batch type
    of tuning, as of the campaigns): each runs ``robot`` (plant and model), no realism, no
    noise key."""
    count = jax.tree.leaves(scenarios)[0].shape[0]
    robots = jax.tree.map(lambda leaf: jnp.broadcast_to(jnp.asarray(leaf), (count, *jnp.shape(leaf))), robot)
    return SampleLoops(robots, scenarios, None, None, None, None)


def envelope_batch(robot: Robot, nominal: Scenario, config: TuneConfig, seed: int, count: int) -> SampleLoops:
    """``count`` samples of the run's envelope drawn with ``seed`` (held-out and validation
    captures): under ``config.realism`` [`flight_batch()`][tuning.tune.flight_batch]'s, else
    perturbed scenarios of the ideal loop ([`ideal_batch()`][tuning.tune.ideal_batch])."""
    if config.realism is not None:
        return flight_batch(robot, nominal, config, seed, count)
    return ideal_batch(robot, sample_scenarios(nominal, seed, range(count), config.ranges))


def training_batch(robot: Robot, nominal: Scenario, config: TuneConfig) -> SampleLoops:
    """The batch every step (or generation) is evaluated on: under a realism, the samples of
    [`flight_batch()`][tuning.tune.flight_batch]; else the nominal scenario and ``batch - 1``
    perturbed ones ([`training_scenarios()`][tuning.tune.training_scenarios]) in the ideal loop."""
    if config.realism is not None:
        return flight_batch(robot, nominal, config, config.seed, config.batch)
    return ideal_batch(robot, training_scenarios(nominal, config))


def make_problem(
    robot: Robot,
    nominal: Scenario,
    base: Gains,
    config: TuneConfig,
    torque_scale_Nm,
    batch: SampleLoops | None = None,
    objective: Objective | None = None,
) -> TuningProblem:
    """The run's [`TuningProblem`][tuning.problem.TuningProblem]: its objective, starting point
    and mask, training batch (fresh batches where ``config.fresh_batches``: step k's of seed
    ``seed + FRESH_SEED_STRIDE * k``) and the batch objective's gradient program (compiled
    on its first call only). ``batch``: under a realism, the training batch instead of
    [`training_batch()`][tuning.tune.training_batch]'s (for example a campaign's own samples,
    [`sample_loops()`][spacegrasp_jax.jobs.montecarlo.sample_loops]), of ``config.batch``
    samples; ``objective``: instead of [`make_objective()`][tuning.tune.make_objective]'s (for
    example with a campaign's criteria)."""
    check_for_scenario(config.ranges, nominal)
    if objective is None:
        objective = make_objective(robot, config, torque_scale_Nm)
    mask = make_mask(base, config.controller, config.frozen)
    params = initial_params(base, config.controller)
    if batch is None:
        batch = training_batch(robot, nominal, config)
    elif config.realism is None or batching.batch_size(batch.scenarios) != config.batch:
        raise ValueError(f"batch: a flight-like loop's batch of config.batch = {config.batch} samples")
    fresh = None
    if config.fresh_batches:
        fresh = lambda step: flight_batch(robot, nominal, config, config.seed + FRESH_SEED_STRIDE * step, config.batch)
    if config.realism is not None:
        value_and_grad = make_flight_value_and_grad(robot, batch, base, mask, config, objective, fresh)
    else:
        mode = config.gradient_settings.gradient
        segment = block_steps(nominal.n_steps, config.batch) if mode == "reverse" else None
        loss = make_loss(robot, batch.scenarios, base, mask, config, objective, segment)
        value_and_grad = make_value_and_grad(loss, params, mode)
    return TuningProblem(
        robot, base, mask, params, objective, config.controller, config.cvar_alpha, batch, fresh, value_and_grad
    )


def setup(robot: Robot, nominal: Scenario, base: Gains, config: TuneConfig, torque_scale_Nm):
    """Objective, initial parameters, mask and the jitted loss gradient for a run
    ([`make_problem()`][tuning.tune.make_problem]'s)."""
    problem = make_problem(robot, nominal, base, config, torque_scale_Nm)
    return problem.objective, problem.mask, problem.start, problem.value_and_grad
