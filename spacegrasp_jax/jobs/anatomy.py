"""Why a capture fails: which success criterion a run missed and by how much, and what set
its final position error.

The final position error ``e`` (EE minus desired, LAR axes; ``z`` is the approach axis) is
split into three parts that add up to it:

* ``estimate``: where the controller's wrong idea of the LAR frame puts the EE. It drives
  the EE to the desired point ``p_des`` of the frame it believes, ``p_hat = p + R dp`` and
  ``R_hat = R exp(dr)`` (``dp``, ``dr``: the estimate's position and rotation-vector
  errors in LAR axes), which lies at ``dp + exp(dr) p_des`` in the true frame: an offset of
  ``dp + (exp(dr) - I) p_des``.
* ``compliance``: how far the law has pressed the EE into the contact sphere. With the
  contact force ``F`` (eq 20, on the EE), the penetration is ``|F| r^3 / k`` along the
  sphere's inward normal, i.e. ``-F r^3 / k``. The desired point lies on the sphere's
  surface, so a law that holds a force pushes the EE off it by exactly this much.
* ``residual``: the rest, ``e - estimate - compliance``: the controller's own error
  (integrator state, oscillation, drift of the base, what the model got wrong).

Those are jnp functions of a run's final metrics, computed where the scenario and the
realism are known (inside a campaign's compiled program and in a single run's summary). The
classification of failures ([`failure_classes()`][spacegrasp_jax.jobs.anatomy.failure_classes]) is NumPy, on the host.
"""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax.core import spatial
from spacegrasp_jax.envelope.criteria import CaptureCriteria
from spacegrasp_jax.loop.realism import Stage

#: The parts of the final position error: name -> (shape, unit, meaning).
ANATOMY_METRICS = {
    "estimate_offset_lar_m": ((3,), "m", "final EE offset set by the controller's LAR estimate error, LAR axes"),
    "compliance_offset_lar_m": ((3,), "m", "final EE offset set by the contact's compliance (-F r^3 / k), LAR axes"),
}


def error_parts(final_metrics: dict, scenario, realism=None) -> dict[str, jax.Array]:
    """The ``ANATOMY_METRICS`` of one run (jnp; vmaps).

    Args:
        final_metrics: the run's metrics (``spacegrasp_jax.envelope.metrics.finish``), for
            ``final_contact_force_N`` (3,) N, LAR axes.
        scenario: the run's [`Scenario`][spacegrasp_jax.envelope.scenario.Scenario] (sphere radius and
            stiffness, the held desired pose ``trajectory.end_pose``).
        realism: the run's [`Realism`][spacegrasp_jax.loop.realism.Realism]; its LAR estimate error
            counts when its ``Stage.ESTIMATE`` is on (``None``: the paper's loop, none).
    """
    force = jnp.asarray(final_metrics["final_contact_force_N"])
    compliance = -force * scenario.sphere_radius**3 / scenario.contact_stiffness
    p_des = scenario.trajectory.end_pose[:3]
    if realism is not None and Stage.ESTIMATE in realism.stages:
        rotation = spatial.rotation_exp(realism.lar_angle_error_rad)
        estimate = realism.lar_position_error_m + spatial.matvec(rotation, p_des) - p_des
    else:
        estimate = jnp.zeros_like(compliance)
    return {"estimate_offset_lar_m": estimate, "compliance_offset_lar_m": compliance}


# ---- on the host ------------------------------------------------------------------------

#: The failure classes, in the order a failed sample is assigned to the first that applies.
#: ``joint_range``: a joint left its range (a robot without ranges, the paper's, never does);
#: ``joint_rate``: a joint turned faster than its rate limit, where the rate limits are criteria
#: (a robot file's own; the paper's arm's assumed limits only detect runaways).
FAILURE_CLASSES = (
    "diverged",
    "runaway",
    "joint_range",
    "joint_rate",
    "torque_threshold",
    "position",
    "orientation",
    "target_speed",
)


