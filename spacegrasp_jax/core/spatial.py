"""Rotations: skew matrices, elementary rotations, unit quaternions, ZYX Euler angles.

Conventions
-----------
* A rotation matrix ``R_a_b`` (3, 3) maps coordinates in frame ``b`` to frame ``a``:
  ``x_a = R_a_b @ x_b``.
* Unit quaternions are scalar-first ``[w, x, y, z]`` (4,) and represent the same
  body-to-inertial rotation as the matrix built by [`quat_to_rotation()`][spacegrasp_jax.core.spatial.quat_to_rotation].
* ZYX Euler angles are returned ordered ``[roll (about x), pitch (about y), yaw (about z)]``
  with ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (modelling notes, eq 14 pairing).

All functions are pure and work on a single element ([`skew()`][spacegrasp_jax.core.spatial.skew], [`cross()`][spacegrasp_jax.core.spatial.cross],
[`matvec()`][spacegrasp_jax.core.spatial.matvec] and [`matmul()`][spacegrasp_jax.core.spatial.matmul] also broadcast over leading axes); use ``jax.vmap`` for
batches.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero


def skew(v):
    """Cross-product matrix ``[v]x`` (..., 3, 3) of ``v`` (..., 3), such that
    ``skew(v) @ u == cross(v, u)``."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    zero = jnp.zeros_like(x)
    return jnp.stack(
        [
            jnp.stack([zero, -z, y], axis=-1),
            jnp.stack([z, zero, -x], axis=-1),
            jnp.stack([-y, x, zero], axis=-1),
        ],
        axis=-2,
    )


def _summed_matvec(A, x):
    # A @ x as a product and a sum over the last axis of A.
    return jnp.sum(A * x[..., None, :], axis=-1)


def _summed_matmul(A, B):
    return jnp.sum(A[..., :, :, None] * B[..., None, :, :], axis=-2)


@jax.custom_jvp
def matvec(A, x):
    """``A @ x`` for a small matrix ``A`` (..., m, n) and vector ``x`` (..., n), leading axes
    broadcast.

    It is written as a product and a sum, which XLA fuses with its neighbours, where a
    ``dot`` is a library call of its own on a CPU when loops run kernel by kernel (about 150
    of them per closed-loop step). Under ``vmap`` too: with loops compiled whole
    (``spacegrasp_jax.jobs.compilation``) a batch runs faster so than with batched ``dot`` calls.
    The derivative is products and sums too (its own rule, so that
    the transposes stay fused).
    """
    return _summed_matvec(A, x)


@jax.custom_jvp
def matmul(A, B):
    """``A @ B`` for small matrices ``A`` (..., m, k) and ``B`` (..., k, n), leading axes
    broadcast; as [`matvec()`][spacegrasp_jax.core.spatial.matvec]."""
    return _summed_matmul(A, B)


def _bilinear_jvp(product, summed):
    """Give the bilinear ``product`` ([`matvec()`][spacegrasp_jax.core.spatial.matvec] or [`matmul()`][spacegrasp_jax.core.spatial.matmul]) the derivative
    ``product(dA, B) + product(A, dB)``, written with ``summed``, its products-and-sums form."""

    @functools.partial(product.defjvp, symbolic_zeros=True)
    def jvp(primals, tangents):
        (A, B), (dA, dB) = primals, tangents
        value = product(A, B)
        tangent = jnp.zeros_like(value)
        if not isinstance(dA, SymbolicZero):
            tangent = tangent + summed(dA, B)
        if not isinstance(dB, SymbolicZero):
            tangent = tangent + summed(A, dB)
        return value, tangent


_bilinear_jvp(matvec, _summed_matvec)
_bilinear_jvp(matmul, _summed_matmul)


@jax.custom_jvp
def cross(a, b):
    """Cross product ``a x b`` of 3-vectors along the last axis (leading axes broadcast),
    as ``jnp.cross``.

    The derivative is written as products with the cross-product matrices of the primal
    vectors, ``d(a x b) = [a]x db - [b]x da``: elementwise products and sums, whose
    transposes XLA fuses. Differentiating ``jnp.cross`` instead transposes its six component
    slices into six zero-paddings, kernels of their own on a CPU (about a third of the
    kernels of a closed-loop step's reverse-mode derivative were such paddings).
    """
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return jnp.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


