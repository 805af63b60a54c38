"""Cartesian impedance through the Dynamic Jacobian's transpose: a law that commands joint
torques, with no joint servo after it.

The EE is pulled towards the desired trajectory by a virtual spring and damper ``(Kd, Bd)``
(the same diagonal gains as the admittance law's desired stiffness and damping), and the
joint torques that exert that virtual wrench are the Dynamic Jacobian's transpose times it:

    F_cmd = Kd e + Bd (twist_des - twist)        (LAR axes; e: pose_error(pose_des, pose))
    u = J_dyn^(EE)^T blockdiag(R_ee_lar, R_ee_lar) F_cmd

Because ``J_dyn`` maps joint rates to the EE twist of the free-floating system at zero
momentum, the torques' power equals the virtual wrench's, ``u . qd = F_cmd . twist``: the
generalised Jacobian transpose of Yoshida and Umetani, the torque-level counterpart of the
paper's pseudoinverse laws. The contact wrench is not fed back: the compliance is the
spring's own. The orientation rows pair ``[roll, pitch, yaw]`` errors with the angular
velocity, as eq 14 does (modelling notes).
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp

from spacegrasp_jax.core import spatial
from spacegrasp_jax.loop.control.admittance import DESIRED_DAMPING, DESIRED_STIFFNESS, pose_error
from spacegrasp_jax.loop.control.groups import group, groups_of
from spacegrasp_jax.loop.control.law import ControlInputs, Output


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ImpedanceGains:
    """The impedance law's gains: the admittance law's desired damping and stiffness groups
    (diagonals; the paper's values are for the admittance law, not this one).

    Attributes:
        Bd: (6,) N s/m, N m s/rad, the virtual damper.
        Kd: (6,) N/m, N m/rad, the virtual spring.
    """

    Bd: jax.Array = group(DESIRED_DAMPING)
    Kd: jax.Array = group(DESIRED_STIFFNESS)


def virtual_wrench(gains: ImpedanceGains, pose, twist, pose_des, twist_des) -> jax.Array:
    """``F_cmd = Kd e + Bd (twist_des - twist)`` (6,) ``[f (N); n (N m)]``, LAR axes.

    Args:
        pose, pose_des: (6,) ``[p (m); roll, pitch, yaw (rad)]`` of the EE in LAR.
        twist, twist_des: (6,) ``[v (m/s); w (rad/s)]`` in LAR.
    """
    return gains.Kd * pose_error(pose_des, pose) + gains.Bd * (twist_des - twist)


def joint_torques(J_dyn_ee: jax.Array, R_lar_ee: jax.Array, wrench_lar: jax.Array) -> jax.Array:
    """``u = J_dyn^(EE)^T blockdiag(R_ee_lar, R_ee_lar) wrench`` (N,) N m.

    Args:
        J_dyn_ee: (6, N) Dynamic Jacobian in the EE frame. R_lar_ee: (3, 3) EE to LAR.
        wrench_lar: (6,) ``[f (N); n (N m)]``, LAR axes.
    """
    wrench_ee = spatial.matvec(R_lar_ee.T, wrench_lar.reshape(2, 3)).reshape(6)
    return J_dyn_ee.T @ wrench_ee


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ImpedanceState:
    """The impedance law is memoryless: its state has no field."""


@dataclasses.dataclass(frozen=True)
class Impedance:
    """Cartesian impedance by the Dynamic Jacobian's transpose, commanding joint torques."""

    name: ClassVar[str] = "impedance"
    title: ClassVar[str] = "impedance control"
    output: ClassVar[Output] = Output.JOINT_TORQUES
    gains_type: ClassVar[type] = ImpedanceGains
    gain_groups: ClassVar[tuple[str, ...]] = tuple(groups_of(ImpedanceGains))
    loop_gain: ClassVar[dict[str, int]] = {"Bd": 1, "Kd": 1}
    style: ClassVar[dict[str, str]] = dict(color="tab:purple", linestyle="-.", label="impedance control")
    paper_max_abs_torque_Nm: ClassVar[None] = None

    def init(self, n_joints: int = 7, dtype=jnp.float64) -> ImpedanceState:
        return ImpedanceState()

    def update(
        self, gains: ImpedanceGains, inputs: ControlInputs, state: ImpedanceState, dt
    ) -> tuple[jax.Array, ImpedanceState]:
        """``(u (N,) N m, state)`` from the pose and twist errors (``dt`` unused)."""
        wrench = virtual_wrench(gains, inputs.pose, inputs.twist, inputs.pose_des, inputs.twist_des)
        return joint_torques(inputs.J_dyn_ee, inputs.R_lar_ee, wrench), state

    def log_fields(self, state: ImpedanceState) -> dict[str, jax.Array]:
        """No field of its own (the log's ``V_ref`` and ``qd_des`` hold zeros)."""
        return {}
