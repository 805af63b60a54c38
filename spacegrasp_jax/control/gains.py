"""The gain set: every law's and the joint servo's gain groups in one differentiable
pytree, with the paper's values.

Each law declares its own gains in its module (a dataclass of
[`GainGroup`][spacegrasp_jax.control.groups.GainGroup] fields, the law's ``gains_type``) and
reads only those; the registry collects them (``registry.GAIN_GROUPS``) and
[`Gains`][spacegrasp_jax.control.gains.Gains] is made from that collection, so one set runs
any law, a file or a tuning run names groups by the same names, and a new law's groups
join the set with its registry entry. Every group is a diagonal held as a 1-D array:

| field | shape | unit | paper | law |
| --- | --- | --- | --- | --- |
| ``Md`` | (6,) | kg, kg m^2 | 800 (desired inertia, eq 9) | admittance |
| ``Bd`` | (6,) | N s/m, N m s/rad | 500 (desired damping) | admittance, impedance |
| ``Kd`` | (6,) | N/m, N m/rad | 600 (desired stiffness) | admittance, impedance |
| ``pinv_damping`` | (1,) | as ``J_dyn``'s entries | 0 (the exact pseudoinverse of eqs 17, 21) | admittance, Cartesian |
| ``K_lin`` | (3,) | 1/s | 3 (eq 22) | Cartesian |
| ``K_eul`` | (3,) | 1/s | 3 | Cartesian |
| ``kp`` | (N,) | N m s/rad | Table 4 (joint PID on the rate error) | joint servo |
| ``ki`` | (N,) | N m/rad | Table 4 | joint servo |
| ``kd`` | (N,) | N m s^2/rad | Table 4 | joint servo |

``pinv_damping`` is the damping a mission sets at design time to keep the law's
pseudoinverse bounded near Dynamic-Jacobian singularities (``J^T (J J^T + damping^2 1)^-1``);
it adds to a law's own (static) ``pinv_damping``, so the paper's gains keep the exact law.

The first three rows of ``Md``/``Bd``/``Kd`` act on the position in the LAR frame, the last
three on the ZYX Euler angles ``[roll, pitch, yaw]``. The joint groups have one gain per
joint of the arm (N; the paper's has 7, and Table 4 is for it).
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax.compilation import require_float64
from spacegrasp_jax.control.groups import PER_JOINT, fields_of_groups
from spacegrasp_jax.control.registry import CONTROLLERS, GAIN_GROUPS, gains_used
from spacegrasp_jax.inputs import numbers, read_document

#: Each group's length; ``"N"``: the arm's number of joints.
GAIN_SHAPES = {name: declaration.length for name, declaration in GAIN_GROUPS.items()}
#: The groups with one gain per joint.
JOINT_GROUPS = tuple(name for name, length in GAIN_SHAPES.items() if length == PER_JOINT)
#: The number of joints of the paper's arm, which Table 4's PID gains are for.
PAPER_JOINTS = 7

#: The gain groups each controller uses (its law's with the joint servo's; the registry's).
GAINS_USED = {name: gains_used(name) for name in CONTROLLERS}


class GainsError(ValueError):
    """Invalid gains; the message names the offending field."""


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Gains(fields_of_groups(GAIN_GROUPS)):
    """The gain set: one array per group of ``registry.GAIN_GROUPS``, in its order ``Md``,
    ``Bd``, ``Kd``, ``pinv_damping``, ``K_lin``, ``K_eul``, ``kp``, ``ki``, ``kd`` (the
    module docstring gives shapes, units and the paper's values).

    Its fields are made from the registry, so a new law's groups join it with the law.
    Build one with [`make_gains()`][spacegrasp_jax.control.gains.make_gains] or
    [`paper_gains()`][spacegrasp_jax.control.gains.paper_gains] and change one with
    ``dataclasses.replace``. A law reads its own view of it (its ``gains_type``,
    [`view()`][spacegrasp_jax.control.groups.view])."""

    def to_dict(self, controller: str | None = None) -> dict[str, list[float]]:
        """Plain lists, for JSON: the groups ``controller`` uses (``GAINS_USED``), or
        every group (``None``)."""
        names = GAINS_USED[controller] if controller is not None else GAIN_SHAPES
        return {name: np.asarray(getattr(self, name)).tolist() for name in names}


def make_gains(*, n_joints: int = PAPER_JOINTS, **fields) -> Gains:
    """Validate and build [`Gains`][spacegrasp_jax.control.gains.Gains] for an arm of ``n_joints``
    joints (the paper's 7 by default); a scalar is broadcast to the field's length, and
    ``pinv_damping`` may be left out (0: the exact pseudoinverse).

    Raises:
        GainsError: missing or unknown field, wrong length (a joint group's not the arm's
            number of joints), non-finite, negative value, or zero where the law needs a
            positive gain (``Md``, ``Bd``, ``Kd``, ``K_lin``, ``K_eul``, ``kp``).
    """
    require_float64("Gains")
    unknown = sorted(set(fields) - set(GAIN_SHAPES))
    if unknown:
        raise GainsError(f"unknown gain(s): {', '.join(unknown)}; expected {', '.join(GAIN_SHAPES)}")
    optional = {name: declaration.default for name, declaration in GAIN_GROUPS.items() if declaration.optional}
    fields = optional | fields
    missing = [name for name in GAIN_SHAPES if name not in fields]
    if missing:
        raise GainsError(f"missing gain(s): {', '.join(missing)}")
    arrays = {}
    for name, length in GAIN_SHAPES.items():
        value = numbers(fields[name], name, GainsError)
        per_joint = length == PER_JOINT
        length = n_joints if per_joint else length
        if value.ndim == 0:
            value = np.full(length, float(value))
        if value.shape != (length,):
            joints = f" (one a joint of this {n_joints}-joint arm)" if per_joint else ""
            raise GainsError(f"{name}: expected {length} values{joints}, got shape {value.shape}")
        positive = GAIN_GROUPS[name].positive
        if np.any(value < 0.0) or (positive and np.any(value == 0.0)):
            bound = "positive" if positive else "non-negative"
            raise GainsError(f"{name}: gains must be {bound}, got {value.tolist()}")
        arrays[name] = jnp.asarray(value)
    return Gains(**arrays)


def paper_gains() -> Gains:
    """Section 4: Kd = 600, Bd = 500, Md = 800 (all six axes), K_lin = K_eul = 3, and the
    joint PID gains of Table 4: every group's declared default."""
    return make_gains(**{name: declaration.default for name, declaration in GAIN_GROUPS.items()})


#: The loops the shipped tuned gains were tuned in -> their data file.
TUNED_GAINS_FILES = {
    "ideal": "tuned_admittance_gains.json",
    "flight": "tuned_admittance_flight_gains.json",
    "free_target": "tuned_admittance_free_target_gains.json",
}


def tuned_gains(loop: str = "ideal") -> Gains:
    """The admittance gains found by ``spacegrasp tune`` for capture success (CMA-ES on the
    capture objective), held out on 1,000 captures of a seed never used to tune.

    ``loop="flight"``: under the ``flight`` realism preset on the Monte-Carlo campaigns'
    envelope, with a torque budget of 4 N m on every joint (40 generations on a batch of 32
    from the paper's gains, then 26 on a batch of 64 with a step of 0.1); they succeed in
    90.6% [88.6, 92.3] of held-out flight-like captures against the paper's 65.7%, with a
    95th-percentile largest peak torque of 2.6 N m against the paper's 4.0.
    ``loop="free_target"``: the flight gains refined on the ``free_target`` envelope
    (free-floating targets of 200 to 2,000 kg, drifting and tumbling; 16 generations on a
    batch of 48); 62.5% [59.5, 65.4] of those captures against the paper's 23.4% (and 61.0%
    for the flight gains, not a significant difference), no runaway.
    ``loop="ideal"``: in the paper's loop on the campaigns' envelope, the torque constraint
    at a quarter of the motors' limits (21 generations); 94.8% [93.2, 96.0] against the
    paper's 89.8%, with a median largest peak of 1.9 N m against 2.8 and no runaway against 15.
    All tune the pseudoinverse's damping too. Shipped as ``spacegrasp_jax/data/*.json`` (the
    groups the admittance law uses; ``K_lin`` and ``K_eul`` are the paper's), each run's
    settings and held-out result beside it (``*.settings.json``; documentation, Tuning the
    gains)."""
    if loop not in TUNED_GAINS_FILES:
        raise ValueError(f"tuned_gains: loop must be one of {', '.join(TUNED_GAINS_FILES)}, got {loop!r}")
    return load_gains(Path(__file__).resolve().parents[1] / "data" / TUNED_GAINS_FILES[loop])


def require_joints(gains: Gains, n_joints: int, source: str = "the gains") -> None:
    """Raise ``GainsError`` unless ``gains``' joint groups have one gain per joint of an arm of
    ``n_joints`` joints (the paper's gains are for its 7)."""
    lengths = {name: np.shape(getattr(gains, name))[-1] for name in JOINT_GROUPS}
    if set(lengths.values()) != {n_joints}:
        raise GainsError(
            f"{source}: {', '.join(f'{name} has {length}' for name, length in lengths.items())} gains, "
            f"but the arm has {n_joints} joints (give a gains file with one per joint)"
        )


class UnusedGainsWarning(UserWarning):
    """A gains file holds groups the chosen controller does not use (they are ignored)."""


def load_gains(path: str | Path, controller: str | None = None, n_joints: int = PAPER_JOINTS) -> Gains:
    """Read gains for an arm of ``n_joints`` joints from a JSON file ``{"Md": [...], "kp": [...],
    ...}`` (scalars allowed).

    A file may hold any subset of the groups: the others take the paper's values
    ([`paper_gains()`][spacegrasp_jax.control.gains.paper_gains]), but for an arm of other
    than the paper's 7 joints the joint groups (``kp``, ``ki``, ``kd``) are required. A file
    written for one controller holds the groups that controller uses (``GAINS_USED``); given
    ``controller``, groups it does not use are accepted and named in an
    [`UnusedGainsWarning`][spacegrasp_jax.control.gains.UnusedGainsWarning].

    Raises:
        GainsError: unreadable file, not a JSON object, or invalid gains (a value that is
            not a number, ``"140"`` or ``true`` included, or a joint group of the wrong
            length); the message names the file.
    """
    path = Path(path)
    document = read_document(path, GainsError, "json")
    unknown = sorted(set(document) - set(GAIN_SHAPES))
    if unknown:
        raise GainsError(f"{path}: unknown gain(s): {', '.join(unknown)}; expected {', '.join(GAIN_SHAPES)}")
    defaults = paper_gains().to_dict()
    if n_joints != PAPER_JOINTS:
        missing = [name for name in JOINT_GROUPS if name not in document]
        if missing:
            raise GainsError(
                f"{path}: {', '.join(missing)}: required for an arm of {n_joints} joints "
                f"(the paper's Table 4 is for its {PAPER_JOINTS})"
            )
    try:
        gains = make_gains(n_joints=n_joints, **(defaults | document))
    except GainsError as error:
        raise GainsError(f"{path}: {error}") from None
    unused = [
        name
        for name in GAIN_SHAPES
        if name in document and controller is not None and name not in GAINS_USED[controller]
    ]
    if unused:
        warnings.warn(
            f"{path}: {', '.join(unused)} not used by the {controller} controller (ignored)",
            UnusedGainsWarning,
            stacklevel=2,
        )
    return gains
