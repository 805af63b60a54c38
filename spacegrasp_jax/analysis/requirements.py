"""What the gains require: success against the width of each perturbation, the widths at
which it falls below a level, and the share of failures each perturbation takes part in.

A GNC engineer brings one question to a requirements review: "to capture 99% of the time
with these gains, the LAR estimate must be within X mm, the F/T bias within Y N, the approach
on time within Z s". This module answers it on the campaigns' own machinery:

* **Requirement curves** ([`curves()`][spacegrasp_jax.analysis.requirements.curves]): for
  each perturbation group (``GROUPS``) and width ``k`` (1x to 4x), a campaign in which that
  group's half-widths are ``k`` times their reference (``REFERENCE_RANGES``) and every other
  group at its reference, and one with every group at ``k`` ("all together"). The same
  seed draws the same units everywhere, so the point at ``k`` moves every sample ``k`` times
  as far: the curves are smooth in ``k``, not re-drawn. Each point's success has its 95%
  Wilson interval.
* **Requirements** ([`crossings()`][spacegrasp_jax.analysis.requirements.crossings]): the width
  at which a curve falls below each level (99% and 90% by default), interpolated linearly
  between the widths run, with the bracket of widths the interval's bounds give (where the
  upper bound falls below the level, where the lower bound does); said in the group's own
  units as the half-widths it may have.
* **Failure attribution** ([`failure_sensitivity()`][spacegrasp_jax.analysis.requirements.failure_sensitivity]):
  grouped Sobol indices ([`spacegrasp_jax.analysis.sensitivity`][spacegrasp_jax.analysis.sensitivity])
  of a capture's failure over the reference envelope, the sensor noise's realisation a group
  of its own: a group's total index is the share of the failures' variance it takes part in.

Reference widths (``REFERENCE_RANGES``): the campaigns' envelope, and, for what it leaves
out, about the flight-like loop's own value of each error: the approach's timing +-3 mm
(+-0.25 s of contact time; 4x: +-1 s), the F/T bias +-0.25 N and +-0.0125 N m per axis
(the preset's fixed bias is up to 0.25 N and 0.01 N m), its noise up to 0.05 N and
0.0025 N m more (the preset's own), and one motor down to 90% of its limit (4x: 60%).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np

from spacegrasp_jax.analysis import sensitivity
from spacegrasp_jax.envelope import statistics
from spacegrasp_jax.envelope.perturbations import Perturbation, PerturbationError, PerturbationRanges, draw_units

#: Perturbation groups: name -> (words, the half-widths it scales, the drawn units it owns).
GROUPS = {
    "lar_pose": ("the LAR's pose", ("lar_position_m", "lar_angle_rad"), ("dp_lar", "dr_lar")),
    "lar_estimate": (
        "the controller's estimate of the LAR pose",
        ("lar_estimate_position_m", "lar_estimate_angle_rad"),
        ("dp_lar_estimate", "dr_lar_estimate"),
    ),
    "initial_state": (
        "the arm's and the satellite's initial state",
        ("q_init_rad", "joint_rate_radps", "base_speed_mps", "base_rate_radps"),
        ("dq_init", "qd_init", "V_base_init"),
    ),
    "contact": (
        "the contact's stiffness and the sphere's radius",
        ("stiffness_factor", "radius_fraction"),
        ("stiffness_scale", "radius_scale"),
    ),
    "satellite_model": (
        "the satellite's mass and inertia (the controller believes the nominal)",
        ("satellite_mass_fraction", "satellite_inertia_fraction"),
        ("satellite_mass_scale", "satellite_inertia_scale"),
    ),
    "approach_timing": ("the approach's timing", ("approach_offset_m",), ("approach_offset",)),
    "ft_bias": ("the F/T sensor's bias", ("ft_force_bias_N", "ft_torque_bias_Nm"), ("ft_force_bias", "ft_torque_bias")),
    "ft_noise": (  # one level for the sensor, as a campaign draws it: ft_torque_noise_std follows
        "the F/T sensor's noise level",
        ("ft_force_noise_std_N", "ft_torque_noise_std_Nm"),
        ("ft_force_noise_std",),
    ),
    "actuator": (
        "a motor at reduced torque",
        ("actuator_torque_loss_fraction",),
        ("actuator_joint", "actuator_torque_scale"),
    ),
    "target": (
        "a free-floating target's mass, inertia, CoM and motion",
        (
            "target_mass_fraction",
            "target_inertia_fraction",
            "target_speed_mps",
            "target_rate_radps",
            "target_mass_log_range",
            "target_com_offset_m",
        ),
        (
            "target_mass_scale",
            "target_inertia_scale",
            "target_velocity",
            "target_angular_velocity",
            "target_mass_log_scale",
            "target_com_offset",
        ),
    ),
}

#: The group name of every perturbation group scaled together.
ALL = "all"

#: The reference envelope the widths multiply (module docstring).
REFERENCE_RANGES = PerturbationRanges(
    approach_offset_m=0.003,
    ft_force_bias_N=0.25,
    ft_torque_bias_Nm=0.0125,
    ft_force_noise_std_N=0.05,
    ft_torque_noise_std_Nm=0.0025,
    actuator_torque_loss_fraction=0.1,
)

#: The widths of a requirement curve, in multiples of the reference.
WIDTHS = (1.0, 1.5, 2.0, 3.0, 4.0)

#: The success levels a requirement is stated at.
LEVELS = (0.99, 0.90)


class RequirementsError(ValueError):
    """Invalid settings of a requirements study; the message names the setting."""


class StudyInterrupted(Exception):
    """A stop request ended the study between two points' chunks; ``--resume`` continues."""


