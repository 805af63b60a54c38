"""``spacegrasp gradients``: the tuning objective's gradient over the envelope, checked."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import jax
import numpy as np

from spacegrasp_jax.cli.common import (
    _check_envelope,
    _claim,
    _gains_record,
    _law,
    _load_inputs,
    _ranges,
    _rate_criterion,
    _realism,
    _robot_links,
    _warn,
    gains_label,
)
from spacegrasp_jax.cli.options import (
    _SEED,
    UsageError,
    _add_command,
    _add_compile_cache_option,
    _add_realism_option,
    _add_run_options,
    _real,
    _whole,
    add_gains_arguments,
    add_objective_arguments,
    add_ranges_arguments,
    tune_setting_error,
)
from spacegrasp_jax.core.model import n_joints
from spacegrasp_jax.envelope import plausibility
from spacegrasp_jax.envelope.perturbations import (
    PerturbationRanges,
)
from spacegrasp_jax.jobs import batching, paper, runfiles
from spacegrasp_jax.jobs.records import Variant, make_record
from spacegrasp_jax.loop.control import (
    CONTROLLERS,
)
from spacegrasp_jax.loop.simulate import RunSpec
from spacegrasp_jax.tuning.gradients import HORIZONS as GRADIENT_HORIZONS
from spacegrasp_jax.tuning.gradients import central_differences, envelope_gradients, finite_rows
from spacegrasp_jax.tuning.gradients import report as gradient_report
from spacegrasp_jax.tuning.objective import Weights
from spacegrasp_jax.tuning.tune import TuneConfig, make_objective


def _gradients(args: argparse.Namespace) -> int:
    batching.use_all_cpu_cores()  # before anything touches a device
    try:
        ranges = _ranges(args, PerturbationRanges())
        horizons = _horizons(args.horizons)
    except ValueError as error:
        raise UsageError(str(error)) from None
    try:  # the objective as tune builds it: the same checks, the same messages
        config = TuneConfig(
            controller=args.controller,
            objective=args.objective,
            weights=Weights.parse(args.weights or ""),
            torque_fraction=args.torque_fraction,
            torque_cap_Nm=args.torque_cap,
        )
    except ValueError as error:
        raise tune_setting_error(error) from None
    robot, scenario, gains = _load_inputs(args)
    config = dataclasses.replace(config, joint_rate_limits_radps=_rate_criterion(args, robot))
    try:
        config.weights.check_target(scenario.free_target)
    except ValueError as error:
        raise UsageError(str(error)) from None
    law = _law(args.controller, args)
    realism = _realism(args, scenario, robot)
    _warn(plausibility.input_warnings(scenario))
    _check_envelope(args, scenario, ranges)
    out = Path(args.out)
    _claim(args, out)
    # A fixed torque scale, so that reports at different gains compare: Table 5's row for the
    # paper's laws, 1 N m a joint for others.
    torque_scale = paper.MAX_ABS_TORQUE_NM.get(args.controller, (1.0,) * n_joints(robot))
    objective = make_objective(robot, config, torque_scale)
    smooth = dataclasses.replace(scenario, contact_law="smooth")  # as tuning: gradients need the smooth law
    print(
        f"gradients on the nominal scenario and {args.n} perturbed ones, horizons {', '.join(f'{h:g}' for h in horizons)} "
        f"of {scenario.duration:g} s, over {jax.device_count()} device(s)...",
        file=sys.stderr,
        flush=True,
    )
    result, evaluate = envelope_gradients(
        RunSpec(robot, smooth, law, realism=realism),
        gains,
        objective,
        n=args.n,
        seed=args.seed,
        ranges=ranges,
        horizons=horizons,
        chunk=batching.chunk_size(args.chunk, args.n + 1),
        progress=sys.stderr,
    )
    document = gradient_report(result, outlier_factor=args.outlier_factor)
    checked = np.flatnonzero(finite_rows(result))[: args.fd_samples]  # the nominal first, if finite
    document["central_differences"] = central_differences(
        result, evaluate, gains, args.controller, samples=checked, seed=args.seed
    )
    sources = {
        "robot": getattr(args, "robot", None) or "paper_robot()",
        "robot_links": _robot_links(args) or None,
        "scenario": getattr(args, "scenario", None) or "paper_scenario()",
        **_gains_record(args.gains, args, args.controller),
    }
    record = make_record(
        robot,
        smooth,
        [Variant(args.controller, gains, gains_label(args.gains))],
        realism=realism,
        criteria=objective.criteria,
        pinv_damping=args.pinv_damping,
        command=getattr(args, "command_line", None),
        sources=sources,
    )
    document["settings"] = {
        "record": record.to_dict(),
        "seed": args.seed,
        "ranges": ranges.to_dict(),
        "objective": config.objective,
        "weights": dataclasses.asdict(config.weights),
        "torque_scale_Nm": objective.torque_scale_Nm,
        "torque_constraint_Nm": objective.torque_constraint_Nm if config.objective == "capture" else None,
        "scenario_duration_s": scenario.duration,
        "contact_law": "smooth",
    }
    runfiles.write_json(out / "gradients.json", document)
    runfiles.write_arrays(
        out / "gradients.npz",
        {"horizons_s": result.horizons_s, "losses": result.losses}
        | {f"gradient.{name}": value for name, value in result.gradients.items()},
    )
    title = f"{args.controller}, {args.n} samples" + (f", realism {args.realism}" if args.realism else "")
    from spacegrasp_jax.analysis import plots

    plots.save_gradient_figures(
        out,
        document["per_sample"]["norm_over_nominal"],
        document["per_sample"]["cosine_with_nominal"],
        document["horizon_growth"]["norms"],
        args.outlier_factor,
        title,
        runfiles.write_atomically,
    )
    _print_gradient_report(document)
    print(f"wrote {out}/: gradients.json, gradients.npz, gradients.png")
    return 0


def _horizons(text: str) -> tuple[float, ...]:
    """``--horizons``: fractions of the scenario's duration, increasing, the last 1."""
    try:
        fractions = tuple(float(item) for item in text.split(","))
    except ValueError:
        raise UsageError(f"--horizons {text!r}: expected fractions such as 0.25,0.5,1") from None
    if not all(0.0 < f <= 1.0 for f in fractions) or list(fractions) != sorted(set(fractions)) or fractions[-1] != 1.0:
        raise UsageError(f"--horizons {text!r}: increasing fractions in (0, 1], the last 1")
    return fractions


