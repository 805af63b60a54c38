"""Scalar measures of a rollout, from its :class:`~spacegrasp_jax.simulate.Log`.

Pure ``jnp`` functions of one (unbatched) log: they run on NumPy arrays too, and under
``jit``/``vmap``/``grad``. "Final" means the last logged step, ``t = duration - dt``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from spacegrasp_jax import spatial


def safe_norm(x, axis=-1):
    """Euclidean norm along ``axis`` whose gradient is 0 (not NaN) at exactly zero: errors
    and forces do hit exact zeros (the start of a run; a contact force that underflows).
    A non-finite ``x`` gives a non-finite norm."""
    squared = jnp.sum(x * x, axis=axis)
    positive = squared > 0.0
    # Not positive: 0 (whose branch has gradient 2x = 0) or NaN, passed through.
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, squared, 1.0)), squared)


def position_error(log):
    """(N,) m, norm of the EE position error in LAR at every step."""
    return safe_norm(log.pose_ee[:, :3] - log.pose_des[:, :3])


def orientation_error(log):
    """(N,) rad, angle of the rotation between the desired and the actual EE orientation."""

    def angle(euler, euler_des):
        R_error = spatial.euler_zyx_to_rotation(euler_des).T @ spatial.euler_zyx_to_rotation(euler)
        return safe_norm(spatial.rotation_log(R_error))

    return jax.vmap(angle)(log.pose_ee[:, 3:], log.pose_des[:, 3:])


def final_position_error(log):
    """() m, EE position error in LAR at the end of the run."""
    return position_error(log)[-1]


def final_orientation_error(log):
    """() rad, EE orientation error at the end of the run."""
    return orientation_error(log)[-1]


def rms_position_error(log):
    """() m, root-mean-square EE position tracking error over the run."""
    return jnp.sqrt(jnp.mean(position_error(log) ** 2))


def max_abs_torque(log):
    """(7,) N m, ``max_t |u_i(t)|`` per joint (Table 5)."""
    return jnp.max(jnp.abs(log.u), axis=0)


def contact_force_norm(log):
    """(N,) N, magnitude of the contact force."""
    return safe_norm(log.contact_force)


def first_contact_time(log):
    """() s, first time the contact force is non-zero; NaN if the EE never touches."""
    touching = contact_force_norm(log) > 0.0
    return jnp.where(jnp.any(touching), log.t[jnp.argmax(touching)], jnp.nan)


def summary(log) -> dict:
    """The per-controller numbers of ``summary.json`` (plain floats and lists)."""
    first_contact = float(first_contact_time(log))
    return {
        "max_abs_torque_Nm": [float(x) for x in max_abs_torque(log)],
        "final_position_error_m": float(final_position_error(log)),
        "final_orientation_error_rad": float(final_orientation_error(log)),
        "rms_position_error_m": float(rms_position_error(log)),
        "max_contact_force_N": float(jnp.max(contact_force_norm(log))),
        "first_contact_s": None if first_contact != first_contact else first_contact,
        "max_linear_momentum_Ns": float(jnp.max(jnp.linalg.norm(log.momentum[:, :3], axis=-1))),
        "max_angular_momentum_Nms": float(jnp.max(jnp.linalg.norm(log.momentum[:, 3:], axis=-1))),
        "max_base_speed_mps": float(jnp.max(jnp.linalg.norm(log.V_base[:, :3], axis=-1))),
        "max_base_rate_radps": float(jnp.max(jnp.linalg.norm(log.V_base[:, 3:], axis=-1))),
    }
