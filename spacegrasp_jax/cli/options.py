"""The options several commands share, their types, and the error a bad one raises."""

from __future__ import annotations

import argparse
import math
import sys

from spacegrasp_jax.core.inputs import did_you_mean
from spacegrasp_jax.envelope.perturbations import (
    FREE_TARGET_FAST_RANGES,
    FREE_TARGET_RANGES,
    LAR_WIDE_RANGES,
    PerturbationRanges,
)
from spacegrasp_jax.loop.control import (
    CONTROLLERS,
)
from spacegrasp_jax.loop.control.schedule import NAMED_GAIN_SETS
from spacegrasp_jax.tuning.objective import OBJECTIVES
from spacegrasp_jax.tuning.tune import TUNING_RANGES, TuneConfig


class UsageError(ValueError):
    """A command-line option is invalid."""


class _Parser(argparse.ArgumentParser):
    """An argument parser whose every rejection is one line (exit 2), naming the option, and
    which takes options only by their whole names (``--contr`` is refused, not read as
    ``--controller``: an abbreviation that matches today can match another option tomorrow)."""

    def __init__(self, *args, **keywords):
        keywords.setdefault("allow_abbrev", False)
        super().__init__(*args, **keywords)

    def parse_known_args(self, args=None, namespace=None):
        self._argv = list(sys.argv[1:] if args is None else args)  # for error()'s suggestions
        return super().parse_known_args(args, namespace)

    def error(self, message: str):
        if message.startswith("unrecognized arguments: "):
            message += self._suggestions(message.removeprefix("unrecognized arguments: ").split())
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")

    def _suggestions(self, unrecognized: list[str]) -> str:
        """`` (did you mean --gains?)`` for each mistyped option, among the options of the
        command the line runs (this parser's own without a command)."""
        parser = self
        commands = getattr(self, "commands", {})
        for token in getattr(self, "_argv", []):
            if token in commands:
                parser = commands[token]
                break
        known = [option for action in parser._actions for option in action.option_strings]
        options = [token.split("=")[0] for token in unrecognized if token.startswith("--")]
        return "".join(did_you_mean(option, known) for option in options)

    def _get_value(self, action: argparse.Action, arg_string: str):
        # Every value typed on the command line is converted here (argparse's one conversion
        # point). An empty string names no file, law or setting: it is refused rather than
        # read as the option's absence (``--ranges=``) or as the current folder
        # (``--realism ''``). A typed option's own type refuses it with its own words.
        if arg_string == "" and action.type is None and action.nargs not in (argparse.PARSER, argparse.REMAINDER):
            raise argparse.ArgumentError(action, f"empty; expected {_expected(action)}")
        return super()._get_value(action, arg_string)


def _expected(action: argparse.Action) -> str:
    """What an option takes, in words for an error: its choices, its metavar (such as
    ``ideal|flight|FILE``), or its help's first clause."""
    if action.choices:
        return "one of " + ", ".join(map(str, action.choices))
    if action.metavar and action.option_strings:  # a positional's metavar is its name, said already
        return action.metavar
    if action.help:
        return action.help.split(" (")[0].split(";")[0]
    return "a value"


def _whole(low: int, high: int):
    """An option's type: a whole number in ``[low, high]``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must be in [{low:,}, {high:,}], got {value:,}")
        return value

    parse.__name__ = "whole number"
    return parse


def _real(low: float, high: float, *, above: bool = False):
    """An option's type: a finite number in ``[low, high]`` (``(low, high]`` if ``above``)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not math.isfinite(value) or value < low or value > high or (above and value == low):
            bounds = f"{'(' if above else '['}{low:g}, {high:g}]"
            raise argparse.ArgumentTypeError(f"must be a finite number in {bounds}, got {text}")
        return value

    parse.__name__ = "number"
    return parse


#: Seeds are 32-bit (``jax.random.PRNGKey``).
_SEED = _whole(0, 2**32 - 1)

#: The help of every command's ``--robot``.
ROBOT_HELP = (
    "robot file (default: the paper's robot): a robot TOML, a URDF arm (see --mount), "
    "or a TOML whose [urdf] table mounts a URDF arm on a satellite"
)


def add_robot_arguments(parser: argparse.ArgumentParser) -> None:
    """``--robot`` and, for a URDF arm, ``--mount``, ``--base-link`` and ``--tip-link``."""
    parser.add_argument("--robot", help=ROBOT_HELP)
    parser.add_argument(
        "--mount",
        metavar="paper|urdf|FILE",
        help="a URDF arm's satellite: paper (default: the paper's 500 kg satellite at its mount point), urdf "
        "(the URDF is the whole servicer, its base link the satellite body) or a TOML with [satellite] and [limits]",
    )
    parser.add_argument(
        "--base-link", metavar="LINK", help="a URDF arm's link bolted to the satellite (default: its one root link)"
    )
    parser.add_argument(
        "--allow-outside-limits",
        action="store_true",
        help="run a capture whose initial joint angles lie outside the robot's joint ranges, with a warning "
        "(default: refused)",
    )
    parser.add_argument(
        "--tip-link",
        metavar="LINK",
        help="a URDF arm's link whose frame is the end-effector's (default: its one leaf link; name it when the "
        "URDF has fingers or tool frames)",
    )


