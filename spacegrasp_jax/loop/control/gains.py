"""The gain set: every law's and the joint servo's gain groups in one differentiable
pytree, with the paper's values.

Each law declares its own gains in its module (a dataclass of
[`GainGroup`][spacegrasp_jax.loop.control.groups.GainGroup] fields, the law's ``gains_type``) and
reads only those; the registry collects them (``registry.GAIN_GROUPS``) and
[`Gains`][spacegrasp_jax.loop.control.gains.Gains] is made from that collection, so one set runs
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

from spacegrasp_jax.core import model
from spacegrasp_jax.core.dynamics import mass_matrix
from spacegrasp_jax.core.inputs import did_you_mean, numbers, read_document
from spacegrasp_jax.core.precision import require_float64
from spacegrasp_jax.loop.control.groups import PER_JOINT, fields_of_groups
from spacegrasp_jax.loop.control.registry import CONTROLLERS, GAIN_GROUPS, gains_used

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
    Build one with [`make_gains()`][spacegrasp_jax.loop.control.gains.make_gains] or
    [`paper_gains()`][spacegrasp_jax.loop.control.gains.paper_gains] and change one with
    ``dataclasses.replace``. A law reads its own view of it (its ``gains_type``,
    [`view()`][spacegrasp_jax.loop.control.groups.view])."""

    def to_dict(self, controller: str | None = None) -> dict[str, list[float]]:
        """Plain lists, for JSON: the groups ``controller`` uses (``GAINS_USED``), or
        every group (``None``)."""
        names = GAINS_USED[controller] if controller is not None else GAIN_SHAPES
        return {name: np.asarray(getattr(self, name)).tolist() for name in names}


def _unknown(names: list[str]) -> str:
    """Unknown gain names, each with the known one it likely meant (``Kp (did you mean kp?)``)."""
    return ", ".join(name + did_you_mean(name, GAIN_SHAPES) for name in names)


def make_gains(*, n_joints: int = PAPER_JOINTS, **fields) -> Gains:
    """Validate and build [`Gains`][spacegrasp_jax.loop.control.gains.Gains] for an arm of ``n_joints``
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
        raise GainsError(f"unknown gain(s): {_unknown(unknown)}; expected {', '.join(GAIN_SHAPES)}")
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
    return load_gains(tuned_gains_file(loop), fill_from="paper")


#: The gain sets known by name (``--gains NAME``): the paper's, and the shipped tuned ones.
NAMED_GAINS = ("paper", *TUNED_GAINS_FILES)


def named_gains(name: str) -> Gains:
    """The gain set ``name`` of ``NAMED_GAINS``: ``"paper"``
    ([`paper_gains()`][spacegrasp_jax.loop.control.gains.paper_gains]) or a shipped tuned set
    ([`tuned_gains(name)`][spacegrasp_jax.loop.control.gains.tuned_gains]); all for the paper's arm."""
    if name not in NAMED_GAINS:
        raise ValueError(f"named_gains: name must be one of {', '.join(NAMED_GAINS)}, got {name!r}")
    return paper_gains() if name == "paper" else tuned_gains(name)


def tuned_gains_file(loop: str) -> Path:
    """The shipped file of [`tuned_gains(loop)`][spacegrasp_jax.loop.control.gains.tuned_gains]
    (it holds the admittance law's groups)."""
    return Path(__file__).resolve().parents[2] / "data" / TUNED_GAINS_FILES[loop]  # spacegrasp_jax/data


#: The starting rule's joint bandwidth, 1/s: ``kp_i`` = this times joint i's effective inertia.
START_RATE_PER_S = 20.0
#: The starting rule's ``ki / kp`` and ``kd / kp``: the ratios of the paper's Table 4 (its
#: first three joints: 10 / 140 rounded to 0.05, 0.01 / 140 = 7e-5 s).
START_KI_PER_KP, START_KD_PER_KP = 0.05, 7e-5


