"""Monte-Carlo campaigns on the host: chunks, sharding over devices and hosts, resume, files.

A campaign evaluates ``n`` perturbed samples ([`perturbations`][spacegrasp_jax.envelope.perturbations]) for one
or more *variants* (a controller with a set of gains). Samples are processed in chunks of
``chunk``; each chunk is one call of a compiled function whose batch axis is sharded over a
1-D mesh of ALL devices of ALL processes (``jax.devices()``). On one CPU that mesh has one
device; with ``jax.distributed`` it spans the cluster; the code path is the same. Only the
per-sample metrics (and, on request, decimated time series) come back to the host.

Files in ``out`` (written by process 0, atomically):

* ``campaign.json``: the configuration, checked on ``resume``;
* ``chunks/<controller>/<gains>/<first sample>.npz``: one file per finished chunk, so an
  interrupted run loses at most the chunk in flight and resumes chunk by chunk;
* ``samples.npz``, ``summary.json`` and ``timeseries_<controller>_<gains>.npz``, once every
  chunk is done (see [`run_campaign()`][spacegrasp_jax.jobs.campaign.run_campaign]); the command line adds the figures.

For several hosts, ``out`` must be a folder that every process can read (a shared file
system): every process reads the finished chunks on resume so that all agree on what is left.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np
from jax.experimental import multihost_utils

from spacegrasp_jax.core.model import Robot, RobotConfigError, n_joints, paper_robot
from spacegrasp_jax.core.robot_files import load_robot
from spacegrasp_jax.envelope import statistics
from spacegrasp_jax.envelope.criteria import CaptureCriteria
from spacegrasp_jax.envelope.metrics import METRICS, TARGET_METRICS
from spacegrasp_jax.envelope.perturbations import PerturbationError, PerturbationRanges, check_for_scenario
from spacegrasp_jax.envelope.scenario import Scenario, scenario_from_dict
from spacegrasp_jax.jobs import anatomy, batching, experiment, records, runfiles
from spacegrasp_jax.jobs.montecarlo import FoldedMetrics, evaluate_samples, sample_loops
from spacegrasp_jax.jobs.records import RecordError, RunRecord, Variant, make_record
from spacegrasp_jax.loop.control import schedule
from spacegrasp_jax.loop.control.registry import law_named
from spacegrasp_jax.loop.control.schedule import gain_set_from_dict
from spacegrasp_jax.loop.realism import Realism, ideal, make_realism
from spacegrasp_jax.loop.simulate import Log, RunSpec

PERCENTILES = (5, 50, 95)


class CampaignError(ValueError):
    """An invalid campaign setting or an output folder that does not match; names the cause."""


@dataclasses.dataclass(frozen=True)
class CampaignConfig:
    """A Monte-Carlo campaign's settings.

    Attributes:
        n: number of samples (sample indices 0 .. n-1).
        seed: campaign seed; sample i is drawn with ``fold_in(PRNGKey(seed), i)``.
        chunk: samples per compiled call; a multiple of the number of devices. Memory grows
            with it; results do not depend on it.
        ranges: perturbation half-widths.
        criteria: when a sample is a capture
            ([`CaptureCriteria`][spacegrasp_jax.envelope.criteria.CaptureCriteria]; the defaults: 5 mm,
            1 deg, a torque threshold of 100 N m, 5 mm/s for a free target's final speed, rates
            no criterion). The commands set its rate limits to the robot's when a robot file
            states them ([`rate_limits_stated()`][spacegrasp_jax.core.robot_files.rate_limits_stated]).
        timeseries_every: keep every k-th log row of every sample (``None``: metrics only).
        pinv_damping: damping of the pseudoinverse (0: exact, the paper).
        device_batch: samples each device simulates at once (``None``: its whole share of the
            chunk). A device's share is run in sub-batches of this size, one after another; on a
            CPU, 128 keeps a sub-batch's states in cache. Must divide the share to take effect.
        realism: the loop's realism ([`spacegrasp_jax.loop.realism`][spacegrasp_jax.loop.realism]; ``None``: the paper's).
        identified: tell the controller each sample's perturbed satellite (a perfectly
            identified plant); by default it believes the nominal robot.
    """

    n: int
    seed: int = 0
    chunk: int = 64
    ranges: PerturbationRanges = PerturbationRanges()
    criteria: CaptureCriteria = CaptureCriteria()
    timeseries_every: int | None = None
    pinv_damping: float = 0.0
    device_batch: int | None = None
    realism: Realism | None = None
    identified: bool = False

    def __post_init__(self):
        for name in ("n", "seed", "chunk"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise CampaignError(f"{name}: must be an integer, got {value!r}")
        if self.n < 1:
            raise CampaignError(f"n: must be at least 1, got {self.n}")
        if self.chunk < 1:
            raise CampaignError(f"chunk: must be at least 1, got {self.chunk}")
        if not 0 <= self.seed < 2**32:
            raise CampaignError(f"seed: must be in [0, 2^32), got {self.seed}")
        if not isinstance(self.criteria, CaptureCriteria):
            raise CampaignError(f"criteria: must be a CaptureCriteria, got {self.criteria!r}")
        if self.timeseries_every is not None and self.timeseries_every < 1:
            raise CampaignError(f"timeseries_every: must be at least 1, got {self.timeseries_every}")
        if self.device_batch is not None and (
            isinstance(self.device_batch, bool) or not isinstance(self.device_batch, int) or self.device_batch < 1
        ):
            raise CampaignError(f"device_batch: must be a positive integer or None, got {self.device_batch!r}")
        if not (math.isfinite(self.pinv_damping) and self.pinv_damping >= 0.0):
            raise CampaignError(f"pinv_damping: must be non-negative, got {self.pinv_damping}")

    def to_dict(self) -> dict:
        fields = {field.name: getattr(self, field.name) for field in dataclasses.fields(self)}
        return fields | {
            "ranges": self.ranges.to_dict(),
            "criteria": self.criteria.to_dict(),
            "realism": (self.realism or ideal()).to_dict(),
        }

    @classmethod
    def from_dict(cls, document: dict, source: str = "campaign settings") -> CampaignConfig:
        """The settings ``to_dict()`` wrote, or a campaign record of an older version (the
        criteria as settings of their own, ``torque_limit_Nm`` for the threshold; no rate
        limits: none were criteria). ``source`` names the record in errors.

        Raises:
            CampaignError: a setting that is not one, or a bad value, naming it.
        """
        fields = dict(document)
        criteria = dict(fields.pop("criteria", {}))
        for name in _CRITERIA_SETTINGS_OF_OLDER_RECORDS:
            if name in fields:
                criteria[name] = fields.pop(name)
        unknown = sorted(set(fields) - {field.name for field in dataclasses.fields(cls)})
        if unknown:
            raise CampaignError(f"{source}: {', '.join(unknown)}: no such setting")
        try:
            fields["criteria"] = CaptureCriteria.from_dict(criteria)
        except ValueError as error:
            raise CampaignError(f"{source}: {error}") from None
        if "ranges" in fields:
            fields["ranges"] = PerturbationRanges.from_mapping(fields["ranges"])
        if "realism" in fields:
            realism = make_realism(fields["realism"], source=source)
            fields["realism"] = None if realism.to_dict() == ideal().to_dict() else realism
        return cls(**fields)


#: The criteria a campaign record of an older version kept among its settings.
_CRITERIA_SETTINGS_OF_OLDER_RECORDS = (
    "position_tolerance_m",
    "orientation_tolerance_rad",
    "torque_limit_Nm",
    "target_speed_limit_mps",
    "joint_rate_limits_radps",
)


@dataclasses.dataclass
class CampaignResult:
    """What a campaign returns.

    Attributes:
        perturbations: field -> (n, ...) the drawn perturbations (shared by all variants).
        metrics: variant key -> metric -> (n, ...) per-sample metrics, plus ``"success"`` (n,).
        timeseries: variant key -> decimated [`Log`][spacegrasp_jax.loop.simulate.Log] with leading axis n (if requested).
        summary: the content of summary.json.
        status: ``"done"`` or ``"interrupted"``.
    """

    perturbations: dict[str, np.ndarray]
    metrics: dict[str, dict[str, np.ndarray]]
    timeseries: dict[str, Log]
    summary: dict
    status: str


# ---- the sharded, chunked evaluation --------------------------------------------------


def _evaluate_chunk(spec, gains, seed, ranges, indices, *, identified):
    return evaluate_samples(spec, gains, seed, indices, ranges=ranges, identified=identified)


def variant_law(variant: Variant, config: CampaignConfig):
    """The law ``variant`` runs, with the campaign's pseudoinverse damping."""
    try:
        return law_named(variant.controller, config.pinv_damping)
    except ValueError as error:
        raise CampaignError(str(error)) from None


