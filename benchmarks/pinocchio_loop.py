"""The peer a user would write without this package: the paper's closed loop as a Python
loop over NumPy, with Pinocchio for the rigid-body dynamics.

Same robot (built here in Pinocchio from a [`Robot`][spacegrasp_jax.core.model.Robot]), same
scenario, same controllers (admittance eqs 9-17 and Cartesian eqs 21-22, joint PID with the
t^2 ramp), same exact contact law and the same RK4 with the torques held over each 1 ms step.
The state is kept in our convention (inertial base twist, satellite quaternion) and converted
to Pinocchio's (base twist in the base frame) at each call. Apart from reading the ``Robot``,
``Scenario`` and ``Gains`` (and ``body_inertials`` for the EE merged into link 7), it uses
none of the package's code: the small rotation helpers and the control law are written again
in NumPy, on purpose, as a user without this package would write them.

Run alone: ``python -m spacegrasp_jax.benchmarks.pinocchio_loop [--duration S]`` prints the time of one
rollout and its agreement with ``spacegrasp_jax``'s rollout of the same scenario.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pinocchio as pin

from spacegrasp_jax.core.model import Robot, body_inertials, n_joints
from spacegrasp_jax.jobs.compilation import configure
from spacegrasp_jax.loop.control.registry import PAPER_CONTROLLERS
from spacegrasp_jax.loop.simulate import RunSpec


def build_model(robot: Robot) -> tuple[pin.Model, int]:
    """Pinocchio model of ``robot`` (free flyer at the satellite CoM, 7 revolute-z joints,
    the EE merged into link 7) and the id of its frame ``ee``."""
    mass, com, inertia = (np.asarray(x, dtype=float) for x in body_inertials(robot))
    model = pin.Model()
    model.gravity = pin.Motion.Zero()
    base = model.addJoint(0, pin.JointModelFreeFlyer(), pin.SE3.Identity(), "satellite")
    model.appendBodyToJoint(
        base,
        pin.Inertia(float(robot.satellite_mass), np.zeros(3), np.asarray(robot.satellite_inertia, dtype=float)),
        pin.SE3.Identity(),
    )
    parent, placement = (
        base,
        pin.SE3(np.asarray(robot.mount_rotation, dtype=float), np.asarray(robot.mount_position, dtype=float)),
    )
    for i in range(n_joints(robot)):
        offset = float(np.asarray(robot.joint_offset)[i])
        joint = model.addJoint(parent, pin.JointModelRZ(), placement, f"joint{i + 1}")
        # Frame i seen from the joint frame: Rz(offset) F_i.
        frame_i = pin.SE3(pin.utils.rpyToMatrix(0.0, 0.0, offset), np.zeros(3)) * pin.SE3(
            np.asarray(robot.frame_rotation, dtype=float)[i], np.asarray(robot.frame_position, dtype=float)[i]
        )
        model.appendBodyToJoint(joint, pin.Inertia(mass[i], com[i], inertia[i]), frame_i)
        parent, placement = joint, frame_i
    ee = model.addFrame(
        pin.Frame(
            "ee",
            parent,
            placement * pin.SE3(np.eye(3), np.asarray(robot.ee_offset, dtype=float)),
            pin.FrameType.OP_FRAME,
        )
    )
    return model, ee


def _rotation(quat_wxyz: np.ndarray) -> np.ndarray:
    w, x, y, z = quat_wxyz
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _euler_zyx(R: np.ndarray) -> np.ndarray:
    return np.array(
        [np.arctan2(R[2, 1], R[2, 2]), -np.arcsin(np.clip(R[2, 0], -1.0, 1.0)), np.arctan2(R[1, 0], R[0, 0])]
    )


def _euler_rates_to_body(angles: np.ndarray) -> np.ndarray:
    cr, sr, cp, sp = np.cos(angles[0]), np.sin(angles[0]), np.cos(angles[1]), np.sin(angles[1])
    return np.array([[1.0, 0.0, -sp], [0.0, cr, sr * cp], [0.0, -sr, cr * cp]])


def _euler_rates_to_body_rate(angles: np.ndarray, angle_rates: np.ndarray) -> np.ndarray:
    """Time derivative of ``_euler_rates_to_body(angles)`` along ``angle_rates``."""
    cr, sr, cp, sp = np.cos(angles[0]), np.sin(angles[0]), np.cos(angles[1]), np.sin(angles[1])
    dr, dp = angle_rates[0], angle_rates[1]
    return np.array(
        [
            [0.0, 0.0, -cp * dp],
            [0.0, -sr * dr, cr * cp * dr - sr * sp * dp],
            [0.0, -cr * dr, -sr * cp * dr - cr * sp * dp],
        ]
    )


def _euler_to_rotation(angles: np.ndarray) -> np.ndarray:
    return pin.utils.rpyToMatrix(*angles)  # Rz(yaw) Ry(pitch) Rx(roll)


class PinocchioClosedLoop:
    """One closed-loop rollout with Pinocchio dynamics; ``run()`` returns the final EE pose in
    LAR (6,) and the peak |u| per joint (7,)."""

    def __init__(self, robot: Robot, scenario, gains, controller: str):
        self.model, self.ee = build_model(robot)
        self.data = self.model.createData()
        self.scenario, self.controller = scenario, controller
        self.gains = {
            name: np.asarray(getattr(gains, name), dtype=float)
            for name in ("Md", "Bd", "Kd", "K_lin", "K_eul", "kp", "ki", "kd")
        }
        self.p_lar, self.R_lar = np.asarray(scenario.p_lar, dtype=float), np.asarray(scenario.R_lar, dtype=float)
        self.centre, self.radius = np.asarray(scenario.sphere_centre, dtype=float), float(scenario.sphere_radius)
        self.stiffness = float(scenario.contact_stiffness)
        trajectory = scenario.trajectory
        self.start, self.end, self.move = (
            np.asarray(trajectory.start_pose, dtype=float),
            np.asarray(trajectory.end_pose, dtype=float),
            float(trajectory.duration),
        )
        if scenario.contact_law != "exact":
            raise ValueError("the Pinocchio peer implements the exact contact law only")

    # ---- Pinocchio calls in our state convention ----

    def _pin_state(self, p, quat, q, V, qd):
        R = _rotation(quat)
        q_pin = np.concatenate([p, quat[1:], quat[:1], q])  # Pinocchio: [x, y, z, qx, qy, qz, qw]
        v_pin = np.concatenate([R.T @ V[:3], R.T @ V[3:], qd])
        return R, q_pin, v_pin

    def _contact_force_lar(self, p_ee: np.ndarray) -> np.ndarray:
        p = self.R_lar.T @ (p_ee - self.p_lar) - self.centre
        d = np.linalg.norm(p)
        if d == 0.0 or d >= self.radius:
            return np.zeros(3)
        return self.stiffness * (self.radius - d) / self.radius**3 * p / d

    def derivative(self, state, u):
        p, quat, q, V, qd = state
        R, q_pin, v_pin = self._pin_state(p, quat, q, V, qd)
        model, data = self.model, self.data
        pin.computeJointJacobians(model, data, q_pin)
        pin.updateFramePlacements(model, data)
        p_ee = data.oMf[self.ee].translation
        force = self.R_lar @ self._contact_force_lar(p_ee)
        J = pin.getFrameJacobian(model, data, self.ee, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
        tau = J[:3].T @ force
        tau[6:] += u
        a = pin.aba(model, data, q_pin, v_pin, tau)
        # Back to our convention: v_pin = [R^T v_s, R^T w_s]; its rate has a transport term.
        v_local, w_local = v_pin[:3], v_pin[3:6]
        V_dot = np.concatenate([R @ (a[:3] + np.cross(w_local, v_local)), R @ a[3:6]])
        w = V[3:]
        quat_dot = 0.5 * np.concatenate([[-w @ quat[1:]], quat[0] * w + np.cross(w, quat[1:])])
        return (V[:3], quat_dot, qd, V_dot, a[6:])

    def control(self, state, V_ref, integral, previous_error, t):
        p, quat, q, V, qd = state
        R, q_pin, v_pin = self._pin_state(p, quat, q, V, qd)
        model, data = self.model, self.data
        M = pin.crba(model, data, q_pin)
        M = np.triu(M) + np.triu(M, 1).T
        pin.computeJointJacobians(model, data, q_pin)
        pin.updateFramePlacements(model, data)
        placement = data.oMf[self.ee]
        J = pin.getFrameJacobian(model, data, self.ee, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
        R_ee = placement.rotation
        R_lar_ee = self.R_lar.T @ R_ee
        pose = np.concatenate([self.R_lar.T @ (placement.translation - self.p_lar), _euler_zyx(R_lar_ee)])
        twist_world = J @ v_pin
        twist = np.concatenate([self.R_lar.T @ twist_world[:3], self.R_lar.T @ twist_world[3:]])
        # Dynamic Jacobian (eq 8): zero momentum, rows 0-5 of M, in Pinocchio's coordinates.
        J_dyn = J[:, 6:] - J[:, :6] @ np.linalg.solve(M[:6, :6], M[:6, 6:])
        J_dyn_ee = np.vstack([R_ee.T @ J_dyn[:3], R_ee.T @ J_dyn[3:]])
        g = self.gains
        # Desired state: quintic profile (eqs 10-13).
        tau = min(max(t / self.move, 0.0), 1.0)
        s = tau**3 * (10 - 15 * tau + 6 * tau**2)
        ds = 30 * tau**2 * (1 - tau) ** 2 / self.move
        dds = 60 * tau * (1 - tau) * (1 - 2 * tau) / self.move**2
        delta = self.end - self.start
        pose_des, rate, acceleration = self.start + s * delta, ds * delta, dds * delta
        angles = pose_des[3:]
        T_eul = _euler_rates_to_body(angles)
        T_rate = _euler_rates_to_body_rate(angles, rate[3:])
        R_des = _euler_to_rotation(angles)
        twist_des = np.concatenate([rate[:3], R_des @ T_eul @ rate[3:]])
        twist_rate_des = np.concatenate([acceleration[:3], R_des @ (T_rate @ rate[3:] + T_eul @ acceleration[3:])])
        error = pose_des - pose
        error[3:] = np.arctan2(np.sin(error[3:]), np.cos(error[3:]))
        if self.controller == "admittance":
            V_ref_ee = np.concatenate([R_lar_ee.T @ V_ref[:3], R_lar_ee.T @ V_ref[3:]])
            qd_des = J_dyn_ee.T @ np.linalg.solve(J_dyn_ee @ J_dyn_ee.T, V_ref_ee)
            # The contact force acts at the EE point: the measured wrench has no moment there.
            wrench = np.concatenate([self._contact_force_lar(placement.translation), np.zeros(3)])
            twist_ref_rate = twist_rate_des + (wrench + g["Bd"] * (twist_des - twist) + g["Kd"] * error) / g["Md"]
            V_ref = V_ref + self.scenario.dt * twist_ref_rate
        else:
            command = np.concatenate(
                [R_lar_ee.T @ (g["K_lin"] * error[:3]), _euler_rates_to_body(pose[3:]) @ (g["K_eul"] * error[3:])]
            )
            qd_des = J_dyn_ee.T @ np.linalg.solve(J_dyn_ee @ J_dyn_ee.T, command)
        rate_error = qd_des - qd
        integral = integral + rate_error * self.scenario.dt
        derivative = (rate_error - previous_error) / self.scenario.dt
        u = min(t, 1.0) ** 2 * (g["kp"] * rate_error + g["ki"] * integral + g["kd"] * derivative)
        return u, V_ref, integral, rate_error, pose

    def run(self):
        initial = self.scenario.initial
        state = tuple(
            np.asarray(x, dtype=float)
            for x in (initial.p_base, initial.quat_base, initial.q, initial.V_base, initial.qd)
        )
        V_ref, integral, previous_error = np.zeros(6), np.zeros(7), np.zeros(7)
        dt, peak, pose = self.scenario.dt, np.zeros(7), None
        for k in range(self.scenario.n_steps):
            u, V_ref, integral, previous_error, pose = self.control(state, V_ref, integral, previous_error, k * dt)
            peak = np.maximum(peak, np.abs(u))
            k1 = self.derivative(state, u)
            k2 = self.derivative(tuple(x + 0.5 * dt * dx for x, dx in zip(state, k1)), u)
            k3 = self.derivative(tuple(x + 0.5 * dt * dx for x, dx in zip(state, k2)), u)
            k4 = self.derivative(tuple(x + dt * dx for x, dx in zip(state, k3)), u)
            state = tuple(x + dt * (a + 2 * b + 2 * c + d) / 6 for x, a, b, c, d in zip(state, k1, k2, k3, k4))
            state = (state[0], state[1] / np.linalg.norm(state[1]), *state[2:])
        return pose, peak


def main(argv=None) -> int:
    configure(compile_cache=False)  # this process is the benchmark's: float64, loops compiled whole, no cache
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=17.0)
    parser.add_argument("--controller", choices=PAPER_CONTROLLERS, default="admittance")
    args = parser.parse_args(argv)
    import spacegrasp_jax as sg
    from spacegrasp_jax.envelope.scenario import paper_scenario
    from spacegrasp_jax.jobs import experiment
    from spacegrasp_jax.loop.control import paper_gains

    robot = sg.paper_robot()
    scenario = paper_scenario(robot, duration=args.duration)
    loop = PinocchioClosedLoop(robot, scenario, paper_gains(), args.controller)
    start = time.perf_counter()
    pose, peak = loop.run()
    seconds = time.perf_counter() - start
    ours = experiment.run(RunSpec(robot, scenario, args.controller), paper_gains())
    print(
        f"Pinocchio loop: {seconds:.2f} s for {scenario.n_steps} steps ({1e6 * seconds / scenario.n_steps:.0f} us/step)"
    )
    print(
        f"final EE pose, last logged step: max |difference| to spacegrasp_jax {np.abs(pose - ours.log.pose_ee[-1]).max():.3e}"
    )
    print(
        f"peak |u| per joint: max relative difference {np.max(np.abs(peak / np.asarray(ours.summary['max_abs_torque_Nm']) - 1)):.3e}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
