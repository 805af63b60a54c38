"""Sweeps over controller gains: batches of gain sets built by scaling a base set, evaluated
in one vmapped program sharded over the local devices, and the Pareto front of the results.

A sweep answers "what happens to peak torque, accuracy and contact force if the admittance
is stiffer, softer, more damped..." on one scenario. Each gain set runs the same closed loop
as [`rollout()`][spacegrasp_jax.loop.simulate.rollout], reduced to the per-run metrics of
``METRICS`` inside the scan, so a batch of full 17 s runs
needs memory for its states only.

Example (scale Kd and Bd of the paper's admittance by 1/2, 1 and 2, on a 2 s approach)::

    import spacegrasp_jax as sg
    from spacegrasp_jax import sweep
    from spacegrasp_jax.loop.control import paper_gains
    from spacegrasp_jax.envelope.scenario import paper_scenario

    sg.configure()
    robot = sg.paper_robot()
    scenario = paper_scenario(robot, duration=2.0, move_duration=2.0)
    scales = sweep.scale_grid(Kd=[0.5, 1, 2], Bd=[0.5, 1, 2])  # 9 combinations
    results = sweep.evaluate_gains(robot, scenario, sweep.scaled_gains(paper_gains(), scales), "admittance")
    front = sweep.pareto_front(results["largest_peak_torque_Nm"], results["final_position_error_m"])
"""

from __future__ import annotations

import itertools
import sys

import jax
import numpy as np

from spacegrasp_jax.core.model import Robot
from spacegrasp_jax.envelope.scenario import Scenario
from spacegrasp_jax.jobs import batching
from spacegrasp_jax.jobs.montecarlo import FoldedMetrics
from spacegrasp_jax.loop.control.gains import GAIN_SHAPES, Gains
from spacegrasp_jax.loop.control.registry import as_controller
from spacegrasp_jax.loop.simulate import RunSpec, closed_loop


class SweepError(ValueError):
    """Invalid sweep input; the message names the offending argument."""


def scale_grid(**axes) -> dict[str, np.ndarray]:
    """Every combination of the given scale factors, flattened (the first axis varies slowest).

    Args:
        **axes: gain group name (``Md``, ``Bd``, ``Kd``, ``K_lin``, ``K_eul``, ``kp``, ``ki``,
            ``kd``) -> 1-D sequence of positive factors.

    Returns:
        group name -> (N,) factors, N the product of the axes' lengths.
    """
    if not axes:
        raise SweepError("scale_grid: give at least one gain group, e.g. scale_grid(Kd=[0.5, 1, 2])")
    for name, values in axes.items():
        _check_factors(name, np.asarray(values, dtype=float))
    combinations = list(itertools.product(*(np.asarray(values, dtype=float) for values in axes.values())))
    return {name: np.array([combination[i] for combination in combinations]) for i, name in enumerate(axes)}


def scaled_gains(base: Gains, scales: dict) -> Gains:
    """A batch of gain sets: set n has every group ``g`` of ``base`` multiplied by
    ``scales[g][n]`` (a whole group scales together, e.g. all six ``Kd`` entries).

    Args:
        base: one gain set (unbatched).
        scales: group name -> (N,) positive factors, all of one length N (see [`scale_grid()`][spacegrasp_jax.analysis.sweep.scale_grid]).

    Returns:
        [`Gains`][spacegrasp_jax.loop.control.gains.Gains] with a leading batch axis of N on every field.
    """
    if not scales:
        raise SweepError("scales: empty; give at least one gain group")
    lengths = {}
    for name, values in scales.items():
        values = np.asarray(values, dtype=float)
        if values.ndim != 1:
            raise SweepError(f"scales[{name!r}]: expected a 1-D sequence of factors, got shape {values.shape}")
        _check_factors(name, values)
        lengths[name] = len(values)
    if len(set(lengths.values())) != 1:
        raise SweepError(f"scales: every group needs the same number of factors, got {lengths}")
    n = next(iter(lengths.values()))
    fields = {}
    for name in GAIN_SHAPES:
        value = np.asarray(getattr(base, name), dtype=float)
        factors = np.asarray(scales.get(name, np.ones(n)), dtype=float)
        fields[name] = factors[:, None] * value[None, :]
    return Gains(**fields)


def stack_gains(gain_sets) -> Gains:
    """A batch of gain sets from a sequence of unbatched [`Gains`][spacegrasp_jax.loop.control.gains.Gains]."""
    gain_sets = list(gain_sets)
    if not gain_sets:
        raise SweepError("gain_sets: empty")
    return jax.tree.map(lambda *leaves: np.stack([np.asarray(leaf, dtype=float) for leaf in leaves]), *gain_sets)


