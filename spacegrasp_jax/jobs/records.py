"""What a run ran, in one record that runs it again: the robot, the scenario, the loop, the laws
with their gains, the capture criteria, the command and the versions.

Every command writes one [`RunRecord`][spacegrasp_jax.jobs.records.RunRecord] (``record`` in a run
folder's ``config.json``, a campaign's ``campaign.json``, a tuning run's ``run.json``, the
margins' and the worst case's files) and reads it back with
[`RunRecord.from_dict()`][spacegrasp_jax.jobs.records.RunRecord.from_dict]: a run, a campaign's
sample and a tuning run replay from the same record
([`replay()`][spacegrasp_jax.jobs.records.replay]), whatever became of the files they were read
from. The record holds the robot as it ran (its frames, every number written so that it reads
back bit for bit: [`robot_to_toml()`][spacegrasp_jax.core.model.robot_to_toml]), the scenario leaf for
leaf, the realism, each law's gains or gain schedule, the criteria, the pseudoinverse's
damping, the robot the controller believes (when it is not the plant) and the sensors' noise
key; where the inputs came from is kept for people (``sources``), never read back.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax.core.model import Robot, RobotConfigError, n_joints, paper_robot, robot_to_toml
from spacegrasp_jax.core.robot_files import robot_from_toml
from spacegrasp_jax.envelope.criteria import CaptureCriteria
from spacegrasp_jax.envelope.scenario import Scenario, scenario_from_dict, scenario_to_dict
from spacegrasp_jax.jobs import experiment, runfiles
from spacegrasp_jax.loop.control.registry import CONTROLLERS, law_named
from spacegrasp_jax.loop.control.schedule import gain_set_from_dict
from spacegrasp_jax.loop.realism import Realism, RealismError, ideal, make_realism
from spacegrasp_jax.loop.simulate import RunSpec

#: The format of the records this version writes (``format``).
RECORD_FORMAT = 1


class RecordError(ValueError):
    """A record that cannot be read; names the record and the cause."""


@dataclasses.dataclass(frozen=True)
class Variant:
    """A law with a set of gains: ``controller``, a law's name; ``gains``, a
    [`Gains`][spacegrasp_jax.loop.control.gains.Gains] or a
    [`GainSchedule`][spacegrasp_jax.loop.control.schedule.GainSchedule]; ``label`` names the gains
    (``"paper"``, a shipped set's name or a file's stem)."""

    controller: str
    gains: object
    label: str = "paper"

    def __post_init__(self):
        if self.controller not in CONTROLLERS:
            raise ValueError(f"controller: expected one of {CONTROLLERS}, got {self.controller!r}")
        if not self.label or not all(c.isalnum() or c in "-_." for c in self.label):
            raise ValueError(f"gains label {self.label!r}: use letters, digits, '-', '_' or '.'")

    @property
    def key(self) -> str:
        """``"<controller>/<label>"``: a campaign's prefix of this variant's arrays."""
        return f"{self.controller}/{self.label}"


def _robot_text(robot: Robot, criteria: CaptureCriteria) -> str | None:
    """The robot as a record holds it: ``None`` for the paper's arm, else its frames. Its rate
    limits are written only where they are criteria, as the robot file it came from did."""
    stated = criteria.joint_rate_limits_radps is not None
    if robot_to_toml(robot) == robot_to_toml(paper_robot()):
        return None
    return robot_to_toml(robot, rate_limits_stated=stated)


@dataclasses.dataclass(frozen=True)
class RunRecord:
    """What a run ran (module docstring).

    Attributes:
        robot: the plant.
        scenario: the scenario as it ran.
        variants: (V,) the laws and their gains, each run on the same plant and scenario.
        realism: the loop's realism (``None``: the paper's ideal loop).
        criteria: the capture criteria the run was judged by.
        pinv_damping: the laws' pseudoinverse damping (0: exact, the paper).
        model_robot: the robot the controller believes (``None``: the plant itself).
        noise_key: the sensors' noise key, as its two uint32 words (``None``: no key given;
            a loop with noise then draws from ``PRNGKey(0)``).
        command: the command line that made the record (``None``: a call from Python).
        versions: [`provenance()`][spacegrasp_jax.jobs.runfiles.provenance] when it was made.
        sources: where the inputs came from, as given (files, shipped sets), for people.
    """

    robot: Robot
    scenario: Scenario
    variants: tuple[Variant, ...]
    realism: Realism | None = None
    criteria: CaptureCriteria = CaptureCriteria()
    pinv_damping: float = 0.0
    model_robot: Robot | None = None
    noise_key: tuple[int, int] | None = None
    command: tuple[str, ...] | None = None
    versions: dict | None = None
    sources: dict = dataclasses.field(default_factory=dict)

    def key(self) -> jax.Array | None:
        """The sensors' noise key (``None`` where the record has none)."""
        return None if self.noise_key is None else jnp.asarray(self.noise_key, dtype=jnp.uint32)

    def spec(self, variant: Variant) -> RunSpec:
        """The [`RunSpec`][spacegrasp_jax.loop.simulate.RunSpec] of ``variant``'s run."""
        return RunSpec(
            self.robot,
            self.scenario,
            law_named(variant.controller, self.pinv_damping),
            realism=self.realism,
            model_robot=self.model_robot,
        )

    def to_dict(self) -> dict:
        """The record as plain JSON (read back by [`from_dict()`][spacegrasp_jax.jobs.records.RunRecord.from_dict])."""
        model = self.model_robot
        return {
            "format": RECORD_FORMAT,
            "robot": _robot_text(self.robot, self.criteria),
            "scenario": scenario_to_dict(self.scenario),
            "realism": (self.realism or ideal()).to_dict(),
            "variants": [
                {"controller": v.controller, "label": v.label, "gains": v.gains.to_dict()} for v in self.variants
            ],
            "criteria": self.criteria.to_dict(),
            "pinv_damping": float(self.pinv_damping),
            "model_robot": None if model is None else robot_to_toml(model),
            "noise_key": None if self.noise_key is None else [int(word) for word in self.noise_key],
            "command": None if self.command is None else list(self.command),
            "versions": self.versions,
            "sources": self.sources,
        }

    @classmethod
    def from_dict(cls, document: dict, source: str = "the record") -> RunRecord:
        """The record that [`to_dict()`][spacegrasp_jax.jobs.records.RunRecord.to_dict] wrote;
        ``source`` names it in errors.

        Raises:
            RecordError: a record of another format, or one whose parts do not read.
        """
        if not isinstance(document, dict) or document.get("format") != RECORD_FORMAT:
            found = document.get("format") if isinstance(document, dict) else type(document).__name__
            raise RecordError(f"{source}: not a run record of format {RECORD_FORMAT} (format {found!r})")
        try:
            text = document["robot"]
            robot = paper_robot() if text is None else robot_from_toml(text, f"{source}: robot")
            model = document.get("model_robot")
            realism = make_realism(document["realism"], source=f"{source}: realism")
            variants = tuple(
                Variant(item["controller"], gain_set_from_dict(item["gains"], n_joints(robot)), item["label"])
                for item in document["variants"]
            )
            key = document.get("noise_key")
            return cls(
                robot=robot,
                scenario=scenario_from_dict(document["scenario"]),
                variants=variants,
                realism=None if realism.to_dict() == ideal().to_dict() else realism,
                criteria=CaptureCriteria.from_dict(document["criteria"]),
                pinv_damping=float(document["pinv_damping"]),
                model_robot=None if model is None else robot_from_toml(model, f"{source}: model_robot"),
                noise_key=None if key is None else tuple(int(word) for word in key),
                command=None if document.get("command") is None else tuple(document["command"]),
                versions=document.get("versions"),
                sources=document.get("sources") or {},
            )
        except (KeyError, TypeError) as error:
            raise RecordError(f"{source}: incomplete record ({error})") from None
        except (RobotConfigError, RealismError, ValueError) as error:
            raise RecordError(f"{source}: {error}") from None


