"""What every tuning method is: an ask/tell object over parameter points, driven by one loop.

A method ([`TuningMethod`][tuning.protocol.TuningMethod]) keeps its state as a value it is
handed back. The driver ([`tuning.driver.optimise()`][tuning.driver.optimise]) repeats

    request, state = method.ask(state)     # points to evaluate, gradients wanted or not
    answers = problem.evaluate(request)    # one evaluator for every method
    state, outcome = method.tell(state, request, answers)

until the outcome says a step is complete (``outcome.row``: the history row of the point
the method holds after it), then owns what is common to every method: the progress line,
validation and early stopping, the best point, checkpoints, resume and Ctrl-C. A point is a
pytree of log-gain parameters ([`tuning.parameters`][tuning.parameters], frozen entries
included); the problem turns it into gains.

A new method is one class with these methods (a test file may write one, ``tests/
test_tuner_interface.py``); ``METHODS`` ([`tuning.tune`][tuning.tune]) names the ones
``spacegrasp tune --method`` knows.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Protocol

import numpy as np


@dataclasses.dataclass(frozen=True)
class Request:
    """Points a method wants evaluated on the problem's training batch.

    Attributes:
        points: P parameter pytrees (log-gains).
        gradient: whether each point's gradient of the batch objective is wanted (then P = 1).
        batch: which training batch: step ``batch``'s fresh batch where the problem draws a
            new batch every step, else the run's one batch whatever its value (0: the run's).
    """

    points: tuple
    gradient: bool = False
    batch: int = 0


@dataclasses.dataclass(frozen=True)
class Answers:
    """The problem's answer to a [`Request`][tuning.protocol.Request], one entry per point.

    Attributes:
        objectives: (P,) the batch objective of each point (the batch mean, or its CVaR);
            forward evaluations give ``inf`` for a point whose objective is not finite.
        summaries: P dicts of the point's batch statistics (the objective's parts as batch
            means, ``max_largest_peak_torque_Nm`` the batch's largest peak, N m), the numbers
            of a history row.
        parts: forward evaluations only: every part of the objective per sample, (P, batch).
        gradients: gradient evaluations only: P pytrees shaped as the points.
        rollouts: closed-loop rollouts the evaluation ran (P times the batch).
    """

    objectives: np.ndarray
    summaries: tuple
    parts: dict | None = None
    gradients: tuple | None = None
    rollouts: int = 0


@dataclasses.dataclass(frozen=True)
class Outcome:
    """What a tell did.

    Attributes:
        row: the history row of the point the method holds now, when this tell completed a
            step (step 0: the starting point evaluated); ``None`` while a step goes on (a
            rejected candidate, a generation's candidates told before its mean is evaluated).
        events: what happened on the way (``{"step", "event", ...}`` dicts, ``events`` of
            the run's checkpoint and summary).
        status: ``"diverged"`` when the method can take no further step (the run ends with
            the point of its last completed step), else ``None``.
    """

    row: dict | None = None
    events: tuple = ()
    status: str | None = None


class TuningMethod(Protocol):
    """A tuning method (module docstring): its settings are its own fields, its state a value.

    Attributes:
        name: its name in the run's files and messages.
        unit: what one of its steps is called (``"step"``, ``"generation"``).
        point_words: what its point is called (``"the gains"``, ``"the mean"``).
        title: its name in sentences (``"the gradient method"``, ``"CMA-ES"``).
        settings_type: the frozen dataclass of its settings (``TuneConfig.settings``; each
            field one of ``spacegrasp tune``'s options of the same name), which its class
            method ``from_config(config)`` reads to make it for a run; a class method
            ``check(config)``, where it has one, refuses settings the rest of the run does not
            allow (``ValueError`` naming the field).
    """

    name: str
    unit: str
    point_words: str
    title: str
    settings_type: type

    def init(self, point, mask, seed: int) -> Any:
        """The state before the first evaluation, from the starting point, which of its
        entries the method may move (``mask``: booleans shaped as the point) and the run's seed."""

    def ask(self, state) -> tuple[Request, Any]:
        """The points to evaluate next, and the state that asked them."""

    def tell(self, state, request: Request, answers: Answers) -> tuple[Any, Outcome]:
        """The state after the answers, and what that completed."""

    def point(self, state):
        """The point the method holds after its last completed step (what validation
        evaluates and ``keep="last"`` hands back)."""

    def best(self, state, history: list[dict], best_step: int, best_point) -> tuple[Any, int | None, str, float]:
        """``keep="best"`` without validation: the point with the least training objective the
        method knows of, the step whose point it is (``None``: none of the steps' points), a
        few words of what it is (``"the point after step 3"``) and its training objective.
        ``best_step`` and ``best_point``: the driver's choice, the step of least objective in
        ``history`` (the method may know of better points, such as a generation's best
        candidate)."""

    def state_arrays(self, state) -> tuple[dict[str, np.ndarray], dict]:
        """The state as named arrays and a JSON-able dict, at a step's end (a checkpoint)."""

    def restore(self, point, mask, seed: int, arrays: dict[str, np.ndarray], meta: dict, steps: int) -> Any:
        """The state [`state_arrays()`][tuning.protocol.TuningMethod.state_arrays] wrote, for a run
        from ``point`` (``mask``, ``seed`` as ``init``'s) after ``steps`` completed steps."""

    def describe(self) -> str:
        """A few words for the run's start line (``"by its reverse-mode gradient"``)."""

    def progress(self, state, row: dict, steps: int) -> str:
        """The progress line after a step (``row``: its history row) of ``steps``."""