def groups_for(free_target: bool) -> tuple[str, ...]:
    """The groups a scenario can be perturbed in: every one, the target's only with a
    free-floating target."""
    return tuple(name for name in GROUPS if free_target or name != "target")


def scaled_group(ranges: PerturbationRanges, group: str, width: float) -> PerturbationRanges:
    """``ranges`` with ``group``'s half-widths ``width`` times theirs (``ALL``: every
    group's, ``ranges.scaled(width)``); the stiffness factor to the power ``width``. Raises
    RequirementsError where a fraction would reach 1."""
    if group != ALL and group not in GROUPS:
        raise RequirementsError(f"group: expected one of {', '.join(GROUPS)} or {ALL}, got {group!r}")
    try:
        return ranges.scaled(width, None if group == ALL else GROUPS[group][1])
    except PerturbationError as error:
        raise RequirementsError(str(error)) from None


def half_widths(ranges: PerturbationRanges, group: str, width: float) -> dict[str, float]:
    """The half-widths ``group`` has at ``width``: the requirement in its own units."""
    fields = [name for members in GROUPS.values() for name in members[1]] if group == ALL else GROUPS[group][1]
    scaled = scaled_group(ranges, group, width)
    return {name: float(getattr(scaled, name)) for name in fields}


def crossings(widths, successes, samples: int, levels=LEVELS) -> dict[str, dict]:
    """Where a curve (``successes`` (W,) of ``samples`` captures at ``widths`` (W,),
    increasing) falls below each level: ``width`` by linear interpolation of the rates
    between the widths run (``None``: it never does up to the last width; the first width
    if it is below there already, ``below_at_first``), and ``bracket``: the widths at which
    the upper and the lower bound of the 95% interval fall below it (``None`` where they
    never do)."""
    widths = np.asarray(widths, dtype=float)
    intervals = [statistics.success_interval(int(s), samples) for s in successes]
    result = {}
    for level in levels:
        found = {}
        for key, values in (
            ("width", [i["rate"] for i in intervals]),
            ("upper_below_at", [i["high"] for i in intervals]),
            ("lower_below_at", [i["low"] for i in intervals]),
        ):
            found[key] = _first_below(widths, np.asarray(values), level)
        result[f"{level:g}"] = {
            "width": found["width"],
            "below_at_first": bool(intervals[0]["rate"] < level),
            "bracket": (found["lower_below_at"], found["upper_below_at"]),
        }
    return result


