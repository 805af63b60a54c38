"""The paper's robot in Pinocchio, built from Tables 1-3 and the documented conventions alone (docs/modelling-notes.md).

Deliberately independent of ``spacegrasp_jax``: the tables are typed again here and the
model is assembled with Pinocchio's own joint, inertia and frame types, so that the
comparison in ``test_dynamics.py`` checks our reading of the paper as well as our algebra.

Pinocchio's free-flyer velocity is the base twist in the base (satellite) frame,
``v_pin = [R^T v_s, R^T w_s, qd]``; ours is ``x_v = [v_s, w_s, qd]`` in the inertial frame.
The helpers below convert between the two.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

HALF_PI = np.pi / 2
# Table 1: theta offset, lambda (d), L (a), alpha.
DH = [
    (HALF_PI, 0.4, 0.0, HALF_PI),
    (HALF_PI, -0.35, 0.0, HALF_PI),
    (0.0, -0.3, 0.6, 0.0),
    (0.0, -0.35, 0.35, 0.0),
    (0.0, -0.3, 0.0, -HALF_PI),
    (HALF_PI, 0.3, 0.0, HALF_PI),
    (0.0, 0.25, 0.0, 0.0),
]
EE_LAMBDA = 0.175
# Table 2: CoM from the origin of frame i-1, in frame i axes; mass.
COM = [
    ((0.0, 0.3, 0.0), 15.0),
    ((0.0, -0.25, 0.0), 13.0),
    ((0.3, 0.0, -0.2), 18.0),
    ((0.25, 0.0, -0.35), 10.0),
    ((0.0, 0.2, 0.0), 8.5),
    ((0.0, 0.25, 0.0), 10.5),
    ((0.0, 0.0, 0.1), 5.0),
]
EE_COM, EE_MASS = (0.0, 0.0, 0.1), 7.0
# Table 3: Ixx, Iyy, Izz, Ixy, Ixz, Iyz about the CoM, frame i axes.
INERTIA = [
    (0.2, 0.15, 0.1, 0, 0, 0),
    (0.2, 0.12, 0.12, 0, 0, 0),
    (0.3, 1.0, 1.0, 0, 0.2, 0),
    (0.08, 0.45, 0.4, 0, 0.1, 0),
    (0.6, 0.55, 0.35, 0, 0, 0),
    (0.75, 0.4, 0.7, 0, 0, 0),
    (0.3, 0.3, 0.3, 0, 0, 0),
]
EE_INERTIA = (0.09, 0.05, 0.12, 0, 0, 0)
SATELLITE_MASS, SATELLITE_INERTIA = 500.0, np.diag([79.0, 79.0, 117.0])
MOUNT = np.array([0.2, 0.2, 0.2])


def _tensor(ixx, iyy, izz, ixy, ixz, iyz):
    return np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]], dtype=float)


def _dh_after_joint(offset, lam, length, alpha):
    """Frame i seen from the joint-i frame (frame i-1 turned by q_i):
    Rz(offset) Tz(lambda) Tx(L) Rx(alpha)."""
    rz = pin.SE3(pin.utils.rpyToMatrix(0.0, 0.0, offset), np.zeros(3))
    tz = pin.SE3(np.eye(3), np.array([0.0, 0.0, lam]))
    tx = pin.SE3(np.eye(3), np.array([length, 0.0, 0.0]))
    rx = pin.SE3(pin.utils.rpyToMatrix(alpha, 0.0, 0.0), np.zeros(3))
    return rz * tz * tx * rx


def build_model() -> tuple[pin.Model, int]:
    """The Pinocchio model (free-flyer base at the satellite CoM, 7 revolute-z joints) and
    the id of its operational frame ``ee`` (frame 7 then Tz(0.175))."""
    model = pin.Model()
    model.gravity = pin.Motion.Zero()  # no gravity in orbit
    base = model.addJoint(0, pin.JointModelFreeFlyer(), pin.SE3.Identity(), "satellite")
    model.appendBodyToJoint(base, pin.Inertia(SATELLITE_MASS, np.zeros(3), SATELLITE_INERTIA), pin.SE3.Identity())
    parent, placement = base, pin.SE3(np.eye(3), MOUNT)  # frame 0 at the mounting point
    for i, (offset, lam, length, alpha) in enumerate(DH):
        joint = model.addJoint(parent, pin.JointModelRZ(), placement, f"joint{i + 1}")
        frame_i = _dh_after_joint(offset, lam, length, alpha)  # in the joint frame
        com, mass = COM[i]
        # Table 2's vector starts at the origin of frame i-1 = the joint frame origin,
        # but is expressed in frame i axes.
        com_joint = frame_i.rotation @ np.array(com)
        inertia_joint = frame_i.rotation @ _tensor(*INERTIA[i]) @ frame_i.rotation.T
        model.appendBodyToJoint(joint, pin.Inertia(mass, com_joint, inertia_joint), pin.SE3.Identity())
        if i == len(DH) - 1:
            ee_com = frame_i.act(np.array(EE_COM))
            ee_inertia = frame_i.rotation @ _tensor(*EE_INERTIA) @ frame_i.rotation.T
            model.appendBodyToJoint(joint, pin.Inertia(EE_MASS, ee_com, ee_inertia), pin.SE3.Identity())
            ee_placement = frame_i * pin.SE3(np.eye(3), np.array([0.0, 0.0, EE_LAMBDA]))
            ee_frame = model.addFrame(pin.Frame("ee", joint, ee_placement, pin.FrameType.OP_FRAME))
        parent, placement = joint, frame_i
    return model, ee_frame


def configuration(p_base, R_base, q, model: pin.Model | None = None) -> np.ndarray:
    """Pinocchio configuration (7 + N,): position, quaternion [x, y, z, w], joint angles. A
    ``model``'s unbounded joints (a URDF's ``continuous`` joints: ``nq`` = 2) have each angle
    written ``(cos q, sin q)``."""
    quat = pin.Quaternion(np.asarray(R_base)).coeffs()  # x, y, z, w
    q = np.asarray(q, dtype=float)
    if model is not None:  # joint 0 is the universe, joint 1 the free flyer
        q = np.concatenate(
            [[np.cos(angle), np.sin(angle)] if joint.nq == 2 else [angle] for joint, angle in zip(model.joints[2:], q)]
        )
    return np.concatenate([np.asarray(p_base), quat, q])


def velocity_map(R_base, n_joints: int = 7) -> np.ndarray:
    """T (6 + N, 6 + N) with ``v_pin = T x_v``; orthogonal, so ``x_v = T.T v_pin``."""
    T = np.eye(6 + n_joints)
    T[:3, :3] = np.asarray(R_base).T
    T[3:6, 3:6] = np.asarray(R_base).T
    return T


def frame_acceleration_offset(R_base, V_base, n_joints: int = 7) -> np.ndarray:
    """c (6 + N,) with ``a_pin = T xdot_v + c``: the body-frame derivative of ``R^T v_s``
    picks up ``-R^T (w_s x v_s)``."""
    R, v_s, w_s = np.asarray(R_base), np.asarray(V_base[:3]), np.asarray(V_base[3:])
    c = np.zeros(6 + n_joints)
    c[:3] = -R.T @ np.cross(w_s, v_s)
    return c


def dynamic_jacobian(model: pin.Model, data: pin.Data, ee_frame: int, state) -> tuple[np.ndarray, np.ndarray]:
    """``(J_dyn (6, N), J_ee (6, 6 + N))`` at ``state`` (a ``random_states.RandomState``), from
    Pinocchio's EE frame Jacobian and centroidal momentum matrix, world axes at the EE point,
    our velocity convention: the EE twist per joint rate when the momentum stays zero."""
    n_joints = len(state.q)
    T = velocity_map(state.R_base, n_joints)
    qp = configuration(state.p_base, state.R_base, state.q, model)
    J_ee = pin.computeFrameJacobian(model, data, qp, ee_frame, pin.LOCAL_WORLD_ALIGNED) @ T
    A = pin.computeCentroidalMap(model, data, qp) @ T  # momentum about the CoM, world axes
    base_velocity_per_qd = -np.linalg.solve(A[:, :6], A[:, 6:])
    return J_ee[:, 6:] + J_ee[:, :6] @ base_velocity_per_qd, J_ee