def failure_classes(sample_metrics: dict, criteria: CaptureCriteria) -> dict[str, np.ndarray]:
    """Which of ``criteria`` each sample missed and by how much (NumPy). A criterion that
    does not apply is not missed: no torque threshold, a fixed target (``sample_metrics``
    without ``final_target_speed_mps``), no rate limits (else the samples'
    ``max_joint_rate_radps``, (n, N), against them).

    Returns:
        ``failed_<class>`` (n,) bool for each of ``FAILURE_CLASSES`` (a sample can miss
        several); ``failure`` (n,) str, the first class it missed or ``"success"``; and
        the margins, each a value over its tolerance (above 1: missed):
        ``position_margin``, ``orientation_margin``, ``torque_margin`` (largest peak over
        the torque threshold; NaN without one), ``target_speed_margin`` (NaN without a
        free-floating target); and ``range_excess_rad``, the furthest any joint went beyond
        its range (rad; above 0: missed; NaN for a robot without ranges); and
        ``joint_rate_margin``, the largest peak joint rate over its limit (NaN without rate
        limits).
    """
    position = np.asarray(sample_metrics["final_position_error_m"], dtype=float)
    n = position.size
    orientation = np.asarray(sample_metrics["final_orientation_error_rad"], dtype=float)
    peak = np.asarray(sample_metrics["largest_peak_torque_Nm"], dtype=float)
    nan = np.full(n, np.nan)
    margins = {
        "position_margin": position / criteria.position_tolerance_m,
        "orientation_margin": orientation / criteria.orientation_tolerance_rad,
        "torque_margin": peak / criteria.torque_threshold_Nm if criteria.torque_threshold_Nm is not None else nan,
        "target_speed_margin": (
            np.asarray(sample_metrics["final_target_speed_mps"], dtype=float) / criteria.target_speed_limit_mps
            if "final_target_speed_mps" in sample_metrics
            else nan
        ),
    }
    diverged = np.isfinite(np.asarray(sample_metrics["first_nonfinite_s"], dtype=float))
    runaway = np.isfinite(np.asarray(sample_metrics.get("first_runaway_s", nan), dtype=float))
    excess = np.asarray(sample_metrics.get("max_range_excess_rad", nan), dtype=float).reshape(n, -1)
    with warnings.catch_warnings():  # a robot without ranges: every joint's excess is NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        range_excess = np.nanmax(excess, axis=1) if excess.size else nan
    rate_margin = nan
    if criteria.joint_rate_limits_radps is not None:
        rates = np.asarray(sample_metrics["max_joint_rate_radps"], dtype=float).reshape(n, -1)
        rate_margin = np.max(rates / np.asarray(criteria.joint_rate_limits_radps, dtype=float), axis=1)
    with np.errstate(invalid="ignore"):
        failed = {
            "diverged": diverged,
            "runaway": runaway & ~diverged,
            "joint_range": range_excess > 0.0,
            "joint_rate": rate_margin > 1.0,
            "torque_threshold": margins["torque_margin"] > 1.0,
            # A NaN error (diverged) is no position failure of its own.
            "position": margins["position_margin"] > 1.0,
            "orientation": margins["orientation_margin"] > 1.0,
            "target_speed": margins["target_speed_margin"] > 1.0,
        }
    failure = np.full(n, "success", dtype=object)
    for name in reversed(FAILURE_CLASSES):
        failure[failed[name]] = name
    margins["range_excess_rad"] = range_excess
    margins["joint_rate_margin"] = rate_margin
    return {f"failed_{name}": failed[name] for name in FAILURE_CLASSES} | {"failure": failure.astype(str)} | margins


def error_decomposition(sample_metrics: dict) -> dict[str, np.ndarray]:
    """The final position error of each sample split as the module docstring says (NumPy):
    ``along_m`` (signed, the approach axis LAR z) and ``across_m`` (its distance from that
    axis), and the norms ``estimate_m``, ``compliance_m``, ``residual_m`` of the three
    parts, all (n,) m and named ``final_error_<part>``. Without the parts in
    ``sample_metrics`` they are NaN."""
    if "final_position_error_lar_m" in sample_metrics:
        error = np.asarray(sample_metrics["final_position_error_lar_m"], float).reshape(-1, 3)
    else:
        error = np.full((np.size(sample_metrics["final_position_error_m"]), 3), np.nan)
    n = error.shape[0]
    estimate = np.asarray(sample_metrics.get("estimate_offset_lar_m", np.full((n, 3), np.nan)), float).reshape(-1, 3)
    compliance = np.asarray(sample_metrics.get("compliance_offset_lar_m", np.full((n, 3), np.nan)), float)
    compliance = compliance.reshape(-1, 3)
    return {
        "final_error_along_m": error[:, 2],
        "final_error_across_m": np.hypot(error[:, 0], error[:, 1]),
        "final_error_estimate_m": np.linalg.norm(estimate, axis=1),
        "final_error_compliance_m": np.linalg.norm(compliance, axis=1),
        "final_error_residual_m": np.linalg.norm(error - estimate - compliance, axis=1),
    }


