"""Per-sample metrics of closed-loop rollouts, accumulated inside the scan, and the batched
evaluation of a Monte-Carlo campaign's samples.

A full [`Log`][spacegrasp_jax.loop.simulate.Log] of a 17 s rollout holds some 1.4 million numbers; a campaign
needs a few numbers per sample. A [`RunSpec`][spacegrasp_jax.loop.simulate.RunSpec] whose observer is
[`FoldedMetrics`][spacegrasp_jax.jobs.montecarlo.FoldedMetrics] runs the same loop as
[`rollout()`][spacegrasp_jax.loop.simulate.rollout] and folds every log row into the running metrics of
[`spacegrasp_jax.envelope.metrics`][spacegrasp_jax.envelope.metrics] as it goes (the functions that give a whole log's metrics), so
a batch needs memory for its states only, plus, on request, every ``every``-th log row.

Everything here is pure: ``jit``, ``vmap`` and sharding are applied by the caller
([`spacegrasp_jax.jobs.campaign`][spacegrasp_jax.jobs.campaign]).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax.core.model import Robot
from spacegrasp_jax.envelope import metrics
from spacegrasp_jax.envelope.criteria import CaptureCriteria
from spacegrasp_jax.envelope.perturbations import (
    Perturbation,
    PerturbationRanges,
    apply_to_robot,
    apply_to_scenario,
    draw,
    sample_keys,
    weakened_joint,
)
from spacegrasp_jax.envelope.scenario import Scenario
from spacegrasp_jax.jobs import anatomy
from spacegrasp_jax.loop.control.gains import Gains
from spacegrasp_jax.loop.realism import Realism, Stage, ideal
from spacegrasp_jax.loop.simulate import Log, RunSpec, closed_loop, loop_realism


@dataclasses.dataclass(frozen=True)
class FoldedMetrics:
    """The observer of a [`closed_loop()`][spacegrasp_jax.loop.simulate.closed_loop] that folds every log row into the
    running ``METRICS`` (and the parts of the final error, ``ANATOMY_METRICS``) as the scan
    goes, and keeps every ``every``-th row.

    Attributes:
        every: if set (static; must divide ``scenario.n_steps`` and be a whole number of
            control periods), also keep every ``every``-th log row, i.e. the rows at
            ``t = 0, every dt, 2 every dt, ...``.
    """

    every: int | None = None

    def periods_per_block(self, body) -> int:
        if self.every is None:
            return 1
        steps = body.periods * body.steps_per_period
        if self.every < 1 or self.every % body.steps_per_period or steps % self.every:
            raise ValueError(
                f"every: {self.every} must divide the {steps} steps and be a multiple of the "
                f"{body.steps_per_period} steps of a control period"
            )
        return self.every // body.steps_per_period

    def init(self, robot: Robot, scenario: Scenario) -> dict:
        return metrics.start(scenario.initial.q.dtype, robot)

    def fold(self, running: dict, rows: Log) -> tuple[dict, Log | None]:
        first = None if self.every is None else jax.tree.map(lambda x: x[0], rows)
        return metrics.accumulate(running, rows), first

    def keep(self, outputs: Log | None) -> Log | None:
        return None if outputs is None else jax.tree.map(lambda x: x[0], outputs)

    def finish(self, running: dict, kept: Log | None, final, scenario: Scenario, realism) -> tuple[dict, Log | None]:
        # A state that turns non-finite in the very last step shows in no logged row.
        final_finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree.leaves(final)]))
        finished = metrics.finish(
            running,
            nonfinite_after_s=jnp.where(final_finite, jnp.inf, scenario.duration),
            free_target=scenario.free_target,
        )
        return finished | anatomy.error_parts(finished, scenario, realism), kept


#: The stream of a sample's sensor noise: ``fold_in(fold_in(PRNGKey(seed), i), NOISE_STREAM)``
#: (the perturbation draws use streams 0-2 of the same sample key).
NOISE_STREAM = 1_000


def evaluate_samples(
    spec: RunSpec,
    gains: Gains,
    seed,
    indices: jax.Array,
    *,
    ranges: PerturbationRanges,
    identified: bool = False,
):
    """Samples ``indices`` (n,) of the campaign ``seed`` (see
    [`perturbations`][spacegrasp_jax.envelope.perturbations]) of the nominal run ``spec``, each
    simulated and reduced to its metrics.

    Each sample runs ``spec`` with its perturbed plant and scenario. The controller believes
    the nominal ``spec.robot`` (times the realism's factors); with ``identified`` it is told
    the perturbed robot (a perfectly identified plant). ``spec.realism``: the loop
    (``None``: ideal); the sample's target estimate error is drawn on top of the realism's
    own, its sensor noise from ``fold_in(fold_in(PRNGKey(seed), i), NOISE_STREAM)``.
    ``spec.observer`` must be a [`FoldedMetrics`][spacegrasp_jax.jobs.montecarlo.FoldedMetrics] (its ``every``: the decimated rows
    to keep).

    Returns:
        ``(perturbations, metrics, rows)``, each with leading axis n: the drawn
        [`Perturbation`][spacegrasp_jax.envelope.perturbations.Perturbation], the metrics dict and
        the decimated logs (``None`` without ``every``). A sample that diverges has NaN
        final errors and a finite ``first_nonfinite_s``; the others are unaffected.

    Raises:
        ValueError: the spec's observer is not a ``FoldedMetrics``, or it has a
            ``model_robot`` (what each sample's controller believes is decided here).
    """
    if not isinstance(spec.observer, FoldedMetrics):
        raise ValueError(f"evaluate_samples: the spec's observer must be a FoldedMetrics, got {spec.observer!r}")
    if spec.model_robot is not None:
        raise ValueError(
            "evaluate_samples: the samples' controllers believe the nominal spec.robot (or, identified, their own "
            "plant); a spec's model_robot would be ignored, so it must be None"
        )
    samples = sample_loops(spec.robot, spec.scenario, seed, indices, ranges, spec.realism, identified)

    def one(robot, scenario, realism, key):
        sample = dataclasses.replace(
            spec, robot=robot, scenario=scenario, realism=realism, model_robot=samples.model_robot
        )
        return closed_loop(sample, gains, key)[1]

    sample_metrics, rows = jax.vmap(one)(samples.robots, samples.scenarios, samples.realisms, samples.keys)
    return samples.perturbations, sample_metrics, rows


@dataclasses.dataclass(frozen=True)
class SampleLoops:
    """What the closed loops of a batch of samples run with ([`sample_loops()`][spacegrasp_jax.jobs.montecarlo.sample_loops]).

    Attributes:
        robots, scenarios, perturbations: the perturbed plants and scenarios and the drawn
            numbers, leading axis n.
        realisms: the samples' realism (their target estimate errors differ), leading axis
            n, or ``None`` for the paper's loop.
        keys: (n, 2) the samples' noise keys (``None`` with ``realisms``).
        model_robot: the robot the controllers believe (``None``: each its own plant).
    """

    robots: Robot
    scenarios: Scenario
    perturbations: object
    realisms: Realism | None
    keys: jax.Array | None
    model_robot: Robot | None


def sample_loops(
    robot, scenario, seed, indices, ranges: PerturbationRanges, realism=None, identified=False
) -> SampleLoops:
    """The samples ``indices`` of a campaign and the loop each runs ([`evaluate_samples()`][spacegrasp_jax.jobs.montecarlo.evaluate_samples])."""
    perturbations = jax.vmap(lambda key: draw(key, ranges, scenario.initial.q.dtype, scenario.initial.q.shape[-1]))(
        sample_keys(seed, indices)
    )
    robots, scenarios, realisms, model_robot = jax.vmap(
        lambda p: perturbed_loop(robot, scenario, p, ranges, realism, identified), out_axes=(0, 0, 0, None)
    )(perturbations)
    if realisms is None:
        return SampleLoops(robots, scenarios, perturbations, None, None, None)
    keys = jax.vmap(lambda k: jax.random.fold_in(k, NOISE_STREAM))(sample_keys(seed, indices))
    return SampleLoops(robots, scenarios, perturbations, realisms, keys, model_robot)


def perturbed_loop(
    robot: Robot,
    scenario: Scenario,
    perturbation: Perturbation,
    ranges: PerturbationRanges,
    realism: Realism | None = None,
    identified: bool = False,
) -> tuple[Robot, Scenario, Realism | None, Robot | None]:
    """The loop one perturbation runs, as a campaign runs it ([`evaluate_samples()`][spacegrasp_jax.jobs.montecarlo.evaluate_samples]).

    Returns:
        ``(plant, scenario, realism, model_robot)``: the perturbed robot and scenario; the
        loop's realism, its target estimate error the perturbation's on top of
        ``realism``'s (``None``: the paper's loop, when nothing needs another); the robot
        the controller believes (``None``: the plant itself), the nominal ``robot`` unless
        ``identified`` or the ranges leave the satellite as it is.
    """
    plant, perturbed = apply_to_robot(robot, perturbation), apply_to_scenario(scenario, perturbation)
    believes_nominal = not identified and ranges.perturbs_robot
    estimates, sensors, actuators = ranges.draws_estimate_errors, ranges.draws_sensor_errors, ranges.draws_actuator_loss
    if not (believes_nominal or estimates or sensors or actuators or loop_realism(realism, scenario) is not None):
        return plant, perturbed, None, None
    base = ideal() if realism is None else realism
    if estimates:
        base = dataclasses.replace(base, stages=base.stages | Stage.ESTIMATE)
    sample_realism = dataclasses.replace(
        base,
        lar_position_error_m=base.lar_position_error_m + perturbation.dp_lar_estimate,
        lar_angle_error_rad=base.lar_angle_error_rad + perturbation.dr_lar_estimate,
    )
    p = perturbation
    if sensors:
        sample_realism = dataclasses.replace(
            sample_realism,
            stages=sample_realism.stages | Stage.SENSORS,
            force_bias=base.force_bias + p.ft_force_bias,
            torque_bias=base.torque_bias + p.ft_torque_bias,
            force_noise_std=base.force_noise_std + p.ft_force_noise_std,
            torque_noise_std=base.torque_noise_std + p.ft_torque_noise_std,
        )
    if actuators:
        limits = jnp.asarray(base.torque_limit_Nm)
        sample_realism = dataclasses.replace(
            sample_realism,
            stages=sample_realism.stages | Stage.ACTUATORS,
            torque_limit_Nm=limits * weakened_joint(p, limits.shape[-1]),
        )
    return plant, perturbed, sample_realism, robot if believes_nominal else None


def perturbed_run(
    spec: RunSpec, perturbation: Perturbation, ranges: PerturbationRanges, identified: bool = False
) -> RunSpec:
    """The nominal run ``spec`` with one perturbation, as a campaign runs that sample
    ([`perturbed_loop()`][spacegrasp_jax.jobs.montecarlo.perturbed_loop]): its plant, scenario, realism and the robot its controller
    believes; the rest of ``spec`` (controller, observer, checkpointing) as it is."""
    plant, perturbed, realism, model_robot = perturbed_loop(
        spec.robot, spec.scenario, perturbation, ranges, spec.realism, identified
    )
    return dataclasses.replace(spec, robot=plant, scenario=perturbed, realism=realism, model_robot=model_robot)


def lost(sample_metrics: dict) -> np.ndarray:
    """(n,) bool: the sample ran away (``first_runaway_s``) or diverged
    (``first_nonfinite_s``) (NumPy)."""
    return np.isfinite(np.asarray(sample_metrics["first_runaway_s"], dtype=float)) | np.isfinite(
        np.asarray(sample_metrics["first_nonfinite_s"], dtype=float)
    )


def success(sample_metrics: dict, criteria: CaptureCriteria):
    """(n,) bool: each sample's capture by ``criteria``
    ([`CaptureCriteria`][spacegrasp_jax.envelope.criteria.CaptureCriteria]): it did not diverge nor run
    away (``first_runaway_s``), no joint left its range, its peak |u_i| stayed at or below the
    torque threshold, it ended within both tolerances (relative to the LAR frame, moving or
    not), with a free-floating target (``sample_metrics`` holds ``final_target_speed_mps``)
    the target's final speed is at most its limit and, where rate limits are criteria, no
    joint's peak rate exceeded its limit (NumPy). Which criterion a failed sample missed:
    [`spacegrasp_jax.jobs.anatomy.failure_classes()`][spacegrasp_jax.jobs.anatomy.failure_classes]."""
    return anatomy.failure_classes(sample_metrics, criteria)["failure"] == "success"