def variant_spec(robot: Robot, scenario: Scenario, variant: Variant, config: CampaignConfig) -> RunSpec:
    """The nominal run of ``variant`` in the campaign, every sample a perturbation of it: its
    law (with the campaign's pseudoinverse damping), the campaign's realism, its metrics
    folded in the loop with every ``timeseries_every``-th row."""
    return RunSpec(
        robot,
        scenario,
        variant_law(variant, config),
        realism=config.realism,
        observer=FoldedMetrics(config.timeseries_every),
    )


def program_gains(variants: list[Variant]) -> dict[str, object]:
    """variant key -> the gains its chunks run with: every gain set of a law in one compiled
    program, constant gains and schedules alike
    ([`schedule.program_gains()`][spacegrasp_jax.loop.control.schedule.program_gains]: a
    variant's own gains where its law's gain sets share one structure, else a ``GainChoice``
    choosing them: constant gains then run bit for bit, a schedule to rounding)."""
    by_law: dict[str, list[Variant]] = {}
    for variant in variants:
        by_law.setdefault(variant.controller, []).append(variant)
    gains = {}
    for group in by_law.values():
        for variant, argument in zip(group, schedule.program_gains([v.gains for v in group]), strict=True):
            gains[variant.key] = argument
    return gains


def _replicated(robot, scenario, variant: Variant, config: CampaignConfig, gains=None) -> tuple:
    """The arguments every device of a chunk receives whole (``gains``: the variant's, or
    what ``program_gains()`` gives it)."""
    gains = variant.gains if gains is None else gains
    return variant_spec(robot, scenario, variant, config), gains, np.uint32(config.seed), config.ranges


