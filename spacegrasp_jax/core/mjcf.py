"""The robot as a MuJoCo model (MJCF text), for side-by-side benchmarks and checks.

The generated model has a free joint at the satellite CoM, N hinges and the EE merged into
link N (as [`body_inertials()`][spacegrasp_jax.core.model.body_inertials] does), no gravity, no geometry and so
no contacts, the RK4 integrator at ``dt`` and one motor per joint (``ctrl`` = joint torque,
N m). It describes the same rigid-body system as [`Robot`][spacegrasp_jax.core.model.Robot]:

* body ``link<i>`` has the pose of frame ``i``. Its hinge sits at the origin of frame
  ``i-1``, about ``z_{i-1}``; at ``q = 0`` the body is placed by ``T_{i-1,i}(0)`` (link 1 in
  the mounting frame's pose on the satellite).
* MuJoCo's free-joint velocity is ``[v_s (world), R_s^T w_s (satellite frame)]``; ours is
  ``[v_s, w_s]``, both in the inertial frame (``qvel_from_state`` converts).
* site ``ee`` is the EE frame's origin.

MuJoCo itself is not a dependency of the package: only ``benchmarks`` and the tests
import it.
"""

from __future__ import annotations

import numpy as np

from spacegrasp_jax.core import spatial
from spacegrasp_jax.core.kinematics import joint_transforms
from spacegrasp_jax.core.model import Robot, body_inertials, n_joints


def _rotation_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``[w, x, y, z]`` of a rotation matrix, as NumPy."""
    return np.asarray(spatial.rotation_to_quat(np.asarray(R, dtype=float)))


def _numbers(values) -> str:
    return " ".join(f"{float(v):.17g}" for v in np.ravel(values))


def _full_inertia(I: np.ndarray) -> str:
    """MuJoCo's ``fullinertia`` order: Ixx Iyy Izz Ixy Ixz Iyz."""
    return _numbers([I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]])


def robot_to_mjcf(robot: Robot, dt: float = 1e-3) -> str:
    """MJCF text of ``robot`` (unbatched) with the RK4 integrator at ``dt`` (s)."""
    mass, com, inertia = (np.asarray(x, dtype=float) for x in body_inertials(robot))
    n = n_joints(robot)
    R_rel, p_rel = (np.asarray(x, dtype=float) for x in joint_transforms(robot, np.zeros(n)))
    frame_rotation = np.asarray(robot.frame_rotation, dtype=float)
    frame_position = np.asarray(robot.frame_position, dtype=float)
    mount_p, mount_R = (np.asarray(x, dtype=float) for x in (robot.mount_position, robot.mount_rotation))
    lines = [
        '<mujoco model="spacegrasp">',
        '  <compiler angle="radian" autolimits="true" inertiafromgeom="false"/>',
        f'  <option timestep="{float(dt):.17g}" integrator="RK4" gravity="0 0 0"/>',
        "  <worldbody>",
        '    <body name="satellite" pos="0 0 0">',
        '      <freejoint name="satellite"/>',
        f'      <inertial pos="0 0 0" mass="{float(robot.satellite_mass):.17g}" fullinertia="{_full_inertia(np.asarray(robot.satellite_inertia, dtype=float))}"/>',
    ]
    indent = "      "
    for i in range(n):
        p, R = p_rel[i], R_rel[i]
        if i == 0:
            p, R = mount_p + mount_R @ p, mount_R @ R  # frame 0: the mount
        hinge = -frame_rotation[i].T @ frame_position[i]  # origin of frame i-1, frame i axes
        axis = frame_rotation[i][2]  # z_{i-1} in frame i axes: Rz(theta) leaves it alone
        lines += [
            f'{indent}<body name="link{i + 1}" pos="{_numbers(p)}" quat="{_numbers(_rotation_to_quat(R))}">',
            f'{indent}  <joint name="joint{i + 1}" type="hinge" pos="{_numbers(hinge)}" axis="{_numbers(axis)}"/>',
            f'{indent}  <inertial pos="{_numbers(com[i])}" mass="{mass[i]:.17g}" fullinertia="{_full_inertia(inertia[i])}"/>',
        ]
        indent += "  "
    lines.append(f'{indent}<site name="ee" pos="{_numbers(np.asarray(robot.ee_offset, dtype=float))}"/>')
    for _ in range(n):
        indent = indent[:-2]
        lines.append(f"{indent}</body>")
    lines += ["    </body>", "  </worldbody>", "  <actuator>"]
    lines += [f'    <motor name="joint{i + 1}" joint="joint{i + 1}" gear="1"/>' for i in range(n)]
    lines += ["  </actuator>", "</mujoco>", ""]
    return "\n".join(lines)


def qpos_from_state(p_base, R_base, q) -> np.ndarray:
    """MuJoCo ``qpos`` (7 + N,): satellite position, quaternion ``[w, x, y, z]``, joint angles."""
    return np.concatenate(
        [
            np.asarray(p_base, dtype=float),
            _rotation_to_quat(np.asarray(R_base, dtype=float)),
            np.asarray(q, dtype=float),
        ]
    )


def qvel_from_state(R_base, V_base, qd) -> np.ndarray:
    """MuJoCo ``qvel`` (6 + N,) from our ``[v_s, w_s]`` (inertial frame) and joint rates."""
    V_base = np.asarray(V_base, dtype=float)
    return np.concatenate([V_base[:3], np.asarray(R_base, dtype=float).T @ V_base[3:], np.asarray(qd, dtype=float)])


__all__ = ["qpos_from_state", "qvel_from_state", "robot_to_mjcf"]
