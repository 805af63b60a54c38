"""``spacegrasp requirements``: what navigation, sensing and timing a gain set requires."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax
import numpy as np

from spacegrasp_jax.analysis import requirements
from spacegrasp_jax.cli.common import (
    _check_envelope,
    _check_joint_ranges,
    _claim,
    _criteria,
    _load_robot,
    _ranges,
    _realism,
    _warn,
)
from spacegrasp_jax.cli.montecarlo import _montecarlo_variants
from spacegrasp_jax.cli.options import (
    _SEED,
    UsageError,
    _add_command,
    _add_compile_cache_option,
    _add_criteria_options,
    _add_overwrite_option,
    _add_realism_option,
    _real,
    _whole,
    add_gains_arguments,
    add_ranges_arguments,
    add_robot_arguments,
)
from spacegrasp_jax.envelope import plausibility, statistics
from spacegrasp_jax.envelope.scenario import load_scenario, paper_scenario
from spacegrasp_jax.jobs import batching, campaign, runfiles
from spacegrasp_jax.loop.control import CONTROLLERS
from spacegrasp_jax.loop.realism import load_realism

#: A study setting -> the option that sets it.
STUDY_OPTIONS = {"groups": "--groups", "widths": "--widths", "levels": "--levels", "n": "--n", "sobol": "--sobol"}


def _numbers(text: str, option: str) -> tuple[float, ...]:
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise UsageError(f"{option}: expected comma-separated numbers, got {text!r}") from None


def _requirements(args: argparse.Namespace) -> int:
    batching.use_all_cpu_cores()  # before anything touches a device
    robot = _load_robot(args)
    scenario = load_scenario(robot, args.scenario) if args.scenario else paper_scenario(robot)
    reference = _ranges(args, requirements.REFERENCE_RANGES)  # its own errors name their option
    try:
        groups = (
            tuple(name for name in args.groups.split(",") if name)
            if args.groups
            else requirements.groups_for(scenario.free_target)
        )
        settings = requirements.StudySettings(
            groups=groups,
            widths=_numbers(args.widths, "--widths"),
            levels=tuple(level / 100.0 for level in _numbers(args.levels, "--levels")),
            n=args.n,
            sobol=args.sobol,
            seed=args.seed,
        )
        if "target" in groups and not scenario.free_target:
            raise UsageError("--groups target: needs a scenario with a free-floating [target]")
        for group in [*groups, requirements.ALL]:  # the widest point of every curve must be a valid envelope
            try:
                requirements.scaled_group(reference, group, settings.widths[-1])
            except requirements.RequirementsError as error:
                raise UsageError(f"--widths {args.widths}: {error}") from None
        variants = _montecarlo_variants(args, robot)
        config = _criteria(
            args,
            robot,
            n=1,
            chunk=batching.chunk_size(args.chunk, args.n),
            device_batch=128 if jax.default_backend() == "cpu" else None,
            realism=load_realism(args.realism, robot) if args.realism else None,
        )
    except requirements.RequirementsError as error:  # a study setting: its message leads with the field
        field, _, rest = str(error).partition(": ")
        raise UsageError(f"{STUDY_OPTIONS.get(field, field)}: {rest}") from None
    _check_joint_ranges(args, robot, scenario)
    _realism(args, scenario, robot)
    _warn(plausibility.input_warnings(scenario))
    _check_envelope(args, scenario, requirements.scaled_group(reference, requirements.ALL, settings.widths[-1]))
    out = Path(args.out)
    _claim(args, out)
    points = (len(groups) + 1) * len(settings.widths)
    sobol = settings.sobol * (len(groups) + 3)
    print(
        f"requirements of {', '.join(v.key for v in variants)}: {points} campaigns of {args.n} captures "
        f"({len(groups)} groups and all together, at {', '.join(f'{w:g}x' for w in settings.widths)} the reference)"
        + (f", and {sobol} captures a gain set for the failures' attribution" if sobol else ""),
        file=sys.stderr,
        flush=True,
    )
    say = lambda line: print(line, file=sys.stderr, flush=True)
    try:
        document = requirements.run_study(
            robot, scenario, variants, config, reference, settings, out, progress=say, stop=args.stop
        )
    except requirements.StudyInterrupted:
        print(f"interrupted; the finished points are in {out}/points. Continue with --resume", file=sys.stderr)
        return 130
    except campaign.CampaignError as error:
        raise UsageError(str(error)) from None
    runfiles.write_json(out / "requirements.json", document)
    _print_study(document)
    from spacegrasp_jax.analysis import plots

    plots.save_requirement_curves(out / "curves.png", document, runfiles.write_atomically)
    print(f"wrote {out}/: requirements.json, curves.png, points/ (one campaign a point)")
    return 0


def _print_study(document: dict) -> None:
    curves = document["curves"]
    for label, lines in document["requirements"].items():
        print(f"{label}:")
        everything = curves[requirements.ALL][label]
        rates = ", ".join(
            f"{w:g}x {statistics.format_interval(i)}"
            for w, i in zip(curves[requirements.ALL]["widths"], everything["intervals"])
        )
        print(f"  all perturbations together: {rates}")
        for line in lines:
            print(f"  {line}")
        attribution = document.get("failure_attribution", {}).get(label)
        if attribution:
            shares = sorted(zip(attribution["total"], attribution["groups"]), reverse=True)
            print(
                f"  failures ({100 * attribution['failure_rate']:.1f}% at the reference) take part in: "
                + ", ".join(f"{group} {np.nan_to_num(share):.2f}" for share, group in shares)
            )


def add_parsers(commands) -> None:
    """The command's parser, added to ``commands``."""
    parser = _add_command(
        commands,
        "requirements",
        help="success against the width of each perturbation: the navigation, sensing and timing the gains require",
    )
    parser.add_argument(
        "--n", type=_whole(1, 10_000_000), default=500, help="captures per point of a curve (default 500)"
    )
    parser.add_argument("--controller", choices=CONTROLLERS, default="admittance")
    add_gains_arguments(parser, repeatable=True)
    parser.add_argument(
        "--baseline", metavar="NAME|FILE", help="a gain set studied first (default: the paper's gains where they fit)"
    )
    parser.add_argument(
        "--groups",
        metavar="NAME,...",
        help=f"the perturbation groups to sweep, of {', '.join(requirements.GROUPS)} (default: every one the "
        "scenario has; target only with a free-floating target)",
    )
    parser.add_argument(
        "--widths",
        default=",".join(f"{w:g}" for w in requirements.WIDTHS),
        metavar="K,...",
        help="the widths, multiples of the reference envelope (default 1,1.5,2,3,4)",
    )
    parser.add_argument(
        "--levels",
        default=",".join(f"{100 * level:g}" for level in requirements.LEVELS),
        metavar="PERCENT,...",
        help="the success levels requirements are stated at (default 99,90)",
    )
    parser.add_argument(
        "--sobol",
        type=_whole(0, 1_048_576),
        default=0,
        metavar="N",
        help="attribute the failures by Sobol indices over N base points (a power of two; N x (groups + 3) "
        "captures a gain set; default 0: none)",
    )
    parser.add_argument("--seed", type=_SEED, default=0, help="the campaigns' seed (default 0)")
    parser.add_argument(
        "--chunk", type=_whole(1, 1_000_000), default=256, help="captures per compiled call (default 256)"
    )
    parser.add_argument("--out", default="results/requirements", help="output folder (default results/requirements)")
    _add_overwrite_option(parser)
    parser.add_argument("--resume", action="store_true", help="continue the study in --out point by point")
    add_ranges_arguments(parser, "the requirements' reference")
    _add_criteria_options(parser)
    parser.add_argument("--scenario", help="nominal scenario TOML/JSON (default: the paper's)")
    add_robot_arguments(parser)
    parser.add_argument(
        "--pinv-damping", type=_real(0.0, 1e3), default=0.0, help="damping of the pseudoinverse (0: exact, the paper)"
    )
    _add_realism_option(parser)
    _add_compile_cache_option(parser)
    parser.set_defaults(run=_requirements)
