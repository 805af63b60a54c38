"""What every control law reads, the interface a law implements, and how a law and the
joint servo after it make a controller.

A law is a small frozen object (optax's and diffrax's style): the object fixes the program
(it is static, hashable, a ``jit`` static argument) and closes over its settings, such as
the pseudoinverse's damping; its state is a pytree the closed loop carries. Its class says
what it is to the rest of the package ([`ControlLaw`][spacegrasp_jax.loop.control.law.ControlLaw]):
its name, what it commands (joint rates for a joint servo, or joint torques), the gain groups
it reads, its plot style and, for the paper's two laws, Table 5's torques. The laws are
listed once, in [`spacegrasp_jax.loop.control.registry`][spacegrasp_jax.loop.control.registry].

A [`Controller`][spacegrasp_jax.loop.control.law.Controller] chains a law with the joint servo
that turns its joint-rate command into torques (the paper's joint PID), or, for a law that
commands torques itself, with none: ``chain(Admittance(), PID())`` is the paper's
admittance controller, ``chain(Impedance())`` a torque law on its own.
"""

from __future__ import annotations

import dataclasses
import enum
from typing import Any, ClassVar, Protocol, runtime_checkable

import jax
import jax.numpy as jnp

from spacegrasp_jax.loop.control.groups import view
from spacegrasp_jax.loop.control.pid import PID, PIDState, saturate

#: A gain set: a [`Gains`][spacegrasp_jax.loop.control.gains.Gains] or a schedule's gains at one
#: instant, any pytree holding each law's groups by name (the registry of the laws, above
#: this module, defines it).
GainSet = Any


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
        J_dyn_ee: (6, N) the Dynamic Jacobian in the EE frame (eq 8).
        R_lar_ee: (3, 3) EE to LAR rotation.
        q, qd: (N,) rad, rad/s, the joint angles and rates as the controller measures them.
        frame_twist: (6,) the moving LAR frame's twist at the EE point ``[v (m/s); w
            (rad/s)]``, LAR axes, which the laws add to their commanded twist (the EE's
            inertial twist is the relative one plus this); zeros for the paper's fixed target.
    """

    pose: jax.Array
    twist: jax.Array
    wrench: jax.Array
    pose_des: jax.Array
    twist_des: jax.Array
    twist_rate_des: jax.Array
    J_dyn_ee: jax.Array
    R_lar_ee: jax.Array
    q: jax.Array
    qd: jax.Array
    frame_twist: jax.Array


class Output(enum.Enum):
    """What a law commands."""

    #: Desired joint rates (N,) rad/s, which a joint servo turns into torques.
    JOINT_RATES = "joint rates"
    #: Joint torques (N,) N m, applied as they are (through the actuators' limits).
    JOINT_TORQUES = "joint torques"


@runtime_checkable
class ControlLaw(Protocol):
    """The interface of a control law (class attributes, then two methods).

    Attributes:
        name: the law's name on the command line, in files, tables and figures.
        title: how figures and tables name it (``"admittance control"``).
        output: what ``update`` commands ([`Output`][spacegrasp_jax.loop.control.law.Output]).
        gains_type: the law's own gains, a dataclass pytree of
            [`group()`][spacegrasp_jax.loop.control.groups.group] fields declaring each gain
            group (length, unit, default, sign); ``update`` gets one.
        gain_groups: its field names, the [`Gains`][spacegrasp_jax.loop.control.gains.Gains]
            groups the law reads (a joint servo's are added by the
            [`Controller`][spacegrasp_jax.loop.control.law.Controller]); ``spacegrasp tune``
            tunes these.
        loop_gain: ``{group: +1 or -1}``, how the law's loop gain scales with each group
            (``+1``: with it, ``-1``: against it); the stability margins scale the loop by
            a factor this way.
        style: matplotlib line style of its curves (``color``, ``linestyle``, ``label``).
        paper_max_abs_torque_Nm: Table 5's maximal absolute joint torques (7,) N m for the
            paper's two laws, ``None`` for laws the paper does not have.
    """

    name: ClassVar[str]
    title: ClassVar[str]
    output: ClassVar[Output]
    gains_type: ClassVar[type]
    gain_groups: ClassVar[tuple[str, ...]]
    loop_gain: ClassVar[dict[str, int]]
    style: ClassVar[dict[str, str]]
    paper_max_abs_torque_Nm: ClassVar[tuple[float, ...] | None]

    def init(self, n_joints: int, dtype=jnp.float64) -> Any:
        """The law's state before its first update, for an arm of ``n_joints`` joints."""

    def update(self, gains: Any, inputs: ControlInputs, state: Any, dt) -> tuple[jax.Array, Any]:
        """``(command (N,), next state)`` from the law's ``gains`` (a ``gains_type``) and
        ``inputs`` over the control period ``dt`` (s)."""

    def log_fields(self, state: Any) -> dict[str, jax.Array]:
        """The [`Log`][spacegrasp_jax.loop.simulate.Log] fields the law fills from the state its
        command was computed from (``{"V_ref": (6,)}`` for the admittance law; others are
        logged as zeros)."""


