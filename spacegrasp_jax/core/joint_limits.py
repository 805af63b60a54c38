"""Joint ranges and rate limits: the starting angles checked against them, and the first time a
run crosses them.

A robot's ranges (``Robot.joint_position_limit``, rad) and rate limits
(``Robot.joint_rate_limit``, rad/s) come from its URDF (``<limit lower upper velocity>``) or
its robot TOML (``[limits]``); the paper's arm has no ranges (``-inf, inf``) and rate limits
of 1 rad/s, which none of its runs reaches. They are not constraints of the dynamics: a joint
driven past its range keeps turning, as the simulated motor is told to, and what a real arm's
end stop or its drive's safety would do there is outside the model. So a run says when and
where it first crossed them, a capture that started outside them is refused, a joint out of
its range fails the capture, and so does a joint faster than a rate limit the robot's file
states ([`rate_criterion()`][spacegrasp_jax.core.joint_limits.rate_criterion]; the paper's arm's
are assumed and only detect runaways).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from spacegrasp_jax.core.model import Robot

#: The scale of a joint range's margin, rad: a joint at its limit has margin 1, one this far
#: beyond it ``e``, one this far inside ``1 / e`` (about 3 degrees).
RANGE_MARGIN_SCALE_RAD = 0.05
#: The largest log margin a range reports: a joint 2.5 rad beyond its range (a runaway) weighs
#: like one 2.5 rad beyond, not like a number that overflows.
_MAX_LOG_MARGIN = 50.0


def rate_criterion(limits) -> tuple[float, ...] | None:
    """Rate limits as a success criterion, checked: ``None`` (no criterion) or (N,) positive
    finite numbers, rad/s, returned as a tuple of floats (a setting's static, hashable form).

    Raises:
        ValueError: anything else, with the value.
    """
    if limits is None:
        return None
    if not (
        isinstance(limits, (tuple, list))
        and limits
        and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x > 0.0 for x in limits
        )
    ):
        raise ValueError(f"must be positive finite numbers (rad/s, one a joint) or None, got {limits!r}")
    return tuple(float(x) for x in limits)


def finite_ranges(robot: Robot) -> tuple[tuple[int, float, float], ...]:
    """``(joint index, low, high)`` rad of each joint of ``robot`` with a range (a finite
    bound), as static numbers for a compiled program (empty for the paper's arm)."""
    limits = np.asarray(robot.joint_position_limit, dtype=np.float64)
    return tuple(
        (int(i), float(low), float(high)) for i, (low, high) in enumerate(limits) if np.isfinite([low, high]).any()
    )


def range_excess(q, ranges: tuple[tuple[int, float, float], ...]):
    """(T, k) rad, how far each ranged joint of ``ranges`` is beyond its range at each row of
    ``q`` (T, N) rad: ``max(low - q, q - high)``, negative inside (jnp; differentiable)."""
    index = np.asarray([joint for joint, _, _ in ranges])
    low = jnp.asarray([low for _, low, _ in ranges])
    high = jnp.asarray([high for _, _, high in ranges])
    angles = jnp.asarray(q)[:, index]
    return jnp.maximum(low - angles, angles - high)


def range_margin(q, ranges: tuple[tuple[int, float, float], ...], temperature: float):
    """() The joint ranges' margin of a run, like the other success criteria's (above 1: a
    joint left its range): ``exp(smoothmax_{t, i} excess_i(t) / RANGE_MARGIN_SCALE_RAD)``
    with ``excess_i = max(low_i - q_i, q_i - high_i)`` (rad, negative inside), the smooth
    maximum of temperature ``temperature`` over the log's rows and the ranged joints.

    Args:
        q: (T, N) rad, the log's joint angles. ranges: [`finite_ranges()`][spacegrasp_jax.core.joint_limits.finite_ranges].
    """
    excess = range_excess(q, ranges) / RANGE_MARGIN_SCALE_RAD
    smooth = temperature * jnp.log(jnp.sum(jnp.exp((excess - jnp.max(excess)) / temperature))) + jnp.max(excess)
    return jnp.exp(jnp.minimum(smooth, _MAX_LOG_MARGIN))


def outside_ranges(robot: Robot, q) -> list[dict]:
    """The joints of ``q`` (N,) rad outside ``robot``'s ranges: for each, ``{"joint"``
    (1-based)``, "angle_rad", "range_rad"}``; empty when every joint is inside (or on) its range."""
    q = np.asarray(q, dtype=np.float64)
    limits = np.asarray(robot.joint_position_limit, dtype=np.float64)
    return [
        {"joint": int(i) + 1, "angle_rad": float(q[i]), "range_rad": limits[i].tolist()}
        for i in np.flatnonzero((q < limits[:, 0]) | (q > limits[:, 1]))
    ]


def first_crossings(t, q, qd, robot: Robot) -> dict:
    """When a run first left a joint's range and first exceeded a joint's rate limit.

    Args:
        t: (T,) s, the log's times. q: (T, N) rad. qd: (T, N) rad/s.
        robot: the robot whose limits apply (the plant's).

    Returns:
        ``{"position": ..., "rate": ...}``, each ``None`` (never crossed) or ``{"t_s", "joint"``
        (1-based, the first joint to cross at that step)``, "value"`` (rad or rad/s)``, "limit"``
        (the range, or the rate limit)``, "joints"`` (every joint that crossed at some point,
        1-based)``, "worst"`` (the largest excursion beyond a limit, rad or rad/s)``}``. Only
        finite steps count.
    """
    t = np.asarray(t, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    qd = np.asarray(qd, dtype=np.float64)
    ranges = np.asarray(robot.joint_position_limit, dtype=np.float64)
    rate_limit = np.asarray(robot.joint_rate_limit, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        below, above = ranges[:, 0] - q, q - ranges[:, 1]
        position_excess = np.where(np.isfinite(q), np.maximum(below, above), -np.inf)
        rate_excess = np.where(np.isfinite(qd), np.abs(qd) - rate_limit, -np.inf)
    return {
        "position": _first(t, q, position_excess, lambda joint: ranges[joint].tolist()),
        "rate": _first(t, qd, rate_excess, lambda joint: float(rate_limit[joint])),
    }


def _first(t: np.ndarray, values: np.ndarray, excess: np.ndarray, limit) -> dict | None:
    crossed = excess > 0.0
    if not crossed.any():
        return None
    step = int(np.argmax(crossed.any(axis=1)))
    joint = int(np.argmax(crossed[step]))
    return {
        "t_s": float(t[step]),
        "joint": joint + 1,
        "value": float(values[step, joint]),
        "limit": limit(joint),
        "joints": [int(j) + 1 for j in np.flatnonzero(crossed.any(axis=0))],
        "worst": float(np.max(excess[crossed])),
    }


def crossing_words(crossings: dict) -> list[str]:
    """``first_crossings()``'s result as sentences, one per kind of limit crossed."""
    words = []
    position = crossings.get("position")
    if position:
        low, high = position["limit"]
        words.append(
            f"joint {position['joint']} left its range [{low:.3f}, {high:.3f}] rad at t = {position['t_s']:.3f} s "
            f"({position['value']:.3f} rad; joints {_listed(position['joints'])} left theirs, by up to "
            f"{position['worst']:.3g} rad)"
        )
    rate = crossings.get("rate")
    if rate:
        words.append(
            f"joint {rate['joint']} exceeded its rate limit {rate['limit']:.3g} rad/s at t = {rate['t_s']:.3f} s "
            f"({rate['value']:.3g} rad/s; joints {_listed(rate['joints'])}, by up to {rate['worst']:.3g} rad/s)"
        )
    return words


def _listed(joints: list[int]) -> str:
    return ", ".join(str(joint) for joint in joints)
