"""The worst-case search at a small budget: other settings of the cross-entropy search, and
how far the gradient's direction climbs, against the campaign of the same rollouts.

    python -m spacegrasp_jax.benchmarks.worstcase_settings --realism ideal --seeds 0-9 \\
        --budget 64 --duration 3 >> notebooks/data/worstcase/settings_budget64.jsonl
    python -m spacegrasp_jax.benchmarks.worstcase_settings --lines --realism ideal --seeds 0-9 \\
        >> notebooks/data/worstcase/gradient_lines_budget64.jsonl
    python -m spacegrasp_jax.benchmarks.worstcase_settings --coordinates --realism ideal --seeds 0-9 \\
        >> notebooks/data/worstcase/gradient_coordinates_budget64.jsonl
    python -m spacegrasp_jax.benchmarks.worstcase_settings --subspace --realism ideal --seeds 0-9 \\
        >> notebooks/data/worstcase/gradient_subspace_budget64.jsonl

For each seed, runs the campaign of ``--budget`` samples (the paper's admittance gains on the
default envelope, measure ``final_error``) and prints one JSON line with its worst and:

* each of ``SETTINGS``' search of the same budget (``spacegrasp_jax.analysis.worstcase.search()``,
  method ``cem``), its worst over the campaign's. A setting is the screening's samples, the
  generation's, the elites, the spread and its shrink; the defaults are ``base``.
* with ``--lines``, for each of the three worst of the campaign's first 16 samples (the
  screening of a budget of 64), the measure along the sign of its gradient in ``U`` at the
  steps ``LINE_STEPS``, with the sample's noise key (``line0``: from the worst).
* with ``--coordinates``, a search of the same budget that lets the gradient choose where
  to look (``gradient_coordinates()``): from the worst of the screening (the campaign's
  first quarter), rounds of one gradient (``worstcase.GRADIENT_COST`` rollouts) and a scan
  of the coordinate of ``U`` with the largest derivative not yet scanned, at
  ``COORDINATE_FRACTIONS`` of the way to its bound on the side the derivative points to
  (forward, in one batch), moving to the scan's best point where it is worse than the
  current. Its worst over the campaign's and its worst after each round.
* with ``--subspace``, a cross-entropy search of the same budget in the ``SUBSPACE``
  coordinates of ``U`` with the largest derivatives at the worst of the screening
  (``gradient_subspace()``): one gradient there, then generations of an eighth of the
  budget drawn around the 2 worst points of its lineage, moving those coordinates only
  (spread 0.3, shrink 0.8, the worst point's noise key). Its worst over the campaign's.

The seeds are design seeds (0-9), not the benchmark's (100-109).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import jax
import numpy as np
from jax.flatten_util import ravel_pytree

import spacegrasp_jax as sg
from spacegrasp_jax.analysis import worstcase
from spacegrasp_jax.benchmarks.worstcase import _numbers, scenario_of
from spacegrasp_jax.core.model import paper_robot
from spacegrasp_jax.envelope import metrics
from spacegrasp_jax.envelope.perturbations import from_units, project_units
from spacegrasp_jax.jobs.campaign import CampaignConfig
from spacegrasp_jax.jobs.montecarlo import perturbed_run
from spacegrasp_jax.loop.control import paper_gains
from spacegrasp_jax.loop.control.registry import law_named
from spacegrasp_jax.loop.realism import load_realism
from spacegrasp_jax.loop.simulate import closed_loop


@dataclasses.dataclass(frozen=True)
class Settings(worstcase.SearchSettings):
    """``SearchSettings`` whose screening and generation sizes are given, not derived."""

    screen: int = 16
    gen: int = 8

    @property
    def screening(self):
        return self.screen

    @property
    def generation(self):
        return self.gen


#: The settings raced, at a budget of 64 (scaled with the budget): name -> fields.
SETTINGS = {
    "base": dict(screen=16, gen=8, elites=4, spread=0.3, shrink=0.8),
    "scr32": dict(screen=32, gen=8, elites=4, spread=0.3, shrink=0.8),
    "e2s02": dict(screen=16, gen=8, elites=2, spread=0.2, shrink=0.8),
    "e1s015": dict(screen=16, gen=8, elites=1, spread=0.15, shrink=0.8),
    "scr32e2s02": dict(screen=32, gen=8, elites=2, spread=0.2, shrink=0.8),
    "scr32e1s01": dict(screen=32, gen=8, elites=1, spread=0.1, shrink=0.8),
    "scr8e2": dict(screen=8, gen=8, elites=2, spread=0.3, shrink=0.8),
    "scr16e4s01": dict(screen=16, gen=8, elites=4, spread=0.1, shrink=0.9),
}


#: The steps along the gradient's sign (in ``U``, the box being [-1, 1]) of ``--lines``.
LINE_STEPS = (0.02, 0.04, 0.06, 0.08, 0.1, 0.12, 0.15, 0.2)


def line_programs(robot, scenario, gains, config: CampaignConfig):
    """``(value_and_gradient, values_at)``: the measure and its gradient in ``U`` at one point
    ``(units, key)``, and the measure at a batch of points and keys, on the nominal
    loop of ``config``'s realism; compiled once for every seed (the seed is in the points)."""
    spec = worstcase.gradient_spec(robot, scenario, law_named("admittance", config.pinv_damping), config.realism)
    ranges = config.ranges

    def value(units, key):
        sample = perturbed_run(spec, from_units(units, ranges), ranges, config.identified)
        return metrics.final_position_error(closed_loop(sample, gains, key)[1])

    return jax.jit(jax.value_and_grad(value)), jax.jit(jax.vmap(value))


