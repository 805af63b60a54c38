"""The tuning race over training seeds: each method run on every seed at equal compute, all
held out together on one campaign of fresh captures, summarised as a skeptic asks.

    python -m spacegrasp_jax.benchmarks.race_seeds --out DIR [--seeds 0,1,2,3,4]
        [--methods gradient_fresh,cmaes_fresh,cmaes_noise,sep_cmaes_fresh] [--minutes 15]
        [--marks 5,10,15] [--gradient-steps-per-minute 6.5] [--heldout 1000] [--heldout-seed 730001]
        [--schedule VARIABLE:X1,...] [--range NAME=HALF_WIDTH ...]

Every run is one method on one training seed, as ``benchmarks.race`` runs it: ``spacegrasp
tune`` in its own process, no compilation cache, on the flight-like loop, the campaigns'
envelope (widened by ``--range``), the capture objective with a 4 N m torque budget and
batches of 32 drawn from the seed; its checkpoint copied at each mark (minutes of wall time
since its process started, compiling included: the machine must do nothing else meanwhile).
The gradient method's cosine schedule spans ``--gradient-steps-per-minute`` times
``--minutes`` steps: measure the rate on the machine (a step of 32 flight-like gradients
took 8.2 s on the 2-core AMD EPYC VM, so 6.5 a minute leaves the compile its time).
Runs go seed by seed, every method of a seed before the next seed, so that a race cut short
still pairs methods on the same seeds. Each run's record names the machine and a hash of
the code it ran (``code``): a race is one code.

Once every run is done, the gains of every run at every mark and the shipped flight gains
are held out in one campaign of ``--heldout`` flight-like captures of ``--heldout-seed``
(same envelope, exact contact law, the campaigns' success criteria). The summary
(``race.json``'s ``summary``) gives, per method and mark:

- each seed's held-out success with its 95% interval, and the exact McNemar test against the
  reference method (``--reference``, the first of ``--methods``) on the same seed and mark;
- the interquartile mean of the seeds' successes with a percentile bootstrap 95% interval over
  the seeds (Agarwal et al., NeurIPS 2021), and the same of the per-seed differences against
  the reference (paired: same seed, same captures).

Resumable: a run cut short by an interruption runs again from its start (its budget must be
one run's); the held-out campaign resumes chunk by chunk. ``race.json`` holds the settings
(a race of other settings in the folder is refused), each finished run and the summary.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import json
import math
import os
import platform
import sys
from pathlib import Path

from spacegrasp_jax.benchmarks.race import METHODS, hold_out, run_method, snapshot_gains

#: The methods raced by default, the reference first: the gradient method on a fresh batch
#: a step, CMA-ES of pycma's default population on a fresh batch a generation, with noise
#: handling (UH-CMA-ES), and separable.
DEFAULT_METHODS = ("gradient_fresh", "cmaes_fresh", "cmaes_noise", "sep_cmaes_fresh")

#: The held-out campaign's seed, fixed before any run of this race.
HELDOUT_SEED = 730001


def code_hash() -> str:
    """A hash of the source of the package this process imports (the simulator, the tuning
    methods and the benchmarks): runs of one hash ran the same code."""
    digest = hashlib.sha256()
    for name in ("spacegrasp_jax", "spacegrasp_jax.tuning", "spacegrasp_jax.benchmarks"):
        root = Path(importlib.util.find_spec(name).origin).parent
        files = sorted(root.glob("*.py")) if name != "spacegrasp_jax" else sorted(root.rglob("*.py"))
        if name == "spacegrasp_jax":  # an installed copy holds the other two inside it, an editable one not
            files = [path for path in files if path.relative_to(root).parts[0] not in ("tuning", "benchmarks")]
        for path in files:
            digest.update(f"{name}:{path.relative_to(root)}\n".encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def machine() -> str:
    """The CPU model and the cores this process may use."""
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{model}, {len(os.sched_getaffinity(0))} cores"


def run_label(method: str, seed: int) -> str:
    return f"{method}_seed{seed}"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m spacegrasp_jax.benchmarks.race_seeds",
        description=__doc__.split("\n\n")[0],
        allow_abbrev=False,
    )
    parser.add_argument("--out", required=True, help="the race's folder")
    parser.add_argument("--seeds", default="0,1,2,3,4", help="training seeds, comma-separated (default 0,1,2,3,4)")
    parser.add_argument(
        "--methods",
        default=",".join(DEFAULT_METHODS),
        help=f"comma-separated, of {', '.join(METHODS)} (default {','.join(DEFAULT_METHODS)})",
    )
    parser.add_argument("--reference", help="the method every other is paired with (default: the first)")
    parser.add_argument("--minutes", type=float, default=15.0, help="each run's wall time (default 15)")
    parser.add_argument("--marks", default="5,10,15", help="minutes at which the gains are taken (default 5,10,15)")
    parser.add_argument(
        "--gradient-steps-per-minute",
        type=float,
        default=6.5,
        help="the gradient method's steps a minute on this machine: its cosine schedule's length (default 6.5)",
    )
    parser.add_argument("--heldout", type=int, default=1000, help="held-out captures (default 1000)")
    parser.add_argument("--heldout-seed", type=int, default=HELDOUT_SEED, help=f"(default {HELDOUT_SEED})")
    parser.add_argument("--schedule", metavar="VARIABLE:X1,X2,...", help="race on a gain schedule (tune --schedule)")
    parser.add_argument(
        "--range",
        action="append",
        default=[],
        metavar="NAME=HALF_WIDTH",
        help="widen the envelope (training and held out), as montecarlo's --range",
    )
    parser.add_argument("--runs-only", action="store_true", help="stop after the runs (no held-out campaign)")
    args = parser.parse_args(argv)
    try:
        seeds = [int(seed) for seed in args.seeds.split(",") if seed]
        marks = sorted(float(mark) for mark in args.marks.split(","))
    except ValueError:
        parser.error(f"--seeds and --marks: comma-separated numbers, got {args.seeds!r} and {args.marks!r}")
    methods = [name for name in args.methods.split(",") if name]
    unknown = sorted(set(methods) - set(METHODS))
    if unknown or not methods:
        parser.error(f"--methods: unknown {', '.join(unknown) or 'empty'}; expected some of {', '.join(METHODS)}")
    reference = args.reference or methods[0]
    if reference not in methods:
        parser.error(f"--reference: {reference} is not one of --methods")
    if not seeds or min(seeds) < 0 or len(set(seeds)) != len(seeds):
        parser.error(f"--seeds: distinct non-negative whole numbers, got {args.seeds!r}")
    if not (math.isfinite(args.gradient_steps_per_minute) and args.gradient_steps_per_minute > 0):
        parser.error(f"--gradient-steps-per-minute: must be a positive number, got {args.gradient_steps_per_minute}")
    if not (math.isfinite(args.minutes) and args.minutes > 0):
        parser.error(f"--minutes: must be a positive number, got {args.minutes}")
    if not marks or marks[0] <= 0 or marks[-1] > args.minutes:
        parser.error("--marks: minutes in (0, --minutes]")
    if args.heldout < 1 or args.heldout_seed < 0:
        parser.error("--heldout must be positive, --heldout-seed non-negative")
    for text in args.range:
        name, equals, value = text.partition("=")
        try:
            float(value)
        except ValueError:
            equals = ""
        if not (name and equals):
            parser.error(f"--range: expected NAME=HALF_WIDTH, got {text!r}")
    problem = tuple(option for text in args.range for option in ("--range", text))

    settings = {
        "minutes": args.minutes,
        "gradient_steps_per_minute": args.gradient_steps_per_minute,
        "marks": marks,
        "seeds": seeds,
        "methods": methods,
    }
    settings |= {"reference": reference, "heldout": args.heldout, "heldout_seed": args.heldout_seed}
    settings |= {"schedule": args.schedule, "ranges": args.range}
    folder = Path(args.out).resolve()
    record_path = folder / "race.json"
    record = json.loads(record_path.read_text()) if record_path.exists() else {"settings": settings, "runs": {}}
    if record["settings"] != settings:
        parser.error(f"{record_path} holds a race of other settings {record['settings']}; choose another --out")

    from spacegrasp_jax.jobs.compilation import configure

    configure()  # float64, for the gains this process reads back from the checkpoints
    folder.mkdir(parents=True, exist_ok=True)
    code, host = code_hash(), machine()
    for seed in seeds:
        for method in methods:
            label = run_label(method, seed)
            if label in record["runs"]:
                continue
            print(f"{label}: {args.minutes:g} minutes of tuning...", file=sys.stderr, flush=True)
            run = run_method(
                method,
                folder / f"seed{seed}",
                minutes=args.minutes,
                marks=marks,
                seed=seed,
                schedule=args.schedule,
                steps_per_minute=args.gradient_steps_per_minute,
                problem=problem,
            )
            record["runs"][label] = run | {"code": code, "machine": host}
            record_path.write_text(json.dumps(record, indent=1) + "\n")
    if args.runs_only:
        return 0
    codes = sorted({run["code"] for run in record["runs"].values()})
    if len(codes) != 1:
        print(f"warning: the runs ran {len(codes)} versions of the code ({', '.join(codes)})", file=sys.stderr)

    gain_files = []
    (folder / "gains").mkdir(exist_ok=True)
    for label, run in record["runs"].items():
        method = label.rsplit("_seed", 1)[0]
        seed_folder = folder / f"seed{label.rsplit('_seed', 1)[1]}"
        for mark, snapshot in run["snapshots"].items():
            path = folder / "gains" / f"{label}_{mark}min.json"
            if not path.exists():
                document = snapshot_gains(seed_folder / snapshot["path"], seed_folder / method)
                path.write_text(json.dumps(document, indent=1) + "\n")
            gain_files.append(path)
    hold_out(folder, folder / "gains" / "shipped_flight.json", gain_files, args.heldout, args.heldout_seed, problem)
    record["summary"] = summarise(folder / "heldout" / "samples.npz", methods, seeds, marks, reference)
    record_path.write_text(json.dumps(record, indent=1) + "\n")
    print(json.dumps(record["summary"]["methods"], indent=1))
    return 0


def summarise(samples: Path, methods: list[str], seeds: list[int], marks: list[float], reference: str) -> dict:
    """The race's verdicts from its held-out ``samples.npz`` (labels ``{method}_seed{s}_{mark}min``):
    ``runs`` (label -> success and McNemar against the reference method on its seed and mark,
    and against the shipped gains) and ``methods`` (method -> mark -> the interquartile mean
    over seeds of the success and, paired by seed, of the difference to the reference)."""
    from spacegrasp_jax.benchmarks.race import _successes
    from spacegrasp_jax.envelope import statistics

    success = _successes(samples)
    runs, by_method = {}, {}
    for method in methods:
        by_method[method] = {}
        for mark in marks:
            rates, differences = [], []
            for seed in seeds:
                label = f"{run_label(method, seed)}_{mark:g}min"
                if label not in success:
                    continue
                hits = success[label]
                row = {"success": statistics.success_interval(int(hits.sum()), int(hits.size))}
                row["vs_shipped"] = statistics.compare_success(success["shipped_flight"], hits)
                rival = f"{run_label(reference, seed)}_{mark:g}min"
                if method != reference and rival in success:
                    row[f"vs_{reference}"] = statistics.compare_success(success[rival], hits)
                    differences.append(row[f"vs_{reference}"]["rate_difference"])
                runs[label] = row
                rates.append(row["success"]["rate"])
            entry = {"success": statistics.across_runs(rates)}
            if differences:
                entry[f"difference_to_{reference}"] = statistics.across_runs(differences)
            by_method[method][f"{mark:g}"] = entry
    shipped = success["shipped_flight"]
    return {
        "reference": reference,
        "shipped_flight": statistics.success_interval(int(shipped.sum()), int(shipped.size)),
        "runs": runs,
        "methods": by_method,
    }


if __name__ == "__main__":
    sys.exit(main())
