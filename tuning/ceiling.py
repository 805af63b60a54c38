"""What caps a campaign's success: each failed capture tuned alone.

Where better gains stop raising the success rate, the failures left may be out of any gains'
reach: the controller's estimate of the LAR off by more than the contact takes back, a
perturbation no admittance absorbs. The evidence is to try. Each failed capture of a campaign
(or a random draw of them), on its own, exactly as the campaign ran it (its plant, scenario,
realism, model and noise key), is tuned by the gradient method from the campaign's gains, a
gain set or a schedule of the same structure, on the capture objective of that one capture
with the campaign's criteria (its tolerances; its torque threshold as every joint's torque
constraint) and the smooth contact law, as tuning does, the pseudoinverse's damping held.
After every step the campaign's own verdict (exact contact law, its criteria) is taken of
the step's gains, and the search stops at the first step that captures. A capture still missed after ``steps`` steps is
beyond what local tuning of these gains reaches.

One gain set must capture every sample at once, so the share of failures that tuning alone
can fix bounds what any single gain set of that structure, found by such a search, could add:
the campaign's success ``S / n`` plus ``F / n`` times the fixed share of its ``F`` failures is
the **ceiling**, with the fixed share's 95% Wilson interval carried through (conditional on
the campaign's captures). It is evidence, not a proof: a search from other gains, or longer,
might fix a capture this one did not, so the ceiling is an estimate from below of what a
capture-by-capture search reaches and, through it, from above of what one gain set does.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import jax
import numpy as np

from spacegrasp_jax.analysis.limit_state import capture_margin
from spacegrasp_jax.envelope.statistics import success_interval
from spacegrasp_jax.jobs import campaign, runfiles
from spacegrasp_jax.jobs.montecarlo import sample_loops
from spacegrasp_jax.tuning import driver
from spacegrasp_jax.tuning.tune import GradientSettings, TuneConfig, make_method, make_objective, make_problem


class CeilingError(ValueError):
    """Settings or a campaign the ceiling cannot be measured on, named."""


class CeilingInterrupted(Exception):
    """A stop was requested between two captures; the rows so far are written."""


@dataclasses.dataclass(frozen=True)
class CeilingSettings:
    """How the failed captures are tuned.

    Attributes:
        failures: how many of the campaign's failed captures are tuned (at most all of
            them), drawn at random without replacement.
        steps: gradient steps a capture at most.
        learning_rate: adam's learning rate on the log-gains.
        seed: which failures are drawn.
    """

    failures: int = 50
    steps: int = 40
    learning_rate: float = 0.1
    seed: int = 0

    def __post_init__(self):
        for name in ("failures", "steps"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise CeilingError(f"{name}: must be a positive integer, got {value!r}")
        rate = self.learning_rate
        if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not (0.0 < rate < math.inf):
            raise CeilingError(f"learning_rate: must be a positive number, got {rate!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise CeilingError(f"seed: must be a non-negative integer, got {self.seed!r}")


def chosen_failures(success: np.ndarray, count: int, seed: int) -> np.ndarray:
    """(m,) sorted indices of ``min(count, F)`` of the failed samples (``success`` False),
    drawn without replacement by ``seed``."""
    failed = np.flatnonzero(~np.asarray(success, dtype=bool))
    if count >= failed.size:
        return failed
    return np.sort(np.random.default_rng(seed).choice(failed, size=count, replace=False))


def ceiling_of(successes: int, samples: int, failures_tried: int, fixed: int) -> dict:
    """The ceiling (module docstring) of a campaign of ``successes`` out of ``samples`` of
    which ``fixed`` of ``failures_tried`` failed captures were fixed by tuning alone: the
    fixed share with its Wilson interval, and the ceiling ``(S + F * share) / n`` with the
    share's interval carried through."""
    share = success_interval(fixed, failures_tried) if failures_tried else None
    failures = samples - successes
    rate = successes / samples
    if share is None:
        return {"success": rate, "fixed_share": None, "ceiling": rate, "low": rate, "high": rate}
    return {
        "success": rate,
        "fixed_share": share,
        "ceiling": (successes + failures * share["rate"]) / samples,
        "low": (successes + failures * share["low"]) / samples,
        "high": (successes + failures * share["high"]) / samples,
    }


