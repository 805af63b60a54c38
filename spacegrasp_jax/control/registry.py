"""The control laws, listed once.

Everything that offers a choice of law reads it from here: the command line's
``--controller`` choices, the gain groups a controller uses and ``spacegrasp tune`` tunes,
the campaigns' variants, the paper's reference torques (Table 5) and the figures' styles.
A new law is one module with a class implementing
[`ControlLaw`][spacegrasp_jax.control.law.ControlLaw] and one entry in ``LAWS``.
"""

from __future__ import annotations

from spacegrasp_jax.control.admittance import Admittance
from spacegrasp_jax.control.cartesian import Cartesian
from spacegrasp_jax.control.impedance import Impedance
from spacegrasp_jax.control.law import ControlLaw, Controller, Output, chain
from spacegrasp_jax.control.pid import PID

#: Name -> law class, in the order the command line and tables show them.
LAWS: dict[str, type] = {law.name: law for law in (Admittance, Cartesian, Impedance)}

#: The laws' names.
CONTROLLERS: tuple[str, ...] = tuple(LAWS)

#: The paper's two laws (those with Table 5's torques), in the paper's order.
PAPER_CONTROLLERS: tuple[str, ...] = tuple(
    name for name, law in LAWS.items() if law.paper_max_abs_torque_Nm is not None
)


def _law_class(name: str) -> type:
    if name not in LAWS:
        raise ValueError(f"controller: expected one of {', '.join(LAWS)}, got {name!r}")
    return LAWS[name]


def law_named(name: str, pinv_damping: float = 0.0) -> ControlLaw:
    """The law called ``name``, with the pseudoinverse's damping ``pinv_damping`` (0:
    exact, the paper) for a law that has a pseudoinverse."""
    law = _law_class(name)
    if "pinv_damping" in law.gain_groups:
        return law(pinv_damping=pinv_damping)
    if pinv_damping:
        raise ValueError(f"pinv_damping: the {name} law has no pseudoinverse to damp")
    return law()


def as_controller(controller: str | ControlLaw | Controller) -> Controller:
    """``controller`` as a [`Controller`][spacegrasp_jax.control.law.Controller]: a law's name
    (the law with its default settings: the paper's exact pseudoinverse) or a law object
    (which carries its settings, [`law_named()`][spacegrasp_jax.control.registry.law_named]),
    chained with the joint PID if it commands joint rates; a controller as it is."""
    if isinstance(controller, str):
        controller = law_named(controller)
    if isinstance(controller, Controller):
        return controller
    if not isinstance(controller, ControlLaw):
        raise ValueError(f"controller: expected a name, a control law or a Controller, got {controller!r}")
    return chain(controller, PID() if controller.output is Output.JOINT_RATES else None)


def controller_name(controller: str | ControlLaw | Controller) -> str:
    """The law's name of ``controller`` (a name, a law or a controller)."""
    return controller if isinstance(controller, str) else as_controller(controller).name


def gains_used(name: str) -> tuple[str, ...]:
    """The gain groups the controller ``name`` reads: its law's, then the joint servo's."""
    law = _law_class(name)
    servo = PID.gain_groups if law.output is Output.JOINT_RATES else ()
    groups = tuple(g for g in law.gain_groups if g != "pinv_damping") + servo
    return groups + (("pinv_damping",) if "pinv_damping" in law.gain_groups else ())


__all__ = [
    "CONTROLLERS",
    "LAWS",
    "PAPER_CONTROLLERS",
    "as_controller",
    "controller_name",
    "gains_used",
    "law_named",
]