def gradient_lines(programs, seed: int, values, starts: int = 3) -> dict:
    """``line0 .. line{starts-1}``: the measure along the sign of the gradient from each of
    the ``starts`` worst of the campaign's first 16 samples (``values``, its measures), by
    ``line_programs()``'s ``programs``."""
    value_and_gradient, values_at = programs
    n = len(values)
    keys = worstcase.noise_keys(seed, range(n))
    units = worstcase.units_of_samples(seed, range(n))
    lines = {}
    for rank, sample in enumerate(np.argsort(-np.asarray(values[:16]))[:starts]):
        start = jax.tree.map(lambda x: x[sample], units)
        _, gradient = value_and_gradient(start, keys[sample])
        points = project_units(
            jax.tree.map(lambda u, g: np.stack([u + step * np.sign(g) for step in LINE_STEPS]), start, gradient)
        )
        same_key = np.repeat(keys[sample][None], len(LINE_STEPS), axis=0)
        lines[f"line{rank}"] = np.asarray(values_at(points, same_key)).tolist()
    return lines


#: Where ``--coordinates`` scans a coordinate: these fractions of the way to its bound.
COORDINATE_FRACTIONS = (0.05, 0.1, 0.2, 0.3, 0.45, 0.6, 0.8, 1.0)


def gradient_coordinates(programs, seed: int, values, budget: int) -> dict:
    """``--coordinates``' search (module docstring) from the campaign's measures ``values``
    (its first quarter is the screening), by ``line_programs()``' ``programs``."""
    value_and_gradient, values_at = programs
    screen = budget // 4
    start = int(np.argmax(values[:screen]))
    key = worstcase.noise_keys(seed, [start])[0]
    flat, unravel = ravel_pytree(jax.tree.map(lambda x: x[0], worstcase.units_of_samples(seed, [start])))
    flat, best = np.asarray(flat), float(values[start])
    fractions = np.asarray(COORDINATE_FRACTIONS)
    spent, scanned, history = screen, [], [best]
    while spent + worstcase.GRADIENT_COST + fractions.size <= budget:
        _, gradient = value_and_gradient(unravel(flat), key)
        spent += worstcase.GRADIENT_COST
        slope = np.asarray(ravel_pytree(gradient)[0])
        if not np.all(np.isfinite(slope)):
            break
        size = np.abs(slope)
        size[scanned] = 0.0
        i = int(np.argmax(size))
        scanned.append(i)
        side = np.sign(slope[i])
        points = np.repeat(flat[None], fractions.size, axis=0)
        points[:, i] = flat[i] + side * (1.0 - side * flat[i]) * fractions
        found = np.asarray(
            values_at(project_units(jax.vmap(unravel)(points)), np.repeat(key[None], fractions.size, axis=0))
        )
        spent += fractions.size
        if np.nanmax(found) > best:
            best, flat = float(np.nanmax(found)), points[int(np.nanargmax(found))]
        history.append(best)
    return {"coordinates": best, "coordinates_rounds": history, "coordinates_rollouts": spent}


#: ``--subspace``'s coordinates: the largest derivatives (about three quarters of the
#: gradient's absolute sum at the screened worst of the 3 s approach).
SUBSPACE = 8