@functools.partial(cross.defjvp, symbolic_zeros=True)
def _cross_jvp(primals, tangents):
    a, b = primals
    da, db = tangents
    value = cross(a, b)
    tangent = jnp.zeros_like(value)
    if not isinstance(db, SymbolicZero):
        tangent = tangent + _summed_matvec(skew(a), db)
    if not isinstance(da, SymbolicZero):
        tangent = tangent - _summed_matvec(skew(b), da)
    return value, tangent


def symmetric_inverse(A):
    """The inverse of a symmetric (3, 3) matrix by its adjugate: its rows are cross products
    of ``A``'s columns over the determinant (elementwise, so XLA fuses it; no LAPACK call)."""
    c0, c1, c2 = jnp.unstack(A, axis=1)
    row0 = cross(c1, c2)
    return jnp.stack([row0, cross(c2, c0), cross(c0, c1)]) / jnp.sum(c0 * row0)


def rot_x(angle):
    """Rotation (3, 3) by ``angle`` [rad] about the x axis."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    one, zero = jnp.ones_like(c), jnp.zeros_like(c)
    return jnp.stack([jnp.stack([one, zero, zero]), jnp.stack([zero, c, -s]), jnp.stack([zero, s, c])])


def rot_y(angle):
    """Rotation (3, 3) by ``angle`` [rad] about the y axis."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    one, zero = jnp.ones_like(c), jnp.zeros_like(c)
    return jnp.stack([jnp.stack([c, zero, s]), jnp.stack([zero, one, zero]), jnp.stack([-s, zero, c])])


