"""Run and compile times of one version of the package, to set beside another's.

    python -m spacegrasp_jax.benchmarks.version_timings --out timings.json [--repeats 5]

Like ``benchmarks.equivalence``, the script imports only names that older versions have too
(by their paths before the layer folders where it must), so it runs as a plain file with an
older version installed; run the versions one after another on a quiet machine, alternating,
and compare the files. The persistent compilation cache is left off, so a compile time is a
compile. What it times (seconds, ``time.perf_counter``):

* ``ideal``, ``flight``: a 17 s capture of the admittance law (the paper's gains in the ideal
  loop; the shipped flight gains in the flight-like loop, noise key 3) through
  ``experiment.run``: its compile time and the median of ``--repeats`` runs;
* ``gradient``: the reverse-mode gradient, with respect to every gain, of a 3 s flight-like
  capture's final error plus its largest peak torque over 100 N m: the first call (compile
  and run) and the median of ``--repeats`` calls;
* ``campaign``: a flight-like campaign of 64 samples (17 s, chunks of 64): its wall time.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp

import spacegrasp_jax as sg

try:
    from spacegrasp_jax.envelope.scenario import paper_scenario
    from spacegrasp_jax.jobs import experiment
    from spacegrasp_jax.jobs.campaign import CampaignConfig, Variant, run_campaign
    from spacegrasp_jax.loop.control.gains import paper_gains, tuned_gains
    from spacegrasp_jax.loop.realism import flight
    from spacegrasp_jax.loop.simulate import RunSpec, rollout
except ImportError:  # a version from before the layer folders
    from spacegrasp_jax import experiment
    from spacegrasp_jax.campaign import CampaignConfig, Variant, run_campaign
    from spacegrasp_jax.control.gains import paper_gains, tuned_gains
    from spacegrasp_jax.realism import flight
    from spacegrasp_jax.scenario import paper_scenario
    from spacegrasp_jax.simulate import RunSpec, rollout


def _run_times(spec, gains, key, repeats: int) -> dict:
    first = experiment.run(spec, gains, key=key)
    runs = [experiment.run(spec, gains, key=key).run_time_s for _ in range(repeats)]
    return {"compile_s": first.compile_time_s, "run_s": statistics.median(runs)}


def measure(repeats: int) -> dict:
    robot = sg.paper_robot()
    scenario = paper_scenario(robot)
    found = {
        "ideal": _run_times(RunSpec(robot, scenario, "admittance"), paper_gains(), None, repeats),
        "flight": _run_times(
            RunSpec(robot, scenario, "admittance", realism=flight()),
            tuned_gains("flight"),
            jax.random.PRNGKey(3),
            repeats,
        ),
    }
    short = paper_scenario(robot, duration=3.0)
    realism, key = flight(), jax.random.PRNGKey(5)

    def loss(gains):
        _, log = rollout(robot, short, gains, "admittance", realism=realism, key=key)
        error = jnp.linalg.norm(log.pose_ee[-1, :3] - log.pose_des[-1, :3])
        return error + jnp.max(jnp.abs(log.u)) / 100.0

    gradient = jax.jit(jax.grad(loss))
    started = time.perf_counter()
    jax.block_until_ready(gradient(tuned_gains("flight")))
    first = time.perf_counter() - started
    calls = []
    for _ in range(repeats):
        started = time.perf_counter()
        jax.block_until_ready(gradient(tuned_gains("flight")))
        calls.append(time.perf_counter() - started)
    found["gradient"] = {"first_call_s": first, "call_s": statistics.median(calls)}
    config = CampaignConfig(n=64, chunk=64, seed=7, realism=flight())
    started = time.perf_counter()
    run_campaign(robot, scenario, [Variant("admittance", tuned_gains("flight"), "flight")], config, progress=None)
    found["campaign"] = {"wall_s": time.perf_counter() - started}
    return found


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="the timings' JSON file")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs of each program (default 5)")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats: must be at least 1, got {args.repeats}")
    sg.configure(compile_cache=False)
    found = measure(args.repeats) | {"version": sg.__version__, "package": str(Path(sg.__file__).parent)}
    args.out.write_text(json.dumps(found, indent=1) + "\n")
    print(json.dumps(found, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