def effective_joint_inertia(mass_matrix: np.ndarray) -> np.ndarray:
    """Each joint's effective inertia in a free-floating system, (N,) kg m^2: the diagonal of
    the joint block of the (6 + N, 6 + N) generalised mass matrix less the satellite's share,
    ``M_qq - M_qb M_bb^-1 M_bq`` (the Schur complement: the inertia a joint's motor meets when
    the satellite is free to recoil, as it is in orbit)."""
    M = np.asarray(mass_matrix, dtype=np.float64)
    base, joints = M[:6, :6], M[6:, 6:]
    coupling = M[:6, 6:]
    return np.diag(joints - coupling.T @ np.linalg.solve(base, coupling)).copy()


def starting_gains(robot, q_init=None, R_base=None) -> Gains:
    """Gains to start tuning from for any arm: the paper's law gains (``Md``, ``Bd``, ``Kd``,
    ``K_lin``, ``K_eul``) and joint PID gains scaled to the arm, ``kp_i`` =
    ``START_RATE_PER_S`` (20/s) times joint i's effective inertia at ``q_init``
    ([`effective_joint_inertia()`][spacegrasp_jax.loop.control.gains.effective_joint_inertia]; the
    paper's Table 4 gains are 5 to 50 times its arm's), ``ki = 0.05 kp`` and ``kd = 7e-5 kp``
    (Table 4's ratios). A start, not a tuned set: ``spacegrasp tune`` takes it from there.

    Args:
        robot: the arm on its satellite ([`Robot`][spacegrasp_jax.core.model.Robot], N joints).
        q_init: (N,) rad, the capture's initial joint angles (default: the paper's, for a
            7-joint arm; required for another).
        R_base: (3, 3) satellite attitude (default: the identity; the effective inertia does
            not depend on it).
    """
    n = model.n_joints(robot)
    if q_init is None:
        if n != PAPER_JOINTS:
            raise GainsError(f"starting_gains: q_init: required for an arm of {n} joints (the paper's is for 7)")
        q_init = model.PAPER_Q_INIT
    R_base = np.eye(3) if R_base is None else R_base
    inertia = effective_joint_inertia(mass_matrix(robot, jnp.asarray(R_base), jnp.asarray(q_init, dtype=jnp.float64)))
    kp = START_RATE_PER_S * inertia
    laws = {name: value for name, value in paper_gains().to_dict().items() if name not in JOINT_GROUPS}
    return make_gains(n_joints=n, **laws, kp=kp, ki=START_KI_PER_KP * kp, kd=START_KD_PER_KP * kp)


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


def required_groups(controller: str | tuple[str, ...] | list[str] | None = None) -> tuple[str, ...]:
    """The groups a gains file must hold to run ``controller``: the groups the law uses
    (``GAINS_USED``; for several laws, those any of them uses; ``None``: every law's), less
    the optional ones (``pinv_damping``: 0, the exact pseudoinverse, when left out)."""
    used = {name for law in _laws(controller) for name in GAINS_USED[law]}
    return tuple(name for name in GAIN_SHAPES if name in used and not GAIN_GROUPS[name].optional)


def _laws(controller) -> tuple[str, ...]:
    """A law's name, several or ``None`` (every law) as a tuple of names."""
    if controller is None:
        return CONTROLLERS
    return (controller,) if isinstance(controller, str) else tuple(controller)


def missing_groups(path: str | Path, controller: str | tuple[str, ...] | list[str] | None = None) -> list[str]:
    """The groups ``controller`` needs that the gains file at ``path`` leaves out (those
    [`load_gains()`][spacegrasp_jax.loop.control.gains.load_gains] takes from ``fill_from``)."""
    document = read_document(Path(path), GainsError, "json")
    return [name for name in required_groups(controller) if name not in document]


