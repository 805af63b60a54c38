"""``spacegrasp montecarlo``: robustness campaigns, sharded and resumable."""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import jax
import numpy as np

from spacegrasp_jax.cli.common import (
    _check_envelope,
    _check_joint_ranges,
    _claim,
    _criteria,
    _gains_option,
    _load_robot,
    _paper_gains_for,
    _ranges,
    _realism,
    _robot_links,
    _warn,
    gain_set_labels,
)
from spacegrasp_jax.cli.options import (
    _SEED,
    UsageError,
    _add_command,
    _add_compile_cache_option,
    _add_criteria_options,
    _add_csv_option,
    _add_overwrite_option,
    _add_realism_option,
    _real,
    _whole,
    add_gains_arguments,
    add_ranges_arguments,
    add_robot_arguments,
)
from spacegrasp_jax.core.model import n_joints
from spacegrasp_jax.envelope import plausibility, statistics
from spacegrasp_jax.envelope.perturbations import (
    PerturbationError,
    PerturbationRanges,
)
from spacegrasp_jax.envelope.scenario import load_scenario, paper_scenario
from spacegrasp_jax.jobs import batching, campaign, runfiles
from spacegrasp_jax.loop.control import (
    CONTROLLERS,
    PAPER_CONTROLLERS,
    paper_gains,
)
from spacegrasp_jax.loop.control.schedule import NAMED_GAIN_SETS
from spacegrasp_jax.loop.realism import load_realism


def _montecarlo_variants(args: argparse.Namespace, robot) -> list[campaign.Variant]:
    """The baseline (``--baseline``: the paper's gains by default, for the paper's 7-joint arm
    and laws) first, then each ``--gains`` set: a campaign tests each against the first."""
    controllers = PAPER_CONTROLLERS if args.controller == "both" else (args.controller,)
    n = n_joints(robot)
    papers = all(controller in PAPER_CONTROLLERS for controller in controllers)
    if args.fill_from is not None and all(path in NAMED_GAIN_SETS for path in args.gains):
        raise UsageError("--fill-from: completes a gains file given with --gains; the campaign's gain sets are whole")
    named = list(args.gains)
    if args.baseline is not None:
        if args.baseline in named:
            raise UsageError(f"--baseline {args.baseline}: also given with --gains; give it once, as the baseline")
        named.insert(0, args.baseline)
    elif not args.gains:
        _paper_gains_for(robot, None if papers else args.controller)
        named.insert(0, "paper")
    elif n == len(paper_gains().kp) and papers:  # the default baseline, where the paper's gains fit
        named.insert(0, named.pop(named.index("paper")) if "paper" in named else "paper")
    labels = gain_set_labels(named)
    gain_sets = [
        (label, _gains_option(name, args, robot, controllers, schedules=True)) for name, label in zip(named, labels)
    ]
    return [campaign.Variant(controller, gains, label) for controller in controllers for label, gains in gain_sets]


