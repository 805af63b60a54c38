"""``spacegrasp worstcase``: the worst capture of the envelope, by gradient ascent."""

from __future__ import annotations

import argparse
import dataclasses
import shlex
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax.analysis import worstcase
from spacegrasp_jax.cli.common import (
    _check_envelope,
    _claim,
    _criteria,
    _gains_record,
    _law,
    _load_inputs,
    _ranges,
    _realism,
    _robot_links,
    _run_caption,
    _warn,
    _write_results,
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
    _whole,
)
from spacegrasp_jax.core.model import n_joints
from spacegrasp_jax.envelope import plausibility
from spacegrasp_jax.envelope.perturbations import (
    PerturbationError,
    PerturbationRanges,
    from_units,
)
from spacegrasp_jax.jobs import batching, campaign, experiment, runfiles
from spacegrasp_jax.jobs.montecarlo import perturbed_run
from spacegrasp_jax.jobs.records import Variant, make_record
from spacegrasp_jax.loop.simulate import RunSpec


def _worstcase(args: argparse.Namespace) -> int:
    """``spacegrasp worstcase``: the worst capture of the envelope by gradient ascent, against
    a campaign of the same rollouts (``spacegrasp_jax.analysis.worstcase``)."""
    batching.use_all_cpu_cores()  # before anything touches a device
    try:
        ranges = _ranges(args, PerturbationRanges())
        if args.starts is not None and args.method != "ascent":
            raise UsageError(
                f"--starts: the gradient ascent's starts; --method {args.method} has none (--method ascent)"
            )
        settings = worstcase.SearchSettings(
            budget=args.budget,
            measure=args.measure,
            method=args.method,
            starts=worstcase.SearchSettings.starts if args.starts is None else args.starts,
        )
    except (worstcase.WorstCaseError, PerturbationError) as error:
        raise UsageError(str(error)) from None
    robot, scenario, gains = _load_inputs(args)
    realism = _realism(args, scenario, robot)
    config = _criteria(args, robot, n=1, seed=args.seed, ranges=ranges, realism=realism)
    if args.measure == "criteria" and config.criteria.torque_threshold_Nm is None:
        _warn(["--measure criteria with --torque-threshold 0: the peak torque is not among the criteria"])
    _warn(plausibility.input_warnings(scenario))
    _check_envelope(args, scenario, ranges)
    out = Path(args.out)
    _claim(args, out)
    unit, meaning = worstcase.MEASURES[args.measure]
    steps = (
        f"{settings.ascent_steps} ascent steps of {settings.starts} starts"
        if settings.method == "ascent"
        else f"{settings.generations} generations of a cross-entropy search, up to {settings.generation} samples each"
    )
    print(
        f"worst case of the {args.controller} law: {meaning}, {args.budget} rollouts "
        f"({settings.screening} screened, {steps}), {scenario.duration:g} s each, over {jax.device_count()} device(s)...",
        file=sys.stderr,
        flush=True,
    )
    say = lambda line: print(line, file=sys.stderr, flush=True)
    found = worstcase.search(robot, scenario, gains, args.controller, config, settings, progress=say)
    say(f"the campaign of the same {args.budget} rollouts (its first {len(found.screening)} are the screening's)...")
    baseline = worstcase.compare_with_campaign(
        robot,
        scenario,
        gains,
        args.controller,
        config,
        args.budget,
        args.measure,
        chunk=settings.campaign_chunk,
        screened=found.screening,
    )
    units = jax.tree.map(jnp.asarray, found.units)
    replay_file = out / "worst_perturbation.json"
    runfiles.write_json(replay_file, worstcase.perturbation_document(found.units, ranges, found.key, config.identified))
    campaign_units = jax.tree.map(
        lambda x: x[0], worstcase.units_of_samples(args.seed, [baseline["sample"]], n_joints=n_joints(robot))
    )
    campaign_key = worstcase.noise_keys(args.seed, [baseline["sample"]])[0]
    runfiles.write_json(
        out / "campaign_worst_perturbation.json",
        worstcase.perturbation_document(campaign_units, ranges, campaign_key, config.identified),
    )
    sources = {
        "robot": args.robot or "paper_robot()",
        "robot_links": _robot_links(args) or None,
        "scenario": args.scenario or "paper_scenario()",
        **_gains_record(args.gains, args, args.controller),
    }
    variant, command = Variant(args.controller, gains, gains_label(args.gains)), getattr(args, "command_line", None)
    nominal_document = campaign.campaign_document(robot, scenario, [variant], config, sources=sources, command=command)
    say("the worst capture again, with its whole log...")
    nominal = RunSpec(robot, scenario, _law(args.controller, args), realism=realism)
    spec = perturbed_run(nominal, from_units(units, ranges), ranges, config.identified)
    result = experiment.run(spec, gains, key=jnp.asarray(found.key, dtype=jnp.uint32), check=False)
    perturbation = jax.tree.map(lambda x: np.asarray(x).tolist(), vars(from_units(units, ranges)))
    replay = replay_command(args, replay_file, out / "replay")
    document = {
        "measure": args.measure,
        "unit": unit,
        "meaning": meaning,
        "worst_found": {
            "value": found.value,
            "start": found.start,
            "start_sample": None if found.start < 0 else found.start_samples[found.start],
            "found_by": found.found_by,
            "units": worstcase.units_to_dict(found.units),
            "perturbation": perturbation,
            "noise_key": [int(x) for x in found.key],
            "summary": campaign.with_capture_verdict(result.summary, config.criteria),
        },
        "campaign": {
            "n": args.budget,
            "seed": args.seed,
            "worst": baseline["value"],
            "worst_sample": baseline["sample"],
        },
        "worse_than_the_campaign": bool(found.value >= baseline["value"]),
        "rollouts": found.rollouts,
        "screening": int(len(found.screening)),
        "compile_s": found.compile_s,
        "search_s": found.search_s,
        "history": found.history,
        "replay": shlex.join(replay),
        "settings": dataclasses.asdict(settings)
        | {"record": nominal_document["record"], "campaign": nominal_document["config"]}
        | {"scenario_duration_s": scenario.duration},
    }
    runfiles.write_json(out / "worstcase.json", document)
    loop = "ideal loop" if realism is None else "flight-like loop"
    found_record = make_record(
        spec.robot,
        spec.scenario,
        [variant],
        realism=spec.realism,
        criteria=config.criteria,
        pinv_damping=config.pinv_damping,
        model_robot=spec.model_robot,
        key=found.key,
        command=command,
        sources=sources | {"worstcase": str(out / "worstcase.json")},
    )
    _write_results(
        out,
        {args.controller: result},
        {"record": found_record.to_dict(), "worstcase": str(out / "worstcase.json")},
        beside_paper=False,
        caption=_run_caption(f"the worst capture found ({args.measure}): {loop}", "its gains", scenario),
        torque_limit_Nm=np.asarray(robot.joint_torque_limit),
        criteria=config.criteria,
    )
    label = f"{args.measure} [{unit}]" if unit else args.measure
    title = f"worst case, {args.controller}, {args.gains or 'paper gains'}" + (
        f", realism {args.realism}" if args.realism else ""
    )
    from spacegrasp_jax.analysis import plots

    plots.save(
        {
            "search.png": plots.figure_worst_case_search(
                found.history, baseline["values"], len(found.screening), label, title
            )
        },
        out,
        runfiles.write_atomically,
    )
    print(
        f"worst {args.measure} found: {worstcase.shown(args.measure, found.value)} ({found.found_by}); worst of a "
        f"campaign of {args.budget}: {worstcase.shown(args.measure, baseline['value'])} (sample {baseline['sample']})"
    )
    print(f"{found.rollouts} rollouts in {found.search_s:.1f} s, after {found.compile_s:.1f} s compiling")
    print(f"replay it: {shlex.join(replay)}")
    if baseline["value"] > found.value:
        print(
            "the campaign's worst sample is worse than the search's: replay it with --perturbation "
            f"{out / 'campaign_worst_perturbation.json'}"
        )
    print(
        f"wrote {out}/: worstcase.json, worst_perturbation.json, campaign_worst_perturbation.json, search.png, "
        "the worst capture's summary.json, figures, timeseries"
    )
    return 0


