"""The one loop that runs every tuning method ([`tuning.protocol`][tuning.protocol]).

It asks the method, has the problem evaluate, tells the method, and after every completed
step: evaluates the method's point on the validation set (early stopping), keeps the best
point, writes the whole run state atomically to its checkpoint, reports progress, and checks
for a stop request (Ctrl-C) and for patience running out. A run resumed from its checkpoint
ends exactly where an uninterrupted one would.

The checkpoint is one ``.npz``: the method's arrays ([`TuningMethod.state_arrays()`][tuning.protocol.TuningMethod.state_arrays]),
the best point's leaves (``best_params_<i>``) and ``meta``, a JSON document with the run's
settings, the completed steps, the history rows, the events, the best step and the method's
own dict. Checkpoints of older versions (one format per method) are read too.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np

from spacegrasp_jax.jobs.runfiles import StopRequest
from spacegrasp_jax.tuning.protocol import TuningMethod

#: The checkpoint layout this version writes (older ones have no ``format``).
CHECKPOINT_FORMAT = 2

#: Which points a run hands back (``TuneConfig.keep``).
KEEPS = ("best", "last")


@dataclasses.dataclass
class DriverState:
    """A run after ``step`` completed steps (what a checkpoint holds).

    Attributes:
        method_state: the method's own state.
        step: completed steps (0: only the starting point evaluated; -1: not even that).
        history: one row per completed step (row k: the method's point after k steps).
        events: the method's events, in order.
        best_step: the step with the least training objective, or validation objective under
            early stopping (the start included).
        best_point: the method's point after ``best_step``.
        rollouts: closed-loop rollouts evaluated so far.
    """

    method_state: object
    step: int = -1
    history: list = dataclasses.field(default_factory=list)
    events: list = dataclasses.field(default_factory=list)
    best_step: int = 0
    best_point: object = None
    rollouts: int = 0


@dataclasses.dataclass(frozen=True)
class DriveResult:
    """What [`optimise()`][tuning.driver.optimise] hands back.

    Attributes:
        state: the run's final [`DriverState`][tuning.driver.DriverState].
        status: ``"done"``, ``"stopped_early"``, ``"interrupted"`` or ``"diverged"``.
        point: the point the run keeps (``keep``).
        kept: what it is: ``rule`` (``"best"``, ``"best by validation"``, ``"last"``), ``step``
            (the step whose point it is; ``None``: a point no history row describes),
            ``what`` (words), ``training_objective`` and, under early stopping,
            ``validation_objective``.
    """

    state: DriverState
    status: str
    point: object
    kept: dict


def _copy(point):
    return jax.tree.map(np.array, point)


def _criterion(row: dict, validating: bool) -> float:
    return row["validation_loss"] if validating else row["loss"]


def save_checkpoint(path: Path, method: TuningMethod, state: DriverState, settings: dict, write_atomically) -> None:
    """Write ``state`` (a step's end) to ``path`` atomically; ``settings``: the run's settings
    (``TuneConfig.to_dict()``), read back by a resume's checks."""
    arrays, method_meta = method.state_arrays(state.method_state)
    arrays = dict(arrays)
    for index, leaf in enumerate(jax.tree.leaves(state.best_point)):
        arrays[f"best_params_{index}"] = np.asarray(leaf)
    meta = {
        "format": CHECKPOINT_FORMAT,
        "config": settings,
        "method": method.name,
        "step": state.step,
        "history": state.history,
        "events": state.events,
        "best_step": state.best_step,
        "rollouts": state.rollouts,
        "method_state": method_meta,
    }
    arrays["meta"] = np.array(json.dumps(meta))
    write_atomically(path, lambda target: np.savez(target, **arrays))


def read_checkpoint(path: Path) -> tuple[dict[str, np.ndarray], dict]:
    """A checkpoint's arrays and ``meta`` (JSON), in this version's layout whatever its version."""
    with np.load(path, allow_pickle=False) as data:
        arrays = {name: data[name] for name in data.files if name != "meta"}
        meta = json.loads(str(data["meta"]))
    if "format" in meta:
        return arrays, meta
    from spacegrasp_jax.tuning.objective import history_of_older_version

    meta = dict(meta, history=history_of_older_version(meta["history"]))
    if "generation" in meta:  # CMA-ES's own layout: the generations asked and told, rows up to the last mean's
        history = meta["history"]
        validation = {
            item["generation"]: item for item in meta.get("validation", []) if item["generation"] < len(history)
        }
        history = [
            row | ({"validation_loss": validation[k]["objective"]} if k in validation else {})
            for k, row in enumerate(history)
        ]
        method_state = {"generation": meta["generation"], "phase": "mean"}
        best_step = len(history) - 1
        if validation:
            best_step = min(validation, key=lambda k: validation[k]["objective"])
            method_state["older_best_mean"] = validation[best_step]["mean"]
        return arrays, {
            "format": CHECKPOINT_FORMAT,
            "config": meta["config"],
            "method": "cmaes",
            "step": len(history) - 1,
            "history": history,
            "events": [],
            "best_step": best_step,
            "rollouts": 0,
            "method_state": method_state,
        }
    # the gradient method's own layout: its state's leaves, the rest in meta
    return arrays, {
        "format": CHECKPOINT_FORMAT,
        "config": meta["config"],
        "method": "gradient",
        "step": meta["step"],
        "history": meta["history"],
        "events": meta["events"],
        "best_step": meta.get("best_step", meta["step"]),  # an older one kept no best step: the last stands for it
        "rollouts": 0,
        "method_state": {
            "scale": meta["scale"],
            "loss": meta["loss"],
            "aux": meta["aux"],
            "start_loss": meta["history"][0]["loss"],
        },
    }


def load_checkpoint(path: Path, method: TuningMethod, point, mask, seed: int) -> DriverState:
    """The [`DriverState`][tuning.driver.DriverState] a checkpoint holds, for a run of
    ``method`` from ``point`` (``mask``: the entries it moves) with ``seed``."""
    arrays, meta = read_checkpoint(path)
    if meta["method"] != method.name:
        raise ValueError(f"{path}: a checkpoint of the {meta['method']} method, not of {method.name}")
    method_state = method.restore(point, mask, seed, arrays, meta["method_state"], meta["step"])
    structure = jax.tree.structure(point)
    count = structure.num_leaves
    if f"best_params_{count - 1}" in arrays:
        best_point = jax.tree.unflatten(structure, [np.asarray(arrays[f"best_params_{i}"]) for i in range(count)])
    elif "older_best_mean" in meta["method_state"]:
        best_point = method.point_of_vector(method_state, np.asarray(meta["method_state"]["older_best_mean"]))
    else:
        best_point = method.point(method_state)
    return DriverState(
        method_state=method_state,
        step=meta["step"],
        history=list(meta["history"]),
        events=list(meta["events"]),
        best_step=meta["best_step"],
        best_point=best_point,
        rollouts=meta.get("rollouts", 0),
    )


def optimise(
    problem,
    method: TuningMethod,
    point,
    mask,
    *,
    steps: int,
    seed: int,
    keep: str = "best",
    patience: int | None = None,
    validate: Callable[[object], float] | None = None,
    checkpoint_path: Path | None = None,
    settings: dict | None = None,
    write_atomically=None,
    resume: DriverState | None = None,
    on_step: Callable[[DriverState, dict], None] | None = None,
    stop: StopRequest | None = None,
) -> DriveResult:
    """Run ``method`` from ``point`` (or, from ``resume``, continue it) for ``steps`` steps on
    ``problem`` (an object with ``evaluate(Request) -> Answers``), moving the entries of the
    point that ``mask`` marks.

    ``validate``: early stopping with ``patience``: the validation objective of the method's
    point after every step (and of the start), recorded as ``validation_loss`` in its row;
    the run stops once it has not improved for ``patience`` steps, and ``keep="best"``
    keeps the best point by it. Without, ``keep="best"`` keeps the method's
    [`best()`][tuning.protocol.TuningMethod.best]. ``checkpoint_path``: written after every
    step (``settings`` recorded in it). ``on_step(state, row)``: after every step, the start
    included. ``stop``: checked between steps; a requested stop ends the run ``"interrupted"``."""
    if keep not in KEEPS:
        raise ValueError(f"keep: expected one of {', '.join(KEEPS)}, got {keep!r}")
    if validate is not None and (patience is None or patience < 1):
        raise ValueError("validate: early stopping needs a patience of at least 1 step")
    validating = validate is not None
    state = resume if resume is not None else DriverState(method.init(point, mask, seed))
    status = "done"
    while state.step < steps:
        if state.step >= 0 and validating and state.step - state.best_step >= patience:
            status = "stopped_early"
            break
        if state.step >= 0 and stop is not None and stop.requested:
            status = "interrupted"
            break
        start = time.perf_counter()
        while True:
            request, state.method_state = method.ask(state.method_state)
            answers = problem.evaluate(request)
            state.rollouts += answers.rollouts
            state.method_state, outcome = method.tell(state.method_state, request, answers)
            state.events.extend(outcome.events)
            if outcome.row is not None or outcome.status is not None:
                break
        if outcome.status is not None:
            status = outcome.status
            break
        state.step += 1
        row = dict(outcome.row, wall_s=time.perf_counter() - start)
        current = method.point(state.method_state)
        if validating:
            row["validation_loss"] = float(validate(current))
        state.history.append(row)
        if state.step == 0 or _criterion(row, validating) < _criterion(state.history[state.best_step], validating):
            state.best_step, state.best_point = state.step, _copy(current)
        if checkpoint_path is not None:
            save_checkpoint(checkpoint_path, method, state, settings or {}, write_atomically)
        if on_step is not None:
            on_step(state, row)
    return DriveResult(state, status, *kept_point(method, state, keep, validating))


def kept_point(method: TuningMethod, state: DriverState, keep: str, validating: bool) -> tuple[object, dict]:
    """The point ``keep`` hands back and the words for it (``DriveResult.kept``)."""
    words = f"{method.point_words} after {method.unit}"
    if keep == "last":
        point, step = method.point(state.method_state), state.step
        kept = {"rule": "last", "step": step, "what": f"{words} {step}"}
    elif validating:
        point, step = state.best_point, state.best_step
        kept = {"rule": "best by validation", "step": step, "what": f"{words} {step}"}
    else:
        point, step, what, objective = method.best(state.method_state, state.history, state.best_step, state.best_point)
        kept = {"rule": "best", "step": step, "what": what, "training_objective": float(objective)}
    if "training_objective" not in kept:
        kept["training_objective"] = state.history[step]["loss"]
    if validating:
        kept["validation_objective"] = state.history[step]["validation_loss"]
    return point, kept
