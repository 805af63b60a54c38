"""``spacegrasp gains --start``: gains to start tuning from, for any arm."""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from spacegrasp_jax.cli.common import _load_robot, _write_out_file
from spacegrasp_jax.cli.options import UsageError, _add_command, add_robot_arguments
from spacegrasp_jax.core.dynamics import mass_matrix
from spacegrasp_jax.core.model import n_joints
from spacegrasp_jax.envelope.scenario import load_scenario, paper_scenario
from spacegrasp_jax.loop.control import CONTROLLERS
from spacegrasp_jax.loop.control.gains import PAPER_JOINTS, START_RATE_PER_S, effective_joint_inertia, starting_gains


def _gains(args: argparse.Namespace) -> int:
    """``spacegrasp gains --start``: the starting rule's gains for the arm of ``--robot`` at
    the initial joint angles of ``--scenario``, as a gains file of the groups ``--controller``
    uses."""
    robot = _load_robot(args)
    n = n_joints(robot)
    if args.scenario is None and n != PAPER_JOINTS:
        raise UsageError(f"--scenario: required for an arm of {n} joints (its q_init; the paper's is for 7)")
    scenario = load_scenario(robot, args.scenario) if args.scenario else paper_scenario(robot)
    state = scenario.initial
    gains = starting_gains(robot, state.q, state.R_base)
    inertia = effective_joint_inertia(mass_matrix(robot, state.R_base, state.q))
    text = json.dumps(gains.to_dict(args.controller), indent=2) + "\n"
    print(
        f"starting gains for the {n}-joint arm at q_init of {args.scenario or 'the paper scenario'}: "
        f"kp = {START_RATE_PER_S:g}/s x effective joint inertia {np.array2string(inertia, precision=3)} kg m^2, "
        f"ki = 0.05 kp, kd = 7e-5 kp; the laws' gains the paper's",
        file=sys.stderr,
    )
    _write_out_file(args, text, f"the {args.controller} law's gains (spacegrasp tune --gains FILE takes it from there)")
    return 0


def add_parsers(commands) -> None:
    """The command's parser, added to ``commands``."""
    gains = _add_command(commands, "gains", help="write gains to start tuning from for any arm (--start)")
    gains.add_argument(
        "--start",
        action="store_true",
        required=True,
        help="the starting rule: kp = 20/s x each joint's effective inertia at q_init (the satellite free), "
        "ki = 0.05 kp, kd = 7e-5 kp, the laws' gains the paper's",
    )
    gains.add_argument(
        "--controller", choices=CONTROLLERS, default="admittance", help="the law whose groups the file holds"
    )
    add_robot_arguments(gains)
    gains.add_argument("--scenario", help="scenario TOML or JSON file, for its q_init (default: the paper's)")
    gains.add_argument("--out", metavar="FILE", help="the gains JSON to write (default: print it)")
    gains.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    gains.set_defaults(run=_gains)