def rot_z(angle):
    """Rotation (3, 3) by ``angle`` [rad] about the z axis."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    one, zero = jnp.ones_like(c), jnp.zeros_like(c)
    return jnp.stack([jnp.stack([c, -s, zero]), jnp.stack([s, c, zero]), jnp.stack([zero, zero, one])])


def quat_to_rotation(quat):
    """Rotation matrix (3, 3) of a unit quaternion ``[w, x, y, z]`` (4,).

    The quaternion is normalised first, so slightly off-unit inputs (integration drift)
    still give an orthonormal matrix.
    """
    w, x, y, z = jnp.unstack(quat / jnp.linalg.norm(quat))
    return jnp.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotation_to_quat(R):
    """Unit quaternion ``[w, x, y, z]`` (4,) with ``w >= 0`` of a rotation matrix (3, 3).

    Shepperd's method: the branch is chosen by the largest of ``w, x, y, z`` so the
    square root never runs on a small number.
    """
    trace = R[0, 0] + R[1, 1] + R[2, 2]
    candidates = jnp.stack(
        [
            jnp.array([1 + trace, R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]),
            jnp.array([R[2, 1] - R[1, 2], 1 + 2 * R[0, 0] - trace, R[0, 1] + R[1, 0], R[0, 2] + R[2, 0]]),
            jnp.array([R[0, 2] - R[2, 0], R[0, 1] + R[1, 0], 1 + 2 * R[1, 1] - trace, R[1, 2] + R[2, 1]]),
            jnp.array([R[1, 0] - R[0, 1], R[0, 2] + R[2, 0], R[1, 2] + R[2, 1], 1 + 2 * R[2, 2] - trace]),
        ]
    )
    diagonal = jnp.array([1 + trace, 1 + 2 * R[0, 0] - trace, 1 + 2 * R[1, 1] - trace, 1 + 2 * R[2, 2] - trace])
    best = jnp.argmax(diagonal)
    quat = candidates[best] / (2 * jnp.sqrt(diagonal[best]))
    return quat * jnp.where(quat[0] < 0, -1.0, 1.0)


def quat_multiply(a, b):
    """Hamilton product ``a * b`` of two quaternions ``[w, x, y, z]`` (4,)."""
    aw, av = jnp.split(a, [1])
    bw, bv = jnp.split(b, [1])
    return jnp.concatenate([aw * bw - jnp.sum(av * bv, keepdims=True), aw * bv + bw * av + cross(av, bv)])


def quat_derivative(quat, omega_inertial):
    """Time derivative (4,) of a body-to-inertial quaternion for an angular velocity
    ``omega_inertial`` (3,) [rad/s] expressed in the inertial frame: ``0.5 [0, w] * quat``."""
    omega_quat = jnp.concatenate([jnp.zeros(1, dtype=quat.dtype), omega_inertial])
    return 0.5 * quat_multiply(omega_quat, quat)


def euler_zyx(R):
    """ZYX Euler angles ``[roll, pitch, yaw]`` (3,) [rad] of ``R = Rz(yaw) Ry(pitch) Rx(roll)``.

    Singular at pitch = +-pi/2 (gimbal lock); the paper's scenario stays far from it.
    """
    roll = jnp.arctan2(R[2, 1], R[2, 2])
    pitch = -jnp.arcsin(jnp.clip(R[2, 0], -1.0, 1.0))
    yaw = jnp.arctan2(R[1, 0], R[0, 0])
    return jnp.stack([roll, pitch, yaw])


def euler_zyx_to_rotation(angles):
    """Rotation (3, 3) ``Rz(yaw) Ry(pitch) Rx(roll)`` of ``angles = [roll, pitch, yaw]`` (3,)."""
    return matmul(matmul(rot_z(angles[2]), rot_y(angles[1])), rot_x(angles[0]))


def rotation_log(R):
    """Rotation vector (3,) [rad] (axis times angle) of a rotation matrix, for angles < pi.

    ``angle = atan2(sin, cos)`` with ``sin`` from the skew part; near the identity the
    factor ``angle / (2 sin(angle))`` is replaced by its series ``1/2 + sin^2/12`` (no square
    root), so the value and the gradient stay finite there.
    """
    vee = jnp.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    cos_angle = (jnp.trace(R) - 1.0) / 2.0
    sin_squared = jnp.dot(vee, vee) / 4.0
    small = (sin_squared < 1e-12) & (cos_angle > 0.0)  # near the identity, not a half turn
    safe_sin = jnp.sqrt(jnp.where(small, 1.0, sin_squared))
    angle = jnp.arctan2(safe_sin, cos_angle)
    factor = jnp.where(small, 0.5 + sin_squared / 12.0, angle / (2.0 * safe_sin))
    return factor * vee


def euler_rates_to_body(angles):
    """``T_eul`` (3, 3) of eq 10: maps ZYX Euler-angle rates ``[roll, pitch, yaw]_dot`` to the
    angular velocity in the rotated (body) frame, ``w_body = T_eul @ angles_dot``.

    Args:
        angles: (3,) rad, ``[roll, pitch, yaw]`` of ``R = Rz(yaw) Ry(pitch) Rx(roll)``.
    """
    roll, pitch = angles[0], angles[1]
    cr, sr = jnp.cos(roll), jnp.sin(roll)
    cp, sp = jnp.cos(pitch), jnp.sin(pitch)
    one, zero = jnp.ones_like(cr), jnp.zeros_like(cr)
    return jnp.stack(
        [
            jnp.stack([one, zero, -sp]),
            jnp.stack([zero, cr, sr * cp]),
            jnp.stack([zero, -sr, cr * cp]),
        ]
    )


def rotation_exp(vector):
    """Rotation (3, 3) of a rotation vector (3,) [rad] (Rodrigues), finite with finite
    gradients at zero (series for small angles)."""
    angle_squared = jnp.dot(vector, vector)
    small = angle_squared < 1e-12
    safe = jnp.where(small, 1.0, angle_squared)
    angle = jnp.sqrt(safe)
    a = jnp.where(small, 1.0 - angle_squared / 6.0, jnp.sin(angle) / angle)
    b = jnp.where(small, 0.5 - angle_squared / 24.0, (1.0 - jnp.cos(angle)) / safe)
    K = skew(vector)
    return jnp.eye(3, dtype=vector.dtype) + a * K + b * K @ K