def _montecarlo(args: argparse.Namespace) -> int:
    # Both before anything touches a device.
    if args.num_processes is not None and args.process_id is not None and args.process_id >= args.num_processes:
        raise UsageError(f"--process-id: must be below --num-processes ({args.num_processes}), got {args.process_id}")
    if args.distributed:
        jax.distributed.initialize(args.coordinator, args.num_processes, args.process_id)
    batching.use_all_cpu_cores()
    robot = _load_robot(args)
    try:
        ranges = _ranges(args, PerturbationRanges())
        variants = _montecarlo_variants(args, robot)
        devices = jax.device_count()
        chunk = batching.chunk_size(args.chunk, args.n)
        config = _criteria(
            args,
            robot,
            n=args.n,
            seed=args.seed,
            chunk=chunk,
            ranges=ranges,
            timeseries_every=args.timeseries_every,
            device_batch=args.device_batch
            if args.device_batch is not None
            else (128 if jax.default_backend() == "cpu" else None),
            realism=load_realism(args.realism, robot) if args.realism else None,
        )
    except (PerturbationError, ValueError) as error:  # a CampaignError is one
        raise UsageError(str(error)) from None
    scenario = load_scenario(robot, args.scenario) if args.scenario else paper_scenario(robot)
    _check_joint_ranges(args, robot, scenario)
    _realism(args, scenario, robot)  # the control period against the scenario, before compiling
    _warn(plausibility.input_warnings(scenario))
    _check_envelope(args, scenario, ranges)
    out = Path(args.out)
    _claim(args, out)
    names = ", ".join(variant.key for variant in variants)
    print(
        f"Monte-Carlo: {args.n} samples x {len(variants)} variant(s) ({names}), {scenario.duration:g} s each, "
        f"chunks of {chunk} over {devices} device(s) in {jax.process_count()} process(es)",
        file=sys.stderr,
        flush=True,
    )
    try:
        result = campaign.run_campaign(
            robot,
            scenario,
            variants,
            config,
            out,
            resume=args.resume,
            robot_source=args.robot or "paper_robot()",
            robot_links=_robot_links(args) or None,
            command=args.command_line,
            stop=args.stop,
            pairs=args.pairs,
        )
    except campaign.CampaignError as error:
        raise UsageError(str(error)) from None
    if result.status == "interrupted":
        print(
            f"interrupted after chunk {result.summary['chunks_done']}/{result.summary['chunks_total']}; "
            f"finished chunks are in {out}/chunks. Continue with: spacegrasp montecarlo {shlex.join(sys.argv[2:]) if sys.argv[1:2] == ['montecarlo'] else '...'} --resume",
            file=sys.stderr,
        )
        return 130
    _print_campaign(result)
    if jax.process_index() == 0:
        tolerance_mm = 1e3 * config.criteria.position_tolerance_m
        from spacegrasp_jax.analysis import plots

        plots.save_campaign_figures(
            out,
            result.metrics,
            campaign.figure_title(result.summary),
            tolerance_mm,
            runfiles.write_atomically,
            torque_threshold_Nm=config.criteria.torque_threshold_Nm,
        )
        if args.csv:
            with np.load(out / "samples.npz") as samples:
                runfiles.write_csv(out / "samples.csv", {name: samples[name] for name in samples.files})
        print(
            f"wrote {out}/: samples.npz{', samples.csv' if args.csv else ''}, summary.json, histograms.png, "
            "torque_vs_error.png, failures.png" + (", timeseries_*.npz" if config.timeseries_every else "")
        )
    return 0


def _print_campaign(result: campaign.CampaignResult) -> None:
    width = max(24, *(len(key) for key in result.summary["variants"]))
    header = f"{'variant':{width}} {'success [95% CI]':>22} {'diverged':>8} {'unstable':>8} {'final pos p50/p95 [mm]':>23} {'peak |u| p50/p95 [N m]':>23} {'contact p95 [N]':>16}"
    print(header)
    for key, summary in result.summary["variants"].items():
        stats = summary["statistics_over_non_diverged"]

        def pair(name, scale=1.0):
            s = stats[name]
            return f"{scale * s['p50']:.3f}/{scale * s['p95']:.3f}" if s.get("count") else "-"

        contact = stats["max_contact_force_N"]
        print(
            f"{key:{width}} {statistics.format_interval(summary['success_interval']):>22} {summary['diverged']:>8d} {summary['unstable']:>8d} {pair('final_position_error_m', 1e3):>23} "
            f"{pair('largest_peak_torque_Nm'):>23} {contact['p95'] if contact.get('count') else float('nan'):>16.3f}"
        )
    for name, comparison in result.summary.get("comparisons", {}).items():
        s, torque = comparison["success"], comparison["largest_peak_torque_Nm"]
        print(
            f"{name}: success {100 * s['rate_difference']:+.1f} points [{100 * s['rate_difference_low']:+.1f}, "
            f"{100 * s['rate_difference_high']:+.1f}] (captured by one only: {s['only_candidate']} vs {s['only_reference']}, "
            f"McNemar p = {s['p_value']:.2g}); largest peak torque median {torque['median_difference']:+.3f} N m "
            f"[{torque['low']:+.3f}, {torque['high']:+.3f}] (lower in {torque['candidate_lower']} vs {torque['reference_lower']}, "
            f"Wilcoxon p = {torque['p_value']:.2g})"
        )
    throughput = result.summary["throughput"]
    if throughput["rollouts_per_s"]:
        print(
            f"throughput: {throughput['rollouts_per_s']:.2f} rollouts/s, {throughput['simulated_s_per_wall_s']:.1f} simulated s per wall s "
            f"on {throughput['devices']} {throughput['platform']} device(s); compile {throughput['compile_s']:.1f} s "
            f"({throughput['programs_compiled']} program(s))"
        )


