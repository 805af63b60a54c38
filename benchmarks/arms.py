"""Arms of their own: what a rollout, a gradient and a Monte-Carlo chunk cost for the paper's
arm, the UR5 (6 joints) and the Panda (7 joints) of ``configs/``, and what a film costs.

    python -m spacegrasp_jax.benchmarks.arms [--out results/benchmarks] [--repeats 5] [--paper-only]

Each program is compiled once, run once to warm up, then timed ``--repeats`` times (median):

* ``rollout``: the 17 s scenario (17,000 RK4 steps), the admittance law;
* ``gradient``: ``jax.value_and_grad`` of the final position error with respect to the gains
  through a 2 s rollout with the smooth contact law (the plain path a user differentiates);
* ``chunk``: 16 perturbed samples of the 17 s scenario (``montecarlo.evaluate_samples``, the
  Monte-Carlo campaigns' default envelope), vmapped;
* ``film``: ``spacegrasp animate``'s drawing of the paper's 17 s capture at 30 frames a second
  into a GIF (the process's start and the run's reading left out).

``--paper-only`` measures the paper's arm alone, with only what every version of the package
has and nothing of ``benchmarks/``, so that the same file run against an older checkout
(``PYTHONPATH=OLD python benchmarks/arms.py --paper-only``) gives the before of a
before/after. Writes ``arms.json``.
"""

from __future__ import annotations

import argparse
import functools
import json
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp

import spacegrasp_jax as sg
from spacegrasp_jax.envelope import metrics
from spacegrasp_jax.envelope.perturbations import PerturbationRanges
from spacegrasp_jax.envelope.scenario import paper_scenario
from spacegrasp_jax.jobs.compilation import configure
from spacegrasp_jax.jobs.montecarlo import FoldedMetrics, evaluate_samples
from spacegrasp_jax.loop.control import paper_gains
from spacegrasp_jax.loop.simulate import RunSpec, rollout

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def timed(function, repeats: int) -> dict:
    """The median, fastest and slowest wall time (s) of ``repeats`` calls of ``function``."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    times.sort()
    return {"median_s": times[len(times) // 2], "min_s": times[0], "max_s": times[-1]}


def _compiled(function, *arguments):
    start = time.perf_counter()
    executable = jax.jit(function).lower(*arguments).compile()
    return executable, time.perf_counter() - start


def _timed(executable, arguments, repeats: int, compile_s: float) -> dict:
    jax.block_until_ready(executable(*arguments))  # warm-up
    run = timed(lambda: jax.block_until_ready(executable(*arguments)), repeats)
    return {"compile_s": compile_s, "run_s": run["median_s"], "run_spread_s": [run["min_s"], run["max_s"]]}


def bench_arm(robot, scenario, short, gains, repeats: int) -> dict:
    """The rollout, gradient and chunk of one arm (``short``: the gradient's 2 s scenario)."""
    results = {}
    function = functools.partial(rollout, controller="admittance")
    executable, compile_s = _compiled(function, robot, scenario, gains)
    results["rollout"] = _timed(executable, (robot, scenario, gains), repeats, compile_s)

    def final_error(log_gains):
        _, log = rollout(robot, short, jax.tree.map(jnp.exp, log_gains), "admittance")
        return metrics.final_position_error(log)

    log_gains = jax.tree.map(jnp.log, gains)
    executable, compile_s = _compiled(jax.value_and_grad(final_error), log_gains)
    results["gradient"] = _timed(executable, (log_gains,), repeats, compile_s)

    chunk = functools.partial(evaluate_samples, ranges=PerturbationRanges())
    arguments = (RunSpec(robot, scenario, "admittance", observer=FoldedMetrics()), gains, 0, jnp.arange(16))
    executable, compile_s = _compiled(chunk, *arguments)
    results["chunk"] = _timed(executable, arguments, max(1, repeats // 2), compile_s)
    return results


def bench_film(robot, scenario, gains) -> dict:
    """``spacegrasp animate``'s drawing of a 17 s capture at 30 frames a second."""
    from spacegrasp_jax.analysis import animation
    from spacegrasp_jax.jobs import experiment

    log = experiment.run(RunSpec(robot, scenario, "admittance"), gains).log
    start = time.perf_counter()
    rows = animation.frame_rows(log.t, 30.0, 1.0)
    scene = animation.capture_scene(robot, scenario, log, rows)
    with tempfile.TemporaryDirectory() as folder:
        frames = animation.write_film(scene, Path(folder) / "film.gif", 30.0)
    return {"frames": frames, "wall_s": time.perf_counter() - start}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="results/benchmarks")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--paper-only", action="store_true")
    args = parser.parse_args(argv)
    configure()
    robot, gains = sg.paper_robot(), paper_gains()
    short = dict(duration=2.0, move_duration=2.0, contact_law="smooth")
    report = {
        "package": str(Path(sg.__file__).parent),
        "paper": bench_arm(robot, paper_scenario(robot), paper_scenario(robot, **short), gains, args.repeats),
    }
    print(json.dumps({"paper": report["paper"]}, indent=1), flush=True)
    if not args.paper_only:
        from spacegrasp_jax.core.model import n_joints
        from spacegrasp_jax.envelope.scenario import load_scenario
        from spacegrasp_jax.loop.control import load_gains

        for name in ("ur5", "panda"):
            arm = sg.load_robot(CONFIGS / f"{name}_on_satellite.toml")
            scenario = load_scenario(arm, CONFIGS / f"{name}_scenario.toml")
            q_init = scenario.initial.q
            report[name] = bench_arm(
                arm,
                scenario,
                paper_scenario(arm, q_init=q_init, **short),
                load_gains(CONFIGS / f"{name}_ideal_gains.json", "admittance", n_joints(arm)),
                args.repeats,
            )
            print(json.dumps({name: report[name]}, indent=1), flush=True)
        report["film"] = bench_film(robot, paper_scenario(robot), gains)
        print(json.dumps({"film": report["film"]}, indent=1), flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "arms.json").write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