def _check_factors(name: str, values: np.ndarray) -> None:
    if name not in GAIN_SHAPES:
        raise SweepError(f"unknown gain group {name!r}; expected one of {', '.join(GAIN_SHAPES)}")
    if values.size == 0 or not np.all(np.isfinite(values)) or np.any(values <= 0.0):
        raise SweepError(f"{name}: scale factors must be finite and positive, got {values.tolist()}")


def _metrics_of_gain_sets(spec, gains):
    """The per-run metrics of ``spec`` with each gain set of the batch ``gains`` (vmapped)."""
    return jax.vmap(lambda g: closed_loop(spec, g)[1][0])(gains)


def evaluate_gains(
    robot: Robot,
    scenario: Scenario,
    gains: Gains,
    controller,
    *,
    chunk: int = 64,
    progress=sys.stderr,
) -> dict[str, np.ndarray]:
    """Run the closed loop once per gain set and return the per-run metrics.

    The batch is split into chunks of ``chunk`` sets (rounded up to a multiple of the device
    count; the last chunk is padded with copies of the final set, dropped from the results),
    each chunk one call of one compiled program sharded over ``jax.devices()``
    ([`spacegrasp_jax.jobs.batching.map_in_chunks()`][spacegrasp_jax.jobs.batching.map_in_chunks]).

    Args:
        robot, scenario: the system and the scenario, the same for every run.
        gains: a batch of N gain sets (leading axis N on every field).
        controller: a law's name (``control.CONTROLLERS``) or a law object
            (``control.Admittance(pinv_damping=0.01)``).
        chunk: gain sets per compiled call (bounds memory).
        progress: stream for one line per chunk (``None``: silent).

    Returns:
        Each metric of ``METRICS`` as an (N, ...) array, plus
        ``diverged`` (N,) bool, true where the run became non-finite.
    """
    try:
        law = as_controller(controller)
    except ValueError as error:
        raise SweepError(str(error)) from None
    if not isinstance(chunk, int) or chunk < 1:
        raise SweepError(f"chunk: expected a positive integer, got {chunk!r}")
    leaves = [np.asarray(getattr(gains, name), dtype=float) for name in GAIN_SHAPES]
    joints = leaves[list(GAIN_SHAPES).index("kp")].shape[-1]
    sizes = {name: joints if size == "N" else size for name, size in GAIN_SHAPES.items()}
    if any(leaf.ndim != 2 or leaf.shape[1] != sizes[name] for leaf, name in zip(leaves, GAIN_SHAPES)):
        shapes = {name: leaf.shape for leaf, name in zip(leaves, GAIN_SHAPES)}
        raise SweepError(f"gains: expected a batch (N, size) on every field, got shapes {shapes}")
    n = leaves[0].shape[0]
    if any(leaf.shape[0] != n for leaf in leaves):
        raise SweepError(f"gains: every field needs the same batch size, got {[leaf.shape[0] for leaf in leaves]}")
    batch = Gains(**dict(zip(GAIN_SHAPES, leaves)))
    results = batching.map_in_chunks(
        "sweep",
        _metrics_of_gain_sets,
        (RunSpec(robot, scenario, law, observer=FoldedMetrics()),),
        batch,
        chunk=chunk,
        progress=progress,
        label="gain sets",
    )
    results["diverged"] = np.isfinite(results["first_nonfinite_s"])
    return results


def pareto_front(*objectives) -> np.ndarray:
    """Which points are Pareto-optimal when every objective is minimised.

    Args:
        *objectives: two or more (N,) arrays, one value per point.

    Returns:
        (N,) bool: true for points that are finite and that no other finite point matches or
        beats in every objective while beating them in at least one.
    """
    if len(objectives) < 2:
        raise SweepError("pareto_front: give at least two objectives")
    values = np.column_stack([np.asarray(objective, dtype=float) for objective in objectives])
    finite = np.all(np.isfinite(values), axis=1)
    optimal = np.zeros(len(values), dtype=bool)
    candidates = values[finite]
    for i in np.flatnonzero(finite):
        dominated = np.any(np.all(candidates <= values[i], axis=1) & np.any(candidates < values[i], axis=1))
        optimal[i] = not dominated
    return optimal


__all__ = ["SweepError", "evaluate_gains", "pareto_front", "scale_grid", "scaled_gains", "stack_gains"]