def _first_below(widths: np.ndarray, values: np.ndarray, level: float) -> float | None:
    below = np.flatnonzero(values < level)
    if below.size == 0:
        return None
    i = int(below[0])
    if i == 0:
        return float(widths[0])
    w0, w1, v0, v1 = widths[i - 1], widths[i], values[i - 1], values[i]
    return float(w0 + (v0 - level) / (v0 - v1) * (w1 - w0))


def curves(
    run_point: Callable[[str, float, PerturbationRanges], dict[str, np.ndarray]],
    reference: PerturbationRanges,
    groups,
    widths=WIDTHS,
    levels=LEVELS,
) -> dict:
    """Requirement curves: ``run_point(group, width, ranges)`` runs the campaign of one point
    and returns each gain set's per-capture success ((n,) bool, label -> flags); for every
    group (and ``ALL``) and width. Returns ``{group: {"widths", "half_widths", label:
    {"successes", "samples", "intervals", "crossings"}}}``."""
    result = {}
    for group in [*groups, ALL]:
        points = [run_point(group, width, scaled_group(reference, group, width)) for width in widths]
        entry = {"widths": list(widths), "half_widths": [half_widths(reference, group, w) for w in widths]}
        for label in points[0]:
            hits = [np.asarray(point[label], dtype=bool) for point in points]
            samples = int(hits[0].size)
            successes = [int(h.sum()) for h in hits]
            entry[label] = {
                "successes": successes,
                "samples": samples,
                "intervals": [statistics.success_interval(s, samples) for s in successes],
                "crossings": crossings(widths, successes, samples, levels),
            }
        result[group] = entry
    return result


def units_of_points(points: np.ndarray, groups, like: Perturbation) -> tuple[Perturbation, np.ndarray]:
    """Design points (M, d) in [0, 1]^d as units (``like``'s fields, leading axis M; the
    fields of no group of ``groups`` at 0, their nominal) and the noise column (M,), the
    last: columns are laid out group by group, field by field, in ``GROUPS``' order (see
    [`design_columns()`][spacegrasp_jax.analysis.requirements.design_columns]). A point of
    ``target_com_offset``'s three columns maps to the unit ball uniformly (radius ``u0^(1/3)``,
    polar ``arccos(2 u1 - 1)``, azimuth ``2 pi u2``); every other column to ``2 u - 1``."""
    points = np.asarray(points, dtype=float)
    count = points.shape[0]
    fields = {name: np.zeros((count, *np.shape(value))) for name, value in vars(like).items()}
    column = 0
    for group in groups:
        for name in GROUPS[group][2]:
            size = int(np.size(vars(like)[name]))
            block = points[:, column : column + size]
            if name == "target_com_offset":
                radius = block[:, 0] ** (1.0 / 3.0)
                polar, azimuth = np.arccos(2.0 * block[:, 1] - 1.0), 2.0 * np.pi * block[:, 2]
                value = radius[:, None] * np.stack(
                    [np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)], axis=1
                )
            else:
                value = 2.0 * block - 1.0
            fields[name] = value.reshape(fields[name].shape)
            column += size
    fields["ft_torque_noise_std"] = fields["ft_force_noise_std"]  # one noise level for the sensor (draw_units)
    return Perturbation(**fields), points[:, column]


def design_columns(groups, like: Perturbation) -> list[list[int]]:
    """The design's column groups for ``groups`` (each group's units' columns, in order),
    then the sensor noise's realisation: one column, a group of its own."""
    columns, column = [], 0
    for group in groups:
        size = sum(int(np.size(vars(like)[name])) for name in GROUPS[group][2])
        columns.append(list(range(column, column + size)))
        column += size
    return [*columns, [column]]


