"""The classical Cartesian law of eqs 21-22: a proportional law on the pose error in LAR,
mapped to joint rates through the pseudoinverse of ``J_dyn^(EE)``."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp

from spacegrasp_jax.core import spatial
from spacegrasp_jax.loop.control.admittance import pose_error
from spacegrasp_jax.loop.control.groups import GainGroup, group, groups_of
from spacegrasp_jax.loop.control.law import ControlInputs, Output
from spacegrasp_jax.loop.control.pseudoinverse import PINV_DAMPING, pseudoinverse_apply


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class CartesianGains:
    """The Cartesian law's gains (diagonals; defaults: section 4's).

    Attributes:
        K_lin: (3,) 1/s, the position gain (3).
        K_eul: (3,) 1/s, the Euler-angle gain (3).
        pinv_damping: (1,) the pseudoinverse's damping (0: exact, eq 21).
    """

    K_lin: jax.Array = group(
        GainGroup(3, "1/s", "Cartesian law's position gain K_lin, diagonal", "eqs (21), (22)", default=3.0)
    )
    K_eul: jax.Array = group(
        GainGroup(3, "1/s", "Cartesian law's Euler-angle gain K_eul, diagonal", "eqs (21), (22)", default=3.0)
    )
    pinv_damping: jax.Array = group(PINV_DAMPING)


def desired_joint_rates(
    gains: CartesianGains, J_dyn_ee: jax.Array, R_lar_ee: jax.Array, pose, pose_des, frame_twist, damping=0.0
) -> jax.Array:
    """Eqs 21-22: ``qd_des`` (N,) rad/s.

    The position error (LAR) times ``K_lin`` is a velocity command rotated into the EE frame
    by ``R_ee_lar``. The Euler-angle error times ``K_eul`` is an Euler-rate command, which
    ``T_eul`` (eq 10) turns into an angular velocity in the EE frame. (Eq 22 writes
    ``R_LAR^EE T_eul``; with eq 10's ``T_eul``, which already yields EE-frame rates, the extra
    rotation would apply twice, so the command is ``T_eul K_eul e``; documentation, modelling notes.)

    Args:
        J_dyn_ee: (6, N) Dynamic Jacobian in the EE frame. R_lar_ee: (3, 3) EE to LAR.
        pose, pose_des: (6,) ``[p (m); roll, pitch, yaw (rad)]`` of the EE in LAR.
        frame_twist: (6,) the moving LAR frame's twist at the EE point, LAR axes, added to
            the command (zeros for the paper's fixed target).
    """
    error = pose_error(pose_des, pose)
    v_ee = spatial.matvec(R_lar_ee.T, gains.K_lin * error[:3])
    w_ee = spatial.matvec(spatial.euler_rates_to_body(pose[3:]), gains.K_eul * error[3:])
    command = jnp.concatenate([v_ee, w_ee])
    command = command + spatial.matvec(R_lar_ee.T, frame_twist.reshape(2, 3)).reshape(6)
    return pseudoinverse_apply(J_dyn_ee, command, damping)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class CartesianState:
    """The Cartesian law is memoryless: its state has no field."""


@dataclasses.dataclass(frozen=True)
class Cartesian:
    """The Cartesian law as a controller (eqs 21-22): the paper's "classical Cartesian
    control"; it commands joint rates to the joint PID.

    Attributes:
        pinv_damping: damping of the pseudoinverse (0: exact, the paper; static), added to
            the gains' own ``pinv_damping``.
    """

    pinv_damping: float = 0.0
    name: ClassVar[str] = "cartesian"
    title: ClassVar[str] = "Cartesian control"
    output: ClassVar[Output] = Output.JOINT_RATES
    gains_type: ClassVar[type] = CartesianGains
    gain_groups: ClassVar[tuple[str, ...]] = tuple(groups_of(CartesianGains))
    loop_gain: ClassVar[dict[str, int]] = {"K_lin": 1, "K_eul": 1}
    style: ClassVar[dict[str, str]] = dict(color="tab:red", linestyle=":", label="Cartesian control")
    #: Table 5 (section 5), joints 1-7.
    paper_max_abs_torque_Nm: ClassVar[tuple[float, ...]] = (1.89, 4.21, 2.72, 0.72, 1.55, 0.35, 0.027)

    def init(self, n_joints: int = 7, dtype=jnp.float64) -> CartesianState:
        return CartesianState()

    def update(
        self, gains: CartesianGains, inputs: ControlInputs, state: CartesianState, dt
    ) -> tuple[jax.Array, CartesianState]:
        """``(qd_des (N,) rad/s, state)`` from the pose error (``dt`` unused)."""
        qd_des = desired_joint_rates(
            gains,
            inputs.J_dyn_ee,
            inputs.R_lar_ee,
            inputs.pose,
            inputs.pose_des,
            inputs.frame_twist,
            self.pinv_damping + gains.pinv_damping[0],
        )
        return qd_des, state

    def log_fields(self, state: CartesianState) -> dict[str, jax.Array]:
        """The Cartesian law has no reference twist (the log's ``V_ref`` holds zeros)."""
        return {}