@dataclasses.dataclass
class _Capture:
    """The programs of one campaign variant's captures: its verdict's and its tuning's."""

    robot: object
    scenario: object
    variant: object
    config: object

    def margin(self, gains, index: int) -> float:
        """The campaign's margin of sample ``index`` run with ``gains`` (exact law, its
        criteria; ``> 0`` exactly when the campaign calls it captured)."""
        devices = jax.device_count()
        config = dataclasses.replace(self.config, chunk=devices)
        variant = dataclasses.replace(self.variant, gains=gains)
        metrics = campaign.evaluate_indices(self.robot, self.scenario, variant, config, [index] * devices)
        judged = {k: v[:1] for k, v in metrics.items() if not k.startswith(("perturbation.", "timeseries."))}
        return float(np.asarray(capture_margin(judged, self.config.criteria))[0])

    def tune(self, index: int, settings: CeilingSettings) -> dict:
        """Sample ``index`` tuned alone (module docstring): its row of ``ceiling.jsonl``."""
        gains = self.variant.gains
        before = self.margin(gains, index)
        smooth = dataclasses.replace(self.scenario, contact_law="smooth")
        config = TuneConfig(
            controller=self.variant.controller,
            steps=settings.steps,
            batch=1,
            seed=self.config.seed,
            frozen=("pinv_damping",),
            ranges=self.config.ranges,
            realism=None if self.config.realism is None else self.config.realism.to_dict(),
            method="gradient",
            settings=GradientSettings(learning_rate=settings.learning_rate),
            keep="best",
        )
        batch = sample_loops(
            self.robot,
            smooth,
            self.config.seed,
            [index],
            self.config.ranges,
            self.config.realism,
            self.config.identified,
        )
        # The capture objective judged as the campaign judges: its tolerances, rate limits and
        # torque threshold (for every joint; none: no torque constraint to speak of).
        threshold = self.config.criteria.torque_threshold_Nm
        objective = dataclasses.replace(
            make_objective(self.robot, config, self.robot.joint_torque_limit),
            criteria=self.config.criteria,
            torque_constraint_Nm=(1e6 if threshold is None else float(threshold),) * len(self.robot.joint_torque_limit),
        )
        problem = make_problem(
            self.robot, smooth, gains, config, self.robot.joint_torque_limit, batch=batch, objective=objective
        )
        margins = []

        class _StopAtCapture:
            requested = False

        stop = _StopAtCapture()

        def validate(point) -> float:
            margins.append(self.margin(problem.gains(point), index))
            if margins[-1] > 0.0:
                stop.requested = True
            return -margins[-1]

        start = time.perf_counter()
        result = driver.optimise(
            problem,
            make_method(config),
            problem.start,
            problem.mask,
            steps=settings.steps,
            seed=config.seed,
            keep="best",
            patience=settings.steps,
            validate=validate,
            stop=stop,
        )
        best = int(result.kept["step"])
        return {
            "sample": int(index),
            "gains": problem.gains(result.point).to_dict(self.variant.controller),
            "margin_before": before,
            "margin_after": margins[best],
            "fixed": bool(margins[best] > 0.0),
            "steps": int(result.state.step),
            "best_step": best,
            "status": "captured" if margins[best] > 0.0 else result.status,
            "wall_s": time.perf_counter() - start,
        }


