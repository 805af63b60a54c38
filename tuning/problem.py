"""The tuning problem every method runs on: what a point is worth on the training batch.

[`TuningProblem`][tuning.problem.TuningProblem] answers a method's
[`Request`][tuning.protocol.Request]: forward rollouts of every point on the batch (the
objective's parts per sample), or one point's objective with its gradient. Its batch is the
run's (``TuneConfig.batch`` samples of ``seed``) or, where the run draws fresh batches, step
k's (seed ``seed + FRESH_SEED_STRIDE * k``, step 0 the run's). A point is a pytree of log-gain
parameters ([`tuning.parameters`][tuning.parameters]).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import numpy as np

from spacegrasp_jax.core.model import Robot
from spacegrasp_jax.jobs import batching
from spacegrasp_jax.jobs.montecarlo import SampleLoops
from spacegrasp_jax.loop.control.gains import Gains
from spacegrasp_jax.tuning import cmaes
from spacegrasp_jax.tuning.objective import BATCH_MAX_PEAK_TORQUE, Objective
from spacegrasp_jax.tuning.parameters import gains_from_params
from spacegrasp_jax.tuning.protocol import Answers, Request


def batch_summary(parts: dict, which: int) -> dict:
    """Point ``which``'s batch statistics from forward parts shaped (P, batch): every part but
    the loss as its batch mean (NaN left out), and the batch's largest peak torque (N m)."""
    summary = {name: float(np.nanmean(value[which])) for name, value in parts.items() if name != "loss"}
    summary[BATCH_MAX_PEAK_TORQUE] = float(np.nanmax(parts["largest_peak_torque_Nm"][which]))
    return summary


@dataclasses.dataclass
class TuningProblem:
    """A run's training problem ([`setup()`][tuning.tune.setup] makes it from a ``TuneConfig``).

    Attributes:
        robot: the robot the controller believes (the model).
        base: the starting gains (a point's frozen entries keep theirs).
        mask: which entries of a point are tuned.
        start: the starting point (log-gains).
        objective: the objective.
        controller: the law's name.
        cvar_alpha: the batch objective: ``None`` the mean, else the mean over the worst
            ``1 - cvar_alpha`` of the batch.
        batch: the run's training batch ([`SampleLoops`][spacegrasp_jax.jobs.montecarlo.SampleLoops];
            without realisms: the paper's ideal loop).
        fresh: step k's batch where the run draws a new one every step (``None``: one batch).
        value_and_grad: ``(point, step) -> ((loss, aux), gradient)`` on step ``step``'s batch
            (``None``: the problem evaluates forward only).
    """

    robot: Robot
    base: Gains
    mask: dict
    start: dict
    objective: Objective
    controller: str
    cvar_alpha: float | None
    batch: SampleLoops
    fresh: Callable[[int], SampleLoops] | None = None
    value_and_grad: Callable | None = None
    _forward: dict = dataclasses.field(default_factory=dict, repr=False)

    @property
    def batch_size(self) -> int:
        return batching.batch_size(self.batch.scenarios)

    def gains(self, point) -> Gains:
        """The gains a point stands for."""
        return gains_from_params(point, self.base, self.mask)

    def batch_key(self, step: int) -> int:
        """Which batch step ``step`` trains on: ``step`` where the run draws fresh batches, else 0."""
        return step if self.fresh is not None and step > 0 else 0

    def batch_of(self, step: int):
        """Step ``step``'s training batch."""
        return self.fresh(step) if self.batch_key(step) else self.batch

    def evaluate(self, request: Request) -> Answers:
        """The [`Answers`][tuning.protocol.Answers] to ``request``."""
        if request.gradient:
            return self._gradient(request)
        return self._forward_parts(request)

    def _gradient(self, request: Request) -> Answers:
        if self.value_and_grad is None:
            raise ValueError("this problem evaluates forward only: no gradient was set up")
        if len(request.points) != 1:
            raise ValueError(f"a gradient is evaluated one point at a time, not {len(request.points)}")
        step = self.batch_key(request.batch)
        (loss, aux), gradient = (
            self.value_and_grad(request.points[0], step) if step else self.value_and_grad(request.points[0])
        )
        return Answers(np.array([float(loss)]), (aux,), gradients=(gradient,), rollouts=self.batch_size)

    def _forward_parts(self, request: Request) -> Answers:
        key = self.batch_key(request.batch)
        evaluator = self._forward.get(key)
        if evaluator is None:  # one evaluator per batch, the last one kept (they share one program)
            evaluator = make_population_evaluator(
                self.robot,
                self.batch_of(key),
                self.controller,
                self.objective,
                chunk=cmaes.population_chunk(self.batch_size),
            )
            self._forward.clear()
            self._forward[key] = evaluator
        parts = evaluator([self.gains(point) for point in request.points])
        objectives = cmaes.batch_objective(parts["loss"], self.cvar_alpha)
        summaries = tuple(batch_summary(parts, which) for which in range(len(request.points)))
        return Answers(objectives, summaries, parts=parts, rollouts=len(request.points) * self.batch_size)


def make_population_evaluator(robot: Robot, samples: SampleLoops, controller: str, objective: Objective, chunk: int):
    """``evaluate(gains: list of P gain sets) -> parts``, every part of the objective shaped
    (P, batch): each gain set on every sample of ``samples``, forward rollouts in one
    sharded, chunked program ([`cmaes.make_item_evaluator()`][tuning.cmaes.make_item_evaluator])."""
    size = batching.batch_size(samples.scenarios)
    items = cmaes.make_item_evaluator(robot, samples, controller, objective, chunk)

    def evaluate(gains: list) -> dict:
        count = len(gains)
        stacked = jax.tree.map(lambda *g: np.stack([np.asarray(x) for x in g]), *gains)
        repeated = jax.tree.map(lambda x: np.repeat(x, size, axis=0), stacked)
        parts = items(repeated, np.tile(np.arange(size), count))
        return {name: value.reshape(count, size) for name, value in parts.items()}

    return evaluate