def _add_overwrite_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the run that --out holds (default: refuse a folder that holds anything)",
    )


#: The exit code of a run whose capture failed by its criteria, under ``--strict``.
CAPTURE_FAILED = 4


def _add_strict_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--strict",
        action="store_true",
        help=f"exit {CAPTURE_FAILED} when a capture fails its success criteria (default: a failed capture is a "
        "result, exit 0)",
    )


def _add_animate_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--animate",
        action="store_true",
        help="also film each capture: capture_<law>.gif and a poster (spacegrasp animate)",
    )
    _add_film_options(parser)


def _add_film_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--fps", type=_real(1.0, 120.0), default=30.0, help="frames a second of film (default 30)")
    parser.add_argument(
        "--speed", type=_real(0.01, 100.0), default=1.0, help="simulated seconds a second of film (default 1)"
    )


def _add_csv_option(parser: argparse.ArgumentParser, what: str) -> None:
    parser.add_argument("--csv", action="store_true", help=f"also write {what} as CSV (one row per row of the .npz)")


def _add_run_options(parser: argparse.ArgumentParser, default_out: str) -> None:
    parser.add_argument("--out", default=default_out, help=f"output folder (default {default_out})")
    _add_overwrite_option(parser)
    add_robot_arguments(parser)
    parser.add_argument(
        "--pinv-damping",
        type=_real(0.0, 1e3),
        default=0.0,
        help="damping of the pseudoinverse (0: exact, the paper)",
    )


def _add_command(commands, name: str, help: str) -> argparse.ArgumentParser:
    """A command's parser whose ``--help`` opens with the line ``spacegrasp --help`` lists."""
    return commands.add_parser(name, help=help, description=help[0].upper() + help[1:] + ".")


def _add_realism_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--realism",
        metavar="ideal|flight|FILE",
        help="the loop's realism: ideal (the paper's, default), flight, or a TOML file (documentation: Flight-like loop)",
    )


#: The envelopes ``--ranges`` knows by name: the campaigns' defaults, the tuning batch's,
#: the campaigns' twice as wide in the LAR's pose and its estimate, and free-floating targets
#: of 200 to 2,000 kg, drifting and tumbling slowly or fast (with a scenario that has a [target]).
NAMED_RANGES = {
    "montecarlo": PerturbationRanges(),
    "tuning": TUNING_RANGES,
    "lar_wide": LAR_WIDE_RANGES,
    "free_target": FREE_TARGET_RANGES,
    "free_target_fast": FREE_TARGET_FAST_RANGES,
}


def add_ranges_arguments(parser: argparse.ArgumentParser, default: str) -> None:
    """``--ranges`` and ``--range`` on ``parser``, whose envelope is ``default`` (a name)."""
    parser.add_argument(
        "--ranges",
        metavar="|".join([*NAMED_RANGES, "FILE"]),
        help=f"perturbation half-widths: a named envelope or a TOML file whose missing keys keep the {default} "
        f"envelope's (default: {default}; documentation: File formats)",
    )
    parser.add_argument(
        "--scale",
        type=_real(0.0, 1e6),
        default=None,
        metavar="K",
        help="the envelope K times as wide: every half-width times K, the contact stiffness's factor to the "
        "power K (before --range; a fraction that would reach 1 is refused)",
    )
    parser.add_argument(
        "--range",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="override one half-width, e.g. q_init_rad=0.05 (repeatable)",
    )


def add_gains_arguments(parser: argparse.ArgumentParser, repeatable: bool = False) -> None:
    """``--gains`` (a named set or a file; ``repeatable``: several, to compare) and
    ``--fill-from`` (where the groups a file leaves out come from) on ``parser``."""
    names = "|".join(NAMED_GAIN_SETS)
    if repeatable:
        parser.add_argument(
            "--gains",
            action="append",
            default=[],
            metavar=f"{names}|FILE",
            help="a gain set to compare with the baseline (the paper's gains unless --baseline): a shipped set by name or a gains JSON file "
            "(repeatable; labelled by name or file name)",
        )
    else:
        parser.add_argument(
            "--gains",
            metavar=f"{names}|FILE",
            help="the gains: a shipped set by name (paper, the default; the tuned ideal, flight and free_target "
            "sets) or a gains JSON file holding every group the law uses",
        )
    parser.add_argument(
        "--fill-from",
        metavar="paper|FILE",
        help="where the groups a gains file leaves out come from (default: none; such a file is refused); "
        "recorded in the run's files",
    )


def _add_envelope_options(parser: argparse.ArgumentParser, seed_help: str) -> None:
    """The gain set, its law and loop, and the envelope and seed its captures are drawn from
    (``margins`` and ``worstcase``)."""
    parser.add_argument("--controller", choices=CONTROLLERS, default="admittance")
    add_gains_arguments(parser)
    parser.add_argument("--scenario", help="nominal scenario TOML/JSON (default: the paper's)")
    _add_realism_option(parser)
    add_ranges_arguments(parser, "montecarlo")
    parser.add_argument("--seed", type=_SEED, default=0, help=seed_help)