def compiled_chunk(robot, scenario, variant: Variant, config: CampaignConfig, gains=None):
    """The compiled evaluation of one chunk of ``config.chunk`` samples
    ([`compile_chunk()`][spacegrasp_jax.jobs.batching.compile_chunk]) and its compile time (s; that of the
    original compile). ``gains``: as ``_replicated()``'s."""
    function = functools.partial(_evaluate_chunk, identified=config.identified)
    try:
        return batching.compile_chunk(
            "campaign",
            function,
            _replicated(robot, scenario, variant, config, gains),
            np.zeros(config.chunk, np.uint32),
            device_batch=config.device_batch,
        )
    except batching.BatchingError as error:
        raise CampaignError(str(error)) from None


def evaluate_indices(
    robot, scenario, variant: Variant, config: CampaignConfig, indices, gains=None
) -> dict[str, np.ndarray]:
    """Samples ``indices`` (``config.chunk`` of them, any values) of the campaign, gathered
    on every host as flat NumPy arrays: ``perturbation.<field>``, the metrics, and
    ``timeseries.<field>`` when requested. ``gains``: the variant's gains as the program
    takes them (``program_gains()``; ``None``: the variant's own)."""
    executable, _ = compiled_chunk(robot, scenario, variant, config, gains)
    indices = np.asarray(indices, dtype=np.uint32)
    if indices.shape != (config.chunk,):
        raise CampaignError(f"indices: expected {config.chunk} of them (the chunk size), got shape {indices.shape}")
    replicated = _replicated(robot, scenario, variant, config, gains)
    perturbations, sample_metrics, rows = batching.run_chunk(executable, replicated, indices)
    arrays = {f"perturbation.{name}": value for name, value in vars(perturbations).items()}
    arrays |= dict(sample_metrics)
    if rows is not None:
        arrays |= {f"timeseries.{name}": value for name, value in vars(rows).items() if value is not None}
    return arrays


# ---- files and resume -----------------------------------------------------------------


def _chunk_path(out: Path, variant: Variant, first: int) -> Path:
    return out / "chunks" / variant.controller / variant.label / f"{first:09d}.npz"


#: The campaign's settings its run record holds (``campaign.json``'s ``record``), not its ``config``.
_RECORDED_SETTINGS = ("realism", "criteria", "pinv_damping")


def campaign_document(
    robot: Robot,
    scenario: Scenario,
    variants,
    config: CampaignConfig,
    *,
    sources: dict | None = None,
    command=None,
) -> dict:
    """What ``campaign.json`` holds: the nominal run's record
    ([`RunRecord`][spacegrasp_jax.jobs.records.RunRecord]: robot, scenario, variants, realism,
    criteria, pinv_damping, command, versions) and the campaign's own settings (``config``:
    size, seed, chunks, ranges, the model the controller believes)."""
    record = make_record(
        robot,
        scenario,
        variants,
        realism=config.realism,
        criteria=config.criteria,
        pinv_damping=config.pinv_damping,
        command=command,
        sources=sources,
    )
    settings = {name: value for name, value in config.to_dict().items() if name not in _RECORDED_SETTINGS}
    return {"record": record.to_dict(), "config": settings}


def _older_campaign_document(document: dict, out: Path, source: str) -> dict:
    """A ``campaign.json`` of an older version (the robot by its file, the variants, the
    scenario and every setting side by side) in today's form."""
    robot_source = document["robot"]
    if document.get("robot_file"):  # the robot as it ran, kept in the folder
        robot_source = str(out / document["robot_file"])
    try:
        robot = paper_robot() if robot_source == "paper_robot()" else load_robot(robot_source)
    except (OSError, ValueError) as error:
        raise CampaignError(f"{source}: its robot {robot_source}: {error}") from None
    config = CampaignConfig.from_dict(document["config"], source=source)
    variants = [
        Variant(item["controller"], gain_set_from_dict(item["gains"], n_joints(robot)), item["gains_label"])
        for item in document["variants"]
    ]
    sources = {"robot": document["robot"], "robot_links": document.get("robot_links")}
    return campaign_document(robot, scenario_from_dict(document["scenario"]), variants, config, sources=sources)


def campaign_record(out: Path) -> tuple[RunRecord, CampaignConfig]:
    """The campaign that ``out`` holds (its ``campaign.json``; one of an older version too):
    its nominal run's record and its settings.

    Raises:
        CampaignError: no readable campaign there.
    """
    path = Path(out) / "campaign.json"
    try:
        document = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise CampaignError(f"{out}: holds no readable campaign ({path.name}: {error})") from None
    if "record" not in document:
        document = _older_campaign_document(document, Path(out), str(path))
    try:
        record = RunRecord.from_dict(document["record"], source=f"{path}: record")
    except RecordError as error:
        raise CampaignError(str(error)) from None
    config = CampaignConfig.from_dict(document["config"], source=str(path))
    config = dataclasses.replace(
        config, realism=record.realism, criteria=record.criteria, pinv_damping=record.pinv_damping
    )
    return record, config