def load_gains(
    path: str | Path,
    controller: str | tuple[str, ...] | list[str] | None = None,
    n_joints: int = PAPER_JOINTS,
    fill_from: str | Path | Gains | None = None,
) -> Gains:
    """Read gains for an arm of ``n_joints`` joints from a JSON file ``{"Md": [...], "kp": [...],
    ...}`` (scalars allowed).

    A file holds every group the law uses ([`required_groups(controller)`][spacegrasp_jax.loop.control.gains.required_groups];
    several laws: any of them; ``None``: every law), so that what runs is what the file says.
    A file that leaves some out is refused, naming them, unless ``fill_from`` says where they
    come from: ``"paper"`` ([`paper_gains()`][spacegrasp_jax.loop.control.gains.paper_gains]; its
    joint groups are for the paper's 7 joints only), another gains file (which must hold
    every group itself), or a [`Gains`][spacegrasp_jax.loop.control.gains.Gains].
    [`missing_groups()`][spacegrasp_jax.loop.control.gains.missing_groups] names the groups filled.
    Groups the law does not use take the paper's values; given a single ``controller``,
    groups in the file that it does not use are accepted and named in an
    [`UnusedGainsWarning`][spacegrasp_jax.loop.control.gains.UnusedGainsWarning].

    Raises:
        GainsError: unreadable file, not a JSON object, a group missing without
            ``fill_from``, or invalid gains (a value that is not a number, ``"140"`` or
            ``true`` included, or a joint group of the wrong length); the message names the
            file.
    """
    path = Path(path)
    return gains_from_document(read_document(path, GainsError, "json"), path, controller, n_joints, fill_from)


def gains_from_document(
    document: dict,
    path: Path,
    controller: str | tuple[str, ...] | list[str] | None = None,
    n_joints: int = PAPER_JOINTS,
    fill_from: str | Path | Gains | None = None,
) -> Gains:
    """[`load_gains()`][spacegrasp_jax.loop.control.gains.load_gains] of a file's ``document``
    (its JSON object), ``path`` naming the file in messages."""
    unknown = sorted(set(document) - set(GAIN_SHAPES))
    if unknown:
        raise GainsError(f"{path}: unknown gain(s): {_unknown(unknown)}; expected {', '.join(GAIN_SHAPES)}")
    missing = [name for name in required_groups(controller) if name not in document]
    fill = _fill_values(path, missing, fill_from, n_joints, controller)
    defaults = paper_gains().to_dict()  # for the groups no law of the run uses (every law uses the joint groups)
    try:
        gains = make_gains(n_joints=n_joints, **(defaults | fill | document))
    except GainsError as error:
        raise GainsError(f"{path}: {error}") from None
    unused = [
        name
        for name in GAIN_SHAPES
        if name in document and isinstance(controller, str) and name not in GAINS_USED[controller]
    ]
    if unused:
        warnings.warn(
            f"{path}: {', '.join(unused)} not used by the {controller} controller (ignored)",
            UnusedGainsWarning,
            stacklevel=2,
        )
    return gains


def _fill_values(path: Path, missing: list[str], fill_from, n_joints: int, controller) -> dict:
    """The values of the ``missing`` groups of the file at ``path``, from ``fill_from``."""
    if not missing:
        return {}
    if fill_from is None:
        laws = _laws(controller)
        whose = ""
        if len(laws) > 1:  # which law of the run needs them
            needing = [law for law in laws if set(missing) & set(GAINS_USED[law])]
            whose = f" (used by the {' and '.join(needing)} law{'s' if len(needing) > 1 else ''})"
        raise GainsError(
            f"{path}: {', '.join(missing)}: missing{whose}; give every group the law uses, or say where the rest "
            f"comes from (--fill-from paper|FILE; fill_from= in Python)"
        )
    if isinstance(fill_from, Gains):
        source = fill_from
    elif str(fill_from) == "paper":
        joints = [name for name in missing if name in JOINT_GROUPS]
        if joints and n_joints != PAPER_JOINTS:
            raise GainsError(
                f"{path}: {', '.join(joints)}: missing, and the paper's Table 4 is for its {PAPER_JOINTS} joints, "
                f"not this arm's {n_joints}: give them in the file (spacegrasp gains --start writes a start)"
            )
        source = paper_gains()
    else:
        document = read_document(Path(fill_from), GainsError, "json")
        lacking = [name for name in missing if name not in document]
        if lacking:
            raise GainsError(f"{fill_from}: {', '.join(lacking)}: missing, and {path} leaves them to this file")
        return {name: document[name] for name in missing}
    return {name: np.asarray(getattr(source, name)).tolist() for name in missing}