def add_parsers(commands) -> None:
    """The command's parser, added to ``commands``."""
    worst = _add_command(
        commands, "worstcase", help="the worst capture of the envelope by search, against a campaign of its rollouts"
    )
    _add_envelope_options(worst, seed_help="campaign seed of the screening (default 0)")
    worst.add_argument(
        "--budget",
        type=_whole(1, 10_000_000),
        default=worstcase.SearchSettings.budget,
        help=f"rollouts in all, a gradient counting {worstcase.GRADIENT_COST} (default {worstcase.SearchSettings.budget})",
    )
    worst.add_argument(
        "--measure",
        choices=tuple(worstcase.MEASURES),
        default=worstcase.SearchSettings.measure,
        help="what makes a capture worse: its final position error, its largest peak torque, or its largest "
        "ratio to the success criteria (default %(default)s)",
    )
    worst.add_argument(
        "--method",
        choices=worstcase.METHODS,
        default=worstcase.SearchSettings.method,
        help="how the rollouts after the screening are spent: cem, a cross-entropy search of forward rollouts, or "
        "ascent, a gradient ascent (default %(default)s: the measured winner, documentation)",
    )
    worst.add_argument(
        "--starts",
        type=_whole(1, 1_000),
        help="the gradient ascent's starts side by side: the screening's worst and a random corner "
        f"(--method ascent; default {worstcase.SearchSettings.starts})",
    )
    _add_criteria_options(worst)
    _add_run_options(worst, "results/worstcase")
    _add_compile_cache_option(worst)
    worst.set_defaults(run=_worstcase)
