"""Schedules that do not trust the clock: a gain schedule on the time since contact against
one on the clock, with first contact up to about 1 s early or late.

    python -m spacegrasp_jax.benchmarks.timing --out notebooks/data/timing [--minutes 15]
        [--seed 0] [--offset 0.012] [--gradient-steps-per-minute 4.5] [--heldout 1000]
        [--heldout-seed 740001]

1. **Tuned at equal wall time.** A schedule on each variable of ``SCHEDULES`` (the clock, on
   the shipped flight schedule's knots; the time since the controller detected the contact,
   ``contact_time``) is tuned by the gradient recipe from the paper's gains for ``--minutes``
   of wall time, each in its own process with no compilation cache (``benchmarks.race``'s
   ``run_method``: the machine must do nothing else meanwhile), on the campaigns' envelope
   with the approach's timing drawn (``approach_offset_m = --offset``: the LAR starts up to
   that much farther or nearer along its approach axis, so that first contact comes up to
   about 1 s later or earlier at 12 mm), the capture objective, a 4 N m torque budget and
   batches of 32 of training seed ``--seed``.
2. **Held out at both timings.** Both schedules, the shipped flight schedule and the shipped
   constant flight gains on ``--heldout`` flight-like captures of ``--heldout-seed`` twice: at
   the nominal timing, and with the timing drawn. The timing is drawn from a stream of its
   own, so that sample ``i`` of both campaigns is the same capture but for when contact comes.
3. **Paired.** ``timing.json``'s ``summary``: per gain set its success at each timing (95%
   Wilson intervals) and the loss the timing costs it (the exact McNemar test of its nominal
   against its drawn-timing captures, with the interval of the difference); and, with the
   timing drawn, each schedule against the clock's.

Resumable: a tuning run cut short runs again from its start (its budget is one run's); the
campaigns resume chunk by chunk. ``timing.json`` holds the settings (other settings in the
folder are refused), each finished run and the summary.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

#: The schedules raced: label -> ``spacegrasp tune --schedule``. The clock's knots are the
#: shipped flight schedule's; after contact, ``contact_time``'s span the contact's phases of
#: a 17 s capture whose first contact comes at 3.3-5.3 s (at most about 13.7 s of contact).
SCHEDULES = {
    "time_schedule": "time:0,4,8,12,17",
    "contact_time_schedule": "contact_time:0,1,3,7,13",
}

#: The held-out campaigns' seed, fixed before any run of this study.
HELDOUT_SEED = 740001

#: The shipped sets held out beside the tuned schedules.
SHIPPED = ("flight_schedule", "flight")


def timing_summary(nominal: dict[str, np.ndarray], drawn: dict[str, np.ndarray], reference: str) -> dict:
    """``{label: {"nominal", "drawn", "loss"}, "versus_<reference>": {label: ...}}`` from each
    gain set's successes (label -> (n,) bool) on the same captures at the nominal timing and
    with the timing drawn: the success intervals, the paired change the timing makes (the
    exact McNemar test, ``rate_difference`` drawn minus nominal, with its interval), and with
    the timing drawn each set against ``reference``."""
    from spacegrasp_jax.envelope import statistics

    if set(nominal) != set(drawn):
        raise ValueError(f"the campaigns hold other gain sets: {sorted(nominal)} and {sorted(drawn)}")
    summary = {}
    for label, hits in nominal.items():
        summary[label] = {
            "nominal": statistics.success_interval(int(hits.sum()), int(hits.size)),
            "drawn": statistics.success_interval(int(drawn[label].sum()), int(drawn[label].size)),
            "timing_change": statistics.compare_success(hits, drawn[label]),
        }
    summary[f"versus_{reference}"] = {
        label: statistics.compare_success(drawn[reference], drawn[label]) for label in drawn if label != reference
    }
    return summary


def _campaign(out: Path, gain_files: list[Path], count: int, seed: int, offset: float | None) -> None:
    command = [sys.executable, "-m", "spacegrasp_jax.cli", "montecarlo", "--n", str(count), "--seed", str(seed)]
    command += ["--realism", "flight", "--controller", "admittance", "--baseline", SHIPPED[0], "--gains", SHIPPED[1]]
    command += [option for path in gain_files for option in ("--gains", str(path))]
    command += [] if offset is None else ["--range", f"approach_offset_m={offset:g}"]
    command += ["--out", str(out)] + (["--resume"] if (out / "campaign.json").exists() else [])
    subprocess.run(command, check=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m spacegrasp_jax.benchmarks.timing", description=__doc__.split("\n\n")[0], allow_abbrev=False
    )
    parser.add_argument("--out", required=True, help="the study's folder")
    parser.add_argument("--minutes", type=float, default=15.0, help="each tuning run's wall time (default 15)")
    parser.add_argument("--seed", type=int, default=0, help="the training seed (default 0)")
    parser.add_argument(
        "--offset", type=float, default=0.012, help="approach_offset_m, m: the timing's half-width (default 0.012)"
    )
    parser.add_argument(
        "--gradient-steps-per-minute",
        type=float,
        default=4.5,
        help="the gradient method's steps a minute on a schedule on this machine (default 4.5: 68 steps in 15 "
        "minutes on the 2-core AMD EPYC VM)",
    )
    parser.add_argument("--heldout", type=int, default=1000, help="held-out captures (default 1000)")
    parser.add_argument("--heldout-seed", type=int, default=HELDOUT_SEED, help=f"(default {HELDOUT_SEED})")
    args = parser.parse_args(argv)
    if not (args.minutes > 0 and args.offset > 0 and args.heldout > 0 and args.gradient_steps_per_minute > 0):
        parser.error("--minutes, --offset, --heldout and --gradient-steps-per-minute must be positive")

    from spacegrasp_jax.benchmarks.race import run_method, snapshot_gains
    from spacegrasp_jax.benchmarks.race_seeds import code_hash, machine

    folder = Path(args.out).resolve()
    settings = {key: value for key, value in vars(args).items() if key != "out"} | {"schedules": SCHEDULES}
    record_path = folder / "timing.json"
    record = json.loads(record_path.read_text()) if record_path.exists() else {"settings": settings, "runs": {}}
    if record["settings"] != settings:
        parser.error(f"{record_path} holds a study of other settings {record['settings']}; choose another --out")
    folder.mkdir(parents=True, exist_ok=True)
    problem = ("--range", f"approach_offset_m={args.offset:g}")
    for label, schedule in SCHEDULES.items():
        if label in record["runs"]:
            continue
        print(f"{label}: {args.minutes:g} minutes of tuning...", file=sys.stderr, flush=True)
        run = run_method(
            "gradient_fresh",
            folder / label,
            minutes=args.minutes,
            marks=[args.minutes],
            seed=args.seed,
            schedule=schedule,
            steps_per_minute=args.gradient_steps_per_minute,
            problem=problem,
        )
        record["runs"][label] = run | {"code": code_hash(), "machine": machine()}
        record_path.write_text(json.dumps(record, indent=1) + "\n")

    gain_files = []
    for label in SCHEDULES:
        path = folder / f"{label}.json"
        if not path.exists():
            (snapshot,) = record["runs"][label]["snapshots"].values()
            document = snapshot_gains(folder / label / snapshot["path"], folder / label / "gradient_fresh")
            path.write_text(json.dumps(document, indent=1) + "\n")
        gain_files.append(path)
    _campaign(folder / "nominal", gain_files, args.heldout, args.heldout_seed, None)
    _campaign(folder / "drawn", gain_files, args.heldout, args.heldout_seed, args.offset)

    from spacegrasp_jax.benchmarks.race import _successes

    nominal, drawn = _successes(folder / "nominal" / "samples.npz"), _successes(folder / "drawn" / "samples.npz")
    record["summary"] = timing_summary(nominal, drawn, "time_schedule")
    record_path.write_text(json.dumps(record, indent=1) + "\n")
    print(json.dumps(record["summary"], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