#: What a law must have to be one: ``ControlLaw``'s attributes and methods.
_LAW_MEMBERS = (
    *ControlLaw.__annotations__,
    *(name for name, member in vars(ControlLaw).items() if callable(member) and not name.startswith("_")),
)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ControllerState:
    """The controller's memory from one control step to the next.

    Attributes:
        law: the law's own state (``AdmittanceState`` with its ``V_ref``, or a memoryless
            law's empty one).
        pid: the joint servo's memory (``PIDState``), or ``()`` for a law that commands
            torques.
        phase: a gain schedule's contact latch, ``(detected, t_detected)`` (0 or 1, and s),
            for a schedule on ``contact_time``
            ([`contact_phase()`][spacegrasp_jax.loop.control.schedule.contact_phase]); ``()``
            otherwise.
    """

    law: Any
    pid: PIDState | tuple
    phase: tuple = ()


@dataclasses.dataclass(frozen=True)
class Controller:
    """A law and the joint servo after it (``servo=None``: the law commands torques).

    Attributes:
        law: a [`ControlLaw`][spacegrasp_jax.loop.control.law.ControlLaw].
        servo: the joint [`PID`][spacegrasp_jax.loop.control.pid.PID] for a law that commands
            joint rates; ``None`` for one that commands torques.
        saturation: with torque limits, how a torque law's command is limited (``"hard"``
            or ``"smooth"``, [`saturate()`][spacegrasp_jax.loop.control.pid.saturate]); a servo
            limits its own.
    """

    law: ControlLaw
    servo: PID | None = None
    saturation: str = "hard"

    def __post_init__(self):
        if not isinstance(self.law, ControlLaw):
            missing = [name for name in _LAW_MEMBERS if not hasattr(self.law, name)]
            raise ValueError(f"controller: {self.law!r} is not a control law: it has no {', '.join(missing)}")
        rates = self.law.output is Output.JOINT_RATES
        if rates and self.servo is None:
            raise ValueError(f"the {self.law.name} law commands joint rates: chain it with a joint servo (PID())")
        if not rates and self.servo is not None:
            raise ValueError(f"the {self.law.name} law commands joint torques: it takes no joint servo")

    @property
    def name(self) -> str:
        return self.law.name

    def with_actuators(self, saturation: str, anti_windup: bool) -> Controller:
        """This controller with the actuators' saturation law (and the servo's anti-windup)."""
        servo = None if self.servo is None else PID(saturation=saturation, anti_windup=anti_windup)
        return Controller(self.law, servo, saturation)

    def init(self, n_joints: int, dtype=jnp.float64) -> ControllerState:
        servo = () if self.servo is None else self.servo.init(n_joints, dtype)
        return ControllerState(law=self.law.init(n_joints, dtype), pid=servo)

    def command(self, gains: GainSet, inputs: ControlInputs, state: Any, dt) -> tuple[jax.Array, Any]:
        """``(command (N,), the law's next state)``: the law's update with its own view of the
        gain set ``gains`` over the control period ``dt`` (s)."""
        return self.law.update(view(self.law.gains_type, gains), inputs, state, dt)

    def torque(
        self, gains: GainSet, command: jax.Array, qd: jax.Array, state: PIDState | tuple, t, dt, limit=None
    ) -> tuple[jax.Array, PIDState | tuple]:
        """``(u (N,) N m, the servo's next state)`` for the law's ``command`` (N,), the joint
        rates ``qd`` (N,) rad/s the servo reads at time ``t`` (s), its view of the gain set
        ``gains``, the servo's period ``dt``
        (s) and the torque limits ``limit`` (N,) N m (``None``: the paper's unlimited motors)."""
        if self.servo is not None:
            return self.servo.update(view(self.servo.gains_type, gains), command - qd, state, t, dt, limit)
        return (command if limit is None else saturate(command, limit, self.saturation)), state

    def desired_rates(self, command: jax.Array) -> jax.Array:
        """(N,) rad/s, the desired joint rates ``command`` stands for: itself for a law that
        commands joint rates, zeros for a torque law."""
        return command if self.servo is not None else jnp.zeros_like(command)

    def logged(self, command: jax.Array, law_state: Any) -> dict[str, jax.Array]:
        """The log's controller fields: ``V_ref`` (6,) and ``qd_des`` (N,) (zeros where the
        law has none) from the ``command`` computed from ``law_state``."""
        fields = {"V_ref": jnp.zeros(6, command.dtype), "qd_des": self.desired_rates(command)}
        return fields | self.law.log_fields(law_state)


def chain(law: ControlLaw, servo: PID | None = None) -> Controller:
    """The controller of ``law`` followed by ``servo`` (``chain(Admittance(), PID())``; a
    torque law alone: ``chain(Impedance())``)."""
    return Controller(law, servo)


__all__ = ["ControlInputs", "ControlLaw", "Controller", "ControllerState", "Output", "chain"]
