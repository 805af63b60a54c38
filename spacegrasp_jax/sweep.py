"""Sweeps over controller gains: batches of gain sets built by scaling a base set, evaluated
in one vmapped program sharded over the local devices, and the Pareto front of the results.

A sweep answers "what happens to peak torque, accuracy and contact force if the admittance
is stiffer, softer, more damped..." on one scenario. Each gain set runs the same closed loop
as :func:`~spacegrasp_jax.simulate.rollout`, reduced to the per-run metrics of
:data:`~spacegrasp_jax.montecarlo.METRICS` inside the scan, so a batch of full 17 s runs
needs memory for its states only.

Example (scale Kd and Bd of the paper's admittance by 1/2, 1 and 2)::

    scales = scale_grid(Kd=[0.5, 1, 2], Bd=[0.5, 1, 2])        # 9 combinations
    results = evaluate_gains(robot, scenario, scaled_gains(paper_gains(), scales), "admittance")
    front = pareto_front(results["largest_peak_torque_Nm"], results["final_position_error_m"])
"""

from __future__ import annotations

import functools
import itertools
import math
import sys
import time

import jax
import numpy as np
from jax.sharding import PartitionSpec

from spacegrasp_jax import compilation
from spacegrasp_jax.campaign import batch_mesh
from spacegrasp_jax.control import CONTROLLERS
from spacegrasp_jax.control.gains import GAIN_SHAPES, Gains
from spacegrasp_jax.model import Robot
from spacegrasp_jax.montecarlo import rollout_metrics
from spacegrasp_jax.scenario import Scenario


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
        scales: group name -> (N,) positive factors, all of one length N (see :func:`scale_grid`).

    Returns:
        :class:`Gains` with a leading batch axis of N on every field.
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
    """A batch of gain sets from a sequence of unbatched :class:`Gains`."""
    gain_sets = list(gain_sets)
    if not gain_sets:
        raise SweepError("gain_sets: empty")
    return jax.tree.map(lambda *leaves: np.stack([np.asarray(leaf, dtype=float) for leaf in leaves]), *gain_sets)


def _check_factors(name: str, values: np.ndarray) -> None:
    if name not in GAIN_SHAPES:
        raise SweepError(f"unknown gain group {name!r}; expected one of {', '.join(GAIN_SHAPES)}")
    if values.size == 0 or not np.all(np.isfinite(values)) or np.any(values <= 0.0):
        raise SweepError(f"{name}: scale factors must be finite and positive, got {values.tolist()}")


@functools.lru_cache(maxsize=None)
def _sharded_metrics(controller: str, pinv_damping: float, devices: tuple):
    """jit of the per-device vmapped metrics, the gains batch sharded over ``devices``."""
    mesh = batch_mesh()

    def on_one_device(robot, scenario, gains):
        return jax.vmap(lambda g: rollout_metrics(robot, scenario, g, controller, pinv_damping)[0])(gains)

    replicated, batched = PartitionSpec(), PartitionSpec("batch")
    return compilation.jit(jax.shard_map(on_one_device, mesh=mesh, in_specs=(replicated, replicated, batched), out_specs=batched, check_vma=False))


def evaluate_gains(
    robot: Robot,
    scenario: Scenario,
    gains: Gains,
    controller: str,
    *,
    chunk: int = 64,
    pinv_damping: float = 0.0,
    progress=sys.stderr,
) -> dict[str, np.ndarray]:
    """Run the closed loop once per gain set and return the per-run metrics.

    The batch is split into chunks of ``chunk`` sets (rounded up to a multiple of the device
    count; the last chunk is padded with copies of the final set, dropped from the results),
    each chunk one call of one compiled program sharded over ``jax.devices()``. Single
    process: for multi-host campaigns use :mod:`spacegrasp_jax.campaign`.

    Args:
        robot, scenario: the system and the scenario, the same for every run.
        gains: a batch of N gain sets (leading axis N on every field).
        controller: ``"admittance"`` or ``"cartesian"``.
        chunk: gain sets per compiled call (bounds memory).
        pinv_damping: damping of the pseudoinverse (0: exact, the paper).
        progress: stream for one line per chunk (``None``: silent).

    Returns:
        Each metric of :data:`~spacegrasp_jax.montecarlo.METRICS` as an (N, ...) array, plus
        ``largest_peak_torque_Nm`` (N,), the largest ``max_abs_torque_Nm`` over the joints, and
        ``diverged`` (N,) bool, true where the run became non-finite.
    """
    if controller not in CONTROLLERS:
        raise SweepError(f"controller: expected one of {', '.join(CONTROLLERS)}, got {controller!r}")
    if not isinstance(chunk, int) or chunk < 1:
        raise SweepError(f"chunk: expected a positive integer, got {chunk!r}")
    leaves = [np.asarray(getattr(gains, name), dtype=float) for name in GAIN_SHAPES]
    if any(leaf.ndim != 2 or leaf.shape[1] != GAIN_SHAPES[name] for leaf, name in zip(leaves, GAIN_SHAPES)):
        shapes = {name: leaf.shape for leaf, name in zip(leaves, GAIN_SHAPES)}
        raise SweepError(f"gains: expected a batch (N, size) on every field, got shapes {shapes}")
    n = leaves[0].shape[0]
    if any(leaf.shape[0] != n for leaf in leaves):
        raise SweepError(f"gains: every field needs the same batch size, got {[leaf.shape[0] for leaf in leaves]}")
    devices = jax.device_count()
    chunk = devices * math.ceil(min(chunk, n) / devices)
    function = _sharded_metrics(controller, float(pinv_damping), tuple(jax.devices()))
    pieces = []
    for first in range(0, n, chunk):
        rows = np.minimum(np.arange(first, first + chunk), n - 1)  # pad with the last set
        block = Gains(**{name: leaf[rows] for name, leaf in zip(GAIN_SHAPES, leaves)})
        start = time.perf_counter()
        metrics = jax.tree.map(np.asarray, function(robot, scenario, block))
        pieces.append({name: value[: min(chunk, n - first)] for name, value in metrics.items()})
        if progress is not None:
            done = min(first + chunk, n)
            print(f"gain sets {done}/{n} ({time.perf_counter() - start:.1f} s for this chunk)", file=progress, flush=True)
    results = {name: np.concatenate([piece[name] for piece in pieces]) for name in pieces[0]}
    results["largest_peak_torque_Nm"] = np.max(results["max_abs_torque_Nm"], axis=1)
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
