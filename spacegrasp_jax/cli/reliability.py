"""``spacegrasp reliability``: how rarely the gains fail on an envelope, below what a campaign
resolves (``spacegrasp_jax.analysis.reliability``)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax.analysis import limit_state, reliability, worstcase
from spacegrasp_jax.cli.common import (
    _check_envelope,
    _claim,
    _criteria,
    _gains_record,
    _load_inputs,
    _ranges,
    _realism,
    _robot_links,
    _warn,
    gains_label,
    replay_command,
)
from spacegrasp_jax.cli.options import (
    UsageError,
    _add_command,
    _add_compile_cache_option,
    _add_criteria_options,
    _add_envelope_options,
    _add_run_options,
    _real,
    _whole,
)
from spacegrasp_jax.envelope import plausibility
from spacegrasp_jax.envelope.perturbations import PerturbationError, PerturbationRanges
from spacegrasp_jax.jobs import batching, campaign, runfiles
from spacegrasp_jax.jobs.records import Variant

#: The settings a resumed run must share with the run that wrote the journal.
SETTINGS_FILE = "settings.json"


def _reliability(args: argparse.Namespace) -> int:
    """``spacegrasp reliability``: the failure probability of the gains on the envelope."""
    batching.use_all_cpu_cores()  # before anything touches a device
    devices = jax.device_count()
    block = args.block if args.block is not None else devices * max(1, round(reliability.Settings.block / devices))
    try:
        ranges = _ranges(args, PerturbationRanges())
        settings = reliability.Settings(
            method=args.method,
            budget=args.budget,
            seed=args.seed,
            conditional_probability=args.level_probability,
            smallest_probability=args.smallest_probability,
            block=block,
            starts=args.starts,
            target_cv=args.target_cv,
            design_points=args.design_points,
        )
    except (reliability.ReliabilityError, PerturbationError) as error:
        raise UsageError(str(error)) from None
    if settings.block % devices:
        raise UsageError(
            f"--block: {settings.block} captures a call are not a whole number for each of the {devices} devices; "
            f"use a multiple of {devices} such as {devices * max(1, settings.block // devices)}"
        )
    robot, scenario, gains = _load_inputs(args, schedules=True)
    realism = _realism(args, scenario, robot)
    config = _criteria(args, robot, n=1, seed=args.seed, ranges=ranges, realism=realism)
    _warn(plausibility.input_warnings(scenario))
    _check_envelope(args, scenario, ranges)
    out = Path(args.out)
    sources = {
        "robot": args.robot or "paper_robot()",
        "robot_links": _robot_links(args) or None,
        "scenario": args.scenario or "paper_scenario()",
        **_gains_record(args.gains, args, args.controller),
    }
    variant, command = Variant(args.controller, gains, gains_label(args.gains)), getattr(args, "command_line", None)
    nominal_document = campaign.campaign_document(robot, scenario, [variant], config, sources=sources, command=command)
    run_settings = {
        "estimator": dataclasses.asdict(settings),
        "campaign": nominal_document["config"],
        "record": nominal_document["record"],
    }
    _check_resume(args, out, run_settings)
    _claim(args, out)
    runfiles.write_json(out / SETTINGS_FILE, run_settings)
    say = lambda line: print(line, file=sys.stderr, flush=True)
    loop = "ideal loop" if realism is None else "flight-like loop"
    say(
        f"reliability of {gains_label(args.gains)} ({args.controller} law, {loop}): {settings.method}, "
        f"{settings.budget:,} rollouts of {scenario.duration:g} s, over {jax.device_count()} device(s)..."
    )
    state = limit_state.limit_state(
        robot,
        scenario,
        gains,
        args.controller,
        config,
        block=settings.block,
        gradient=settings.method in reliability.GRADIENT_METHODS,
    )
    say(f"the envelope's standard space: {state.space.dimension} coordinates")
    result = reliability.estimate(state.limit_state, settings, journal=out / "journal", say=say)
    replays = _write_design_points(args, out, result, state, config)
    document = {
        "estimate": result.to_dict(),
        "summary": result.summary(),
        "standard_space": state.space.describe(),
        "compile_s": state.compile_s,
        "design_point_files": replays,
        "settings": run_settings,
    }
    runfiles.write_json(out / "reliability.json", document)
    from spacegrasp_jax.analysis import plots

    title = f"failure probability, {args.controller}, {gains_label(args.gains)}" + (
        f", realism {args.realism}" if args.realism else ""
    )
    plots.save(
        {"reliability.png": plots.figure_reliability(result, reliability.journal_points(out / "journal"), title)},
        out,
        runfiles.write_atomically,
    )
    print(f"{settings.method}: {result.summary()}")
    compiled = ", ".join(f"{name} {seconds:.1f} s" for name, seconds in state.compile_s.items())
    print(
        f"{result.points:,} points, {result.gradients:,} gradients in {result.wall_s:.1f} s, after compiling ({compiled})"
    )
    if result.attribution:
        common = ", ".join(f"{name} {100 * share:.0f}%" for name, share in list(result.attribution.items())[:4])
        print(f"what the failing captures have in common: {common}")
    for k, point in enumerate(result.design_points[:3]):
        share = ", ".join(f"{name} {100 * value:.0f}%" for name, value in list(point["importance"].items())[:3])
        print(
            f"design point {k + 1}: |z| = {point['distance']:.2f}, fails {point['failure']} (margin {point['g']:.3f}); {share}"
        )
    if replays:
        print(f"replay the most probable failure: {replays[0]['replay']}")
    print(f"wrote {out}/: reliability.json, reliability.png, design_points/, journal/")
    return 0


def _check_resume(args, out: Path, run_settings: dict) -> None:
    """A resumed run's settings are those of the run that wrote the journal."""
    path = out / SETTINGS_FILE
    if not args.resume or not path.exists():
        return
    stored = json.loads(path.read_text())
    wanted = runfiles.plain(run_settings)
    for part in ("estimator", "campaign"):
        for name, value in wanted[part].items():
            if stored.get(part, {}).get(name) != value:
                raise UsageError(
                    f"--resume: {out} was run with {part} setting {name} = {stored.get(part, {}).get(name)!r}, "
                    f"this command has {value!r}"
                )


