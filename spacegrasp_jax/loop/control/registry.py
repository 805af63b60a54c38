"""The control laws, listed once.

Everything that offers a choice of law reads it from here: the command line's
``--controller`` choices, the gain groups a controller uses and ``spacegrasp tune`` tunes,
the campaigns' variants, the paper's reference torques (Table 5) and the figures' styles.
The gain groups are collected here too: each law declares its own in its module (its
``gains_type``), and ``GAIN_GROUPS`` is every law's and the joint servo's, from which the
one gain set [`Gains`][spacegrasp_jax.loop.control.gains.Gains] is made. A new law is one module
with a class implementing [`ControlLaw`][spacegrasp_jax.loop.control.law.ControlLaw] and its
gains, and one entry in ``LAWS``.
"""

from __future__ import annotations

from spacegrasp_jax.loop.control.admittance import Admittance
from spacegrasp_jax.loop.control.cartesian import Cartesian
from spacegrasp_jax.loop.control.groups import GainGroup, groups_of
from spacegrasp_jax.loop.control.impedance import Impedance
from spacegrasp_jax.loop.control.law import ControlLaw, Controller, Output, chain
from spacegrasp_jax.loop.control.pid import PID

#: Name -> law class, in the order the command line and tables show them.
LAWS: dict[str, type] = {law.name: law for law in (Admittance, Cartesian, Impedance)}

#: The laws' names.
CONTROLLERS: tuple[str, ...] = tuple(LAWS)


def collect_gain_groups(laws, servo=PID) -> dict[str, GainGroup]:
    """``{name: GainGroup}`` of every group the ``laws`` and the joint ``servo`` read (each
    law's in the given order, then the servo's).

    Raises:
        ValueError: two of them declare the same group differently.
    """
    collected: dict[str, GainGroup] = {}
    owners: dict[str, str] = {}
    for owner in (*laws, servo):
        name = getattr(owner, "name", "joint servo")
        for group, declaration in groups_of(owner.gains_type).items():
            if collected.setdefault(group, declaration) != declaration:
                raise ValueError(
                    f"gain group {group!r}: the {name} law declares it unlike the {owners[group]} law "
                    f"({declaration} against {collected[group]})"
                )
            owners.setdefault(group, name)
    return collected


#: Every gain group a law or the joint servo reads, the fields of the one gain set ``Gains``.
GAIN_GROUPS: dict[str, GainGroup] = collect_gain_groups(LAWS.values())

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
    """``controller`` as a [`Controller`][spacegrasp_jax.loop.control.law.Controller]: a law's name
    (the law with its default settings: the paper's exact pseudoinverse) or a law object
    (which carries its settings, [`law_named()`][spacegrasp_jax.loop.control.registry.law_named]),
    chained with the joint PID if it commands joint rates; a controller as it is."""
    if isinstance(controller, str):
        controller = law_named(controller)
    if isinstance(controller, Controller):
        return controller
    if not isinstance(controller, ControlLaw):
        raise ValueError(f"controller: expected a name, a control law or a Controller, got {controller!r}")
    return chain(controller, PID() if controller.output is Output.JOINT_RATES else None)


def gains_used(law: str | ControlLaw) -> tuple[str, ...]:
    """The gain groups a controller reads: its law's (``law``: a name of the registry, or any
    law object, a law of your own too), then the joint servo's for a law that commands joint
    rates."""
    law = _law_class(law) if isinstance(law, str) else law
    return tuple(law.gain_groups) + (PID.gain_groups if law.output is Output.JOINT_RATES else ())


__all__ = [
    "CONTROLLERS",
    "GAIN_GROUPS",
    "LAWS",
    "PAPER_CONTROLLERS",
    "as_controller",
    "collect_gain_groups",
    "gains_used",
    "law_named",
]
