"""Hand-made rollout logs for the tests of the measures built on them."""

from __future__ import annotations

import numpy as np

from spacegrasp_jax.loop.simulate import Log

#: The widths of a log's required fields (``t`` aside).
WIDTHS = dict(
    pose_ee=6,
    pose_des=6,
    twist_ee=6,
    contact_force=3,
    momentum=6,
    V_base=6,
    u=7,
    fts_force=3,
    fts_torque=3,
    V_ref=6,
    qd_des=7,
    q=7,
    qd=7,
    target_position=3,
    target_quat=4,
    target_velocity=3,
    target_angular_velocity=3,
    momentum_total=6,
)


def log_of(t, **fields) -> Log:
    """A log at the times ``t`` (N,), every required field zeros unless given (the target's
    attitude: the identity)."""
    n = len(t)
    defaults = {name: np.zeros((n, width)) for name, width in WIDTHS.items()}
    defaults["target_quat"] = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    return Log(t=t, **(defaults | fields))