def anatomy_summary(sample_metrics: dict) -> dict:
    """A campaign variant's failures: the count of each class (first missed and any
    missed), and the medians of the error decomposition over every sample and over the
    position failures (m). ``sample_metrics`` holds the metrics and their
    [`failure_classes()`][spacegrasp_jax.jobs.anatomy.failure_classes]."""
    classes = sample_metrics
    parts = error_decomposition(sample_metrics)
    position_failures = classes["failed_position"]

    def medians(selection):
        if not np.any(selection):  # nothing to take a median of
            return None
        chosen = {name.removeprefix("final_error_"): np.abs(values[selection]) for name, values in parts.items()}
        return {
            name: float(np.median(v[np.isfinite(v)])) if np.isfinite(v).any() else None for name, v in chosen.items()
        }

    finite = np.isfinite(parts["final_error_along_m"])
    return {
        "first_failure": {name: int(np.sum(classes["failure"] == name)) for name in ("success", *FAILURE_CLASSES)},
        "any_failure": {name: int(np.sum(classes[f"failed_{name}"])) for name in FAILURE_CLASSES},
        "error_parts_median_m": medians(finite),
        "error_parts_median_m_position_failures": medians(position_failures & finite),
    }


def verdict_line(summary: dict, classes: dict[str, np.ndarray], criteria: CaptureCriteria) -> str | None:
    """One line for a single run that failed its capture (``None`` if it succeeded): the
    class, the numbers that decided it and the error's parts. ``summary``: the run's
    summary.json (metrics as floats and lists); ``classes``: [`failure_classes()`][spacegrasp_jax.jobs.anatomy.failure_classes] of it
    as a one-sample batch by ``criteria``."""
    failure = str(classes["failure"][0])
    if failure == "success":
        return None
    missed = [name for name in FAILURE_CLASSES if classes[f"failed_{name}"][0]]
    numbers = []
    if "runaway" in missed or "diverged" in missed:
        when = summary.get("first_runaway_s") if "runaway" in missed else summary.get("first_nonfinite_s")
        numbers.append(
            f"at t = {when:.2f} s, peak joint rate {max(summary['max_joint_rate_radps']):.3g} rad/s, "
            f"peak torque {summary['largest_peak_torque_Nm']:.3g} N m"
        )
    if "joint_range" in missed:
        excess = np.asarray(summary["max_range_excess_rad"], dtype=float)
        joint = int(np.nanargmax(excess))
        numbers.append(
            f"joint {joint + 1} went {excess[joint]:.3g} rad beyond its range"
            + (
                f" (first left at t = {summary['first_range_exit_s']:.2f} s)"
                if summary.get("first_range_exit_s")
                else ""
            )
        )
    if "joint_rate" in missed and "runaway" not in missed:
        rates = np.asarray(summary["max_joint_rate_radps"], dtype=float)
        limits = np.asarray(criteria.joint_rate_limits_radps, dtype=float)
        joint = int(np.argmax(rates / limits))
        numbers.append(f"joint {joint + 1} turned at {rates[joint]:.3g} rad/s > its limit {limits[joint]:g}")
    if "torque_threshold" in missed and "runaway" not in missed:
        numbers.append(
            f"peak torque {summary['largest_peak_torque_Nm']:.3g} N m > the threshold {criteria.torque_threshold_Nm:g}"
        )
    if "position" in missed:
        parts = error_decomposition(
            {
                name: np.asarray([value])
                for name, value in summary.items()
                if name in ("final_position_error_lar_m", *ANATOMY_METRICS)
            }
        )
        numbers.append(
            f"final position error {1e3 * summary['final_position_error_m']:.2f} mm > "
            f"{1e3 * criteria.position_tolerance_m:g} (along the approach {1e3 * parts['final_error_along_m'][0]:+.2f}, "
            f"across {1e3 * parts['final_error_across_m'][0]:.2f}; estimate {1e3 * parts['final_error_estimate_m'][0]:.2f}, "
            f"compliance {1e3 * parts['final_error_compliance_m'][0]:.2f}, residual {1e3 * parts['final_error_residual_m'][0]:.2f})"
        )
    if "orientation" in missed:
        numbers.append(
            f"final orientation error {np.degrees(summary['final_orientation_error_rad']):.2f} deg > "
            f"{np.degrees(criteria.orientation_tolerance_rad):g}"
        )
    if "target_speed" in missed:
        numbers.append(
            f"target pushed to {1e3 * summary['final_target_speed_mps']:.2f} mm/s > "
            f"{1e3 * criteria.target_speed_limit_mps:g}"
        )
    return f"capture failed ({failure}): " + "; ".join(numbers)


__all__ = [
    "ANATOMY_METRICS",
    "FAILURE_CLASSES",
    "anatomy_summary",
    "error_decomposition",
    "error_parts",
    "failure_classes",
    "verdict_line",
]
