"""What every controller reads, and how a law is chosen.

A law is a small frozen object with ``init(dtype) -> state`` and
``update(gains, inputs, state, dt) -> (qd_des, state)`` (optax's and diffrax's style): the
object fixes the program (it is static, hashable, a ``jit`` static argument), its state is a
pytree the closed loop carries. [`Admittance`][spacegrasp_jax.control.admittance.Admittance] and
[`Cartesian`][spacegrasp_jax.control.cartesian.Cartesian] are the two laws; the joint PID stage
([`PID`][spacegrasp_jax.control.pid.PID]) turns their desired joint rates into torques.
"""

from __future__ import annotations

import dataclasses

import jax


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ControlInputs:
    """What the controller reads at one update, all in the LAR frame unless said otherwise.

    Attributes:
        pose: (6,) EE pose ``[p (m); roll, pitch, yaw (rad)]``.
        twist: (6,) EE twist ``[v (m/s); w (rad/s)]``.
        wrench: (6,) ``[f (N); n (N m)]`` the contact exerts on the EE, about the EE point
            (eqs 18-19).
        pose_des, twist_des, twist_rate_des: (6,) the desired trajectory and its first two
            derivatives (eqs 10-13).
        J_dyn_ee: (6, 7) the Dynamic Jacobian in the EE frame (eq 8).
        R_lar_ee: (3, 3) EE to LAR rotation.
        frame_twist: (6,) the moving LAR frame's twist at the EE point ``[v (m/s); w
            (rad/s)]``, LAR axes, which the laws add to their commanded twist (the EE's
            inertial twist is the relative one plus this); ``None`` for a stationary target.
    """

    pose: jax.Array
    twist: jax.Array
    wrench: jax.Array
    pose_des: jax.Array
    twist_des: jax.Array
    twist_rate_des: jax.Array
    J_dyn_ee: jax.Array
    R_lar_ee: jax.Array
    frame_twist: jax.Array | None = None


def law_named(name: str, pinv_damping: float = 0.0):
    """The law called ``name`` (``"admittance"`` or ``"cartesian"``) with the pseudoinverse's
    damping ``pinv_damping`` (0: exact, the paper)."""
    from spacegrasp_jax.control.admittance import Admittance
    from spacegrasp_jax.control.cartesian import Cartesian

    laws = {"admittance": Admittance, "cartesian": Cartesian}
    if name not in laws:
        raise ValueError(f"controller: expected one of {', '.join(laws)}, got {name!r}")
    return laws[name](pinv_damping=pinv_damping)


__all__ = ["ControlInputs", "law_named"]