def run_ceiling(
    folder: Path, out: Path, settings: CeilingSettings, label: str | None = None, progress=None, stop=None
) -> dict:
    """The ceiling of the campaign in ``folder`` (``spacegrasp montecarlo``'s, its
    ``samples.npz`` and ``campaign.json``) for its variant ``label`` (``"<law>/<gains>"``;
    ``None``: its only one): ``settings.failures`` of its failed captures tuned alone, a row
    each appended to ``out/ceiling.jsonl`` as it ends (a row there is not run again: an
    interrupted run goes on where it stopped) with the gains its search kept (``gains``:
    the best step's by the campaign's margin; ``spacegrasp replay CAMPAIGN --sample K
    --gains FILE`` runs them), then ``out/ceiling.json`` (the settings, the campaign, the
    rows and the ceiling). Returns that document. ``progress``: called with a line per
    capture (``None``: quiet); ``stop``: an object whose ``requested`` ends the run between two
    captures.

    Raises:
        CeilingError: no such variant, an ideal-loop campaign, or other settings than the
            rows already in ``out``.
        CeilingInterrupted: ``stop`` was requested; the rows so far are in ``out``.
        campaign.CampaignError: the campaign cannot be read.
    """
    robot, scenario, variants, config = campaign.load_campaign(folder)
    by_key = {variant.key: variant for variant in variants}
    if label is None:
        if len(by_key) != 1:
            raise CeilingError(f"{folder}: a campaign of {len(by_key)} variants; name one of {', '.join(by_key)}")
        (label,) = by_key
    if label not in by_key:
        raise CeilingError(f"{folder}: no variant {label!r}; expected one of {', '.join(by_key)}")
    if config.realism is None:
        raise CeilingError(f"{folder}: an ideal-loop campaign; the ceiling tunes captures of a flight-like loop")
    _, by_variant = campaign.load_samples(Path(folder) / "samples.npz")
    success = np.asarray(by_variant[label]["success"], dtype=bool)
    indices = chosen_failures(success, settings.failures, settings.seed)

    out.mkdir(parents=True, exist_ok=True)
    header = {"campaign": str(Path(folder).resolve()), "variant": label, "settings": dataclasses.asdict(settings)}
    rows_path = out / "ceiling.jsonl"
    lines = rows_path.read_text().splitlines() if rows_path.exists() else []
    if lines and json.loads(lines[0]) != header:
        raise CeilingError(f"{rows_path}: rows of other settings {lines[0]}; choose another --out")
    rows = [json.loads(line) for line in lines[1:]]
    done = {row["sample"] for row in rows}
    capture = _Capture(robot, scenario, by_key[label], config)
    with rows_path.open("a") as stream:
        if not lines:
            stream.write(json.dumps(header) + "\n")
        for k, index in enumerate(indices):
            if int(index) in done:
                continue
            if stop is not None and stop.requested:
                raise CeilingInterrupted(f"stopped after {len(rows)} of {len(indices)} captures")
            row = capture.tune(int(index), settings)
            gains_path = out / "gains" / f"sample_{int(index)}.json"
            gains_path.parent.mkdir(exist_ok=True)
            runfiles.write_json(gains_path, row.pop("gains"))
            row["gains_file"] = str(gains_path.relative_to(out))
            stream.write(json.dumps(row) + "\n")
            stream.flush()
            rows.append(row)
            if progress is not None:
                verdict = "captured" if row["fixed"] else "still missed"
                progress(
                    f"failure {k + 1}/{len(indices)} (sample {index}): {verdict} after {row['steps']} steps, margin "
                    f"{row['margin_before']:+.3f} -> {row['margin_after']:+.3f} ({row['wall_s']:.0f} s)"
                )
    fixed = sum(row["fixed"] for row in rows)
    document = {
        **header,
        "samples": int(success.size),
        "successes": int(success.sum()),
        "failures": int((~success).sum()),
        "failures_tried": len(rows),
        "fixed": int(fixed),
        **ceiling_of(int(success.sum()), int(success.size), len(rows), int(fixed)),
        "rows": rows,
    }
    runfiles.write_json(out / "ceiling.json", document)
    return document


__all__ = ["CeilingError", "CeilingInterrupted", "CeilingSettings", "ceiling_of", "chosen_failures", "run_ceiling"]