def _same_run(a: dict, b: dict) -> bool:
    """Whether two documents of ``campaign_document()`` describe the same campaign: their
    records but for when, how and from where they were made, and their settings."""
    made = ("command", "versions", "sources")
    strip = lambda document: {
        "record": {key: value for key, value in document["record"].items() if key not in made},
        "config": document["config"],
    }
    return json.dumps(runfiles.plain(strip(a)), sort_keys=True) == json.dumps(runfiles.plain(strip(b)), sort_keys=True)


def _check_resume(out: Path, document: dict, resume: bool) -> None:
    path = out / "campaign.json"
    if not path.exists():
        return
    if not resume:
        raise CampaignError(
            f"{out} already holds a campaign: pass --resume (resume=True) to continue it, or choose another output folder"
        )
    previous, config = campaign_record(out)
    previous = {"record": previous.to_dict(), "config": {**config.to_dict()}}
    previous["config"] = {k: v for k, v in previous["config"].items() if k not in _RECORDED_SETTINGS}
    if _same_run(previous, document):
        return
    # The first part that differs, named: the robot by what it is, never by the path it was read from.
    for part, key in (("record", "robot"), ("record", "variants"), ("record", "scenario"), ("record", None)):
        old, new = previous[part], document[part]
        if key is not None and json.dumps(runfiles.plain(old[key])) != json.dumps(runfiles.plain(new[key])):
            raise CampaignError(f"{out}: cannot resume, the {key} differs from the interrupted campaign's")
    changed = sorted(
        {k for k in document["config"] if previous["config"].get(k) != document["config"][k]}
        | {
            k
            for k in ("realism", "criteria", "pinv_damping", "model_robot")
            if json.dumps(runfiles.plain(previous["record"].get(k)))
            != json.dumps(runfiles.plain(document["record"][k]))
        }
    )
    raise CampaignError(
        f"{out}: cannot resume, the config differs from the interrupted campaign's ({', '.join(changed)})"
    )


def _load_chunk(path: Path) -> dict[str, np.ndarray] | None:
    try:
        with np.load(path) as data:
            return {name: data[name] for name in data.files}
    except (OSError, ValueError):
        return None  # a chunk file that cannot be read is recomputed


# ---- summary --------------------------------------------------------------------------


def _statistics(values: np.ndarray) -> dict:
    """Mean, standard deviation, percentiles, min and max over the finite entries."""
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return {"count": 0}
    percentiles = np.percentile(finite, PERCENTILES)
    return {
        "count": int(finite.size),
        "mean": float(finite.mean()),
        "std": float(finite.std()),
        **{f"p{p}": float(v) for p, v in zip(PERCENTILES, percentiles)},
        "min": float(finite.min()),
        "max": float(finite.max()),
    }


def classify(sample_metrics: dict[str, np.ndarray], config: CampaignConfig) -> dict[str, np.ndarray]:
    """[`spacegrasp_jax.jobs.anatomy.failure_classes()`][spacegrasp_jax.jobs.anatomy.failure_classes] of the samples by the campaign's criteria."""
    return anatomy.failure_classes(sample_metrics, config.criteria)


#: The metrics a run or a sample reports (a free target's where there is one).
_REPORTED = (*METRICS, *TARGET_METRICS, *anatomy.ANATOMY_METRICS)


def run_failure_classes(summary: dict, criteria: CaptureCriteria | None = None) -> dict[str, np.ndarray]:
    """[`failure_classes()`][spacegrasp_jax.jobs.anatomy.failure_classes] of one run's summary (its
    metrics as floats and lists, ``metrics.summary``) as a one-sample batch, by ``criteria``
    (``None``: the campaigns' defaults)."""
    sample = {name: np.asarray([value], dtype=float) for name, value in summary.items() if name in _REPORTED}
    return anatomy.failure_classes(sample, CaptureCriteria() if criteria is None else criteria)


def with_capture_verdict(summary: dict, criteria: CaptureCriteria | None = None) -> dict:
    """``summary`` (one run's, ``metrics.summary``) and its verdict by ``criteria`` (``None``:
    the campaigns' defaults): whether the run is a capture (``capture_success``), the
    criteria (``capture_criteria``, [`CaptureCriteria.to_dict()`][spacegrasp_jax.envelope.criteria.CaptureCriteria.to_dict]), which it missed and by how much (``capture_failure``,
    ``capture_missed``, ``capture_margins``: value over tolerance, ``None`` where a criterion
    does not apply) and the parts of its final position error (``final_error_parts_m``). What
    ``spacegrasp simulate`` writes into ``summary.json``. A diverged run's summary is returned
    as it is."""
    if summary.get("diverged"):
        return summary
    criteria = CaptureCriteria() if criteria is None else criteria
    classes = run_failure_classes(summary, criteria)
    parts = anatomy.error_decomposition(
        {name: np.asarray([summary[name]]) for name in ("final_position_error_lar_m", *anatomy.ANATOMY_METRICS)}
    )
    return summary | {
        "capture_success": bool(classes["failure"][0] == "success"),
        "capture_criteria": criteria.to_dict(),
        "capture_failure": str(classes["failure"][0]),
        "capture_missed": [name for name in anatomy.FAILURE_CLASSES if classes[f"failed_{name}"][0]],
        "capture_margins": {
            name: (None if not np.isfinite(classes[name][0]) else float(classes[name][0]))
            for name in (
                "position_margin",
                "orientation_margin",
                "torque_margin",
                "target_speed_margin",
                "joint_rate_margin",
            )
        },
        "final_error_parts_m": {
            name.removeprefix("final_error_").removesuffix("_m"): float(v[0]) for name, v in parts.items()
        },
    }


