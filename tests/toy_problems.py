"""Tuning problems written by hand, for the driver and the methods: an objective of a
parameter vector (and its gradient) answering the methods' requests as the simulator's
problem does (``spacegrasp_jax.tuning.problem``), in microseconds."""

from __future__ import annotations

import numpy as np

from spacegrasp_jax.tuning import cmaes
from spacegrasp_jax.tuning.problem import batch_summary
from spacegrasp_jax.tuning.protocol import Answers, Request


class ToyProblem:
    """``batch_parts(vectors (P, n)) -> parts (P, batch)`` for forward requests (every part a
    history row reports; ``loss`` and ``largest_peak_torque_Nm`` at least), and/or
    ``value_and_grad(point) -> ((loss, aux), gradient)`` for gradient requests. A point is
    ``{"x": vector}``. ``evaluated``: every point asked, in order."""

    def __init__(self, batch_parts=None, value_and_grad=None, cvar_alpha=None):
        self.batch_parts, self.value_and_grad, self.cvar_alpha = batch_parts, value_and_grad, cvar_alpha
        self.evaluated = []

    def evaluate(self, request: Request) -> Answers:
        self.evaluated.extend(request.points)
        if request.gradient:
            (loss, aux), gradient = self.value_and_grad(request.points[0])
            return Answers(np.array([float(loss)]), (aux,), gradients=(gradient,), rollouts=1)
        parts = self.batch_parts(np.stack([np.asarray(point["x"], dtype=float) for point in request.points]))
        objectives = cmaes.batch_objective(parts["loss"], self.cvar_alpha)
        summaries = tuple(batch_summary(parts, which) for which in range(len(request.points)))
        return Answers(objectives, summaries, parts=parts, rollouts=parts["loss"].size)


def start(n: int, value: float = 0.0) -> tuple[dict, dict]:
    """A starting point of ``n`` numbers, all tuned: ``(point, mask)``."""
    return {"x": np.full(n, value)}, {"x": np.ones(n, dtype=bool)}


class StopAfter:
    """A stop request that comes after ``count`` completed steps (the driver asks once a step)."""

    def __init__(self, count: int):
        self.count = count

    @property
    def requested(self) -> bool:
        self.count -= 1
        return self.count < 0


def descend(value_and_grad, point, config, **options):
    """The gradient method of ``config`` (a ``TuneConfig``) from ``point`` on
    ``value_and_grad`` by the driver: its ``DriveResult``."""
    import jax

    from spacegrasp_jax.tuning import driver
    from spacegrasp_jax.tuning.tune import make_method

    mask = jax.tree.map(lambda leaf: np.ones(np.shape(leaf), dtype=bool), point)
    problem = ToyProblem(value_and_grad=value_and_grad)
    return driver.optimise(
        problem,
        make_method(config),
        point,
        mask,
        steps=config.steps,
        seed=config.seed,
        keep=config.keep,
        patience=config.patience,
        **options,
    )
