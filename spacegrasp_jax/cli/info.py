"""``spacegrasp info``: the robot's mass, CoM, EE pose and joints, and its URDF."""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import spacegrasp_jax as sg
from spacegrasp_jax.cli.common import _load_robot, _rate_criterion, _warn
from spacegrasp_jax.cli.options import UsageError, _add_command, add_robot_arguments
from spacegrasp_jax.core import joint_limits, spatial, urdf
from spacegrasp_jax.core.model import body_inertials, n_joints
from spacegrasp_jax.envelope.scenario import load_scenario


def _info(args: argparse.Namespace) -> int:
    urdf_file = None if args.urdf is None else Path(args.urdf)
    if urdf_file is not None:
        if urdf_file.exists():
            raise UsageError(f"--urdf: {urdf_file} exists; name a new file (info never overwrites one)")
        folder = next(parent for parent in urdf_file.absolute().parents if parent.exists())
        if not folder.is_dir():
            raise UsageError(f"--urdf: {folder} is not a folder, so {urdf_file} cannot be written")
    robot = _load_robot(args)
    n = n_joints(robot)
    if args.scenario:
        q_init, where = load_scenario(robot, args.scenario).initial.q, f"the scenario's q_init ({args.scenario})"
    elif n == len(sg.PAPER_Q_INIT):
        q_init, where = sg.PAPER_Q_INIT, "the paper's q_init"
    else:
        q_init, where = np.zeros(n), "q = 0 (give --scenario for its q_init)"
    q = jnp.asarray(q_init, dtype=jnp.float64)
    for item in joint_limits.outside_ranges(robot, q):  # info shows the robot: a warning, not a refusal
        low, high = item["range_rad"]
        _warn(
            [
                f"{where}: joint {item['joint']} at {item['angle_rad']:.4g} rad is outside its range [{low:.4g}, {high:.4g}]"
            ]
        )
    p_base, R_base = jnp.zeros(3), jnp.eye(3)
    total_mass = float(robot.satellite_mass + jnp.sum(robot.link_mass) + robot.ee_mass)
    com = np.asarray(jax.jit(sg.system_com)(robot, p_base, R_base, q))
    p_ee, R_ee = jax.jit(sg.ee_pose)(robot, p_base, R_base, q)
    euler = np.asarray(spatial.euler_zyx(R_ee))
    M = np.asarray(jax.jit(sg.mass_matrix)(robot, R_base, q))
    source = args.robot or "paper robot (Tables 1-3)"
    print(f"robot: {source}, {n} joints")
    mount = np.asarray(robot.mount_position)
    print(
        f"satellite: {float(robot.satellite_mass):.3f} kg (with what is fixed to the arm's base), principal moments "
        f"{np.array2string(np.linalg.eigvalsh(np.asarray(robot.satellite_inertia)), precision=4)} kg m^2; "
        f"frame 0 at [{mount[0]: .4f}, {mount[1]: .4f}, {mount[2]: .4f}] m from its CoM"
    )
    mass, _, _ = body_inertials(robot)
    print(
        f"{'joint':>5}  {'link mass [kg]':>14}  {'range [rad]':>20}  {'rate limit [rad/s]':>18}  {'torque limit [N m]':>18}"
    )
    for i in range(n):
        lower, upper = np.asarray(robot.joint_position_limit)[i]
        span = "none" if np.isinf(lower) and np.isinf(upper) else f"[{lower:.4f}, {upper:.4f}]"
        print(
            f"{i + 1:>5}  {float(mass[i]):>14.4f}  {span:>20}  {float(robot.joint_rate_limit[i]):>18.4g}  "
            f"{float(robot.joint_torque_limit[i]):>18.4g}"
        )
    print(f"(link {n}'s mass includes the end-effector's and everything fixed to it)")
    if _rate_criterion(args, robot) is None:
        print("rate limits: assumed (no robot file states them): only ten times them fails a capture, as a runaway")
    else:
        print("rate limits: the file's own: a capture in which a joint turns faster fails (joint_rate)")
    print(
        f"configuration: {where} = {np.round(np.asarray(q), 6).tolist()} rad, satellite CoM at the origin, identity attitude"
    )
    print(f"total mass:               {total_mass:.3f} kg")
    print(f"system CoM (inertial):    [{com[0]: .6f}, {com[1]: .6f}, {com[2]: .6f}] m")
    print(f"EE position (inertial):   [{float(p_ee[0]): .6f}, {float(p_ee[1]): .6f}, {float(p_ee[2]): .6f}] m")
    print(f"EE ZYX angles [roll, pitch, yaw]: [{euler[0]: .6f}, {euler[1]: .6f}, {euler[2]: .6f}] rad")
    print("EE rotation (EE to inertial):")
    for row in np.asarray(R_ee):
        print(f"    [{row[0]: .6f}, {row[1]: .6f}, {row[2]: .6f}]")
    print(f"mass matrix ({6 + n}x{6 + n}) condition number: {np.linalg.cond(M):.6g}")
    if urdf_file is not None:
        urdf_file.parent.mkdir(parents=True, exist_ok=True)
        urdf_file.write_text(urdf.robot_to_urdf(robot))
        print(f"URDF written to {urdf_file} (it has no free joint: load it with a floating base)")
    return 0


def add_parsers(commands) -> None:
    """The command's parser, added to ``commands``."""
    info = _add_command(commands, "info", help="print the robot's mass, CoM, EE pose at q_init and cond(M)")
    add_robot_arguments(info)
    info.add_argument("--scenario", help="scenario TOML/JSON whose q_init to show the robot at")
    info.add_argument(
        "--urdf", metavar="FILE", help="also write the robot as URDF to FILE, a new file (for Pinocchio, Drake, ROS)"
    )
    info.set_defaults(run=_info)