def make_record(
    robot: Robot,
    scenario: Scenario,
    variants,
    *,
    realism: Realism | None = None,
    criteria: CaptureCriteria | None = None,
    pinv_damping: float = 0.0,
    model_robot: Robot | None = None,
    key=None,
    command=None,
    sources: dict | None = None,
) -> RunRecord:
    """A [`RunRecord`][spacegrasp_jax.jobs.records.RunRecord] of a run about to be made, with
    this process's versions; ``key``: the sensors' noise key (a JAX key or ``None``)."""
    return RunRecord(
        robot=robot,
        scenario=scenario,
        variants=tuple(variants),
        realism=realism,
        criteria=CaptureCriteria() if criteria is None else criteria,
        pinv_damping=pinv_damping,
        model_robot=model_robot,
        noise_key=None if key is None else tuple(int(word) for word in np.asarray(key, dtype=np.uint32)),
        command=None if command is None else tuple(command),
        versions=runfiles.provenance(),
        sources=dict(sources or {}),
    )


def replay(record: RunRecord, *, check: bool = True) -> dict[str, experiment.RunResult]:
    """Every variant of ``record`` run again as it ran: variant key -> its
    [`RunResult`][spacegrasp_jax.jobs.experiment.RunResult] (full log)."""
    return {
        variant.key: experiment.run(record.spec(variant), variant.gains, key=record.key(), check=check)
        for variant in record.variants
    }


__all__ = ["RECORD_FORMAT", "RecordError", "RunRecord", "Variant", "make_record", "replay"]
