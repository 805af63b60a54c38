"""``spacegrasp benchmark``: speed and memory against MuJoCo and Pinocchio."""

from __future__ import annotations

import argparse
from pathlib import Path

from spacegrasp_jax.cli.common import _claim
from spacegrasp_jax.cli.options import UsageError, _add_command, _add_overwrite_option, _whole


def _benchmark(args: argparse.Namespace) -> int:
    try:
        import mujoco  # noqa: F401
        import pinocchio  # noqa: F401

        from spacegrasp_jax.benchmarks import suite
    except ImportError as error:  # the peers, or the benchmarks package outside a checkout
        raise UsageError(f"the benchmark needs the test extra (pip install -e '.[test]'): {error}") from None
    _claim(args, Path(args.out))
    return suite.main([*(["--quick"] if args.quick else []), "--out", args.out, "--repeats", str(args.repeats)])


def add_parsers(commands) -> None:
    """The command's parser, added to ``commands``."""
    benchmark = _add_command(
        commands, "benchmark", help="speed and memory against MuJoCo and a Pinocchio loop (needs the test extra)"
    )
    benchmark.add_argument(
        "--quick",
        action="store_true",
        help="toy sizes: exercises every part in about two minutes; numbers mean nothing",
    )
    benchmark.add_argument(
        "--out", default="results/benchmarks", help="folder for benchmark.json (default results/benchmarks)"
    )
    _add_overwrite_option(benchmark)
    benchmark.add_argument(
        "--repeats", type=_whole(1, 1000), default=3, help="repeats per timing, median reported (default 3)"
    )
    benchmark.set_defaults(run=_benchmark)
