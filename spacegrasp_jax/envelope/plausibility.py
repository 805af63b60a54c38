"""Plausibility: inputs that are probably a mistake (a unit slip: degrees for radians,
millimetres for metres) and results that are probably not what the user wanted (a run that
never touched the target), each said in one line with the value and what was probably
meant. Nothing here refuses anything: a user may mean an odd value.

The command line prints each line as ``spacegrasp: warning: ...``: the inputs' before
compiling, the result's after the run (a failed capture or a runaway has its own verdict
line, [`spacegrasp_jax.jobs.anatomy.verdict_line()`][spacegrasp_jax.jobs.anatomy.verdict_line]).
"""

from __future__ import annotations

import inspect
import math

import numpy as np

from spacegrasp_jax.envelope.scenario import Scenario, paper_scenario

#: The paper's contact sphere (section 4; eq 20): its radius (m) and stiffness ``k`` (N m^2).
PAPER_CONTACT = {
    name: inspect.signature(paper_scenario).parameters[name].default for name in ("sphere_radius", "contact_stiffness")
}

#: How far from the paper's a contact parameter may be before it is called implausible.
CONTACT_FACTOR = 100.0

#: The heaviest and lightest plausible free-floating target (kg): the heaviest spacecraft
#: assembled in orbit, the ISS, is about 4.2e5 kg; a target under 1 kg is not a satellite
#: with a launch adapter ring.
TARGET_MASS_RANGE_KG = (1.0, 1.0e6)

#: The fastest plausible target at the start of a capture: drift (m/s) and tumble (rad/s).
#: A capture is attempted at mm/s and deg/s; these bounds catch values written in mm/s or
#: deg/s, and a target that the arm could not follow in any case.
TARGET_SPEED_MPS = 1.0
TARGET_RATE_RADPS = 1.0


def input_warnings(scenario: Scenario) -> list[str]:
    """One line for each input of ``scenario`` outside a physically sensible range: joint
    angles beyond a turn (degrees?), a contact radius or stiffness more than
    ``CONTACT_FACTOR`` times from the paper's, a target outside
    ``TARGET_MASS_RANGE_KG`` or whose radius of gyration is not between 1 cm and 100 m,
    a target drifting faster than ``TARGET_SPEED_MPS`` or tumbling faster than
    ``TARGET_RATE_RADPS``."""
    lines = []
    q = np.asarray(scenario.initial.q, dtype=float)
    for joint in np.flatnonzero(np.abs(q) > 2.0 * math.pi):
        lines.append(
            f"q_init[{joint}] = {q[joint]:g} rad is more than a turn: degrees? ({math.radians(q[joint]):.4g} rad)"
        )
    for name, field, unit in (
        ("contact sphere radius", "sphere_radius", "m"),
        ("contact stiffness", "contact_stiffness", "N m^2"),
    ):
        value, paper = float(getattr(scenario, field)), PAPER_CONTACT[field]
        ratio = value / paper
        if ratio > CONTACT_FACTOR or ratio < 1.0 / CONTACT_FACTOR:
            hint = f": millimetres? ({value / 1e3:g} m)" if unit == "m" and ratio > CONTACT_FACTOR else ""
            lines.append(f"{name} = {value:g} {unit} is {ratio:.3g} times the paper's {paper:g} {unit}{hint}")
    if scenario.free_target:
        lines += _target_warnings(scenario)
    return lines


def _target_warnings(scenario: Scenario) -> list[str]:
    lines = []
    mass = float(scenario.target.mass)
    low, high = TARGET_MASS_RANGE_KG
    if not low <= mass <= high:
        lines.append(
            f"target mass = {mass:g} kg is outside a satellite's range ({low:g} to {high:g} kg; the ISS is about 4.2e5 kg)"
        )
    moments = np.linalg.eigvalsh(np.asarray(scenario.target.inertia, dtype=float))
    gyration = np.sqrt(np.abs(moments) / mass)
    if np.any(gyration < 0.01) or np.any(gyration > 100.0):
        lines.append(
            f"target inertia: radii of gyration {', '.join(f'{g:.3g}' for g in gyration)} m for {mass:g} kg are not "
            f"a body's (1 cm to 100 m): g m^2 or another unit?"
        )
    state = scenario.initial.target
    speed = float(np.linalg.norm(np.asarray(state.v, dtype=float)))
    if speed > TARGET_SPEED_MPS:
        lines.append(f"target velocity = {speed:g} m/s: mm/s? ({speed / 1e3:g} m/s)")
    rate = float(np.linalg.norm(np.asarray(state.w, dtype=float)))
    if rate > TARGET_RATE_RADPS:
        lines.append(f"target angular velocity = {rate:g} rad/s: deg/s? ({math.radians(rate):.4g} rad/s)")
    return lines


def result_warnings(summary: dict) -> list[str]:
    """One line for a finished run (its ``summary.json``) that is probably not what was
    wanted: it never touched the target. A diverged run has no such line (its error says
    what happened)."""
    if summary.get("diverged"):
        return []
    force = summary.get("max_contact_force_N")
    if force is not None and not force > 0.0:
        return [
            "the end-effector never touched the target (max contact force 0 N): check the contact sphere "
            "(radius, centre), the trajectory's end pose and the duration"
        ]
    return []


__all__ = [
    "CONTACT_FACTOR",
    "PAPER_CONTACT",
    "TARGET_MASS_RANGE_KG",
    "TARGET_RATE_RADPS",
    "TARGET_SPEED_MPS",
    "input_warnings",
    "result_warnings",
]
