"""Four short tuning runs at fixed seeds, stored so that a change to the tuner's code shows
whether it changes what a run computes: the gradient method and CMA-ES, each in the paper's
ideal loop and in the flight-like loop, on a 1 s scenario.

``python tests/tuner_reference.py`` runs them under the test suite's compiler settings and
writes ``tests/data/tuner_reference/<name>.npz`` (every number of each step's history row but
its wall time, the tuned gains, the held-out evaluation's per-sample parts) and records this
machine in ``machines.json`` (``tests/stored_results.py``): do that only with a version whose
results are the reference, then commit the files. ``tests/test_tuner_reference.py`` runs the
same four runs and compares.
"""

from __future__ import annotations

import csv
import io
import json
import os
import sys
from pathlib import Path

import numpy as np

FOLDER = Path(__file__).parent / "data" / "tuner_reference"

#: name -> (TuneConfig fields, held-out captures)
RUNS = {
    "gradient_ideal": (dict(method="gradient", steps=3, batch=2, seed=3), 3),
    "gradient_flight_fresh": (
        dict(
            method="gradient",
            steps=3,
            batch=4,
            seed=5,
            realism="flight",
            fresh_batches=True,
            aggregate="median_of_means",
        ),
        3,
    ),
    "cmaes_ideal": (dict(method="cmaes", steps=3, batch=2, population=4, seed=7), 3),
    "cmaes_flight": (dict(method="cmaes", steps=3, batch=2, population=4, seed=11, realism="flight"), 3),
}

SCENARIO_TOML = "duration = 1.0\n[trajectory]\nduration = 1.0\n"


def run(name: str, folder: Path) -> dict[str, np.ndarray]:
    """Run ``RUNS[name]`` in ``folder`` (made empty) and return its numbers as flat arrays."""
    from spacegrasp_jax.loop.realism import load_realism
    from spacegrasp_jax.tuning.run import tune
    from spacegrasp_jax.tuning.tune import TuneConfig

    fields, holdout = RUNS[name]
    fields = dict(fields)
    if "realism" in fields:
        fields["realism"] = load_realism(fields["realism"]).to_dict()
    folder.mkdir(parents=True, exist_ok=True)
    scenario = folder / "short.toml"
    scenario.write_text(SCENARIO_TOML)
    tune(
        folder / "run",
        config=TuneConfig.of(**fields),
        scenario_file=str(scenario),
        holdout=holdout,
        progress=io.StringIO(),
    )
    return numbers(folder / "run")


def numbers(out: Path) -> dict[str, np.ndarray]:
    """A finished run's numbers: ``history/<column>`` (wall times left out), ``gains/<group>``
    (the tuned gains, before the held-out choice), ``holdout/<part>`` (per sample)."""
    arrays = {}
    with (out / "history.csv").open() as file:
        rows = list(csv.DictReader(file))
    for column in rows[0]:
        if column != "wall_s":
            arrays[f"history/{column}"] = np.array([float(row[column]) for row in rows])
    summary = json.loads((out / "summary.json").read_text())
    tuned = out / ("gains.json" if summary["gains_file"] == "tuned" else "gains_tuned.json")
    for group, value in json.loads(tuned.read_text()).items():
        if isinstance(value, list | float | int):
            arrays[f"gains/{group}"] = np.asarray(value, dtype=float)
    with np.load(out / "holdout.npz") as holdout:
        arrays |= {f"holdout/{part}": holdout[part] for part in holdout.files}
    return arrays


def main() -> None:
    import tempfile

    os.environ.setdefault("XLA_FLAGS", "--xla_backend_optimization_level=0")  # the suite's (tests/conftest.py)
    import stored_results

    import spacegrasp_jax as sg

    sg.configure()
    FOLDER.mkdir(parents=True, exist_ok=True)
    names = sys.argv[1:] or list(RUNS)
    with tempfile.TemporaryDirectory() as scratch:
        for name in names:
            arrays = run(name, Path(scratch) / name)
            np.savez(FOLDER / f"{name}.npz", **arrays)
            print(f"{name}: {len(arrays)} arrays", flush=True)
    (FOLDER / "machines.json").write_text(
        json.dumps({"reproduced_to_1e-12_on": [stored_results.fingerprint()]}, indent=2) + "\n"
    )


if __name__ == "__main__":
    main()
