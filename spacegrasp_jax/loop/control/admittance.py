"""The active 6-DoF force/torque (admittance) law of eqs 9-17.

The EE is made to behave as a mass-spring-damper ``(Md, Bd, Kd)`` around the desired
trajectory, driven by the external wrench measured at the EE (eq 9). Eq 14 gives the
reference twist rate, eq 15 integrates it (state ``V_ref``), eq 16 turns it into the EE frame
and eq 17 maps it to desired joint rates through the pseudoinverse of ``J_dyn^(EE)``.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp

from spacegrasp_jax.core import spatial
from spacegrasp_jax.loop.control.groups import GainGroup, group, groups_of
from spacegrasp_jax.loop.control.law import ControlInputs, Output
from spacegrasp_jax.loop.control.pseudoinverse import PINV_DAMPING, pseudoinverse_apply

# Eq 9's diagonal gains; the first three rows act on the position in the LAR frame, the last
# three on the ZYX Euler angles [roll, pitch, yaw]. Section 4 gives each the same value on
# all six axes.
DESIRED_INERTIA = GainGroup(
    6, "kg (x, y, z), kg m^2 (roll, pitch, yaw)", "desired inertia M_d, diagonal", "eqs (9), (14)", default=800.0
)
DESIRED_DAMPING = GainGroup(
    6, "N s/m (x, y, z), N m s/rad (roll, pitch, yaw)", "desired damping B_d, diagonal", "eqs (9), (14)", default=500.0
)
DESIRED_STIFFNESS = GainGroup(
    6, "N/m (x, y, z), N m/rad (roll, pitch, yaw)", "desired stiffness K_d, diagonal", "eqs (9), (14)", default=600.0
)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class AdmittanceGains:
    """The admittance law's gains (diagonals; defaults: section 4's).

    Attributes:
        Md: (6,) kg, kg m^2, the desired inertia (800).
        Bd: (6,) N s/m, N m s/rad, the desired damping (500).
        Kd: (6,) N/m, N m/rad, the desired stiffness (600).
        pinv_damping: (1,) the pseudoinverse's damping (0: exact, eq 17).
    """

    Md: jax.Array = group(DESIRED_INERTIA)
    Bd: jax.Array = group(DESIRED_DAMPING)
    Kd: jax.Array = group(DESIRED_STIFFNESS)
    pinv_damping: jax.Array = group(PINV_DAMPING)


def pose_error(pose_des: jax.Array, pose: jax.Array) -> jax.Array:
    """``pose_des - pose`` (6,) with the Euler-angle differences wrapped to (-pi, pi]."""
    position, angles = jnp.split(pose_des - pose, 2)
    return jnp.concatenate([position, jnp.arctan2(jnp.sin(angles), jnp.cos(angles))])


def reference_twist_rate(
    gains: AdmittanceGains, pose, twist, pose_des, twist_des, twist_rate_des, wrench_lar
) -> jax.Array:
    """Eq 14: the reference twist rate ``dV_ref/dt`` (6,) in the LAR frame.

    Args:
        pose, pose_des: (6,) ``[p (m); roll, pitch, yaw (rad)]`` of the EE in LAR.
        twist, twist_des: (6,) ``[v (m/s); w (rad/s)]`` in LAR; the orientation rows pair
            ``[roll, pitch, yaw]`` errors with ``[w_x, w_y, w_z]`` (modelling notes).
        twist_rate_des: (6,) desired ``[a; dw/dt]`` in LAR.
        wrench_lar: (6,) ``[f (N); n (N m)]`` the contact exerts on the EE, LAR axes.
    """
    restoring = wrench_lar + gains.Bd * (twist_des - twist) + gains.Kd * pose_error(pose_des, pose)
    return twist_rate_des + restoring / gains.Md


def desired_joint_rates(J_dyn_ee: jax.Array, R_lar_ee: jax.Array, V_ref_lar: jax.Array, damping=0.0) -> jax.Array:
    """Eqs 16-17: ``qd_des = (J_dyn^(EE))^# blockdiag(R_ee_lar, R_ee_lar) V_ref`` (N,) rad/s.

    Args:
        J_dyn_ee: (6, N) Dynamic Jacobian in the EE frame.
        R_lar_ee: (3, 3) EE to LAR rotation.
        V_ref_lar: (6,) reference twist in LAR.
    """
    V_ref_ee = spatial.matvec(R_lar_ee.T, V_ref_lar.reshape(2, 3)).reshape(6)
    return pseudoinverse_apply(J_dyn_ee, V_ref_ee, damping)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class AdmittanceState:
    """The admittance law's state.

    Attributes:
        V_ref: (6,) reference EE twist in LAR, the integrator of eq 15 (``V_ref(0) = 0``).
    """

    V_ref: jax.Array


@dataclasses.dataclass(frozen=True)
class Admittance:
    """The admittance law as a controller (eqs 9-17): the paper's "active 6 DoF force/torque
    control"; it commands joint rates to the joint PID.

    Attributes:
        pinv_damping: damping of the pseudoinverse (0: exact, the paper; static), added to
            the gains' own ``pinv_damping``.
    """

    pinv_damping: float = 0.0
    name: ClassVar[str] = "admittance"
    title: ClassVar[str] = "admittance control"
    output: ClassVar[Output] = Output.JOINT_RATES
    gains_type: ClassVar[type] = AdmittanceGains
    gain_groups: ClassVar[tuple[str, ...]] = tuple(groups_of(AdmittanceGains))
    # A larger Md, Bd or Kd makes the EE follow the wrench and the error more slowly.
    loop_gain: ClassVar[dict[str, int]] = {"Md": -1, "Bd": -1, "Kd": -1}
    style: ClassVar[dict[str, str]] = dict(color="tab:blue", linestyle="--", label="admittance control")
    #: Table 5 (section 5), joints 1-7.
    paper_max_abs_torque_Nm: ClassVar[tuple[float, ...]] = (1.50, 2.45, 1.68, 0.86, 1.10, 0.17, 0.036)

    def init(self, n_joints: int = 7, dtype=jnp.float64) -> AdmittanceState:
        return AdmittanceState(V_ref=jnp.zeros(6, dtype=dtype))

    def update(
        self, gains: AdmittanceGains, inputs: ControlInputs, state: AdmittanceState, dt
    ) -> tuple[jax.Array, AdmittanceState]:
        """``(qd_des (N,) rad/s, next state)``: the command from ``V_ref(k)`` (eqs 16-17), then
        eq 15 by forward Euler over the control period ``dt`` (s)."""
        # Relative to a moving target, the command adds the LAR frame's own twist.
        V_command = state.V_ref + inputs.frame_twist
        qd_des = desired_joint_rates(
            inputs.J_dyn_ee, inputs.R_lar_ee, V_command, self.pinv_damping + gains.pinv_damping[0]
        )
        rate = reference_twist_rate(
            gains, inputs.pose, inputs.twist, inputs.pose_des, inputs.twist_des, inputs.twist_rate_des, inputs.wrench
        )
        return qd_des, AdmittanceState(V_ref=state.V_ref + dt * rate)

    def log_fields(self, state: AdmittanceState) -> dict[str, jax.Array]:
        """``V_ref`` (6,): the reference twist in LAR the command was computed from."""
        return {"V_ref": state.V_ref}
