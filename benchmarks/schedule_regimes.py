"""What each regime of a gain schedule does: the schedule held out beside its own gains frozen
at each knot, on the same fresh captures.

    python -m spacegrasp_jax.benchmarks.schedule_regimes --schedule flight_schedule|FILE --out DIR
        [--n 1000] [--seed 20261208] [--realism flight] [--gains flight ...] [montecarlo options]

A schedule's gains at one knot, held for the whole capture, are a constant gain set
(``margins.frozen_gains``): the gains of one regime. A campaign of ``--n`` captures of
``--seed`` runs the schedule, each frozen knot (``knot_<x>``), the paper's gains and every
``--gains`` set named for comparison, all on the same captures, so the paired tests and the
failure classes of the campaign's ``summary.json`` and ``samples.npz`` say which failures each regime alone
leaves and which only the whole schedule removes (``notebooks/09_gain_schedules.ipynb``).
Options after the known ones go to ``spacegrasp montecarlo`` unchanged (``--scenario``,
``--ranges``, ...). Writes ``DIR/gains/`` (the frozen sets as gains files) and the campaign in
``DIR/campaign/`` (resumable: run the same command again).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from spacegrasp_jax import cli
from spacegrasp_jax.analysis.margins import frozen_gains, schedule_knots
from spacegrasp_jax.jobs import runfiles
from spacegrasp_jax.jobs.compilation import configure
from spacegrasp_jax.loop.control.schedule import NAMED_GAIN_SETS, load_schedule, named_gain_set


def frozen_files(schedule, folder: Path, law: str = "admittance") -> list[Path]:
    """Write the schedule's gains frozen at each of its knots to ``folder/knot_<x>.json``;
    returns the files in the knots' order."""
    folder.mkdir(parents=True, exist_ok=True)
    files = []
    for x in schedule_knots(schedule):
        path = folder / f"knot_{x:g}.json"
        runfiles.write_json(path, frozen_gains(schedule, x).to_dict(law))
        files.append(path)
    return files


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    parser.add_argument("--schedule", required=True, help="a shipped schedule's name or a schedule file")
    parser.add_argument("--out", required=True, help="the folder of the frozen gains and the campaign")
    parser.add_argument("--n", type=int, default=1000)
    parser.add_argument("--seed", type=int, required=True, help="the captures' seed, chosen before any result")
    parser.add_argument("--gains", action="append", default=[], help="a further gain set to compare (repeatable)")
    args, campaign_options = parser.parse_known_args(argv)
    configure()  # this process is the benchmark's: float64, as the campaign's command sets it
    out = Path(args.out)
    if args.schedule in NAMED_GAIN_SETS:
        schedule = named_gain_set(args.schedule)
    else:
        schedule = load_schedule(args.schedule, "admittance")
    files = frozen_files(schedule, out / "gains")
    gains = [args.schedule, *args.gains, *(str(path) for path in files)]
    command = ["montecarlo", "--controller", "admittance", "--n", str(args.n), "--seed", str(args.seed)]
    command += [option for name in gains for option in ("--gains", name)]
    resume = (out / "campaign" / "campaign.json").is_file()
    return cli.main([*command, *campaign_options, "--out", str(out / "campaign"), *(["--resume"] if resume else [])])


if __name__ == "__main__":
    sys.exit(main())