class _RenamedOption(argparse.Action):
    """An option under the name it had before (hidden from the help): stores into the new
    option's destination and warns once on stderr, naming the new option."""

    def __init__(self, option_strings, dest, new_name: str, **kwargs):
        self.new_name = new_name
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        print(
            f"spacegrasp: warning: {option_string} is now {self.new_name} (the old name will be removed)",
            file=sys.stderr,
        )
        setattr(namespace, self.dest, values)


def _add_criteria_options(parser: argparse.ArgumentParser) -> None:
    """A capture's success criteria (``criteria.CaptureCriteria``), and what the controller is
    told of each sample."""
    parser.add_argument(
        "--tolerance-mm",
        type=_real(0.0, 1e6, above=True),
        default=5.0,
        help="success: final position error at most this (default 5 mm)",
    )
    parser.add_argument(
        "--tolerance-deg",
        type=_real(0.0, 180.0, above=True),
        default=1.0,
        help="success: final orientation error at most this (default 1 deg)",
    )
    parser.add_argument(
        "--torque-threshold",
        type=_real(0.0, 1e6),
        default=100.0,
        metavar="NM",
        help="success: peak |u_i| at most this, else the sample counts as unstable (default 100 N m; 0: none)",
    )
    parser.add_argument(
        "--torque-limit",
        type=_real(0.0, 1e6),
        dest="torque_threshold",
        action=_RenamedOption,
        new_name="--torque-threshold",
        help=argparse.SUPPRESS,
    )
    parser.add_argument(
        "--target-speed-limit",
        type=_real(0.0, 100.0, above=True),
        default=0.005,
        metavar="MPS",
        help="success, with a free-floating target: its final speed at most this (default 0.005 m/s)",
    )
    parser.add_argument(
        "--identified",
        action="store_true",
        help="tell the controller each sample's perturbed satellite (default: it believes the nominal robot)",
    )


def _add_compile_cache_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--compile-cache",
        metavar="DIR|none",
        help="keep compiled programs in DIR for later runs (default: $JAX_COMPILATION_CACHE_DIR, "
        "else ~/.cache/spacegrasp-jax/xla; 'none': compile everything afresh)",
    )
    parser.add_argument(
        "--verbose",
        action="store_true",
        help="show XLA's and JAX's own log (XLA's slow-compile banner among it; hidden by default)",
    )


#: TuneConfig's fields -> the options that set them (for messages).
TUNE_OPTIONS = {
    "frozen": "--freeze",
    "optimizer": "--optimizer",
    "cvar_alpha": "--cvar",
    "learning_rate": "--lr",
    "torque_guard_Nm": "--torque-guard",
    "aggregate": "--aggregate",
    "torque_fraction": "--torque-fraction",
    "torque_cap_Nm": "--torque-cap",
    "population": "--population",
    "step_size": "--step-size",
    "separable": "--separable",
    "noise_handling": "--noise-handling",
    "method": "--method",
    "gradient": "--gradient",
    "objective": "--objective",
    "weights": "--weights",
    "fresh_batches": "--fresh-batches",
    "gradient_from_s": "--gradient-from",
    "keep": "--keep",
    "patience": "--patience",
    "validation_size": "--validation-size",
}


def tune_setting_error(error: ValueError) -> UsageError:
    """A ``TuneConfig`` (or ``Weights``) refusal as a usage error naming the option: its
    message's leading field name (``torque_cap_Nm: ...``) becomes the option (``--torque-cap: ...``)."""
    field, separator, rest = str(error).partition(": ")
    option = TUNE_OPTIONS.get(field)
    return UsageError(f"{option}: {rest}" if separator and option else str(error))


def add_objective_arguments(parser: argparse.ArgumentParser) -> None:
    """``--objective``, its torque constraint (``--torque-fraction``, ``--torque-cap``) and
    ``--weights``: the objective ``tune`` minimises, and ``gradients`` differentiates."""
    parser.add_argument(
        "--objective",
        choices=OBJECTIVES,
        default=TuneConfig.objective,
        help=f"capture: the margins to the success criteria, torque a constraint at the motors' limits; weighted: "
        f"errors against torque relative to the starting gains (default {TuneConfig.objective})",
    )
    parser.add_argument(
        "--torque-fraction",
        type=_real(0.0, 10.0, above=True),
        default=1.0,
        help="the capture objective's torque constraint as a fraction of the motors' limits (default 1)",
    )
    parser.add_argument(
        "--torque-cap",
        type=_real(0.0, 1000.0, above=True),
        default=None,
        metavar="NM",
        help="the capture objective's torque budget in N m for every joint, where below its fraction of the "
        "limit (default: none)",
    )
    parser.add_argument(
        "--weights",
        help="the weighted objective's weights, e.g. final_position=1,peak_torque=4 (documentation: Tuning the gains)",
    )
