"""``spacegrasp margins``: gain and delay margins, time-domain and linear."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax

from spacegrasp_jax.analysis import margins, stability
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
    _warn,
    gains_label,
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
from spacegrasp_jax.envelope.perturbations import (
    PerturbationError,
    PerturbationRanges,
)
from spacegrasp_jax.jobs import batching, campaign, runfiles
from spacegrasp_jax.jobs.records import Variant
from spacegrasp_jax.loop.control.schedule import VARIABLES, GainSchedule
from spacegrasp_jax.loop.simulate import RunSpec


def _margins(args: argparse.Namespace) -> int:
    """``spacegrasp margins``: the gain and delay margins of one gain set, by bisection on
    batched rollouts over envelope samples (``spacegrasp_jax.analysis.margins``)."""
    batching.use_all_cpu_cores()  # before anything touches a device
    try:
        margins.require_joint_servo(args.controller)
        ranges = _ranges(args, PerturbationRanges())
        settings = margins.MarginSettings(
            samples=args.samples,
            max_factor=args.max_factor,
            factor_resolution=args.factor_resolution,
            max_delay_periods=args.max_delay,
            max_servo_delay_ticks=args.max_servo_delay,
        )
    except (margins.MarginError, PerturbationError) as error:
        raise UsageError(str(error)) from None
    robot, scenario, gains = _load_inputs(args, schedules=True)
    realism = _realism(args, scenario, robot)
    config = _criteria(args, robot, n=args.samples, seed=args.seed, ranges=ranges, realism=realism)
    _warn(plausibility.input_warnings(scenario))
    _check_envelope(args, scenario, ranges)
    out = Path(args.out)
    _claim(args, out)
    period = margins.control_period(scenario, realism)
    print(
        f"margins of the {args.controller} law: probes of {args.samples} envelope samples, {scenario.duration:g} s each, "
        f"control period {period:g} s, over {jax.device_count()} device(s)...",
        file=sys.stderr,
        flush=True,
    )
    sources = {
        "robot": args.robot or "paper_robot()",
        "robot_links": _robot_links(args) or None,
        "scenario": args.scenario or "paper_scenario()",
        **_gains_record(args.gains, args, args.controller),
    }
    variant = Variant(args.controller, gains, gains_label(args.gains))
    nominal = campaign.campaign_document(
        robot, scenario, [variant], config, sources=sources, command=getattr(args, "command_line", None)
    )
    record = {"record": nominal["record"], "campaign": nominal["config"], "scenario_duration_s": scenario.duration}
    title = f"{args.controller}, {args.gains or 'paper gains'}, {args.samples} samples" + (
        f", realism {args.realism}" if args.realism else ""
    )

    tolerance_mm = 1e3 * config.criteria.position_tolerance_m
    if not isinstance(gains, GainSchedule):
        result = _margins_of(args, robot, scenario, gains, config, settings, realism)
        result["settings"] |= {"gains": gains.to_dict(args.controller), **record}
        _save_margins(out, result, tolerance_mm, title)
        runfiles.write_json(out / "margins.json", result)
        for line in _result_lines(result):
            print(line)
        linear_files = ", eigenvalues.png, bode.png, nichols.png, frequency_response.npz" if result["linear"] else ""
        print(f"wrote {out}/: margins.json, margins.png{linear_files}")
        return 0
    # A schedule: the frozen gains at each knot, each checked as a constant gain set.
    per_knot = []
    for number, x in enumerate(margins.schedule_knots(gains)):
        print(f"knot {number + 1}: {gains.variable} = {x:g} {VARIABLES[gains.variable]}", file=sys.stderr, flush=True)
        frozen = margins.frozen_gains(gains, x)
        result = _margins_of(args, robot, scenario, frozen, config, settings, realism)
        result["settings"] |= {"gains": frozen.to_dict(args.controller)}
        per_knot.append({"x": x, "margins": result})
        knot_title = f"{title}, {gains.variable} = {x:g} {VARIABLES[gains.variable]}"
        folder = out / f"knot_{number + 1}"
        folder.mkdir(parents=True, exist_ok=True)
        _save_margins(folder, result, tolerance_mm, knot_title)
        for line in _result_lines(result):
            print(f"  {line}")
    worst = margins.worst_knots(per_knot)
    linear = [(item["x"], item["margins"]["linear"]) for item in per_knot if item["margins"]["linear"]]
    if linear:
        x, fastest = max(linear, key=lambda pair: pair[1]["fastest_growth_per_s"])
        worst["linear_growth"] = {"x": x, "size": fastest["fastest_growth_per_s"]}
    document = {
        "schedule": gains.to_dict(args.controller),
        "knots": per_knot,
        "worst": worst,
        "settings": {"samples": args.samples, **record},
    }
    runfiles.write_json(out / "margins.json", document)
    unit = VARIABLES[gains.variable]
    print(f"the worst knot of each margin ({len(per_knot)} knots on {gains.variable}):")
    for name, item in worst.items():
        size = f"{item['size']:+.3g} 1/s" if name == "linear_growth" else f"{item['size']:.3g}"
        print(f"  {name}: {size} at {gains.variable} = {item['x']:g} {unit}")
    print(f"wrote {out}/: margins.json, knot_*/margins.png")
    return 0


def _margins_of(args, robot, scenario, gains, config, settings, realism) -> dict:
    """The margins of one constant gain set, with the linear analysis unless it is skipped."""
    result = margins.find_margins(
        robot,
        scenario,
        gains,
        args.controller,
        config,
        settings,
        progress=lambda line: print(line, file=sys.stderr, flush=True),
    )
    result["linear"] = None
    if args.no_linear:
        result["linear_skipped"] = "--no-linear"
    elif scenario.free_target:
        result["linear_skipped"] = "the linear analysis covers the paper's stationary target only"
        print(f"linear analysis skipped: {result['linear_skipped']}", file=sys.stderr)
    else:
        print(
            "linearising the loop at the end of the nominal capture (the capture run once, then one Jacobian a factor)...",
            file=sys.stderr,
            flush=True,
        )
        result["linear"] = stability.linear_analysis(
            RunSpec(robot, scenario, _law(args.controller, args), realism=realism),
            gains,
            settings,
            growth_limit_per_s=args.growth_limit,
        )
    return result


def _save_margins(folder: Path, result: dict, tolerance_mm: float, title: str) -> None:
    """The figures of one gain set's margins in ``folder`` and, with a linear analysis, its
    loops' frequency response (``frequency_response.npz``: per loop its frequencies (Hz), the
    loci's magnitude (dB) and phase (deg)), taken out of ``result`` (left JSON-ready)."""
    from spacegrasp_jax.analysis import plots

    bode = result["linear"].pop("bode") if result.get("linear") else None
    if bode is not None:
        arrays = {f"{loop}/{name}": value for loop, data in bode.items() for name, value in data.items()}
        runfiles.write_arrays(folder / "frequency_response.npz", arrays)
    plots.save_margin_figures(folder, result, tolerance_mm, title, runfiles.write_atomically, bode=bode)


