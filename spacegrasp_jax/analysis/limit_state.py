"""A capture's margin as the limit state of reliability methods.

The margin ``g`` of a capture is how far it stays inside the campaign's success criteria
([`CaptureCriteria`][spacegrasp_jax.envelope.criteria.CaptureCriteria]), in the most critical of them:

    g = 1 - max( final position error / position tolerance,
                 final orientation error / orientation tolerance,
                 largest peak torque / torque threshold,             with a threshold
                 final target speed / its limit,                     with a free-floating target
                 exp(furthest excess beyond a joint's range / 0.05 rad),  for a robot with ranges
                 largest peak joint rate / its limit )               where rate limits are criteria

(the worst-case search's ``criteria`` measure, with the target's speed), and ``LOST_MARGIN`` for
a capture that ran away or diverged. ``g < 0`` exactly when the campaign calls the capture
failed (``montecarlo.success()``): every ratio exceeds 1 exactly when its criterion is missed.
A failed capture's margin says by how much: -0.1 is 10% past a tolerance. The margin is linear
in the ratios, not in their logarithms: a final error that grows in proportion to a
perturbation (the LAR estimate's error) gives a margin that does too, which FORM's
linearisations need.

``g`` is a function of the standard normal coordinates ``z`` of the envelope's perturbations
([`StandardSpace`][spacegrasp_jax.envelope.standard_space.StandardSpace]) and, in a flight-like
loop, of the sensor noise (about 1.3e5 normal draws a capture). The noise is not made
coordinates: it is a random input drawn from its own distribution, one draw (a noise key) a
point, as a campaign draws it (the reliability methods' module docstring says why every
estimator stays unbiased that way). Point ``k`` of a run gets the noise of the campaign's sample
``k`` of the run's seed; FORM's search holds the noise of sample 0. A Monte-Carlo estimate runs
the campaign's own samples: its failures are the campaign's, sample for sample.

The gradient ``dg/dz`` is the closed loop's reverse-mode gradient through the campaign's own
metrics, one point at a time, each control period checkpointed.
"""

from __future__ import annotations

import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax.analysis import worstcase
from spacegrasp_jax.analysis.reliability import GRADIENT_COST, LimitState
from spacegrasp_jax.core import joint_limits
from spacegrasp_jax.core.model import Robot
from spacegrasp_jax.envelope.criteria import CaptureCriteria
from spacegrasp_jax.envelope.perturbations import from_units
from spacegrasp_jax.envelope.scenario import Scenario
from spacegrasp_jax.envelope.standard_space import StandardSpace
from spacegrasp_jax.jobs import anatomy, compilation
from spacegrasp_jax.jobs.campaign import CampaignConfig, Variant, variant_spec
from spacegrasp_jax.jobs.experiment import loop_options
from spacegrasp_jax.jobs.montecarlo import perturbed_run
from spacegrasp_jax.loop.simulate import closed_loop

#: The margin of a capture that ran away or diverged: as far past the criteria as a torque a
#: thousand times its threshold.
LOST_MARGIN = -1000.0


def capture_margin(sample_metrics: dict, criteria: CaptureCriteria) -> jax.Array:
    """(n,) or () the margin ``g`` of captures (module docstring) from their campaign metrics
    (``montecarlo.evaluate_samples()``'s, NumPy or JAX; a free-floating target's
    ``final_target_speed_mps`` among them when there is one). Differentiable where finite."""
    m = {name: jnp.asarray(value) for name, value in sample_metrics.items()}
    ratios = [
        m["final_position_error_m"] / criteria.position_tolerance_m,
        m["final_orientation_error_rad"] / criteria.orientation_tolerance_rad,
    ]
    if criteria.torque_threshold_Nm is not None:
        ratios.append(m["largest_peak_torque_Nm"] / criteria.torque_threshold_Nm)
    if "final_target_speed_mps" in m:
        ratios.append(m["final_target_speed_mps"] / criteria.target_speed_limit_mps)
    excess = m["max_range_excess_rad"]  # (..., N), NaN for a joint without a range
    furthest = jnp.max(jnp.where(jnp.isnan(excess), -jnp.inf, excess), axis=-1)  # -inf: no ranges, never the max
    ratios.append(jnp.exp(jnp.minimum(furthest / joint_limits.RANGE_MARGIN_SCALE_RAD, 50.0)))
    if criteria.joint_rate_limits_radps is not None:
        ratios.append(jnp.max(m["max_joint_rate_radps"] / jnp.asarray(criteria.joint_rate_limits_radps), axis=-1))
    margin = 1.0 - jnp.max(jnp.stack(ratios), axis=0)
    lost = jnp.isfinite(m["first_runaway_s"]) | jnp.isfinite(m["first_nonfinite_s"]) | ~jnp.isfinite(margin)
    return jnp.where(lost, LOST_MARGIN, jnp.maximum(margin, LOST_MARGIN))


@dataclasses.dataclass(frozen=True)
class CaptureLimitState:
    """The capture's margin over an envelope's standard space, as the reliability methods call
    it (``limit_state()``).

    Attributes:
        limit_state: the [`LimitState`][spacegrasp_jax.analysis.reliability.LimitState].
        space: the envelope's standard space.
        config: the campaign whose samples and criteria it follows (its ``seed``: the noise
            draws' and the Monte-Carlo samples').
        compile_s: seconds spent compiling its programs, by program.
    """

    limit_state: LimitState
    space: StandardSpace
    config: CampaignConfig
    compile_s: dict


