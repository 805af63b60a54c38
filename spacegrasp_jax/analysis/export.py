"""Gains in the forms flight software takes: JSON, YAML, a C header and CSV.

Every format holds the same numbers, written so that they read back exactly (the shortest
decimal that round-trips a float64), with each group's unit, what it is and the paper's
equation that uses it, and the loop settings the gains were designed and checked in: the
control and servo periods, the delay, the joint torque limits with the saturation law and
anti-windup, the F/T sensor's low-pass cutoff, and the PID gain ramp of the paper (every PID
gain scaled by ``min(t / 1 s, 1)^2`` over the first second). Gains tuned in one loop are
not the same gains in another: flight software that runs other periods or limits than these
runs a controller that was never checked.

A gain schedule ([`GainSchedule`][spacegrasp_jax.loop.control.schedule.GainSchedule]) exports as
JSON (its file, with units) or as a C header holding each group's knot table and the blend
as a small C function, ``<prefix>_gains_at(x, &gains)``, the same arithmetic as the
simulator's (tested against it at 1,000 points to 1e-12).

[`export_text()`][spacegrasp_jax.analysis.export.export_text] writes one format;
[`loop_settings()`][spacegrasp_jax.analysis.export.loop_settings] reads the settings from a realism and
a scenario's step. ``spacegrasp export`` is the command line's face of it.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math

import numpy as np

from spacegrasp_jax.loop.control.gains import GAINS_USED, Gains
from spacegrasp_jax.loop.control.registry import GAIN_GROUPS
from spacegrasp_jax.loop.control.schedule import VARIABLES, GainSchedule
from spacegrasp_jax.loop.realism import Realism

#: The formats [`export_text()`][spacegrasp_jax.analysis.export.export_text] writes.
FORMATS = ("json", "yaml", "c-header", "csv")


#: Each gain group's unit, meaning and equation (the paper's numbering), as its law declares
#: it ([`GainGroup`][spacegrasp_jax.loop.control.groups.GainGroup]).
GROUPS = GAIN_GROUPS


@dataclasses.dataclass(frozen=True)
class LoopSettings:
    """The loop the gains assume.

    Attributes:
        control_period_s: s, the law's period (the Dynamic-Jacobian admittance or the
            Cartesian law, and the F/T sensor's reading).
        servo_period_s: s, the joint PID's period (reads the joint sensors at each tick).
        delay_periods: whole control periods between measurement and actuation.
        torque_limit_Nm: (N,) N m, each joint's torque limit (``inf``: none).
        saturation: ``"hard"`` (clip) or ``"smooth"`` (``limit tanh(u / limit)``).
        anti_windup: whether the PID's integrator holds while the torque saturates.
        ft_cutoff_hz: Hz, the first-order low-pass on the measured wrench (0: none).
        pid_ramp_s: s, the PID gains are scaled by ``min(t / pid_ramp_s, 1)^2``.
    """

    control_period_s: float
    servo_period_s: float
    delay_periods: int
    torque_limit_Nm: tuple[float, ...]
    saturation: str
    anti_windup: bool
    ft_cutoff_hz: float
    pid_ramp_s: float = 1.0


#: The joint PID as the gains assume it (``spacegrasp_jax.loop.control.pid``), for the files' comments.
PID_FORM = (
    "u = ramp(t) (kp e + ki I + kd D) per joint at the servo period T, e = qd_des - qd (rad/s); "
    "I += e T (this tick's error included); D = (e - e_previous) / T; ramp(t) = min(t / pid_ramp_s, 1)^2"
)

#: Each setting's unit and meaning, for the files' comments.
SETTINGS = {
    "control_period_s": ("s", "period of the law (admittance or Cartesian) and of the F/T reading"),
    "servo_period_s": ("s", "period of the joint PID, which reads the joint sensors"),
    "delay_periods": ("control periods", "delay between measurement and actuation"),
    "torque_limit_Nm": ("N m", "joint torque limits, one a joint (inf: none)"),
    "saturation": ("", "saturation law: hard (clip) or smooth (limit tanh(u / limit))"),
    "anti_windup": ("", "the PID integrator holds while the torque saturates"),
    "ft_cutoff_hz": ("Hz", "first-order low-pass on the measured wrench (0: none)"),
    "pid_ramp_s": ("s", "kp, ki, kd scaled by min(t / pid_ramp_s, 1)^2 (the paper, section 4)"),
}


def loop_settings(realism: Realism | None, dt: float, n_joints: int = 7) -> LoopSettings:
    """The settings of a loop: ``realism`` (``None``: the paper's ideal loop) on a scenario
    of step ``dt`` (s), for an arm of ``n_joints`` joints (the paper's 7)."""
    if realism is None:
        return LoopSettings(dt, dt, 0, (math.inf,) * n_joints, "hard", True, 0.0)
    return LoopSettings(
        control_period_s=realism.steps_per_period(dt) * dt,
        servo_period_s=realism.steps_per_servo(dt) * dt,
        delay_periods=int(realism.delay_periods),
        torque_limit_Nm=tuple(float(x) for x in np.asarray(realism.torque_limit_Nm)),
        saturation=realism.saturation,
        anti_windup=bool(realism.anti_windup),
        ft_cutoff_hz=float(realism.cutoff_hz),
    )


#: The formats a gain schedule exports to.
SCHEDULE_FORMATS = ("json", "c-header")


def export_text(
    gains: Gains | GainSchedule,
    controller: str,
    settings: LoopSettings,
    file_format: str,
    *,
    source: str = "",
    prefix: str = "SG",
) -> str:
    """The gains ``controller`` uses (``GAINS_USED``) and ``settings`` as the text of a file
    of ``file_format`` (one of ``FORMATS``). ``source``: where the gains came from (a
    comment); ``prefix``: the C header's names (``<prefix>_kp``, ``<prefix>_Kd``: a gain
    keeps its case, ``Kd`` and ``kd`` being two groups; ``<prefix>_CONTROL_PERIOD_S``, ...).

    A gain schedule writes ``SCHEDULE_FORMATS`` only.

    Raises:
        ValueError: an unknown format or controller, a prefix that is not a C identifier,
            or a schedule in a format other than ``SCHEDULE_FORMATS``.
    """
    if controller not in GAINS_USED:
        raise ValueError(f"controller: expected one of {', '.join(GAINS_USED)}, got {controller!r}")
    if file_format in ("c-header",) and (not prefix.isidentifier() or not prefix.isascii()):
        raise ValueError(f"prefix: {prefix!r} is not a C identifier")
    if isinstance(gains, GainSchedule):
        return _schedule_text(gains, controller, settings, file_format, source, prefix)
    values = {name: [float(x) for x in np.asarray(getattr(gains, name))] for name in GAINS_USED[controller]}
    title = f"spacegrasp-jax gains of the {controller} law" + (f", from {source}" if source else "")
    if file_format == "json":
        return _json(values, controller, settings, title)
    if file_format == "yaml":
        return _yaml(values, controller, settings, title)
    if file_format == "c-header":
        return _c_header(values, controller, settings, title, prefix)
    if file_format == "csv":
        return _csv(values, settings)
    raise ValueError(f"format: expected one of {', '.join(FORMATS)}, got {file_format!r}")


def _schedule_text(
    schedule: GainSchedule, controller: str, settings: LoopSettings, file_format: str, source: str, prefix: str
) -> str:
    if file_format not in SCHEDULE_FORMATS:
        raise ValueError(
            f"format: a gain schedule exports as {' or '.join(SCHEDULE_FORMATS)} (its knot tables), not {file_format}"
        )
    names = GAINS_USED[controller]
    knots = {name: [float(x) for x in np.asarray(schedule.knots[name])] for name in names}
    values = {name: [[float(x) for x in row] for row in np.asarray(schedule.values[name])] for name in names}
    title = f"spacegrasp-jax gain schedule of the {controller} law" + (f", from {source}" if source else "")
    if file_format == "json":
        document = json.loads(_json({name: rows[0] for name, rows in values.items()}, controller, settings, title))
        document["gains"] = schedule.to_dict(controller)
        document["blend"] = BLEND_FORM
        return json.dumps(document, indent=1) + "\n"
    return _c_schedule(knots, values, schedule.variable, controller, settings, title, prefix)


#: The schedule's blend, for the files' comments (documentation, Gain schedules).
BLEND_FORM = (
    "between knots x_i <= x < x_i+1: s = (x - x_i) / (x_i+1 - x_i), w = s^2 (3 - 2 s), "
    "g = exp((1 - w) log g_i + w log g_i+1); x is held to [x_0, x_K-1]; a group of one knot is constant"
)


def _c_schedule(
    knots: dict, values: dict, variable: str, controller: str, settings: LoopSettings, title: str, prefix: str
) -> str:
    """The C header of a schedule: the constant parts as a gain set's, each group's knot table,
    and ``<prefix>_gains_at()``."""
    base = _c_header({name: rows[0] for name, rows in values.items()}, controller, settings, title, prefix)
    body, end = base.rsplit("#endif", 1)
    lines = [
        "/* The gain schedule: each group's gains at its knots on the scheduling variable, and",
        f" * {prefix}_gains_at(x, &gains), the gains at x. The arrays above are the first knot's.",
        f" * {BLEND_FORM}. */",
        f'#define {prefix}_SCHEDULE_VARIABLE "{variable}" /* [{VARIABLES[variable]}] */',
    ]
    for name in values:
        count, length = len(knots[name]), len(values[name][0])
        rows = ", ".join("{" + ", ".join(map(_c_number, row)) + "}" for row in values[name])
        lines.append(f"#define {prefix}_{name}_KNOT_COUNT {count}")
        lines.append(
            f"static const double {prefix}_{name}_KNOTS[{count}] = {{{', '.join(map(_c_number, knots[name]))}}};"
        )
        lines.append(f"static const double {prefix}_{name}_AT_KNOTS[{count}][{length}] = {{{rows}}};")
    fields = " ".join(f"double {name}[{len(values[name][0])}];" for name in values)
    lines += [
        "",
        f"typedef struct {{ {fields} }} {prefix}_gains;",
        "",
        "/* One group's gains at x from its knot table (count knots, length gains a knot). */",
        f"static inline void {prefix}_blend(int count, const double *knots, int length, const double *table, double x,",
        "                            double *out) {",
        "    int i = 0, j;",
        "    double s, w;",
        "    if (count == 1) {",
        "        for (j = 0; j < length; ++j) out[j] = table[j];",
        "        return;",
        "    }",
        "    if (x < knots[0]) x = knots[0];",
        "    if (x > knots[count - 1]) x = knots[count - 1];",
        "    while (i < count - 2 && x >= knots[i + 1]) ++i;",
        "    s = (x - knots[i]) / (knots[i + 1] - knots[i]);",
        "    w = s * s * (3.0 - 2.0 * s);",
        "    for (j = 0; j < length; ++j)",
        "        out[j] = exp((1.0 - w) * log(table[i * length + j]) + w * log(table[(i + 1) * length + j]));",
        "}",
        "",
        f"/* The gains at x, the scheduling variable ({variable}, {VARIABLES[variable]}). */",
        f"static inline void {prefix}_gains_at(double x, {prefix}_gains *gains) {{",
    ]
    for name in values:
        lines.append(
            f"    {prefix}_blend({prefix}_{name}_KNOT_COUNT, {prefix}_{name}_KNOTS, {len(values[name][0])}, "
            f"&{prefix}_{name}_AT_KNOTS[0][0], x, gains->{name});"
        )
    lines += ["}", ""]
    return body + "\n".join(lines) + "\n#endif" + end


def _settings_dict(settings: LoopSettings) -> dict:
    return dataclasses.asdict(settings) | {"torque_limit_Nm": list(settings.torque_limit_Nm)}


def _json(values: dict, controller: str, settings: LoopSettings, title: str) -> str:
    document = {
        "about": title,
        "controller": controller,
        "gains": values,
        "units": {name: GROUPS[name].unit for name in values},
        "meaning": {name: GROUPS[name].meaning for name in values},
        "equations": {name: GROUPS[name].equation for name in values},
        "settings": {
            name: ([None if math.isinf(x) else x for x in value] if name == "torque_limit_Nm" else value)
            for name, value in _settings_dict(settings).items()
        },
        "settings_units": {name: unit for name, (unit, _) in SETTINGS.items()},
        "settings_note": "torque_limit_Nm: null means no limit",
        "pid_form": PID_FORM,
    }
    return json.dumps(document, indent=1) + "\n"


def _yaml_number(value: float) -> str:
    """A float as YAML 1.1 and 1.2 readers both read it back exactly (``1.0e-05``, not
    ``1e-05``, which YAML 1.1 reads as a string; ``.inf`` for infinity)."""
    if math.isinf(value):
        return ".inf" if value > 0 else "-.inf"
    text = repr(float(value))
    mantissa, separator, exponent = text.partition("e")
    if separator and "." not in mantissa:
        text = f"{mantissa}.0e{exponent}"
    return text


def _yaml(values: dict, controller: str, settings: LoopSettings, title: str) -> str:
    lines = [f"# {title}", f"# joint PID: {PID_FORM}", f"controller: {controller}", "gains:"]
    for name, numbers in values.items():
        group = GROUPS[name]
        lines.append(f"  # {group.meaning}; {group.unit}; {group.equation}")
        lines.append(f"  {name}: [{', '.join(_yaml_number(x) for x in numbers)}]")
    lines.append("settings:  # the loop these gains were designed and checked in")
    for name, value in _settings_dict(settings).items():
        unit, meaning = SETTINGS[name]
        if isinstance(value, list):
            text = f"[{', '.join(_yaml_number(x) for x in value)}]"
        elif isinstance(value, bool):
            text = "true" if value else "false"
        elif isinstance(value, str):
            text = value
        elif isinstance(value, int):
            text = str(value)
        else:
            text = _yaml_number(value)
        lines.append(f"  # {meaning}" + (f" [{unit}]" if unit else ""))
        lines.append(f"  {name}: {text}")
    return "\n".join(lines) + "\n"


def _c_number(value: float) -> str:
    if math.isinf(value):
        return "INFINITY" if value > 0 else "-INFINITY"
    return repr(float(value))


def _c_header(values: dict, controller: str, settings: LoopSettings, title: str, prefix: str) -> str:
    guard = f"{prefix.upper()}_GAINS_H"
    lines = [
        f"/* {title}.",
        " * Arrays of doubles, one entry per axis or joint; the settings below are the loop",
        " * these gains were designed and checked in.",
        f" * Joint PID: {PID_FORM}. */",
        f"#ifndef {guard}",
        f"#define {guard}",
        "",
        "#include <math.h> /* INFINITY: no torque limit */",
        "",
        f'#define {prefix}_CONTROLLER "{controller}"',
    ]
    for name, numbers in values.items():
        group = GROUPS[name]
        lines.append("")
        lines.append(f"/* {group.meaning}; {group.unit}; {group.equation} */")
        lines.append(f"#define {prefix}_{name}_LENGTH {len(numbers)}")  # the paper's case: Kd is not kd
        lines.append(f"static const double {prefix}_{name}[{len(numbers)}] = {{{', '.join(map(_c_number, numbers))}}};")
    lines.append("")
    lines.append("/* The loop settings. */")
    for name, value in _settings_dict(settings).items():
        unit, meaning = SETTINGS[name]
        comment = f"/* {meaning}" + (f" [{unit}]" if unit else "") + " */"
        symbol = f"{prefix}_{name.upper()}"
        if isinstance(value, list):
            lines.append(comment)
            lines.append(f"static const double {symbol}[{len(value)}] = {{{', '.join(map(_c_number, value))}}};")
        elif name == "saturation":
            lines.append(f"#define {symbol}_SMOOTH {int(value == 'smooth')} {comment}")
        elif isinstance(value, bool):
            lines.append(f"#define {symbol} {int(value)} {comment}")
        elif isinstance(value, int):
            lines.append(f"#define {symbol} {value} {comment}")
        else:
            lines.append(f"#define {symbol} {_c_number(value)} {comment}")
    lines += ["", f"#endif /* {guard} */", ""]
    return "\n".join(lines)


def _csv(values: dict, settings: LoopSettings) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["kind", "name", "index", "value", "unit", "reference"])
    for name, numbers in values.items():
        group = GROUPS[name]
        for index, value in enumerate(numbers):
            writer.writerow(["gain", name, index, repr(value), group.unit, f"{group.meaning}; {group.equation}"])
    for name, value in _settings_dict(settings).items():
        unit, meaning = SETTINGS[name]
        items = value if isinstance(value, list) else [value]
        for index, item in enumerate(items):
            text = repr(float(item)) if isinstance(item, float) else str(item).lower()
            writer.writerow(["setting", name, index, text, unit, meaning])
    return buffer.getvalue()


__all__ = [
    "BLEND_FORM",
    "FORMATS",
    "SCHEDULE_FORMATS",
    "GROUPS",
    "PID_FORM",
    "SETTINGS",
    "LoopSettings",
    "export_text",
    "loop_settings",
]
