"""Kinematics against Pinocchio and finite differences."""

from __future__ import annotations

import jax
import numpy as np
import pinocchio as pin
import pinocchio_reference as ref

import spacegrasp_jax as sg
from spacegrasp_jax.core import spatial

RTOL = 1e-9


def test_frames_and_ee_pose_match_pinocchio(robot, random_states, pinocchio_model):
    model, data, ee_frame = pinocchio_model
    fk = jax.jit(sg.forward_kinematics)
    for s in random_states:
        pin.framesForwardKinematics(model, data, ref.configuration(s.p_base, s.R_base, s.q, model))
        frames = fk(robot, s.p_base, s.R_base, s.q)
        np.testing.assert_allclose(frames.p_ee, data.oMf[ee_frame].translation, rtol=0, atol=1e-12)
        np.testing.assert_allclose(frames.R_ee, data.oMf[ee_frame].rotation, rtol=0, atol=1e-12)
        p_ee, R_ee = sg.ee_pose(robot, s.p_base, s.R_base, s.q)
        # ee_pose runs op by op here, forward_kinematics compiled: equal up to rounding.
        np.testing.assert_allclose(p_ee, frames.p_ee, rtol=0, atol=1e-15)
        np.testing.assert_allclose(R_ee, frames.R_ee, rtol=0, atol=1e-15)
        for joint in range(7):  # Pinocchio joint k + 2 sits at frame k, turning about its z axis
            placement = data.oMi[joint + 2]
            np.testing.assert_allclose(frames.joint_origin[joint], placement.translation, rtol=0, atol=1e-12)
            np.testing.assert_allclose(frames.joint_axis[joint], placement.rotation[:, 2], rtol=0, atol=1e-12)


def test_ee_jacobians_match_pinocchio(robot, random_states, pinocchio_model):
    model, data, ee_frame = pinocchio_model
    for s in random_states:
        qp = ref.configuration(s.p_base, s.R_base, s.q, model)
        J = pin.computeFrameJacobian(model, data, qp, ee_frame, pin.LOCAL_WORLD_ALIGNED) @ ref.velocity_map(s.R_base)
        J_s, J_m = sg.ee_jacobians(robot, s.R_base, s.q)
        np.testing.assert_allclose(J_s, J[:, :6], rtol=0, atol=RTOL * np.abs(J).max())
        np.testing.assert_allclose(J_m, J[:, 6:], rtol=0, atol=RTOL * np.abs(J).max())


def test_ee_jacobians_match_finite_differences(robot, random_states):
    """Eq 5 against central differences of the EE pose along a random motion."""
    pose = jax.jit(sg.ee_pose)
    for s in random_states[:5]:
        J_s, J_m = sg.ee_jacobians(robot, s.R_base, s.q)
        twist = J_s @ s.V_base + J_m @ s.qd
        h = 1e-6

        def moved(t):
            R = np.asarray(jax.scipy.linalg.expm(spatial.skew(s.V_base[3:] * t))) @ s.R_base
            return pose(robot, s.p_base + s.V_base[:3] * t, R, s.q + s.qd * t)

        (p_a, R_a), (p_b, R_b) = moved(h), moved(-h)
        measured = np.concatenate([(p_a - p_b) / (2 * h), spatial.rotation_log(R_a @ R_b.T) / (2 * h)])
        np.testing.assert_allclose(twist, measured, rtol=0, atol=1e-8 * np.abs(twist).max())
