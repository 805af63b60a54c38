"""The tuning race: methods that use the gradient against CMA-ES, at equal wall time, held
out on fresh captures.

    python -m spacegrasp_jax.benchmarks.race [--methods cmaes,gradient_fresh] [--minutes 15] [--marks 5,10,15]
        [--seed 0] [--heldout 1000] [--heldout-seed 20261202] [--schedule time:0,4,8,12,17]
        [--out notebooks/data/race] [--against FOLDER]

Every method tunes the 39 constant admittance and PID gains from the paper's (with
``--schedule VARIABLE:X1,X2,...``, a gain schedule: those gains at every knot, ``spacegrasp
tune --schedule``) on the same
problem: the flight-like loop (``--realism flight``), the Monte-Carlo campaigns' envelope,
the capture objective with a torque budget of 4 N m, a training batch of 32 drawn with
``--seed``. Each runs as a user runs it, ``spacegrasp tune`` in its own process with no
compilation cache (compiling counts), for ``--minutes`` of wall time. The driver copies the
run's checkpoint at each of ``--marks`` (minutes since the process started), then stops the
run. The gains of each copy (the gradient method's parameters, CMA-ES's mean) and the paper's
and the shipped flight gains are then held out together in one campaign of ``--heldout``
fresh flight-like captures of ``--heldout-seed`` (exact contact law, the campaigns' success
criteria), so every comparison is paired: McNemar against CMA-ES at the same mark and
against the shipped gains.

Methods (``METHODS``): ``cmaes`` (population 8, the shipped recipe's first call);
``cmaes_fresh``, ``cmaes_noise`` and ``sep_cmaes_fresh`` (pycma's default population, a fresh
batch a generation; with noise handling, UH-CMA-ES; separable);
``gradient`` (adam on the batch's clipped gradients, one batch: the documentation's earlier
comparison); ``gradient_fresh`` (adam on the median of four group means of a fresh batch's gradients
a step, ``--fresh-batches --aggregate median_of_means``); ``gradient_fresh_trimmed`` and
``gradient_fresh_clip`` (the same with the trimmed or the clipped mean; the trimmed mean
agreed best with itself in ``benchmarks.estimators``); ``gradient_fresh_truncated``
(``gradient_fresh`` with truncated backpropagation from 8.5 s, ``--gradient-from 8.5``: a
cheaper gradient, so more steps in the time).

A method added to a finished race runs in a folder of its own with ``--against`` the
race's: its held-out campaign draws the same captures (same settings), so its gains are
compared, paired, with the race's.

Resumable: ``race.json`` records each finished method's snapshots; a method cut short by an
interruption runs again from its start (its wall time must be one run's), and the held-out
campaign resumes chunk by chunk. Writes ``race.json`` and ``heldout/`` (the campaign).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

#: Method -> the options of ``spacegrasp tune`` beyond the common ones.
METHODS = {
    "cmaes": ["--method", "cmaes", "--population", "8", "--steps", "100000"],
    "gradient": ["--method", "gradient", "--aggregate", "clip", "--steps", "{steps}"],
    "gradient_fresh": ["--method", "gradient", "--fresh-batches", "--aggregate", "median_of_means"]
    + ["--steps", "{steps}"],
    "gradient_fresh_trimmed": [
        "--method",
        "gradient",
        "--fresh-batches",
        "--aggregate",
        "trimmed",
        "--steps",
        "{steps}",
    ],
    "gradient_fresh_clip": ["--method", "gradient", "--fresh-batches", "--aggregate", "clip", "--steps", "{steps}"],
    "gradient_fresh_truncated": ["--method", "gradient", "--fresh-batches", "--aggregate", "median_of_means"]
    + ["--gradient-from", "8.5", "--steps", "{steps}"],
    "cmaes_fresh": ["--method", "cmaes", "--fresh-batches", "--steps", "100000"],
    "cmaes_noise": ["--method", "cmaes", "--fresh-batches", "--noise-handling", "--steps", "100000"],
    "sep_cmaes_fresh": ["--method", "cmaes", "--separable", "--fresh-batches", "--steps", "100000"],
}

#: The gradient methods' steps a minute of wall time on 2 cores (a batch of 32 flight-like
#: gradients takes about 11 s): their cosine schedule ends when the time does.
GRADIENT_STEPS_PER_MINUTE = 5

#: Steps a minute of the methods whose gradient costs less: a step of 32 flight-like
#: gradients cut at 8.5 s took 4.7 s on 2 cores (a first run of the race, stopped after 25 steps).
STEPS_PER_MINUTE = {"gradient_fresh_truncated": 12}


def steps_for(method: str, minutes: float, steps_per_minute: float | None = None) -> int:
    """The steps a gradient method's cosine schedule spans in ``minutes`` (``steps_per_minute``:
    this machine's rate, else the first race's)."""
    rate = steps_per_minute or STEPS_PER_MINUTE.get(method, GRADIENT_STEPS_PER_MINUTE)
    return max(1, round(rate * minutes))


def common_options(seed: int) -> list[str]:
    return ["--realism", "flight", "--ranges", "montecarlo", "--objective", "capture", "--torque-cap", "4"] + [
        "--batch",
        "32",
        "--seed",
        str(seed),
        "--holdout",
        "0",
        "--compile-cache",
        "none",
    ]


def run_method(
    method: str,
    folder: Path,
    *,
    minutes: float,
    marks: list[float],
    seed: int,
    schedule: str | None = None,
    steps_per_minute: float | None = None,
    problem: tuple[str, ...] = (),
) -> dict:
    """One method's run: ``{mark: snapshot path}`` and the run's facts. ``steps_per_minute``:
    the gradient methods' steps a minute on this machine ([`steps_for()`][spacegrasp_jax.benchmarks.race.steps_for]);
    ``problem``: options of ``spacegrasp tune`` added to the common ones (another envelope:
    ``--range NAME=HALF_WIDTH``)."""
    out = folder / method
    if out.exists():
        shutil.rmtree(out)
    snapshots = folder / f"{method}_snapshots"
    snapshots.mkdir(parents=True, exist_ok=True)
    steps = str(steps_for(method, minutes, steps_per_minute))
    options = [option.replace("{steps}", steps) for option in METHODS[method]]
    command = [sys.executable, "-m", "spacegrasp_jax.cli", "tune", "--out", str(out), *common_options(seed), *options]
    command += ["--schedule", schedule] if schedule else []
    command += list(problem)
    start = time.monotonic()
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    taken = {}
    for mark in marks:
        while time.monotonic() - start < 60.0 * mark and process.poll() is None:
            time.sleep(0.5)
        checkpoint = out / "checkpoint.npz"
        if checkpoint.exists():  # written atomically after every step
            target = snapshots / f"{mark:g}min.npz"
            shutil.copyfile(checkpoint, target)
            taken[f"{mark:g}"] = {"path": str(target.relative_to(folder)), "at_s": time.monotonic() - start}
            taken[f"{mark:g}"] |= snapshot_work(target)
    if process.poll() is None:
        process.send_signal(signal.SIGINT)  # stops after the step under way; a second one at once
        try:
            process.wait(timeout=120)
        except subprocess.TimeoutExpired:
            process.send_signal(signal.SIGINT)
            process.wait(timeout=60)
    stderr = process.stderr.read() if process.stderr else ""
    return {
        "command": " ".join(["spacegrasp", *command[3:]]),
        "snapshots": taken,
        "exit": process.returncode,
        "log_tail": stderr[-2000:],
    }


def snapshot_work(path: Path) -> dict:
    """What a run had done when its checkpoint ``path`` was copied: its steps (CMA-ES:
    generations), the forward rollouts (CMA-ES: the start's mean, then each generation's
    candidates and mean on the batch) or the gradients of one capture (the start, each step
    and each rejected candidate on a batch) it had computed."""
    with np.load(path, allow_pickle=False) as stored:
        meta = json.loads(str(stored["meta"]))
    batch = meta["config"]["batch"]
    if "format" in meta:  # the driver's checkpoint: it counts the rollouts
        kind = "gradients" if meta["method"] == "gradient" else "rollouts"
        return {"steps": meta["step"], kind: meta["rollouts"]}
    if "generation" in meta:  # a CMA-ES checkpoint of an older version
        generations = meta["generation"]
        return {"steps": generations, "rollouts": (1 + generations * (meta["config"]["population"] + 1)) * batch}
    rejected = sum(int(row.get("rejected_candidates", 0)) for row in meta["history"])
    return {"steps": meta["step"], "gradients": (1 + meta["step"] + rejected) * batch}


def snapshot_gains(path: Path, run_folder: Path) -> dict:
    """The gains (a gains.json document) a checkpoint copy stands for."""
    from spacegrasp_jax.loop.control import paper_gains
    from spacegrasp_jax.tuning import driver
    from spacegrasp_jax.tuning.parameters import gains_from_params, initial_params, make_mask
    from spacegrasp_jax.tuning.run import tuned_base
    from spacegrasp_jax.tuning.tune import TuneConfig, make_method

    config = TuneConfig.from_dict(json.loads((run_folder / "run.json").read_text())["config"])
    base = tuned_base(paper_gains(), config)  # the paper's gains, or their schedule
    mask = make_mask(base, "admittance")
    params = initial_params(base, "admittance")
    tuner = make_method(config)
    state = driver.load_checkpoint(path, tuner, params, mask, config.seed)
    return gains_from_params(tuner.point(state.method_state), base, mask).to_dict("admittance")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m spacegrasp_jax.benchmarks.race", description=__doc__.split("\n\n")[0], allow_abbrev=False
    )
    parser.add_argument("--methods", default="cmaes,gradient_fresh", help=f"comma-separated, of {', '.join(METHODS)}")
    parser.add_argument("--minutes", type=float, default=15.0, help="wall time of each run (default 15)")
    parser.add_argument("--marks", default="5,10,15", help="minutes at which the gains are taken (default 5,10,15)")
    parser.add_argument("--seed", type=int, default=0, help="the training batch's seed (default 0)")
    parser.add_argument("--heldout", type=int, default=1000, help="held-out captures (default 1000)")
    parser.add_argument("--heldout-seed", type=int, default=20261202, help="their campaign seed (default 20261202)")
    parser.add_argument(
        "--schedule",
        metavar="VARIABLE:X1,X2,...",
        help="race on a gain schedule (tune --schedule; default: constant gains)",
    )
    parser.add_argument("--out", default="results/race", help="folder (default results/race)")
    parser.add_argument(
        "--against",
        metavar="FOLDER",
        help="a finished race of the same settings whose held-out captures this one's are paired with: "
        "its gain sets join the comparisons (McNemar against its CMA-ES and gradient_fresh at the same mark)",
    )
    args = parser.parse_args(argv)
    if not (math.isfinite(args.minutes) and args.minutes > 0):
        parser.error(f"--minutes: must be a positive number, got {args.minutes}")
    methods = [name for name in args.methods.split(",") if name]
    unknown = sorted(set(methods) - set(METHODS))
    if unknown or not methods:
        parser.error(f"--methods: unknown {', '.join(unknown) or 'empty'}; expected some of {', '.join(METHODS)}")
    try:
        marks = sorted(float(mark) for mark in args.marks.split(","))
    except ValueError:
        parser.error(f"--marks: expected comma-separated minutes, got {args.marks!r}")
    if not marks or marks[0] <= 0 or marks[-1] > args.minutes:
        parser.error("--marks: minutes in (0, --minutes]")
    if args.heldout < 1 or args.seed < 0 or args.heldout_seed < 0:
        parser.error("--heldout must be positive, the seeds non-negative")

    from spacegrasp_jax.jobs.compilation import configure

    settings = {"minutes": args.minutes, "marks": marks, "seed": args.seed, "heldout": args.heldout}
    settings["heldout_seed"] = args.heldout_seed
    if args.schedule:  # a race of constant gains keeps the settings it was recorded with
        settings["schedule"] = args.schedule
    folder = Path(args.out)
    record_path = folder / "race.json"
    record = json.loads(record_path.read_text()) if record_path.exists() else {"settings": {}, "methods": {}}
    if record["settings"] and record["settings"] != settings:
        parser.error(f"{record_path} holds a race of other settings {record['settings']}; choose another --out")
    against = None
    if args.against:
        against = Path(args.against)
        try:
            other = json.loads((against / "race.json").read_text())
        except (OSError, ValueError) as error:
            parser.error(f"--against: {against}: no finished race ({error})")
        if "heldout" not in other or other["settings"] != settings:
            parser.error(f"--against: {against} holds no finished race of these settings {settings}")
    configure()  # float64, for the gains this process reads back from the checkpoints
    folder.mkdir(parents=True, exist_ok=True)
    record["settings"] = settings
    for method in methods:
        if method in record["methods"]:
            print(f"{method}: done before", file=sys.stderr)
            continue
        print(f"{method}: {args.minutes:g} min of tuning...", file=sys.stderr, flush=True)
        record["methods"][method] = run_method(
            method, folder, minutes=args.minutes, marks=marks, seed=args.seed, schedule=args.schedule
        )
        record_path.write_text(json.dumps(record, indent=1) + "\n")

    gain_files = []
    for method in methods:
        for mark, snapshot in record["methods"][method]["snapshots"].items():
            path = folder / f"{method}_{mark}min.json"
            if not path.exists():
                document = snapshot_gains(folder / snapshot["path"], folder / method)
                path.write_text(json.dumps(document, indent=1) + "\n")
            gain_files.append(path)
    hold_out(folder, folder / "shipped_flight.json", gain_files, args.heldout, args.heldout_seed)
    paired = None if against is None else against / "heldout" / "samples.npz"
    record["heldout"] = summarise(folder / "heldout" / "samples.npz", methods, paired)
    if against is not None:  # where the paired race lies, from this one's folder
        record["against"] = os.path.relpath(against, folder)
    record_path.write_text(json.dumps(record, indent=1) + "\n")
    print(json.dumps(record["heldout"], indent=1))
    return 0


def hold_out(
    folder: Path, shipped: Path, gain_files: list[Path], count: int, seed: int, problem: tuple[str, ...] = ()
) -> None:
    """The held-out campaign of a race in ``folder/heldout`` (resumed where it stopped): the
    shipped flight gains (copied to ``shipped``), the paper's and ``gain_files`` on ``count``
    flight-like captures of ``seed`` (``problem``: ``montecarlo`` options of another envelope)."""
    import spacegrasp_jax
    from spacegrasp_jax.loop.control.gains import TUNED_GAINS_FILES

    shutil.copyfile(Path(spacegrasp_jax.__file__).resolve().parent / "data" / TUNED_GAINS_FILES["flight"], shipped)
    campaign = [sys.executable, "-m", "spacegrasp_jax.cli", "montecarlo", "--n", str(count)]
    campaign += ["--seed", str(seed), "--realism", "flight", "--controller", "admittance", *problem]
    campaign += [option for path in [shipped, *gain_files] for option in ("--gains", str(path))]
    campaign += ["--out", str(folder / "heldout")]
    if (folder / "heldout" / "campaign.json").exists():
        campaign.append("--resume")
    print(f"held out: {len(gain_files) + 2} gain sets on {count} captures...", file=sys.stderr, flush=True)
    subprocess.run(campaign, check=True)


def summarise(samples: Path, methods: list[str], paired: Path | None = None) -> dict:
    """Held-out success with its interval per gain set, and McNemar against CMA-ES at the
    same mark and against the shipped gains. With ``paired``, another race's held-out
    ``samples.npz`` on the same captures: its CMA-ES and ``gradient_fresh`` join the
    comparisons of this race's methods (the shipped gains' successes must agree capture by
    capture, else the captures are not the same and nothing is paired)."""
    from spacegrasp_jax.envelope import statistics

    success = _successes(samples)
    others = {}
    if paired is not None:
        others = _successes(paired)
        if not np.array_equal(others["shipped_flight"], success["shipped_flight"]):
            raise ValueError(f"{paired}: the shipped gains' held-out successes differ: not the same captures")
    table = {}
    for label, hits in success.items():
        row = {"success": statistics.success_interval(int(hits.sum()), int(hits.size))}
        row["vs_shipped"] = statistics.compare_success(success["shipped_flight"], hits)
        method, _, mark = label.rpartition("_")
        if method in methods and method != "cmaes":
            for rival in ("cmaes", "gradient_fresh"):
                rivals = success if f"{rival}_{mark}" in success else others
                if rival != method and f"{rival}_{mark}" in rivals:
                    row[f"vs_{rival}_same_mark"] = statistics.compare_success(rivals[f"{rival}_{mark}"], hits)
        table[label] = row
    return table


def _successes(samples: Path) -> dict[str, np.ndarray]:
    """Each gain set's held-out successes (label -> (n,) bool) in a campaign's ``samples.npz``."""
    from spacegrasp_jax.jobs.campaign import load_samples

    _, by_variant = load_samples(samples)
    return {key.split("/", 1)[1]: np.asarray(value["success"], dtype=bool) for key, value in by_variant.items()}


if __name__ == "__main__":
    sys.exit(main())
