"""``spacegrasp ceiling``: how high a campaign's success could go, each failed capture tuned alone."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from spacegrasp_jax.cli.common import _claim
from spacegrasp_jax.cli.options import (
    _SEED,
    UsageError,
    _add_command,
    _add_compile_cache_option,
    _add_overwrite_option,
    _real,
    _whole,
)
from spacegrasp_jax.envelope import statistics
from spacegrasp_jax.jobs import batching, campaign


def _ceiling(args: argparse.Namespace) -> int:
    from spacegrasp_jax.tuning import ceiling

    batching.use_all_cpu_cores()  # before anything touches a device
    folder = Path(args.campaign)
    try:
        record, config = campaign.campaign_record(folder)
    except campaign.CampaignError as error:
        raise UsageError(str(error)) from None
    if not (folder / "samples.npz").is_file():
        raise UsageError(f"{folder}: holds no samples.npz (an unfinished campaign? finish it with montecarlo --resume)")
    keys = [variant.key for variant in record.variants]
    if args.variant is None and len(keys) > 1:
        raise UsageError(f"--variant: {folder} holds {len(keys)} variants; name one of {', '.join(keys)}")
    if args.variant is not None and args.variant not in keys:
        raise UsageError(f"--variant: {folder} has no variant {args.variant!r}; it has {', '.join(keys)}")
    if config.realism is None:
        raise UsageError(f"{folder}: a campaign of the ideal loop; the ceiling tunes flight-like captures (--realism)")
    try:
        settings = ceiling.CeilingSettings(
            failures=args.failures, steps=args.steps, learning_rate=args.lr, seed=args.seed
        )
    except ceiling.CeilingError as error:
        raise UsageError(str(error)) from None
    out = Path(args.out)
    _claim(args, out)
    say = lambda line: print(line, file=sys.stderr, flush=True)
    label = args.variant or keys[0]
    say(
        f"the ceiling of {label} in {folder}: up to {args.failures} failed captures, each tuned alone for up to {args.steps} steps"
    )
    try:
        document = ceiling.run_ceiling(folder, out, settings, label, progress=say, stop=args.stop)
    except ceiling.CeilingInterrupted as error:
        say(f"interrupted ({error}); the rows so far are in {out}/ceiling.jsonl. Continue with --resume")
        return 130
    except ceiling.CeilingError as error:
        raise UsageError(str(error)) from None
    share = document["fixed_share"]
    print(
        f"{label}: {document['successes']} of {document['samples']} captured; of {document['failures_tried']} of its "
        f"{document['failures']} failures, {document['fixed']} captured when tuned alone"
        + (f" ({statistics.format_interval(share)})" if share else "")
    )
    print(
        f"ceiling: {100 * document['ceiling']:.1f}% [{100 * document['low']:.1f}, {100 * document['high']:.1f}] "
        f"(success {100 * document['success']:.1f}%)"
    )
    print(f"wrote {out}/: ceiling.json, ceiling.jsonl, gains/ (each capture's tuned gains)")
    return 0


def add_parsers(commands) -> None:
    """The command's parser, added to ``commands``."""
    parser = _add_command(
        commands,
        "ceiling",
        help="how high a campaign's success could go: each failed capture tuned alone, still missed or captured",
    )
    parser.add_argument("campaign", metavar="CAMPAIGN_DIR", help="a montecarlo output folder (a flight-like loop's)")
    parser.add_argument(
        "--variant", metavar="LAW/GAINS", help="the variant whose failures are tuned (default: the campaign's only one)"
    )
    parser.add_argument(
        "--failures",
        type=_whole(1, 1_000_000),
        default=50,
        help="failed captures tuned, drawn at random among the campaign's (default 50)",
    )
    parser.add_argument(
        "--steps", type=_whole(1, 100_000), default=40, help="gradient steps a capture at most (default 40)"
    )
    parser.add_argument(
        "--lr",
        type=_real(0.0, 10.0, above=True),
        default=0.1,
        help="adam's learning rate on the log-gains (default 0.1)",
    )
    parser.add_argument("--seed", type=_SEED, default=0, help="which failures are drawn (default 0)")
    parser.add_argument("--out", default="results/ceiling", help="output folder (default results/ceiling)")
    _add_overwrite_option(parser)
    parser.add_argument("--resume", action="store_true", help="continue the rows in --out capture by capture")
    _add_compile_cache_option(parser)
    parser.set_defaults(run=_ceiling)