def gradient_subspace(programs, seed: int, values, budget: int) -> dict:
    """``--subspace``' search (module docstring) from the campaign's measures ``values`` (its
    first quarter is the screening), by ``line_programs()``' ``programs``."""
    value_and_gradient, values_at = programs
    screen = budget // 4
    start = int(np.argmax(values[:screen]))
    key = worstcase.noise_keys(seed, [start])[0]
    flat, unravel = ravel_pytree(jax.tree.map(lambda x: x[0], worstcase.units_of_samples(seed, [start])))
    _, gradient = value_and_gradient(unravel(flat), key)
    coordinates = np.argsort(-np.abs(np.asarray(ravel_pytree(gradient)[0])))[:SUBSPACE]
    rng = np.random.default_rng(seed)
    points, measured = [np.asarray(flat)], [float(values[start])]
    spent, spread, generation = screen + worstcase.GRADIENT_COST, 0.3, max(8, budget // 8)
    while spent < budget:
        count = min(generation, budget - spent)
        parents = rng.choice(np.argsort(-np.asarray(measured))[:2], size=count)
        children = np.stack([points[i] for i in parents])
        children[:, coordinates] += spread * rng.standard_normal((count, coordinates.size))
        children = np.clip(children, -1.0, 1.0)
        found = values_at(project_units(jax.vmap(unravel)(children)), np.repeat(key[None], count, axis=0))
        points += list(children)
        measured += [float(x) for x in np.asarray(found)]
        spent, spread = spent + count, 0.8 * spread
    return {"subspace": float(np.nanmax(measured)), "subspace_start": float(values[start]), "subspace_rollouts": spent}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--realism", default="ideal")
    parser.add_argument("--seeds", default="0-9")
    parser.add_argument("--budget", type=int, default=64)
    parser.add_argument("--duration", type=float, default=3.0)
    modes = parser.add_mutually_exclusive_group()
    modes.add_argument("--lines", action="store_true", help="the gradient's lines instead of the settings")
    modes.add_argument(
        "--coordinates", action="store_true", help="the gradient-chosen coordinate search instead of the settings"
    )
    modes.add_argument(
        "--subspace", action="store_true", help="the cross-entropy search in the gradient's largest coordinates"
    )
    args = parser.parse_args(argv)
    if args.realism not in ("ideal", "flight") and not Path(args.realism).is_file():
        parser.error(f"--realism: expected ideal, flight or a realism file, got {args.realism!r}")
    try:
        seeds = _numbers(args.seeds)
    except ValueError:
        parser.error(f"--seeds: expected whole numbers such as 0-9 or 1,5, got {args.seeds!r}")
    if args.budget < 64 or args.budget % 64:
        parser.error(f"--budget: a multiple of 64 (the settings are sized at 64 and scaled), got {args.budget}")
    if not 0.0 < args.duration <= 17.0:
        parser.error(f"--duration: in (0, 17] s, got {args.duration}")
    sg.configure()
    robot = paper_robot()
    scenario = scenario_of(robot, args.duration)
    gains = paper_gains()
    realism = None if args.realism == "ideal" else load_realism(args.realism, robot)
    programs = None
    for seed in seeds:
        config = CampaignConfig(n=1, seed=seed, realism=realism)
        campaign = worstcase.compare_with_campaign(
            robot, scenario, gains, "admittance", config, args.budget, "final_error", chunk=8
        )
        row = {"realism": args.realism, "duration_s": args.duration, "budget": args.budget, "seed": seed}
        row["campaign"] = campaign["value"]
        if args.subspace:
            programs = programs or line_programs(robot, scenario, gains, config)
            found = gradient_subspace(programs, seed, np.asarray(campaign["values"]), args.budget)
            print(json.dumps(row | found | {"ratio": found["subspace"] / campaign["value"]}), flush=True)
            continue
        if args.coordinates:
            programs = programs or line_programs(robot, scenario, gains, config)
            found = gradient_coordinates(programs, seed, np.asarray(campaign["values"]), args.budget)
            print(json.dumps(row | found | {"ratio": found["coordinates"] / campaign["value"]}), flush=True)
            continue
        if args.lines:
            row["screen16"] = float(np.max(campaign["values"][:16]))
            programs = programs or line_programs(robot, scenario, gains, config)
            print(json.dumps(row | gradient_lines(programs, seed, campaign["values"])), flush=True)
            continue
        for name, fields in SETTINGS.items():
            fields = dict(fields, screen=fields["screen"] * args.budget // 64, gen=fields["gen"] * args.budget // 64)
            found = worstcase.search(
                robot, scenario, gains, "admittance", config, Settings(budget=args.budget, **fields)
            )
            row[name] = found.value / campaign["value"]
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
