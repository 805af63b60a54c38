"""A flight-like campaign of the shipped constant flight gains and the shipped flight schedule:
programs compiled, compile time and captures per second, for one or more installs in one run.

    python -m spacegrasp_jax.benchmarks.campaign_throughput [--n 1000] [--out results/benchmarks]
        [--python LABEL=PYTHON ...] [--seed 20261207]

Each install (``--python``: a label and a Python executable with its own ``spacegrasp_jax``,
an older version say; default: this one, labelled ``this``) runs ``spacegrasp montecarlo
--controller admittance --baseline flight --gains flight_schedule --realism flight
--compile-cache none`` in a process of its own, one after another, on the same ``--n``
captures of ``--seed``. Reports each install's programs compiled, compile time, run time and
captures per second (both gain sets' captures over the run time), and, gain set by gain set,
whether its samples equal the first install's bit for bit, their largest relative difference
and the captures whose verdict is the same. Writes
``campaign_throughput.json``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from spacegrasp_jax.benchmarks.dynamics import machine


def run_install(python: str, n: int, seed: int, out: Path) -> dict:
    """One campaign with ``python``'s ``spacegrasp_jax``: its throughput record and wall time."""
    command = [
        python,
        "-m",
        "spacegrasp_jax.cli",
        "montecarlo",
        "--n",
        str(n),
        "--seed",
        str(seed),
        "--controller",
        "admittance",
        "--baseline",
        "flight",
        "--gains",
        "flight_schedule",
        "--realism",
        "flight",
        "--compile-cache",
        "none",
        "--out",
        str(out),
    ]
    started = time.perf_counter()
    # Run from the output's folder: ``-m`` puts the working directory first on the path, and a
    # checkout's spacegrasp_jax there would shadow the install's.
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, cwd=out.parent)
    wall_s = time.perf_counter() - started
    throughput = json.loads((out / "summary.json").read_text())["throughput"]
    return {"command": " ".join(command[1:]), "wall_s": wall_s, **throughput}


def compare_samples(a: Path, b: Path) -> dict:
    """Two campaigns' samples, variant by variant: whether every array is the same bit for
    bit, the largest relative difference of a metric, and the captures whose verdict (failure
    class, ``"success"`` for a capture) is the same."""
    from spacegrasp_jax.jobs.campaign import load_samples

    _, first = load_samples(a / "samples.npz")
    _, second = load_samples(b / "samples.npz")
    report = {}
    for key, metrics in first.items():
        other = second[key]
        largest, where, identical = 0.0, None, True
        for name, value in metrics.items():
            if value.dtype.kind != "f":
                identical &= bool(np.array_equal(value, other[name]))
                continue
            identical &= bool(np.array_equal(value, other[name], equal_nan=True))
            both = np.isfinite(value) & np.isfinite(other[name])
            scale = np.maximum(np.abs(value[both]), np.finfo(float).tiny)
            relative = np.abs(value[both] - other[name][both]) / scale
            if both.any() and relative.max() > largest:
                k = int(np.argmax(relative))
                largest, where = float(relative[k]), {"metric": name, "value": float(value[both].ravel()[k])}
        report[key] = {
            "identical": identical,
            "largest_relative_difference": largest,
            "largest_where": where,
            "same_verdict": int(np.sum(metrics["failure"] == other["failure"])),
            "captures": int(metrics["failure"].size),
        }
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=1000, help="captures per gain set (default 1000)")
    parser.add_argument("--seed", type=int, default=20261207, help="campaign seed (default 20261207)")
    parser.add_argument(
        "--python",
        action="append",
        metavar="LABEL=PYTHON",
        help="an install to run (repeatable; default: this one, labelled 'this')",
    )
    parser.add_argument("--out", default="results/benchmarks")
    args = parser.parse_args(argv)
    if args.n < 1:
        parser.error(f"--n: must be at least 1, got {args.n}")
    installs = {}
    for entry in args.python or [f"this={sys.executable}"]:
        label, _, python = entry.partition("=")
        if not label or not python:
            parser.error(f"--python: expected LABEL=PYTHON, got {entry!r}")
        if label in installs:
            parser.error(f"--python: the label {label!r} is given twice")
        if shutil.which(python) is None:
            parser.error(f"--python: {python} is not an executable Python")
        installs[label] = python
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    with tempfile.TemporaryDirectory() as scratch:
        folders = {}
        for label, python in installs.items():
            folders[label] = Path(scratch).resolve() / label
            results[label] = run_install(python, args.n, args.seed, folders[label])
            r = results[label]
            print(
                f"{label:>10}: {r.get('programs_compiled', 'not recorded:')} program(s), compile {r['compile_s']:.1f} s, "
                f"run {r['run_s']:.1f} s, {r['rollouts_per_s']:.2f} captures/s",
                flush=True,
            )
        first = next(iter(folders))
        for label in list(folders)[1:]:
            results[label]["against_" + first] = compare_samples(folders[first], folders[label])
            print(f"{label:>10} against {first}: {results[label]['against_' + first]}")
    document = {"machine": machine(), "n": args.n, "seed": args.seed, "installs": results}
    (out / "campaign_throughput.json").write_text(json.dumps(document, indent=1) + "\n")
    print(f"wrote {out / 'campaign_throughput.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