def variant_summary(sample_metrics: dict[str, np.ndarray], config: CampaignConfig) -> dict:
    """Statistics of every metric over the samples that did not diverge, success rate with
    its 95% interval, the diverged and the unstable samples, the five worst samples by final
    position error and by peak torque, and the failures' anatomy
    ([`spacegrasp_jax.jobs.anatomy.anatomy_summary()`][spacegrasp_jax.jobs.anatomy.anatomy_summary])."""
    diverged = np.flatnonzero(np.isfinite(sample_metrics["first_nonfinite_s"]))
    ok = np.ones(len(sample_metrics["first_nonfinite_s"]), dtype=bool)
    ok[diverged] = False
    over_non_diverged = {}
    for name in (*METRICS, *(name for name in TARGET_METRICS if name in sample_metrics)):
        if name not in sample_metrics:
            continue
        values = np.asarray(sample_metrics[name])
        if values.ndim == 2:  # per joint or per axis
            over_non_diverged[name] = [_statistics(values[ok, j]) for j in range(values.shape[1])]
        elif name != "first_nonfinite_s":
            over_non_diverged[name] = _statistics(values[ok])
    peak = np.asarray(sample_metrics["largest_peak_torque_Nm"])
    classes = classify(sample_metrics, config)
    unstable = np.flatnonzero(ok & classes["failed_torque_threshold"])

    def worst(values):
        order = np.argsort(np.where(np.isfinite(values), values, np.inf))[::-1]
        return [int(i) for i in order[:5]]

    successes = int(np.sum(sample_metrics["success"]))
    return {
        "samples": int(ok.size),
        "success_rate": float(np.mean(sample_metrics["success"])),
        "successes": successes,
        "success_interval": statistics.success_interval(successes, ok.size),
        "diverged": int(diverged.size),
        "diverged_samples": [int(i) for i in diverged],
        "unstable": int(unstable.size),
        "unstable_samples": [int(i) for i in unstable],
        "worst_by_final_position_error": worst(np.asarray(sample_metrics["final_position_error_m"])),
        "worst_by_peak_torque": worst(peak),
        "statistics_over_non_diverged": over_non_diverged,
        "failures": anatomy.anatomy_summary(sample_metrics | classes),
    }


#: The metrics that a comparison of two gain sets tests pairwise (lower is better).
COMPARED_METRICS = ("final_position_error_m", "final_orientation_error_rad", "largest_peak_torque_Nm")


#: Which pairs of a campaign's gain sets it tests: each against the first of its law (the
#: baseline), or every pair of the same law.
PAIRS = ("baseline", "all")


def comparisons(
    metrics_by_variant: dict[str, dict[str, np.ndarray]], variants: list[Variant], pairs: str = "baseline"
) -> dict:
    """Gain sets of the same controller against one another, on the same samples: the exact
    McNemar test of their success flags and the paired tests of ``COMPARED_METRICS``
    ([`spacegrasp_jax.envelope.statistics`][spacegrasp_jax.envelope.statistics]).

    ``pairs="baseline"`` tests each gain set against the first of its controller (the
    baseline); ``"all"`` tests every pair, each against the one listed before it. Keyed
    ``"<candidate key> vs <reference key>"``, the baseline's pairs first."""
    if pairs not in PAIRS:
        raise ValueError(f"pairs: expected one of {PAIRS}, got {pairs!r}")
    tested = []
    for i, reference in enumerate(variants):
        for variant in variants[i + 1 :]:
            if variant.controller != reference.controller:
                continue
            is_baseline = reference is next(v for v in variants if v.controller == reference.controller)
            if is_baseline or pairs == "all":
                tested.append((not is_baseline, reference, variant))
    result = {}
    for _, reference, variant in sorted(tested, key=lambda pair: pair[0]):
        a, b = metrics_by_variant[reference.key], metrics_by_variant[variant.key]
        result[f"{variant.key} vs {reference.key}"] = {
            "reference": reference.key,
            "candidate": variant.key,
            "success": statistics.compare_success(a["success"], b["success"]),
            **{name: statistics.compare_metric(a[name], b[name]) for name in COMPARED_METRICS},
        }
    return result


# ---- the campaign -----------------------------------------------------------------------


def _progress_line(
    done_chunks: int, total_chunks: int, variant: Variant, samples_done: int, n: int, rate: float | None, diverged: int
) -> str:
    speed = f"{rate:.2f} rollouts/s" if rate else "compiling or resuming"
    return runfiles.progress_bar(
        done_chunks,
        total_chunks,
        f"chunk {done_chunks}/{total_chunks} | {variant.key}: {samples_done}/{n} samples | {speed} | diverged {diverged}",
    )