def noise_keys_of(noise: np.ndarray, seed: int) -> np.ndarray:
    """(M, 2) noise keys for the noise column's values in [0, 1]: ``fold_in(PRNGKey(seed),
    floor(u 2^31))``: one realisation per value, the same value the same realisation."""
    base = jax.random.PRNGKey(seed)
    indices = np.minimum(np.floor(np.asarray(noise) * 2**31), 2**31 - 1).astype(np.uint32)
    return np.asarray(jax.vmap(lambda i: jax.random.fold_in(base, i))(indices))


def failure_sensitivity(
    failures_at: Callable[[Perturbation, np.ndarray], np.ndarray],
    groups,
    count: int,
    seed: int,
    n_joints: int,
) -> dict:
    """Grouped Sobol indices of a capture's failure over the reference envelope:
    ``failures_at(units, keys)`` (leading axis M) -> (M,) 0 or 1, evaluated on Saltelli's
    design of ``count`` base points (a power of two) for ``groups`` and the noise
    ([`sensitivity.sobol_indices()`][spacegrasp_jax.analysis.sensitivity.sobol_indices]).
    Returns ``{"groups": [..., "sensor_noise"], "failure_rate", the indices' fields}``."""
    like = jax.tree.map(np.asarray, draw_units(jax.random.PRNGKey(0), n_joints=n_joints))
    design = sensitivity.saltelli_design(design_columns(groups, like), count, seed)
    units, noise = units_of_points(design.points, groups, like)
    failures = np.asarray(failures_at(units, noise_keys_of(noise, seed)), dtype=float)
    indices = sensitivity.sobol_indices(design, failures)
    return {
        "groups": [*groups, "sensor_noise"],
        "failure_rate": float(np.mean(failures[: 2 * count])),
        **{name: np.asarray(value).tolist() if np.ndim(value) else value for name, value in indices.items()},
    }


def requirement_lines(study: dict, label: str, reference: PerturbationRanges) -> list[str]:
    """The requirements ``label``'s gains impose, one line per group and level, in words."""
    lines = []
    for group, entry in study.items():
        if group == ALL or label not in entry:
            continue
        for level, crossing in entry[label]["crossings"].items():
            words = GROUPS[group][0]
            if crossing["width"] is None:
                widest = entry["widths"][-1]
                lines.append(f"{100 * float(level):g}%: {words} up to {widest:g}x the reference or more")
            elif crossing["below_at_first"]:
                lines.append(f"{100 * float(level):g}%: below already at the reference width of {words}")
            else:
                width = crossing["width"]
                values = ", ".join(
                    f"{name} {value:.3g}" for name, value in half_widths(reference, group, width).items()
                )
                lines.append(f"{100 * float(level):g}%: {words} within {width:.2f}x the reference ({values})")
    return lines


__all__ = [
    "ALL",
    "GROUPS",
    "LEVELS",
    "REFERENCE_RANGES",
    "WIDTHS",
    "RequirementsError",
    "StudyInterrupted",
    "StudySettings",
    "crossings",
    "curves",
    "design_columns",
    "failure_sensitivity",
    "groups_for",
    "half_widths",
    "noise_keys_of",
    "requirement_lines",
    "run_study",
    "scaled_group",
    "units_of_points",
]


@dataclasses.dataclass(frozen=True)
class StudySettings:
    """A requirements study's sizes.

    Attributes:
        groups: the perturbation groups whose curves are run (``GROUPS``' names).
        widths: the widths, in multiples of the reference, increasing.
        levels: the success levels the requirements are stated at.
        n: captures per point of a curve (every point draws the same ``n``).
        sobol: base points of the failure attribution's design (a power of two; 0: none):
            ``sobol * (len(groups) + 3)`` captures per gain set.
        seed: the campaigns' seed, and the design's.
    """

    groups: tuple[str, ...]
    widths: tuple[float, ...] = WIDTHS
    levels: tuple[float, ...] = LEVELS
    n: int = 500
    sobol: int = 0
    seed: int = 0

    def __post_init__(self):
        unknown = [group for group in self.groups if group not in GROUPS]
        if unknown or not self.groups or len(set(self.groups)) != len(self.groups):
            raise RequirementsError(
                f"groups: distinct names of {', '.join(GROUPS)}, got {', '.join(self.groups) or 'none'}"
            )
        widths = [float(w) for w in self.widths]
        if not widths or any(not (math.isfinite(w) and w > 0) for w in widths) or widths != sorted(set(widths)):
            raise RequirementsError(f"widths: positive multiples, increasing, got {self.widths}")
        if not self.levels or any(not 0.0 < level < 1.0 for level in self.levels):
            raise RequirementsError(f"levels: success levels in (0, 1), got {self.levels}")
        if self.n < 1:
            raise RequirementsError(f"n: captures per point, at least 1, got {self.n}")
        if self.sobol and (self.sobol < 2 or self.sobol & (self.sobol - 1)):
            raise RequirementsError(f"sobol: a power of two of at least 2 base points (0: none), got {self.sobol}")