def add_parsers(commands) -> None:
    """The command's parser, added to ``commands``."""
    montecarlo = _add_command(
        commands, "montecarlo", help="robustness campaign over perturbed captures (sharded, resumable)"
    )
    montecarlo.add_argument("--n", type=_whole(1, 100_000_000), required=True, help="number of perturbed samples")
    montecarlo.add_argument(
        "--controller", choices=(*CONTROLLERS, "both"), default="both", help="a law, or both of the paper's (default)"
    )
    add_gains_arguments(montecarlo, repeatable=True)
    montecarlo.add_argument(
        "--baseline",
        metavar="NAME|FILE",
        help="the gain set every other is tested against, paired on the same captures: a shipped set by name "
        "or a gains file (default: the paper's gains, where they fit the arm; they run only as the baseline or "
        "when named with --gains)",
    )
    montecarlo.add_argument(
        "--pairs",
        choices=campaign.PAIRS,
        default="baseline",
        help="which gain sets are tested against one another: each against the baseline (default), or every pair",
    )
    montecarlo.add_argument("--seed", type=_SEED, default=0, help="campaign seed (default 0)")
    montecarlo.add_argument(
        "--chunk",
        type=_whole(1, 1_000_000),
        default=256,
        help="samples per compiled call, a multiple of the device count (default 256)",
    )
    montecarlo.add_argument(
        "--device-batch",
        type=_whole(1, 1_000_000),
        default=None,
        metavar="K",
        help="samples each device simulates at once (default 128 on CPU, its whole share on GPU)",
    )
    montecarlo.add_argument("--out", default="results/montecarlo", help="output folder (default results/montecarlo)")
    _add_overwrite_option(montecarlo)
    _add_csv_option(montecarlo, "samples.npz")
    add_ranges_arguments(montecarlo, "montecarlo")
    _add_criteria_options(montecarlo)
    montecarlo.add_argument(
        "--timeseries-every",
        type=_whole(1, 100_000_000),
        default=None,
        metavar="K",
        help="also keep every K-th log row of every sample",
    )
    montecarlo.add_argument("--scenario", help="nominal scenario TOML/JSON (default: the paper's)")
    add_robot_arguments(montecarlo)
    montecarlo.add_argument(
        "--pinv-damping", type=_real(0.0, 1e3), default=0.0, help="damping of the pseudoinverse (0: exact, the paper)"
    )
    montecarlo.add_argument("--resume", action="store_true", help="continue the campaign in --out chunk by chunk")
    _add_realism_option(montecarlo)
    cluster = montecarlo.add_argument_group("several hosts (jax.distributed; run the same command on every host)")
    cluster.add_argument(
        "--distributed",
        action="store_true",
        help="call jax.distributed.initialize (auto-detects SLURM and similar without the options below)",
    )
    cluster.add_argument("--coordinator", help="HOST:PORT of process 0")
    cluster.add_argument("--num-processes", type=_whole(1, 65_536), help="number of processes")
    cluster.add_argument("--process-id", type=_whole(0, 65_535), help="this process's rank, 0 .. num-processes - 1")
    _add_compile_cache_option(montecarlo)
    montecarlo.set_defaults(run=_montecarlo)
