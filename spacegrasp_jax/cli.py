"""The ``spacegrasp`` command line."""

from __future__ import annotations

import argparse
import sys

import jax
import jax.numpy as jnp
import numpy as np

import spacegrasp_jax as sg
from spacegrasp_jax import spatial


def _info(args: argparse.Namespace) -> int:
    robot = sg.load_robot(args.robot) if args.robot else sg.paper_robot()
    q = jnp.asarray(sg.PAPER_Q_INIT)
    p_base, R_base = jnp.zeros(3), jnp.eye(3)
    total_mass = float(robot.satellite_mass + jnp.sum(robot.link_mass) + robot.ee_mass)
    com = np.asarray(jax.jit(sg.system_com)(robot, p_base, R_base, q))
    p_ee, R_ee = jax.jit(sg.ee_pose)(robot, p_base, R_base, q)
    euler = np.asarray(spatial.euler_zyx(R_ee))
    M = np.asarray(jax.jit(sg.mass_matrix)(robot, R_base, q))
    source = args.robot or "paper robot (Tables 1-3)"
    print(f"robot: {source}")
    print(f"configuration: q_init = {list(sg.PAPER_Q_INIT)} rad, satellite CoM at the origin, identity attitude")
    print(f"total mass:               {total_mass:.3f} kg")
    print(f"system CoM (inertial):    [{com[0]: .6f}, {com[1]: .6f}, {com[2]: .6f}] m")
    print(f"EE position (inertial):   [{float(p_ee[0]): .6f}, {float(p_ee[1]): .6f}, {float(p_ee[2]): .6f}] m")
    print(f"EE ZYX angles [roll, pitch, yaw]: [{euler[0]: .6f}, {euler[1]: .6f}, {euler[2]: .6f}] rad")
    print("EE rotation (EE to inertial):")
    for row in np.asarray(R_ee):
        print(f"    [{row[0]: .6f}, {row[1]: .6f}, {row[2]: .6f}]")
    print(f"mass matrix (13x13) condition number: {np.linalg.cond(M):.6g}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="spacegrasp", description=sg.__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"spacegrasp-jax {sg.__version__}")
    commands = parser.add_subparsers(dest="command", required=True)
    info = commands.add_parser("info", help="print the robot's mass, CoM, EE pose at q_init and cond(M)")
    info.add_argument("--robot", help="robot TOML file (default: the paper's robot)")
    info.set_defaults(run=_info)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except sg.RobotConfigError as error:
        print(f"spacegrasp: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