def limit_state(
    robot: Robot,
    scenario: Scenario,
    gains,
    controller: str,
    config: CampaignConfig,
    *,
    block: int,
    gradient: bool = True,
) -> CaptureLimitState:
    """The capture's margin of ``gains`` (constant or a schedule) under the campaign
    ``config`` (its envelope, realism, criteria and seed), over the envelope's standard space
    (module docstring); compiles its programs now: a forward one of ``block`` points and, with
    ``gradient``, the margin's value and gradient at one point (a forward program of one point,
    for FORM's line search, on first use)."""
    joints = scenario.initial.q.shape[-1]
    space = StandardSpace.of(config.ranges, free_target=scenario.free_target, n_joints=joints)
    compile_s = {}
    programs = {}

    def forward_program(size: int):
        """The forward program of ``size`` points, compiled on first use."""
        if size not in programs:
            name = "forward" if size == block else "forward, one point"
            programs[size], compile_s[name] = worstcase.units_evaluator(
                robot, scenario, gains, controller, config, size, f"reliability, {name}"
            )
        return programs[size]

    def metrics_at(units, keys) -> dict:
        """The campaign metrics of points: a single one (FORM's line search) by the program of
        a point a device, more ``block`` at a time."""
        size = jax.device_count() if len(keys) == 1 else block  # one point a device, the others idle
        return _in_blocks(forward_program(size), units, keys, size)

    to_units = jax.jit(jax.vmap(space.to_units))
    criteria = config.criteria

    def outputs(sample_metrics: dict, keys: np.ndarray, z: np.ndarray | None = None) -> dict:
        g = np.asarray(capture_margin(sample_metrics, criteria), dtype=np.float64)
        failure = anatomy.failure_classes(sample_metrics, criteria)["failure"]
        result = {"g": g, "failure": failure.astype(str), "noise_key": np.asarray(keys, dtype=np.uint32)}
        return result if z is None else result | {"z": z}

    def evaluate(z: np.ndarray, keys: np.ndarray) -> dict:
        if space.dimension == 0:
            raise ValueError("the envelope draws nothing: its failure probability is 0 or 1")
        units = jax.tree.map(np.asarray, to_units(jnp.asarray(z)))
        return outputs(metrics_at(units, keys), keys)

    def values(z: np.ndarray, first: int) -> dict:
        return evaluate(z, worstcase.noise_keys(config.seed, range(first, first + len(z))))

    fixed_key = worstcase.noise_keys(config.seed, range(1))

    def fixed_values(z: np.ndarray) -> dict:
        return evaluate(z, np.repeat(fixed_key, len(z), axis=0))

    def campaign_values(start: int, stop: int) -> dict:
        indices = range(start, stop)
        units = worstcase.units_of_samples(config.seed, indices, n_joints=joints)
        keys = worstcase.noise_keys(config.seed, indices)
        return outputs(metrics_at(units, keys), keys, space.from_units(units))

    if space.dimension:
        forward_program(block)  # compiled now, not inside the first timed call
    value_and_gradient = None
    if gradient:
        gradient_program, gradient_s = _gradient_program(robot, scenario, gains, controller, config, space)
        compile_s["gradient"] = gradient_s

        def value_and_gradient(z: np.ndarray) -> dict:
            value, slope = gradient_program(jnp.asarray(z, dtype=jnp.float64), jnp.asarray(fixed_key[0]))
            metrics_like = {"g": np.asarray(value), "gradient": np.asarray(slope)}
            return metrics_like | {"noise_key": fixed_key[0]}

    state = LimitState(
        dimension=space.dimension,
        values=values,
        value_and_gradient=value_and_gradient,
        fixed_values=fixed_values,
        campaign_values=campaign_values,
        gradient_cost=GRADIENT_COST,
        names=space.names,
    )
    return CaptureLimitState(state, space, config, compile_s)


def _in_blocks(metrics_at, units, keys: np.ndarray, block: int) -> dict:
    """The campaign metrics of points ``units`` (leading axis n) and ``keys`` (n, 2), ``block``
    at a time."""
    parts = []
    for start in range(0, len(keys), block):
        piece = jax.tree.map(lambda x: x[start : start + block], units)
        parts.append(metrics_at(piece, keys[start : start + block]))
    return {name: np.concatenate([np.asarray(p[name]) for p in parts]) for name in parts[0]}


def _gradient_program(robot, scenario, gains, controller, config: CampaignConfig, space: StandardSpace):
    """``(program, compile_s)``: ``program(z (d,), key (2,)) -> (g, dg/dz)`` compiled."""
    variant = Variant(controller, gains)
    spec = variant_spec(robot, scenario, variant, dataclasses.replace(config, timeseries_every=None))
    spec = dataclasses.replace(spec, options=loop_options(checkpoint=True))
    margin = functools.partial(_margin_at, spec=spec, gains=gains, config=config, space=space)
    started = time.perf_counter()
    z = jnp.zeros(space.dimension, dtype=jnp.float64)
    key = jnp.zeros(2, dtype=jnp.uint32)
    program = compilation.jit(jax.value_and_grad(margin)).lower(z, key).compile()
    return program, time.perf_counter() - started


def _margin_at(z, key, *, spec, gains, config: CampaignConfig, space: StandardSpace):
    units = space.to_units(z)
    sample = perturbed_run(spec, from_units(units, config.ranges), config.ranges, config.identified)
    sample_metrics = closed_loop(sample, gains, key)[1][0]
    return capture_margin(sample_metrics, config.criteria)


__all__ = ["LOST_MARGIN", "CaptureLimitState", "capture_margin", "limit_state"]