def _result_lines(result: dict) -> list[str]:
    return margins.margin_lines(result) + (stability.linear_lines(result["linear"]) if result["linear"] else [])


def add_parsers(commands) -> None:
    """The command's parser, added to ``commands``."""
    margin = _add_command(
        commands, "margins", help="gain and delay margins of a gain set, by bisection on envelope samples"
    )
    _add_envelope_options(margin, seed_help="campaign seed of the samples (default 0)")
    margin.add_argument(
        "--samples",
        type=_whole(1, 100_000),
        default=margins.MarginSettings.samples,
        help=f"envelope samples every probe runs (default {margins.MarginSettings.samples})",
    )
    margin.add_argument(
        "--max-factor",
        type=_real(1.0, 1e6, above=True),
        default=margins.MarginSettings.max_factor,
        help=f"search the gain factors in [1/F, F] (default {margins.MarginSettings.max_factor:g})",
    )
    margin.add_argument(
        "--factor-resolution",
        type=_real(1.0, 1e6, above=True),
        default=margins.MarginSettings.factor_resolution,
        metavar="RATIO",
        help="stop bisecting when the factor that holds and the one that fails differ by at most this ratio "
        f"(default {margins.MarginSettings.factor_resolution:g})",
    )
    margin.add_argument(
        "--max-delay",
        type=_whole(1, 100_000),
        default=margins.MarginSettings.max_delay_periods,
        metavar="PERIODS",
        help=f"the largest extra delay searched, in control periods (default {margins.MarginSettings.max_delay_periods})",
    )
    margin.add_argument(
        "--max-servo-delay",
        type=_whole(1, 100_000),
        default=margins.MarginSettings.max_servo_delay_ticks,
        metavar="TICKS",
        help="the largest delay at the servo's input searched, in servo ticks, where the servos run at their own "
        f"rate (default {margins.MarginSettings.max_servo_delay_ticks})",
    )
    margin.add_argument(
        "--growth-limit",
        type=_real(0.0, 1e6),
        default=1.0,
        metavar="PER_S",
        help="the linear analysis counts a mode growing faster than this (1/s) as unstable (default 1)",
    )
    margin.add_argument(
        "--no-linear",
        action="store_true",
        help="skip the linear analysis (the period map's eigenvalues and the linear gain margins)",
    )
    _add_criteria_options(margin)
    _add_run_options(margin, "results/margins")
    _add_compile_cache_option(margin)
    margin.set_defaults(run=_margins)
