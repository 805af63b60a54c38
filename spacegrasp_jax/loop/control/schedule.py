"""Gain schedules: a gain set whose groups vary with a scheduling variable that flight
software has, so one controller can be stiff on the approach and compliant in contact.

Each group of [`Gains`][spacegrasp_jax.loop.control.gains.Gains] has its own knots ``x_0 < ... <
x_{K-1}`` on the variable and its gains at each knot. Between two knots the log-gains are
blended with the smoothstep ``w = s^2 (3 - 2 s)``, ``s = (x - x_i) / (x_{i+1} - x_i)``:

    log g(x) = (1 - w) log g_i + w log g_{i+1}

so every gain stays positive, the schedule is continuously differentiable in ``x``, and each
gain stays between its values at the two knots (no overshoot: a gain's range over the
schedule is its knots' range). Before the first knot and after the last the gains are the
end knots'. A group with one knot is constant, its values used as they are: a schedule of
one knot a group runs bit for bit as the constant gain set it holds.

The variables (``VARIABLES``), each read at the
start of a control period, as the controller sees it:

* ``"time"`` (s): since the approach began (the scenario's start);
* ``"distance"`` (m): the estimated distance from the EE to the LAR origin (its sensors, its
  model and its LAR estimate: what the law reads as the pose);
* ``"force"`` (N): the magnitude of the F/T sensor's force reading (filtered and biased as
  the realism says: what the law reads as the wrench);
* ``"contact_time"`` (s): the time since the controller detected the contact, 0 before it:
  contact is detected the first period the F/T force it reads exceeds ``CONTACT_FORCE_N``,
  and latched ([`contact_phase()`][spacegrasp_jax.loop.control.schedule.contact_phase]). It
  marks the capture's phases whatever their timing: an approach that starts farther away,
  or is slower, meets the contact gains at contact, not at a time on the clock.

A file is the gains file with groups that may be ``{"knots": [...], "values": [[...], ...]}``
and a ``"schedule"`` entry naming the variable ([`load_schedule()`][spacegrasp_jax.loop.control.schedule.load_schedule];
documentation, File formats).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax.core.inputs import numbers, read_document
from spacegrasp_jax.loop.control.gains import (
    GAIN_SHAPES,
    GAINS_USED,
    NAMED_GAINS,
    Gains,
    GainsError,
    gains_from_document,
    load_gains,
    make_gains,
    named_gains,
)

#: The scheduling variables and their units (module docstring).
VARIABLES = {"time": "s", "distance": "m", "force": "N", "contact_time": "s"}

#: The F/T force (N, magnitude, as the controller reads it) above which ``contact_time``
#: detects the contact: above the flight-like loop's sensor bias (0.36 N in magnitude) and
#: noise (0.05 N per axis), below the first contact's force within a few periods.
CONTACT_FORCE_N = 1.0

#: The shipped gain schedules by name -> their data file (beside it, ``*.settings.json``: the
#: command, the selection and the held-out result).
TUNED_SCHEDULE_FILES = {
    "flight_schedule": "tuned_admittance_flight_schedule.json",
    "free_target_schedule": "tuned_admittance_free_target_schedule.json",
}

#: Every gain set known by name (``--gains NAME``): the constant ones
#: (``control.gains.NAMED_GAINS``) and the shipped schedules.
NAMED_GAIN_SETS = NAMED_GAINS + tuple(TUNED_SCHEDULE_FILES)

#: The shipped sets tuned in the flight-like loop (``--realism flight``; their
#: ``*.settings.json`` give the command): run in the ideal loop they meet a loop they were not
#: tuned for, and the command line says so.
TUNED_IN_FLIGHT_LOOP = ("flight", "free_target", "flight_schedule", "free_target_schedule")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class GainSchedule:
    """Gains that vary with a scheduling variable (module docstring).

    A pytree: the knots and the gains at them are leaves (a tuning gradient reaches the
    gains at every knot), the variable and each group's number of knots are its structure.

    Attributes:
        knots: group -> (K,) the variable's values at the group's knots, increasing (unit:
            ``VARIABLES[variable]``); K = 1: the group is constant.
        values: group -> (K, n) the group's gains at each knot (n: its length, as in
            ``Gains``).
        variable: static: one of ``VARIABLES``.
    """

    knots: dict
    values: dict
    variable: str = dataclasses.field(default="time", metadata=dict(static=True))

    def at(self, x) -> Gains:
        """The gains at ``x`` (a scalar of the variable; traced or not)."""
        return Gains(**{name: interpolate(self.knots[name], self.values[name], x) for name in GAIN_SHAPES})

    def knot_counts(self) -> dict[str, int]:
        """group -> its number of knots."""
        return {name: int(np.shape(self.knots[name])[-1]) for name in GAIN_SHAPES}

    def to_dict(self, controller: str | None = None) -> dict:
        """The schedule as its file holds it (JSON-ready): the groups ``controller`` uses
        (``GAINS_USED``, the optional pseudoinverse damping included; every group: ``None``),
        a constant group as a list, a scheduled one as its knots and values."""
        names = GAIN_SHAPES if controller is None else GAINS_USED[controller]
        document: dict = {"schedule": {"variable": self.variable, "unit": VARIABLES[self.variable]}}
        for name in names:
            knots, values = np.asarray(self.knots[name]), np.asarray(self.values[name])
            if knots.shape[-1] == 1:
                document[name] = values[0].tolist()
            else:
                document[name] = {"knots": knots.tolist(), "values": values.tolist()}
        return document


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class GainChoice:
    """One of several gain sets of different structures (constant gains, schedules of any
    variable and knots), the one in force chosen by an index that is an argument, not a
    structure: every gain set of a campaign's law runs in one compiled program
    ([`program_gains()`][spacegrasp_jax.loop.control.schedule.program_gains]).

    The loop evaluates every option at the start of a period and keeps the chosen one's
    gains (``lax.select_n``): constant gains run bit for bit as in a program of their own; a
    schedule's blend is fused differently by the compiler beside the other options, so a
    run with it agrees with its own program's to rounding (relative differences up to a few
    1e-12 in the contact force on the flight-like loop; documentation, Monte-Carlo).

    Attributes:
        options: the gain sets (``Gains`` or ``GainSchedule``), one of each structure; those
            not chosen hold any valid gains of their structure.
        chosen: () int32, the index of the option in force.
    """

    options: tuple
    chosen: jax.Array

    @property
    def latched(self) -> bool:
        """Whether an option schedules on ``contact_time`` (the loop then carries the latch)."""
        return any(isinstance(o, GainSchedule) and o.variable == "contact_time" for o in self.options)


def structure(gains) -> tuple:
    """What decides the program a gain set (``Gains``, ``GainSchedule``) compiles into: its
    pytree structure (a schedule's variable included) and its leaves' shapes."""
    leaves, treedef = jax.tree.flatten(gains)
    return treedef, tuple(np.shape(leaf) for leaf in leaves)


def program_gains(gain_sets: list) -> list:
    """``gain_sets`` (``Gains`` or ``GainSchedule``) as the loop's argument, one per set:
    each set as it is where all share one structure, otherwise each a
    [`GainChoice`][spacegrasp_jax.loop.control.schedule.GainChoice] of the same options (the
    first set of each structure) choosing its own, so that all run in one program."""
    kinds: dict = {}
    for gains in gain_sets:
        kinds.setdefault(structure(gains), gains)
    if len(kinds) == 1:
        return list(gain_sets)
    order = list(kinds)
    chosen = [order.index(structure(gains)) for gains in gain_sets]
    return [
        GainChoice(
            options=tuple(gains if k == i else kinds[key] for k, key in enumerate(order)),
            chosen=np.int32(i),
        )
        for gains, i in zip(gain_sets, chosen, strict=True)
    ]


def interpolate(knots: jax.Array, values: jax.Array, x) -> jax.Array:
    """(n,) the group's gains at ``x`` from its ``knots`` (K,) and ``values`` (K, n): the
    smoothstep blend of the log-gains of the two knots around ``x`` (module docstring); with
    one knot, ``values[0]`` as it is."""
    if knots.shape[-1] == 1:
        return values[0]
    x = jnp.clip(x, knots[0], knots[-1])
    i = jnp.clip(jnp.searchsorted(knots, x, side="right") - 1, 0, knots.shape[-1] - 2)
    s = (x - knots[i]) / (knots[i + 1] - knots[i])
    w = s * s * (3.0 - 2.0 * s)
    return jnp.exp((1.0 - w) * jnp.log(values[i]) + w * jnp.log(values[i + 1]))


def constant_schedule(gains: Gains, variable: str = "time") -> GainSchedule:
    """``gains`` as a schedule of one knot a group (at 0): it runs bit for bit as ``gains``."""
    _check_variable(variable)
    return GainSchedule(
        knots={name: jnp.zeros(1) for name in GAIN_SHAPES},
        values={name: jnp.asarray(getattr(gains, name))[None] for name in GAIN_SHAPES},
        variable=variable,
    )


def schedule_of(gains: Gains, variable: str, knots, groups) -> GainSchedule:
    """``gains`` as a schedule on ``variable`` whose ``groups`` each have the ``knots``, every
    knot's gains ``gains``' (a start for tuning a schedule); the other groups constant."""
    knots = [float(x) for x in knots]
    return make_schedule(
        gains, variable, {name: (knots, [np.asarray(getattr(gains, name))] * len(knots)) for name in groups}
    )


def make_schedule(base: Gains, variable: str, groups: dict) -> GainSchedule:
    """A schedule on ``variable`` whose ``groups`` (group -> ``(knots, values)``: (K,)
    increasing finite knots and (K, n) positive gains, or a scalar broadcast per knot) vary
    and whose other groups are ``base``'s, constant.

    Raises:
        GainsError: an unknown variable or group, knots not increasing or not finite, gains
            not positive and finite, or of the wrong shape; the message names the group.
    """
    _check_variable(variable)
    schedule = constant_schedule(base, variable)
    knots, values = dict(schedule.knots), dict(schedule.values)
    for name, (group_knots, group_values) in groups.items():
        if name not in GAIN_SHAPES:
            raise GainsError(f"schedule: unknown gain group {name!r}; expected one of {', '.join(GAIN_SHAPES)}")
        x = numbers(group_knots, f"{name}.knots", GainsError)
        if x.ndim != 1 or x.size < 1 or not np.all(np.isfinite(x)) or np.any(np.diff(x) <= 0.0):
            raise GainsError(f"{name}.knots: need one or more finite values, strictly increasing; got {x.tolist()}")
        length = np.shape(getattr(base, name))[-1]
        rows = []
        for k, row in enumerate(group_values if np.ndim(group_values) else [group_values] * x.size):
            row = numbers(row, f"{name}.values[{k}]", GainsError)
            rows.append(np.full(length, float(row)) if row.ndim == 0 else row)
        v = np.asarray(rows, dtype=float)
        if v.shape != (x.size, length):
            raise GainsError(f"{name}.values: expected {x.size} rows of {length} gains (one a knot), got {v.shape}")
        if x.size > 1 and not (np.all(np.isfinite(v)) and np.all(v > 0.0)):
            raise GainsError(f"{name}.values: a scheduled group's gains must be positive and finite (log-blended)")
        for row in v:  # each knot's gains must be a valid gain set on their own
            make_gains(n_joints=np.shape(base.kp)[-1], **(base_dict(base) | {name: row}))
        knots[name], values[name] = jnp.asarray(x), jnp.asarray(v)
    return GainSchedule(knots=knots, values=values, variable=variable)


def base_dict(gains: Gains) -> dict[str, np.ndarray]:
    """Every group of ``gains`` as a NumPy array."""
    return {name: np.asarray(getattr(gains, name)) for name in GAIN_SHAPES}


def _check_variable(variable: str) -> None:
    if variable not in VARIABLES:
        raise GainsError(f"schedule.variable: expected one of {', '.join(VARIABLES)}, got {variable!r}")


def is_schedule_file(path: str | Path) -> bool:
    """Whether the gains file at ``path`` holds a schedule (a ``"schedule"`` entry)."""
    try:
        document = read_document(Path(path), GainsError, "json")
    except GainsError:
        return False  # not readable as gains at all: the gains reader says why
    return isinstance(document, dict) and "schedule" in document


def load_schedule(path: str | Path, controller=None, n_joints: int = 7, fill_from=None) -> GainSchedule:
    """Read a gain schedule (module docstring): a gains file
    ([`load_gains()`][spacegrasp_jax.loop.control.gains.load_gains]'s rules: every group the law
    uses, ``fill_from``) whose groups may be ``{"knots": [...], "values": [[...], ...]}``, with
    ``"schedule": {"variable": "time"}``. A file without ``"schedule"`` is a constant gain
    set, read as a one-knot schedule on time.

    Raises:
        GainsError: as ``load_gains()``, or a bad ``schedule`` entry, knots or values; the
            message names the file and the group.
    """
    path = Path(path)
    document = read_document(path, GainsError, "json")
    header = document.pop("schedule", {"variable": "time"})
    if not isinstance(header, dict) or set(header) - {"variable", "unit"}:
        raise GainsError(f'{path}: schedule: expected {{"variable": one of {", ".join(VARIABLES)}}}, got {header!r}')
    variable = header.get("variable")
    scheduled = {name: value for name, value in document.items() if isinstance(value, dict)}
    for name, value in scheduled.items():
        if set(value) != {"knots", "values"}:
            raise GainsError(
                f"{path}: {name}: a scheduled group holds exactly 'knots' and 'values', got {sorted(value)}"
            )
        if not isinstance(value["values"], list) or not value["values"]:
            raise GainsError(f"{path}: {name}.values: expected a list of one row (or one number) a knot")
    constant = {name: value for name, value in document.items() if name not in scheduled}
    # The constant groups, and each scheduled group's first knot, make the base set: the
    # gains file's rules (which groups the law needs, filling) apply to it as to any file.
    first = {name: value["values"][0] for name, value in scheduled.items()}
    try:
        base = gains_from_document(constant | first, path, controller, n_joints, fill_from)
        unit = header.get("unit", VARIABLES.get(variable))
        if variable in VARIABLES and unit != VARIABLES[variable]:
            raise GainsError(f"schedule.unit: {variable} is in {VARIABLES[variable]}, got {unit!r}")
        return make_schedule(base, variable, {name: (v["knots"], v["values"]) for name, v in scheduled.items()})
    except GainsError as error:
        message = str(error)
        raise GainsError(message if message.startswith(str(path)) else f"{path}: {message}") from None


def tuned_schedule_file(name: str = "flight_schedule") -> Path:
    """The data file of the shipped schedule ``name`` (``TUNED_SCHEDULE_FILES``)."""
    if name not in TUNED_SCHEDULE_FILES:
        raise ValueError(f"tuned_schedule: expected one of {', '.join(TUNED_SCHEDULE_FILES)}, got {name!r}")
    return Path(__file__).resolve().parents[2] / "data" / TUNED_SCHEDULE_FILES[name]  # spacegrasp_jax/data


def tuned_schedule(name: str = "flight_schedule") -> GainSchedule:
    """The shipped gain schedule ``name`` for the paper's arm and the admittance law.

    ``"flight_schedule"``: every admittance and PID group on the time since the approach
    began, knots at 0, 4, 8, 12 and 17 s (195 gains) tuned by the gradient method (a fresh
    batch of 32 flight-like captures a step, the median of four group means of their
    gradients, 75 steps, 15 minutes on 2 cores; the capture objective with a 4 N m budget)
    from the paper's gains, then a hold knot at 18 s with ``tuned_gains("flight")``, which
    it keeps from then on (the 17 s knot's gains alone do not hold a capture); the
    pseudoinverse exact. Held out on 1,000 fresh flight-like captures of a seed chosen before
    any result, and on 30 s captures (documentation, Gain schedules).

    ``"free_target_schedule"``: the same groups and knots for the free-target envelope,
    tuned by the same recipe on that envelope (75 steps) from ``tuned_gains("free_target")``;
    for the paper's 17 s capture window (past its last knot it holds two thirds of 30 s
    captures). Held out on 1,000 fresh flight-like captures of that envelope."""
    return load_schedule(tuned_schedule_file(name), "admittance")


def named_gain_set(name: str):
    """The gain set ``name`` names (``NAMED_GAIN_SETS``): a ``Gains`` or a shipped ``GainSchedule``."""
    return tuned_schedule(name) if name in TUNED_SCHEDULE_FILES else named_gains(name)


def gain_set_from_dict(document: dict, n_joints: int = 7):
    """A gain set as a record holds it (``Gains.to_dict()`` or ``GainSchedule.to_dict()``):
    a ``Gains``, or a ``GainSchedule`` where the document has a ``"schedule"`` entry."""
    document = dict(document)
    if "schedule" not in document:
        return make_gains(n_joints=n_joints, **document)
    variable = document.pop("schedule").get("variable")
    scheduled = {name: value for name, value in document.items() if isinstance(value, dict)}
    constant = {name: value for name, value in document.items() if name not in scheduled}
    first = {name: value["values"][0] for name, value in scheduled.items()}
    base = make_gains(n_joints=n_joints, **(constant | first))
    return make_schedule(base, variable, {name: (v["knots"], v["values"]) for name, v in scheduled.items()})


def load_gains_or_schedule(path: str | Path, controller=None, n_joints: int = 7, fill_from=None):
    """A ``Gains`` for a constant gains file, a ``GainSchedule`` for a schedule file."""
    if is_schedule_file(path):
        return load_schedule(path, controller, n_joints, fill_from)
    return load_gains(path, controller, n_joints, fill_from)


def scheduling_variable(variable: str, t, pose: jax.Array, wrench: jax.Array) -> jax.Array:
    """The value of ``variable`` (``VARIABLES``) the controller has at the start of a period:
    ``t`` (s), the EE pose it reads ``[p (m); angles]`` in LAR, and the F/T reading ``[f (N);
    n (N m)]`` it reads. The norms are smoothed at zero (``sqrt(|v|^2 + eps^2) - eps``, eps
    = 1e-9 of the unit) so that their gradient stays finite."""
    if variable == "time":
        return t
    if variable == "contact_time":
        raise ValueError("contact_time: a latched variable, read with contact_phase() and the loop's phase memory")
    vector = pose[:3] if variable == "distance" else wrench[:3]
    eps = 1e-9
    return jnp.sqrt(jnp.sum(vector * vector) + eps * eps) - eps


def contact_phase(phase: tuple, t, wrench: jax.Array) -> tuple[jax.Array, tuple]:
    """``(contact_time, next phase)`` at the start of a period: ``phase = (detected,
    t_detected)`` the latch so far (0 and 0 before any contact), ``t`` (s) and the F/T reading
    ``wrench`` (6,) the controller reads. Contact is detected where the force's magnitude
    exceeds ``CONTACT_FORCE_N`` and stays so (a capture has one contact phase: a bounce off
    the ring does not restart it); ``contact_time`` is ``t - t_detected`` after, 0 before."""
    detected, t_detected = phase
    now = (jnp.sum(wrench[:3] * wrench[:3]) > CONTACT_FORCE_N**2).astype(t_detected.dtype)
    t_detected = jnp.where(detected > 0, t_detected, t)
    detected = jnp.maximum(detected, now)
    return jnp.where(detected > 0, t - t_detected, jnp.zeros_like(t_detected)), (detected, t_detected)


def contact_time_series(t: np.ndarray, force: np.ndarray) -> np.ndarray:
    """(T,) ``contact_time`` along a run's ``t`` (T,) and F/T force readings ``force`` (T, 3)
    (NumPy; every row a period's start, as the controller reads them)."""
    above = np.sum(np.asarray(force) ** 2, axis=-1) > CONTACT_FORCE_N**2
    if not above.any():
        return np.zeros_like(np.asarray(t, dtype=float))
    first = int(np.argmax(above))
    return np.where(np.arange(len(t)) >= first, np.asarray(t) - t[first], 0.0)


def schedule_curves(schedule: GainSchedule, points: int = 241) -> dict[str, dict]:
    """Each scheduled group's gains along its variable, for a figure: group -> ``x``
    (points,) from a tenth of the knots' span before the first to as far after the last,
    ``gains`` (points, n) there, ``knots`` (K,) and ``at_knots`` (K, n) (NumPy)."""
    curves = {}
    for name in GAIN_SHAPES:
        knots = np.asarray(schedule.knots[name])
        if knots.size < 2:
            continue
        margin = 0.1 * (knots[-1] - knots[0])
        x = np.linspace(knots[0] - margin, knots[-1] + margin, points)
        values = jnp.asarray(schedule.values[name])
        gains = np.asarray(jax.vmap(lambda v: interpolate(jnp.asarray(knots), values, v))(jnp.asarray(x)))
        curves[name] = {"x": x, "gains": gains, "knots": knots, "at_knots": np.asarray(values)}
    return curves


def variable_series(variable: str, log) -> np.ndarray:
    """(T,) the scheduling variable along a run's log (NumPy fields): ``time`` its ``t``;
    ``force`` the norm of the F/T force the controller read (``fts_force_measured`` where the
    loop logs readings, else ``fts_force``), ``contact_time`` the time since it first exceeded
    ``CONTACT_FORCE_N`` (the log's rows are plant steps: at a control period longer than a
    step, detection may come a few steps earlier than the controller's); ``distance`` the norm of the logged EE position in
    LAR (the true one: the controller's estimate differs by its LAR estimate's error)."""
    if variable == "time":
        return np.asarray(log.t)
    if variable == "contact_time":
        force = log.fts_force_measured if log.fts_force_measured is not None else log.fts_force
        return contact_time_series(np.asarray(log.t), np.asarray(force))
    if variable == "force":
        force = log.fts_force_measured if log.fts_force_measured is not None else log.fts_force
        return np.linalg.norm(np.asarray(force), axis=-1)
    return np.linalg.norm(np.asarray(log.pose_ee)[:, :3], axis=-1)


def gains_along(schedule: GainSchedule, x: np.ndarray) -> dict[str, np.ndarray]:
    """Each scheduled group's gains at the values ``x`` (T,) of its variable: group -> (T, n)."""
    at = jax.jit(jax.vmap(lambda value: schedule.at(value)))(jnp.asarray(x))
    return {name: np.asarray(getattr(at, name)) for name, count in schedule.knot_counts().items() if count > 1}


def scheduled_knots(schedule: GainSchedule) -> list[float]:
    """Every knot of every scheduled group (more than one knot), once, in increasing order
    (``[]`` when no group is scheduled)."""
    return sorted(
        {float(x) for name, count in schedule.knot_counts().items() if count > 1 for x in schedule.knots[name]}
    )


def regime_labels(schedule: GainSchedule, x: np.ndarray) -> list[str]:
    """What regime a run was in at each value ``x`` (T,) of ``schedule``'s variable, in words
    for a film's frames: the interval between two of the scheduled groups' knots (all of
    them together) that holds it, e.g. ``"time 5.20 s: regime 2 of 4 (4-8 s)"``; before
    the first knot and after the last the gains are the end knots', so those say so."""
    unit = VARIABLES[schedule.variable]
    knots = scheduled_knots(schedule)
    if len(knots) < 2:
        return [f"{schedule.variable} {value:.3g} {unit}: constant gains" for value in np.asarray(x, dtype=float)]
    labels = []
    for value in np.asarray(x, dtype=float):
        i = int(np.searchsorted(knots, value, side="right"))
        if i == 0:
            where = f"before the first knot ({knots[0]:g} {unit})"
        elif i == len(knots):
            where = f"after the last knot ({knots[-1]:g} {unit})"
        else:
            where = f"regime {i} of {len(knots) - 1} ({knots[i - 1]:g}-{knots[i]:g} {unit})"
        labels.append(f"{schedule.variable} {value:.3g} {unit}: {where}")
    return labels


__all__ = [
    "NAMED_GAIN_SETS",
    "TUNED_SCHEDULE_FILES",
    "GainChoice",
    "GainSchedule",
    "named_gain_set",
    "tuned_schedule",
    "tuned_schedule_file",
    "VARIABLES",
    "constant_schedule",
    "gain_set_from_dict",
    "interpolate",
    "is_schedule_file",
    "load_gains_or_schedule",
    "load_schedule",
    "make_schedule",
    "program_gains",
    "schedule_curves",
    "gains_along",
    "regime_labels",
    "scheduled_knots",
    "schedule_of",
    "variable_series",
    "scheduling_variable",
    "structure",
]