def _stop_everywhere(stop: runfiles.StopRequest | None) -> bool:
    """Whether to stop after this chunk: asked in this process or, with several processes,
    in any of them (a collective: every process stops after the same chunk, so none is left
    waiting in the next chunk's collectives)."""
    requested = stop is not None and stop.requested
    if jax.process_count() == 1:
        return requested
    return bool(np.any(multihost_utils.process_allgather(np.asarray(requested))))


def run_campaign(
    robot: Robot,
    scenario: Scenario,
    variants: list[Variant],
    config: CampaignConfig,
    out: Path | None = None,
    *,
    resume: bool = False,
    robot_source: str = "paper_robot()",
    robot_links: dict | None = None,
    command=None,
    progress=sys.stderr,
    stop: runfiles.StopRequest | None = None,
    on_chunk: Callable[[Variant, int], None] | None = None,
    pairs: str = "baseline",
) -> CampaignResult:
    """Run (or, with ``resume``, continue) a campaign; write its files to ``out`` if given.

    Args:
        robot, scenario: the nominal system; every sample perturbs them.
        variants: the controller/gains pairs to evaluate on the same samples.
        config: sizes, seed, ranges and criteria.
        out: output folder (``None``: nothing written and no resume).
        resume: continue the campaign already in ``out`` (its configuration must match).
        robot_source, robot_links: where ``robot`` was read from and, for a URDF arm, its
            mount and links (``load_robot``'s keywords), as the record says them; the robot
            itself is kept in ``out`` (``runfiles.ROBOT_FILE``) when it came from a file.
        command: the command line that runs the campaign, for its record (``None``: a call
            from Python).
        progress: stream for the progress bar (``None``: silent).
        stop: checked after each chunk; when set, the run stops with status "interrupted".
        on_chunk: called after each finished chunk with the variant and its first index.
        pairs: the gain sets the summary tests against one another
            ([`comparisons()`][spacegrasp_jax.jobs.campaign.comparisons]): each against the
            first of its law (``"baseline"``) or every pair (``"all"``).

    Raises:
        CampaignError: invalid variants, a chunk size that is not a multiple of the device
            count, or an ``out`` that holds a different campaign.
    """
    if not variants:
        raise CampaignError("no variants to evaluate")
    if pairs not in PAIRS:
        raise CampaignError(f"pairs: expected one of {PAIRS}, got {pairs!r}")
    keys = [variant.key for variant in variants]
    if len(set(keys)) != len(keys):
        raise CampaignError(f"variants must differ in controller or gains label, got {keys}")
    devices = jax.device_count()
    if config.chunk % devices:
        raise CampaignError(
            f"chunk: {config.chunk} is not a multiple of the {devices} devices; use a multiple such as {devices * max(1, round(config.chunk / devices))}"
        )
    try:
        check_for_scenario(config.ranges, scenario)
    except PerturbationError as error:
        raise CampaignError(str(error)) from None
    if config.timeseries_every is not None and scenario.n_steps % config.timeseries_every:
        raise CampaignError(f"timeseries_every: {config.timeseries_every} does not divide the {scenario.n_steps} steps")
    writer = out is not None and jax.process_index() == 0
    sources = {"robot": robot_source, "robot_links": robot_links or None}
    document = campaign_document(robot, scenario, variants, config, sources=sources, command=command)
    if out is not None:
        _check_resume(out, document, resume)
        if jax.process_count() > 1:  # every process checks the folder before process 0 writes in it
            multihost_utils.sync_global_devices("spacegrasp campaign: folder checked")
        if writer:
            if robot_source != "paper_robot()":  # the robot as it ran, for --robot
                runfiles.write_robot(
                    out,
                    robot,
                    robot_source,
                    robot_links,
                    rate_limits_stated=config.criteria.joint_rate_limits_radps is not None,
                )
            runfiles.write_json(out / "campaign.json", document)

    starts = list(range(0, config.n, config.chunk))
    total_chunks = len(starts) * len(variants)
    done_chunks, run_s, computed_samples = 0, 0.0, 0
    compile_s_by_program: dict[int, float] = {}  # variants of one law share a program: counted once
    gains_of = program_gains(variants)
    chunks: dict[str, dict[int, dict]] = {variant.key: {} for variant in variants}
    status = "done"
    for variant in variants:
        compiled = False
        diverged = 0
        for first in starts:
            path = _chunk_path(out, variant, first) if out is not None else None
            arrays = _load_chunk(path) if path is not None and path.exists() else None
            if arrays is None:
                if not compiled:
                    executable, seconds = compiled_chunk(robot, scenario, variant, config, gains_of[variant.key])
                    compile_s_by_program[id(executable)] = seconds
                    compiled = True
                start = time.perf_counter()
                # Indices past n pad the last chunk; they are computed and dropped.
                indices = np.arange(first, first + config.chunk)
                arrays = evaluate_indices(robot, scenario, variant, config, indices, gains_of[variant.key])
                arrays = {name: value[: config.n - first] for name, value in arrays.items()}
                run_s += time.perf_counter() - start
                computed_samples += config.chunk
                if writer:
                    runfiles.write_arrays(path, arrays, compressed=False)
            chunks[variant.key][first] = arrays
            diverged += int(np.isfinite(arrays["first_nonfinite_s"]).sum())
            done_chunks += 1
            if on_chunk is not None:
                on_chunk(variant, first)
            if progress is not None:
                rate = computed_samples / run_s if run_s > 0 else None
                runfiles.show_progress(
                    progress,
                    _progress_line(
                        done_chunks,
                        total_chunks,
                        variant,
                        min(first + config.chunk, config.n),
                        config.n,
                        rate,
                        diverged,
                    ),
                )
            if _stop_everywhere(stop):
                status = "interrupted"
                break
        if status == "interrupted":
            break
    if progress is not None:
        runfiles.end_progress(progress)

    throughput = {
        "devices": devices,
        "device_kind": jax.devices()[0].device_kind,
        "platform": jax.devices()[0].platform,
        "processes": jax.process_count(),
        "compile_s": sum(compile_s_by_program.values()),
        "programs_compiled": len(compile_s_by_program),
        "run_s": run_s,
        "rollouts_computed_this_run": computed_samples,
        "rollouts_per_s": computed_samples / run_s if run_s > 0 else None,
        "simulated_s_per_wall_s": computed_samples * scenario.duration / run_s if run_s > 0 else None,
        "scenario_steps_per_s": computed_samples * scenario.n_steps / run_s if run_s > 0 else None,
    }
    if status == "interrupted":
        summary = {"status": status, "chunks_done": done_chunks, "chunks_total": total_chunks, "throughput": throughput}
        return CampaignResult({}, {}, {}, summary, status)

    perturbations, all_metrics, timeseries, summaries = {}, {}, {}, {}
    for variant in variants:
        merged = {
            name: np.concatenate([chunks[variant.key][first][name] for first in starts])
            for name in chunks[variant.key][starts[0]]
        }
        perturbations = {
            name.removeprefix("perturbation."): value
            for name, value in merged.items()
            if name.startswith("perturbation.")
        }
        sample_metrics = {name: merged[name] for name in _REPORTED if name in merged}
        classes = classify(sample_metrics, config)
        sample_metrics |= classes | {"success": classes["failure"] == "success"}
        sample_metrics |= anatomy.error_decomposition(sample_metrics)
        all_metrics[variant.key] = sample_metrics
        if config.timeseries_every is not None:
            fields = {
                name.removeprefix("timeseries."): value
                for name, value in merged.items()
                if name.startswith("timeseries.")
            }
            timeseries[variant.key] = Log(**fields)
        summaries[variant.key] = variant_summary(sample_metrics, config)
    summary = {
        "status": status,
        "n": config.n,
        "seed": config.seed,
        "duration_s": scenario.duration,
        "dt_s": scenario.dt,
        "contact_law": scenario.contact_law,
        "target": f"free, {float(scenario.target.mass):g} kg nominal" if scenario.free_target else "fixed",
        "capture_criteria": config.criteria.to_dict(),
        "ranges": config.ranges.to_dict(),
        "realism": (config.realism or ideal()).to_dict(),
        "controller_believes": "each sample's perturbed robot" if config.identified else "the nominal robot",
        "throughput": throughput,
        "variants": summaries,
        "comparisons": comparisons(all_metrics, variants, pairs),
    }
    result = CampaignResult(perturbations, all_metrics, timeseries, summary, status)
    if writer:
        write_results(out, result)
    return result


