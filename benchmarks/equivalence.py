"""Whether a change of the code left every result as it was: arrays saved by one version of the
package, compared with another's.

    python -m spacegrasp_jax.benchmarks.equivalence --save reference.npz
    python -m spacegrasp_jax.benchmarks.equivalence --against reference.npz [--tolerance 1e-9]

The script imports only names that older versions of the package have too (by their paths
before the layer folders where it must), so it also runs as a plain file
(``python benchmarks/equivalence.py --save ...``) with an older version installed.
What it saves (float64):

* ``reproduction/<law>/<field>``: the paper's 17 s capture by each law in the ideal loop (the
  reproduction of Table 5), every field of the log, every 10th step and the last;
* ``flight/<field>``: a 2 s flight-like rollout of the shipped flight gains with sensor noise
  (key 3), every step;
* ``campaign/<metric>``: a flight-like campaign of 8 samples at seed 7 with the flight gains
  (17 s), every sample's metrics;
* ``gradient/<loop>/<group>``: the gradient of a 3 s capture's final position error (m, the EE's
  distance from its desired pose) plus its largest peak torque over 100 N m with respect to every gain group, ideal and flight-like.

``--against`` prints, for each array both versions have, the largest difference relative to
the array's largest magnitude, and exits 1 if any is over the tolerance. Arrays only one side
has (a metric added since) are listed; an array renamed since is compared under its new name
(``RENAMED``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import spacegrasp_jax as sg

try:
    from spacegrasp_jax.envelope.scenario import paper_scenario
    from spacegrasp_jax.jobs.campaign import CampaignConfig, Variant, run_campaign
    from spacegrasp_jax.loop.control import PAPER_CONTROLLERS
    from spacegrasp_jax.loop.control.gains import paper_gains, tuned_gains
    from spacegrasp_jax.loop.realism import flight
    from spacegrasp_jax.loop.simulate import rollout
except ImportError:  # a version from before the layer folders
    from spacegrasp_jax.campaign import CampaignConfig, Variant, run_campaign
    from spacegrasp_jax.control import PAPER_CONTROLLERS
    from spacegrasp_jax.control.gains import paper_gains, tuned_gains
    from spacegrasp_jax.realism import flight
    from spacegrasp_jax.scenario import paper_scenario
    from spacegrasp_jax.simulate import rollout


def _log_arrays(log, every: int) -> dict[str, np.ndarray]:
    arrays = {}
    for name, value in vars(log).items():
        if value is None:
            continue
        value = np.asarray(value)
        if value.ndim and value.shape[0] > 1:
            rows = np.r_[np.arange(0, value.shape[0], every), value.shape[0] - 1]
            value = value[rows]
        arrays[name] = value
    return arrays


def _gradient(robot, scenario, realism, key) -> dict[str, np.ndarray]:
    gains = tuned_gains("flight")

    def loss(gains):
        _, log = rollout(robot, scenario, gains, "admittance", realism=realism, key=key)
        error = jnp.linalg.norm(log.pose_ee[-1, :3] - log.pose_des[-1, :3])
        return error + jnp.max(jnp.abs(log.u)) / 100.0

    gradient = jax.jit(jax.grad(loss))(gains)
    return {name: np.asarray(getattr(gradient, name)) for name in vars(gradient) if getattr(gradient, name) is not None}


def arrays_of_this_version() -> dict[str, np.ndarray]:
    """Every array the module docstring lists, computed by the installed package."""
    robot = sg.paper_robot()
    arrays = {}
    scenario = paper_scenario(robot)
    for law in PAPER_CONTROLLERS:
        _, log = rollout(robot, scenario, paper_gains(), law)
        arrays |= {f"reproduction/{law}/{k}": v for k, v in _log_arrays(log, 10).items()}
    short = paper_scenario(robot, duration=2.0)
    _, log = rollout(robot, short, tuned_gains("flight"), "admittance", realism=flight(), key=jax.random.PRNGKey(3))
    arrays |= {f"flight/{k}": v for k, v in _log_arrays(log, 1).items()}
    config = CampaignConfig(n=8, seed=7, chunk=8, realism=flight())
    result = run_campaign(
        robot, scenario, [Variant("admittance", tuned_gains("flight"), "flight")], config, progress=None
    )
    for key, metrics in result.metrics.items():
        arrays |= {
            f"campaign/{name}": np.asarray(v, dtype=float)
            for name, v in metrics.items()
            if np.asarray(v).dtype.kind in "fib"
        }
    three = paper_scenario(robot, duration=3.0)
    for loop, realism, key in (("ideal", None, None), ("flight", flight(), jax.random.PRNGKey(5))):
        arrays |= {f"gradient/{loop}/{k}": v for k, v in _gradient(robot, three, realism, key).items()}
    return arrays


#: Arrays a later version names otherwise: the older name -> today's.
RENAMED = {"campaign/failed_torque_limit": "campaign/failed_torque_threshold"}


def differences(reference: dict[str, np.ndarray], current: dict[str, np.ndarray]) -> dict[str, float]:
    """Each shared array's largest difference over its largest magnitude (``inf``: the shapes
    differ; 0 for two zero arrays; NaNs must sit in the same places)."""
    found = {}
    for name in sorted(set(reference) & set(current)):
        a, b = np.asarray(reference[name], dtype=float), np.asarray(current[name], dtype=float)
        if a.shape != b.shape or not np.array_equal(np.isnan(a), np.isnan(b)):
            found[name] = float("inf")
            continue
        finite = np.isfinite(a)
        if not np.array_equal(a[~finite], b[~finite], equal_nan=True):
            found[name] = float("inf")
            continue
        scale = float(np.max(np.abs(a[finite]), initial=0.0))
        gap = float(np.max(np.abs(a[finite] - b[finite]), initial=0.0))
        found[name] = 0.0 if gap == 0.0 else gap / (scale if scale > 0.0 else 1.0)
    return found


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--save", type=Path, help="write this version's arrays to this .npz file")
    mode.add_argument("--against", type=Path, help="compare this version's arrays with a saved .npz file")
    parser.add_argument("--tolerance", type=float, default=1e-9, help="largest relative difference (default 1e-9)")
    args = parser.parse_args(argv)
    if not args.tolerance >= 0.0:
        parser.error(f"--tolerance: must be a non-negative number, got {args.tolerance}")
    if args.against is not None and not args.against.is_file():
        parser.error(f"--against: no such file: {args.against}")
    sg.configure()
    current = arrays_of_this_version()
    if args.save is not None:
        np.savez_compressed(args.save, **current)
        print(f"{len(current)} arrays written to {args.save}")
        return 0
    with np.load(args.against) as data:
        reference = {RENAMED.get(name, name): data[name] for name in data.files}
    found = differences(reference, current)
    worst = max(found.values(), default=0.0)
    for name, gap in found.items():
        if gap > args.tolerance:
            print(f"differs: {name}: {gap:.3g}")
    for name in sorted(set(reference) ^ set(current)):
        print(f"only {'in the saved file' if name in reference else 'in this version'}: {name}")
    exact = sum(gap == 0.0 for gap in found.values())
    print(f"{len(found)} arrays compared, {exact} bit for bit; largest relative differences:")
    for name in sorted(found, key=found.get, reverse=True)[:5]:
        print(f"  {name}: {found[name]:.3g}")
    print(f"largest {worst:.3g}, tolerance {args.tolerance:g}: {'within' if worst <= args.tolerance else 'OVER'}")
    return 1 if worst > args.tolerance else 0


if __name__ == "__main__":
    sys.exit(main())
