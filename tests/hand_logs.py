"""Hand-made rollout logs for the tests of the measures built on them."""

from __future__ import annotations

import numpy as np

from spacegrasp_jax.simulate import Log

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
)


def log_of(t, **fields) -> Log:
    """A log at the times ``t`` (N,), every required field zeros unless given."""
    n = len(t)
    return Log(t=t, **{name: fields.get(name, np.zeros((n, width))) for name, width in WIDTHS.items()})