def write_results(out: Path, result: CampaignResult) -> None:
    """samples.npz, summary.json and the decimated time series (the figures are the
    caller's: [`spacegrasp_jax.analysis.plots.save_campaign_figures()`][spacegrasp_jax.analysis.plots.save_campaign_figures])."""
    arrays = {f"perturbation/{name}": value for name, value in result.perturbations.items()}
    for key, sample_metrics in result.metrics.items():
        arrays |= {f"{key}/{name}": value for name, value in sample_metrics.items()}
    runfiles.write_arrays(out / "samples.npz", arrays)
    runfiles.write_json(out / "summary.json", result.summary)
    for key, log in result.timeseries.items():
        runfiles.write_timeseries(out / f"timeseries_{key.replace('/', '_')}.npz", log)


def figure_title(summary: dict) -> str:
    """The title of a campaign's figures, from its summary: the samples, the loop (ideal or
    flight-like) and the target; the gains are the legend's."""
    loop = "ideal loop" if summary["realism"] == ideal().to_dict() else "flight-like loop"
    return (
        f"Monte-Carlo: {summary['n']} perturbed captures, seed {summary['seed']}, "
        f"{summary['duration_s']:g} s, {summary['contact_law']} contact law\n"
        f"{loop}, {summary.get('target', 'fixed')} target"
    )


#: The failure classes older campaigns named otherwise, and today's names.
_OLDER_CLASS_NAMES = {"torque_limit": "torque_threshold"}


def load_samples(path: Path) -> tuple[dict[str, np.ndarray], dict[str, dict[str, np.ndarray]]]:
    """``(perturbations, metrics by variant key)`` from a campaign's samples.npz; an older
    campaign's failure classes in today's names (``torque_limit`` is ``torque_threshold``)."""
    perturbations, by_variant = {}, {}
    with np.load(path) as data:
        for name in data.files:
            head, _, field = name.rpartition("/")
            if head == "perturbation":
                perturbations[field] = data[name]
                continue
            value = data[name]
            for old, new in _OLDER_CLASS_NAMES.items():
                if field == "failure":
                    value = np.where(value == old, new, value)
                field = field.replace(f"failed_{old}", f"failed_{new}")
            by_variant.setdefault(head, {})[field] = value
    return perturbations, by_variant