def _print_gradient_report(document: dict) -> None:
    nominal = document["nominal"]
    print(f"nominal: loss {nominal['loss']:.4g}, |gradient| {nominal['gradient_norm']:.4g}")
    print(
        f"non-finite gradients: {document['nonfinite']['count']} of {document['samples']} perturbed samples"
        + ("" if nominal["finite"] else "; the nominal's is not finite either")
    )
    ratio, cosine, outliers = document["norm_over_nominal"], document["cosine_with_nominal"], document["outliers"]
    print(
        f"|gradient| / nominal: median {ratio['median']:.3g}, p95 {ratio['p95']:.3g}, largest {ratio['largest']:.3g}; "
        f"over {outliers['factor']:g}x: {outliers['count']} ({outliers['fraction']:.1%})"
    )
    print(
        f"cosine with the nominal gradient: median {cosine['median']:.3f}, 5th percentile {cosine['p05']:.3f}, "
        f"negative {cosine['fraction_negative']:.1%}"
    )
    print(f"{'group':>6} {'sign agreement (per entry)':>40}  median |gradient|")
    for name, group in document["groups"].items():
        agreement = " ".join(f"{value:.2f}" for value in np.asarray(group["sign_agreement"], dtype=float))
        print(f"{name:>6} {agreement:>40}  {group['norm_median']:.3g}")
    for row in document["horizon_growth"]["norms"]:
        print(
            f"horizon {row['horizon_s']:>7.3f} s: median |gradient| {row['median_norm']:.3g}, largest {row['largest_norm']:.3g}"
        )
    for check in document["central_differences"]:
        print(
            f"central differences, sample {check['sample']}: slope {check['gradient_slope']:.6g} vs "
            f"{check['finite_difference_slope']:.6g} (relative error {check['relative_error']:.1e})"
        )


def add_parsers(commands) -> None:
    """The command's parser, added to ``commands``."""
    gradient_health = _add_command(
        commands, "gradients", help="the tuning objective's gradient over perturbed scenarios: is it trustworthy?"
    )
    gradient_health.add_argument("--n", type=_whole(1, 1_000_000), required=True, help="perturbed scenarios")
    gradient_health.add_argument("--controller", choices=CONTROLLERS, default="admittance")
    add_gains_arguments(gradient_health)
    gradient_health.add_argument("--scenario", help="nominal scenario TOML/JSON (default: the paper's)")
    _add_realism_option(gradient_health)
    add_ranges_arguments(gradient_health, "montecarlo")
    gradient_health.add_argument("--seed", type=_SEED, default=0, help="seed of the samples (default 0)")
    add_objective_arguments(gradient_health)
    gradient_health.add_argument(
        "--horizons",
        default=",".join(f"{h:g}" for h in GRADIENT_HORIZONS),
        help="fractions of the duration at which the gradient is taken, the last 1 (default %(default)s)",
    )
    gradient_health.add_argument(
        "--fd-samples",
        type=_whole(0, 100),
        default=3,
        help="samples checked against central differences (default 3)",
    )
    gradient_health.add_argument(
        "--outlier-factor",
        type=_real(1.0, 1e300, above=True),
        default=100.0,
        help="list the samples whose gradient norm exceeds this many times the nominal's (default 100)",
    )
    gradient_health.add_argument(
        "--chunk", type=_whole(1, 1_000_000), default=16, help="samples per compiled call (default 16)"
    )
    _add_run_options(gradient_health, "results/gradients")
    _add_compile_cache_option(gradient_health)
    gradient_health.set_defaults(run=_gradients)