def _write_design_points(args, out: Path, result: reliability.Estimate, state, config) -> list[dict]:
    """Each most probable failure point as a perturbation file ``simulate --perturbation``
    replays, and the command that does."""
    folder = out / "design_points"
    written = []
    for k, point in enumerate(result.design_points):
        units = jax.tree.map(np.asarray, state.space.to_units(jnp.asarray(point["z"])))
        path = folder / f"{k + 1}.json"
        key = np.asarray(point["noise_key"], dtype=np.uint32)
        runfiles.write_json(path, worstcase.perturbation_document(units, config.ranges, key, config.identified))
        command = replay_command(args, path, out / f"replay_{k + 1}")
        written.append(
            {"file": str(path), "margin": point["g"], "failure": point["failure"], "replay": shlex.join(command)}
        )
    return written


def add_parsers(commands) -> None:
    """The command's parser, added to ``commands``."""
    parser = _add_command(
        commands,
        "reliability",
        help="the failure probability of the gains on the envelope, below what a campaign resolves, "
        "and the most probable failures",
    )
    _add_envelope_options(parser, seed_help="seed of the estimator's draws and of the captures' noise (default 0)")
    parser.add_argument(
        "--method",
        choices=reliability.METHODS,
        default=reliability.Settings.method,
        help="subset: subset simulation; form_is: importance sampling at FORM's design points (uses the "
        "gradient); cross_entropy: cross-entropy importance sampling; montecarlo: the campaign's own samples "
        "(default %(default)s: the measured winner on a capture, documentation)",
    )
    parser.add_argument(
        "--budget",
        type=_whole(1, 100_000_000),
        default=reliability.Settings.budget,
        help=f"rollouts in all, a gradient counting {reliability.GRADIENT_COST:g} (default {reliability.Settings.budget})",
    )
    parser.add_argument(
        "--level-probability",
        type=_real(0.0, 0.5, above=True),
        default=reliability.Settings.conditional_probability,
        help="subset simulation's and cross-entropy's conditional probability of a level (default %(default)s)",
    )
    parser.add_argument(
        "--smallest-probability",
        type=_real(0.0, 0.5, above=True),
        default=reliability.Settings.smallest_probability,
        help="the levels are sized to reach it within the budget (default %(default)g)",
    )
    parser.add_argument(
        "--block",
        type=_whole(1, 100_000),
        help=f"captures a compiled call runs side by side, a multiple of the devices (default: the multiple "
        f"nearest {reliability.Settings.block})",
    )
    parser.add_argument(
        "--starts",
        type=_whole(1, 1_000),
        default=reliability.Settings.starts,
        help="FORM's starting points, the origin and points on the unit sphere (form_is; default %(default)s)",
    )
    parser.add_argument(
        "--target-cv",
        type=_real(0.0, 10.0),
        default=reliability.Settings.target_cv,
        help="stop sampling once the estimate's coefficient of variation is below this (form_is, montecarlo; "
        "default 0: spend the budget)",
    )
    parser.add_argument(
        "--design-points",
        type=_whole(1, 1_000),
        default=reliability.Settings.design_points,
        help="the most probable failures written as perturbation files (default %(default)s)",
    )
    parser.add_argument("--resume", action="store_true", help="continue the run in --out from its journal")
    _add_criteria_options(parser)
    _add_run_options(parser, "results/reliability")
    _add_compile_cache_option(parser)
    parser.set_defaults(run=_reliability)
