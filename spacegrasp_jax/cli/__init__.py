"""The ``spacegrasp`` command line: one module per command (its options, its handler and its
printers), and the options and inputs several commands share (``options``, ``common``)."""

from __future__ import annotations

import argparse
import contextlib
import signal
import sys
import warnings

import jax
import matplotlib

matplotlib.use("Agg")  # the command line only writes figures to files; before pyplot is imported

import spacegrasp_jax as sg  # noqa: E402
from spacegrasp_jax.analysis import animation
from spacegrasp_jax.cli import (  # noqa: E402  (the commands, in the order --help lists them)
    animate,
    benchmark,
    ceiling,
    compare,
    export,
    gains,
    gradients,
    info,
    margins,
    montecarlo,
    reliability,
    requirements,
    runs,
    tune,
    worstcase,
)
from spacegrasp_jax.cli.options import UsageError, _Parser  # noqa: E402
from spacegrasp_jax.envelope.perturbations import PerturbationError  # noqa: E402
from spacegrasp_jax.envelope.scenario import ScenarioError  # noqa: E402
from spacegrasp_jax.jobs import compilation, experiment, runfiles
from spacegrasp_jax.loop.control import GainsError, UnusedGainsWarning  # noqa: E402
from spacegrasp_jax.loop.realism import RealismError  # noqa: E402

#: The file in the compile cache's folder that keeps each program's last compile time, for
#: the line printed before the program compiles again (``compilation.CompileAnnouncer``).
COMPILE_TIMES = "spacegrasp-compile-times.json"


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="spacegrasp", description=" ".join(sg.__doc__.split("\n\n")[0].split()))
    parser.add_argument("--version", action="version", version=f"spacegrasp-jax {sg.__version__}")
    commands = parser.add_subparsers(dest="command", required=True)
    parser.commands = commands.choices  # command name -> its parser
    info.add_parsers(commands)
    runs.add_parsers(commands)
    animate.add_parsers(commands)
    compare.add_parsers(commands)
    export.add_parsers(commands)
    gains.add_parsers(commands)
    tune.add_parsers(commands)
    montecarlo.add_parsers(commands)
    gradients.add_parsers(commands)
    margins.add_parsers(commands)
    worstcase.add_parsers(commands)
    reliability.add_parsers(commands)
    requirements.add_parsers(commands)
    ceiling.add_parsers(commands)
    benchmark.add_parsers(commands)
    return parser


#: The commands that stop cleanly at a safe point on a first signal -> the unit they finish.
_SAFE_POINTS = {"montecarlo": "chunk", "tune": "step", "requirements": "chunk", "ceiling": "capture"}


def _given_options(parser: argparse.ArgumentParser, argv: list[str]) -> set[str]:
    """The destinations of the options that ``argv`` gives explicitly (not by default): the
    command's parser run again with every default suppressed."""
    command, rest = None, []
    for index, token in enumerate(argv):
        if token in parser.commands:
            command, rest = parser.commands[token], argv[index + 1 :]
            break
    if command is None:
        return set()
    defaults = {action: action.default for action in command._actions}
    try:
        for action in defaults:
            action.default = argparse.SUPPRESS
        given, _ = command.parse_known_args(rest)
    finally:
        for action, default in defaults.items():
            action.default = default
    return set(vars(given)) & {action.dest for action in defaults}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exit:  # --help, --version (0) or a rejected option (2, one line printed)
        return exit.code
    args.given = _given_options(parser, argv)
    args.command_line = ["spacegrasp", *argv]  # what the run's record says made it
    # The command owns its process: float64 and loops compiled whole, before anything runs,
    # and compiled programs kept on disk for the next run.
    compilation.enable_float64()
    compilation.compile_loops_whole()
    announcer = None
    if "compile_cache" in args:
        if not args.verbose:  # XLA's C++ log, its "Very slow compile?" banner among it, and JAX's
            jax.config.update("jax_logging_level", "CRITICAL")
        try:
            cache = compilation.use_compile_cache(args.compile_cache)
        except compilation.CacheFolderError as error:
            print(f"spacegrasp: error: --compile-cache: {error}, or pass --compile-cache none", file=sys.stderr)
            return 2
        print(f"compilation cache: {cache if cache else 'off'}", file=sys.stderr)
        announcer = compilation.CompileAnnouncer(sys.stderr, cache / COMPILE_TIMES if cache else None)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", UnusedGainsWarning)
            show_warning = warnings.showwarning

            def notice(message, category, *rest, **keywords):
                if issubclass(category, UnusedGainsWarning):
                    print(f"spacegrasp: notice: {message}", file=sys.stderr)
                else:
                    show_warning(message, category, *rest, **keywords)

            warnings.showwarning = notice
            # Commands with safe points (montecarlo, tune) stop at the next one on a first
            # signal, the others at once; then a signal ends the process at once (130).
            unit = _SAFE_POINTS.get(args.command)
            listening = compilation.listening(announcer) if announcer else contextlib.nullcontext()
            stop = runfiles.StopRequest(unit or "run", patience=1 if unit else 0, hard_exit=True)
            with listening, stop as args.stop:
                code = args.run(args)
                if getattr(args, "distributed", False):
                    jax.distributed.shutdown()  # with every process, before a late signal can interrupt it
                return code
    except (
        sg.RobotConfigError,
        GainsError,
        ScenarioError,
        PerturbationError,
        RealismError,
        UsageError,
        animation.AnimationError,
        runfiles.OutputFolderError,
    ) as error:
        print(f"spacegrasp: error: {error}", file=sys.stderr)
        return 2
    except experiment.SimulationDiverged as error:
        print(f"spacegrasp: error: {error}", file=sys.stderr)
        return 3


def run_command() -> None:
    """The process's entry point (``spacegrasp``, ``python -m spacegrasp_jax.cli``): exits
    with [`main()`][spacegrasp_jax.cli.main]'s code."""
    code = main()
    # The command is over and its files are written. A signal that lands while the
    # interpreter shuts down (one sent to every process of a campaign, after this one had
    # already stopped with the others) would otherwise end it by the signal, not this code.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    sys.exit(code)