def run_study(
    robot,
    scenario,
    variants: list,
    config,
    reference: PerturbationRanges,
    settings: StudySettings,
    out: Path,
    *,
    progress: Callable[[str], None] | None = None,
    stop=None,
) -> dict:
    """Run a requirements study of ``variants`` (campaign ``Variant``s, one law) about the
    reference envelope ``reference``, as campaigns of ``config`` (its criteria, realism,
    chunk; its ``n``, ``seed`` and ``ranges`` set per point); each point's campaign in
    ``out/points/<group>_x<width>`` (resumed where it stopped). Returns the document
    ``requirements.json`` holds: ``curves``, ``requirements`` (lines per gain set) and, with
    ``settings.sobol``, ``failure_attribution`` per gain set."""
    from spacegrasp_jax.analysis import worstcase
    from spacegrasp_jax.jobs import campaign
    from spacegrasp_jax.jobs.montecarlo import success

    say = progress or (lambda line: None)

    def run_point(group: str, width: float, ranges: PerturbationRanges) -> dict[str, np.ndarray]:
        folder = out / "points" / f"{group}_x{width:g}"
        point_config = dataclasses.replace(config, n=settings.n, seed=settings.seed, ranges=ranges)
        say(f"{group} at {width:g}x the reference: {settings.n} captures x {len(variants)} gain set(s)...")
        result = campaign.run_campaign(
            robot,
            scenario,
            variants,
            point_config,
            folder,
            resume=(folder / "campaign.json").exists(),
            progress=None,
            stop=stop,
        )
        if result.status != "done":
            raise StudyInterrupted
        return {variant.key: np.asarray(result.metrics[variant.key]["success"], dtype=bool) for variant in variants}

    document = {
        "settings": dataclasses.asdict(settings) | {"reference": reference.to_dict()},
        "curves": curves(run_point, reference, settings.groups, settings.widths, settings.levels),
    }
    document["requirements"] = {
        variant.key: requirement_lines(document["curves"], variant.key, reference) for variant in variants
    }
    if settings.sobol:
        attribution = {}
        reference_config = dataclasses.replace(config, n=1, seed=settings.seed, ranges=reference)
        for variant in variants:
            say(f"failure attribution of {variant.key}: {settings.sobol * (len(settings.groups) + 3)} captures...")
            size = config.chunk
            metrics_at, _ = worstcase.units_evaluator(
                robot,
                scenario,
                variant.gains,
                variant.controller,
                reference_config,
                size,
                f"requirements, {variant.key}",
            )

            def failures_at(units, keys, metrics_at=metrics_at):
                count, pieces = len(keys), []
                for start in range(0, count, size):
                    if stop is not None and stop.requested:
                        raise StudyInterrupted
                    block = jax.tree.map(lambda x: x[start : start + size], (units, keys))
                    pieces.append(~success(metrics_at(*block), config.criteria))
                return np.concatenate(pieces)

            attribution[variant.key] = failure_sensitivity(
                failures_at, settings.groups, settings.sobol, settings.seed, scenario.initial.q.shape[-1]
            )
        document["failure_attribution"] = attribution
    return document