def load_campaign(out: Path) -> tuple[Robot, Scenario, list[Variant], CampaignConfig]:
    """The campaign that ``out`` holds (``campaign_record()``) as ``(robot, scenario, variants,
    config)``, what [`replay()`][spacegrasp_jax.jobs.campaign.replay] takes.

    Raises:
        CampaignError: no readable campaign there.
    """
    record, config = campaign_record(out)
    return record.robot, record.scenario, list(record.variants), config


def sample_record(record: RunRecord, config: CampaignConfig, index: int, variants=None) -> RunRecord:
    """The record of sample ``index`` of the campaign of ``record`` and ``config``: its
    perturbed plant and scenario, its realism and noise key, the robot its controller
    believes, for ``variants`` (default: the campaign's). A
    [`replay()`][spacegrasp_jax.jobs.records.replay] of it runs the sample as the campaign did."""
    loops = sample_loops(
        record.robot, record.scenario, config.seed, [index], config.ranges, config.realism, config.identified
    )
    first = lambda tree: None if tree is None else jax.tree.map(lambda x: x[0], tree)
    return dataclasses.replace(
        record,
        robot=first(loops.robots),
        scenario=first(loops.scenarios),
        variants=tuple(record.variants if variants is None else variants),
        realism=first(loops.realisms),
        model_robot=loops.model_robot,
        noise_key=None if loops.keys is None else tuple(int(word) for word in np.asarray(first(loops.keys))),
        versions=runfiles.provenance(),
    )


def replay_sample(robot: Robot, scenario: Scenario, config: CampaignConfig, index: int) -> tuple[Robot, Scenario]:
    """The perturbed ``(robot, scenario)`` of sample ``index`` (the plant and its scenario;
    [`replay()`][spacegrasp_jax.jobs.campaign.replay] runs the sample's whole loop)."""
    loops = sample_loops(robot, scenario, config.seed, [index], config.ranges, config.realism, config.identified)
    return jax.tree.map(lambda x: x[0], loops.robots), jax.tree.map(lambda x: x[0], loops.scenarios)


def robot_and_scenario_of_run(folder, config: dict) -> tuple[Robot, Scenario]:
    """The robot and scenario a run folder's ``config.json`` (``config``, read) ran: its
    record's ([`RunRecord`][spacegrasp_jax.jobs.records.RunRecord]). A folder of an older version:
    the robot kept in it (``robot_file``) or named (or the paper's) and its scenario; for a
    replay of a campaign sample, the sample's perturbed plant and scenario, from the
    campaign's folder ([`replay_sample()`][spacegrasp_jax.jobs.campaign.replay_sample]).

    Raises:
        experiment.RunFolderError: the record, the robot file or the campaign cannot be read.
    """
    if "record" in config:
        try:
            record = RunRecord.from_dict(config["record"], source=f"{folder}: config.json's record")
        except RecordError as error:
            raise experiment.RunFolderError(str(error)) from None
        return record.robot, record.scenario
    if "campaign_record" in config:
        try:
            robot, scenario, _, campaign_config = load_campaign(Path(config["campaign"]))
        except CampaignError as error:
            raise experiment.RunFolderError(
                f"{folder}: a replay of {config['campaign']}, which cannot be read: {error}"
            ) from None
        return replay_sample(robot, scenario, campaign_config, int(config["sample"]))
    source = config["robot"]
    if config.get("robot_file"):  # the robot as it ran, kept in the folder
        source = str(Path(folder) / config["robot_file"])
    try:
        robot = paper_robot() if source == "paper_robot()" else load_robot(source)
    except RobotConfigError as error:
        raise experiment.RunFolderError(f"{folder}: its robot {source}: {error}") from None
    return robot, scenario_from_dict(config["scenario"])


def replay(robot: Robot, scenario: Scenario, variant: Variant, config: CampaignConfig, index: int, check: bool = False):
    """Sample ``index`` of the campaign run again with its full log, as the campaign ran it
    (same plant, scenario, loop, model and noise): a [`RunResult`][spacegrasp_jax.jobs.experiment.RunResult]."""
    nominal = make_record(robot, scenario, [variant], realism=config.realism, pinv_damping=config.pinv_damping)
    return records.replay(sample_record(nominal, config, index), check=check)[variant.key]


__all__ = [
    "CampaignConfig",
    "CampaignError",
    "CampaignResult",
    "Variant",
    "campaign_document",
    "campaign_record",
    "sample_record",
    "classify",
    "compiled_chunk",
    "program_gains",
    "evaluate_indices",
    "load_campaign",
    "load_samples",
    "replay",
    "replay_sample",
    "robot_and_scenario_of_run",
    "figure_title",
    "variant_law",
    "variant_spec",
    "run_campaign",
    "run_failure_classes",
    "variant_summary",
    "with_capture_verdict",
    "write_results",
]
