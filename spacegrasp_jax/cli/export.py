"""``spacegrasp export``: gains and loop settings for flight software."""

from __future__ import annotations

import argparse

from spacegrasp_jax.analysis import export
from spacegrasp_jax.cli.common import _load_inputs, _realism, _write_out_file
from spacegrasp_jax.cli.options import (
    UsageError,
    _add_command,
    _add_realism_option,
    add_gains_arguments,
    add_robot_arguments,
)
from spacegrasp_jax.core.model import n_joints
from spacegrasp_jax.loop.control import (
    CONTROLLERS,
    NAMED_GAINS,
)
from spacegrasp_jax.loop.control.schedule import TUNED_SCHEDULE_FILES


def _c_identifier(text: str) -> str:
    """An option's type: a C identifier (letters, digits and underscores, not starting with a digit)."""
    if not (text.isascii() and text.isidentifier()):
        raise argparse.ArgumentTypeError(f"expected a C identifier such as SG, got {text!r}")
    return text


def _source_words(gains: str | None) -> str:
    """Where the exported gains came from, as the file's first line says it."""
    if gains is None or gains == "paper":
        return "paper_gains()"
    if gains in TUNED_SCHEDULE_FILES:
        return f"the shipped {gains} (tuned_schedule({gains!r}))"
    return f"the shipped {gains} gains (tuned_gains({gains!r}))" if gains in NAMED_GAINS else gains


def _export(args: argparse.Namespace) -> int:
    """``spacegrasp export``: a gain set with its units, equations and the loop's settings, as
    one file of ``--format`` (printed without ``--out``)."""
    robot, scenario, gains = _load_inputs(args, schedules=True)
    realism = _realism(args, scenario, robot)
    settings = export.loop_settings(realism, scenario.dt, n_joints(robot))
    try:
        text = export.export_text(
            gains, args.controller, settings, args.format, source=_source_words(args.gains), prefix=args.prefix
        )
    except ValueError as error:
        raise UsageError(str(error)) from None
    _write_out_file(args, text, f"the {args.controller} gains, their units and equations, and the loop's settings")
    return 0


def add_parsers(commands) -> None:
    """The command's parser, added to ``commands``."""
    export_gains = _add_command(
        commands, "export", help="write gains for flight software: JSON, YAML, a C header or CSV, with units"
    )
    add_gains_arguments(export_gains)
    export_gains.add_argument("--controller", choices=CONTROLLERS, default="admittance")
    export_gains.add_argument("--format", choices=export.FORMATS, required=True)
    _add_realism_option(export_gains)
    export_gains.add_argument("--scenario", help="scenario TOML or JSON file, for its step (default: the paper's)")
    add_robot_arguments(export_gains)
    export_gains.add_argument(
        "--prefix", type=_c_identifier, default="SG", help="the C header's names: PREFIX_kp, ... (default SG)"
    )
    export_gains.add_argument("--out", metavar="FILE", help="the file to write (default: print it)")
    export_gains.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    export_gains.set_defaults(run=_export)
