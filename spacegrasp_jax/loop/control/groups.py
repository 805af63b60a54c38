"""What a law declares of each gain it reads, and the typed gains pytree of one law.

Every gain matrix of the paper is diagonal, so each gain group is held as its diagonal, a
1-D array. A law (and the joint servo) declares its gains in its own module as a frozen
dataclass pytree with one [`group()`][spacegrasp_jax.loop.control.groups.group] field per group,
which says the group's length, unit, meaning, where the paper has it, its default and its
sign constraint ([`GainGroup`][spacegrasp_jax.loop.control.groups.GainGroup]):

```python
@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ImpedanceGains:
    Bd: jax.Array = group(DESIRED_DAMPING)
    Kd: jax.Array = group(DESIRED_STIFFNESS)
```

The law's ``update`` reads only that pytree. The registry
([`spacegrasp_jax.loop.control.registry`][spacegrasp_jax.loop.control.registry]) collects every law's
and the servo's groups into one gain set,
[`Gains`][spacegrasp_jax.loop.control.gains.Gains], which files, tuning, campaigns and the closed
loop hold (one set runs either of the paper's laws); a controller hands each law its own
[`view()`][spacegrasp_jax.loop.control.groups.view] of it. Two laws may read the same group (the
impedance law reads the admittance law's ``Bd`` and ``Kd``) only if they declare it alike.
"""

from __future__ import annotations

import dataclasses
from typing import Any

#: The length of a group with one gain per joint of the arm.
PER_JOINT = "N"


@dataclasses.dataclass(frozen=True)
class GainGroup:
    """One gain group: a diagonal held as a 1-D array.

    Attributes:
        length: the number of gains: an integer, or ``"N"`` (``PER_JOINT``) for one a joint.
        unit: the gains' unit (``"N/m (x, y, z), N m/rad (roll, pitch, yaw)"``).
        meaning: what the group is (``"desired stiffness K_d, diagonal"``).
        equation: where the paper has it (``"eqs (9), (14)"``, ``"Table 4"``).
        default: the value a gain set takes where none is given: the paper's, for the
            paper's groups; a number (every entry) or one per entry (a per-joint default
            is for the paper's 7-joint arm).
        positive: the law needs every gain strictly positive (``False``: zero allowed,
            e.g. no integral action).
        optional: a gain description may leave the group out (it then takes ``default``);
            otherwise [`make_gains()`][spacegrasp_jax.loop.control.gains.make_gains] requires it.
    """

    length: int | str
    unit: str
    meaning: str
    equation: str
    default: float | tuple[float, ...]
    positive: bool = True
    optional: bool = False


def group(declaration: GainGroup) -> Any:
    """A dataclass field of a law's gains pytree holding the group ``declaration``."""
    return dataclasses.field(metadata={"gain_group": declaration})


def groups_of(gains_type: type) -> dict[str, GainGroup]:
    """``{name: GainGroup}`` of a law's gains dataclass, in its fields' order."""
    return {field.name: field.metadata["gain_group"] for field in dataclasses.fields(gains_type)}


def fields_of_groups(groups: dict[str, GainGroup]) -> type:
    """A frozen dataclass with one array field per group of ``groups`` (in its order), each
    declaring its group: the base of a gain set holding them all (decorate the subclass with
    ``dataclasses.dataclass(frozen=True)`` and ``jax.tree_util.register_dataclass``)."""
    fields = [(name, Any, group(declaration)) for name, declaration in groups.items()]
    return dataclasses.make_dataclass("GainGroups", fields, frozen=True, namespace={"__module__": __name__})


def view(gains_type: type, gains: Any) -> Any:
    """``gains`` (a gain set holding at least ``gains_type``'s groups, e.g. a
    [`Gains`][spacegrasp_jax.loop.control.gains.Gains]) as a ``gains_type``: the same arrays, no
    copy, so the law reads its own groups and nothing else."""
    if isinstance(gains, gains_type):
        return gains
    return gains_type(**{name: getattr(gains, name) for name in groups_of(gains_type)})


__all__ = ["PER_JOINT", "GainGroup", "fields_of_groups", "group", "groups_of", "view"]
