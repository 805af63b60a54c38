"""Per-sample metrics of closed-loop rollouts, accumulated inside the scan, and the batched
evaluation of a Monte-Carlo campaign's samples.

A full :class:`~spacegrasp_jax.simulate.Log` of a 17 s rollout holds some 1.4 million numbers; a campaign
needs a few numbers per sample. :func:`rollout_metrics` runs the same scan body as
:func:`~spacegrasp_jax.simulate.rollout` but folds every log row into the running metrics of
:mod:`spacegrasp_jax.metrics` as it goes (the functions that give a whole log's metrics), so
a batch needs memory for its states only, plus, on request, every ``every``-th log row.

Everything here is pure: ``jit``, ``vmap`` and sharding are applied by the caller
(:mod:`spacegrasp_jax.campaign`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax import metrics
from spacegrasp_jax.control.gains import Gains
from spacegrasp_jax.model import Robot
from spacegrasp_jax.perturbations import PerturbationRanges, sample
from spacegrasp_jax.scenario import Scenario
from spacegrasp_jax.simulate import Log, closed_loop_step, initial_state


def rollout_metrics(
    robot: Robot,
    scenario: Scenario,
    gains: Gains,
    controller: str,
    pinv_damping: float = 0.0,
    every: int | None = None,
) -> tuple[dict[str, jax.Array], Log | None]:
    """One closed-loop rollout reduced to its :data:`~spacegrasp_jax.metrics.METRICS`, in one ``lax.scan``.

    Args:
        robot, scenario, gains, controller, pinv_damping: as :func:`~spacegrasp_jax.simulate.rollout`.
        every: if set (static; must divide ``scenario.n_steps``), also return every
            ``every``-th log row, i.e. the rows at ``t = 0, every dt, 2 every dt, ...``.

    Returns:
        ``(metrics, rows)``: a dict of the metrics' arrays and the decimated
        :class:`~spacegrasp_jax.simulate.Log` (``None`` without ``every``).
    """
    step = closed_loop_step(robot, scenario, gains, controller, pinv_damping)
    n_steps = scenario.n_steps
    dtype = scenario.initial.q.dtype

    # The step number rides in the carry rather than being scanned over: the loop then reads
    # no array longer than 64 numbers, and XLA's CPU runtime runs its body as a sequence.
    def step_and_fold(carry, _):
        state, running, k = carry
        state, row = step(state, k)
        return (state, metrics.accumulate(running, jax.tree.map(lambda x: x[None], row)), k + 1), row

    carry = (initial_state(scenario, controller), metrics.start(dtype), jnp.zeros((), dtype))
    if every is None:
        (final, running, _), _ = jax.lax.scan(
            lambda c, _: (step_and_fold(c, None)[0], None), carry, None, length=n_steps
        )
        rows = None
    else:
        if every < 1 or n_steps % every:
            raise ValueError(f"every: {every} must be a positive divisor of the {n_steps} steps")

        def block(carry, _):
            carry, rows = jax.lax.scan(step_and_fold, carry, None, length=every)
            return carry, jax.tree.map(lambda x: x[0], rows)

        (final, running, _), rows = jax.lax.scan(block, carry, None, length=n_steps // every)
    # A state that turns non-finite in the very last step shows in no logged row.
    final_finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree.leaves(final)]))
    return metrics.finish(running, nonfinite_after_s=jnp.where(final_finite, jnp.inf, scenario.duration)), rows


def evaluate_samples(
    robot: Robot,
    scenario: Scenario,
    gains: Gains,
    seed,
    indices: jax.Array,
    *,
    controller: str,
    ranges: PerturbationRanges,
    pinv_damping: float = 0.0,
    every: int | None = None,
):
    """Samples ``indices`` (n,) of the campaign ``seed`` (see
    :mod:`~spacegrasp_jax.perturbations`), each simulated and reduced to its metrics.

    Returns:
        ``(perturbations, metrics, rows)``, each with leading axis n: the drawn
        :class:`~spacegrasp_jax.perturbations.Perturbation`, the metrics dict and
        the decimated logs (``None`` without ``every``). A sample that diverges has NaN
        final errors and a finite ``first_nonfinite_s``; the others are unaffected.
    """
    robots, scenarios, perturbations = sample(robot, scenario, seed, indices, ranges)
    one = lambda r, s: rollout_metrics(r, s, gains, controller, pinv_damping, every)
    sample_metrics, rows = jax.vmap(one)(robots, scenarios)
    return perturbations, sample_metrics, rows


def over_torque_limit(sample_metrics: dict, torque_limit_Nm: float | None):
    """(n,) bool: the sample's peak |u_i| on some joint exceeded ``torque_limit_Nm`` (N m;
    ``None``: never). NaN peaks (diverged samples) are not over it (NumPy)."""
    peak = np.asarray(sample_metrics["largest_peak_torque_Nm"])
    limit = np.inf if torque_limit_Nm is None else torque_limit_Nm
    with np.errstate(invalid="ignore"):
        return peak > limit


def success(
    sample_metrics: dict,
    position_tolerance_m: float,
    orientation_tolerance_rad: float,
    torque_limit_Nm: float | None = None,
):
    """(n,) bool: the sample did not diverge, its peak |u_i| stayed at or below
    ``torque_limit_Nm`` (N m; ``None``: no limit), and it ended within both tolerances (NumPy)."""
    position = np.asarray(sample_metrics["final_position_error_m"])
    orientation = np.asarray(sample_metrics["final_orientation_error_rad"])
    diverged = np.isfinite(np.asarray(sample_metrics["first_nonfinite_s"]))
    with np.errstate(invalid="ignore"):
        within = (position <= position_tolerance_m) & (orientation <= orientation_tolerance_rad)
    return ~diverged & ~over_torque_limit(sample_metrics, torque_limit_Nm) & within
