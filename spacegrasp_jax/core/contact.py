"""The contact sphere of eq 20 and the force/torque sensor of eqs 18-19.

The sphere (radius ``r``, stiffness ``k`` in N m^2) is fixed in the LAR frame. Inside it, a
force pushes the end-effector point radially outwards from the centre:

    f = k (r - d) / r^3 * p / d,    d = |p| < r,    p = EE point - sphere centre      (eq 20)

and no torque acts. The exact law has a kink at the boundary (the force magnitude's slope
jumps from ``-k/r^3`` to 0) and an undefined direction at the centre. The smooth variant
replaces ``max(r - d, 0)`` by a softplus of width ``1/sharpness`` and ``d`` in the direction
by ``sqrt(d^2 + 1/sharpness^2)``: it is C-infinity, has finite gradients everywhere including
the centre (where it is zero), and tends to the exact law as ``sharpness`` (1/m) grows.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from spacegrasp_jax.core.spatial import cross, matvec


def contact_force_exact(p_from_centre: jax.Array, radius, stiffness) -> jax.Array:
    """Eq 20: force (3,) N on the EE point, in the axes of ``p_from_centre`` (3,) m.

    At the centre itself the direction is undefined; the force is set to zero there, with
    a guarded division so that gradients stay finite (not meaningful) at that single point.
    """
    distance_squared = jnp.sum(p_from_centre * p_from_centre)
    at_centre = distance_squared == 0.0
    distance = jnp.sqrt(jnp.where(at_centre, 1.0, distance_squared))
    magnitude = stiffness * jnp.maximum(radius - distance, 0.0) / radius**3
    return jnp.where(at_centre, 0.0, magnitude / distance) * p_from_centre


def contact_force_smooth(p_from_centre: jax.Array, radius, stiffness, sharpness) -> jax.Array:
    """Smooth variant of eq 20: force (3,) N, same axes as ``p_from_centre`` (3,) m.

    ``sharpness`` (1/m) sets the width ``1/sharpness`` of the softened boundary and of the
    regularised centre; ``sharpness -> inf`` recovers [`contact_force_exact()`][spacegrasp_jax.core.contact.contact_force_exact] for
    ``p != 0``. Outside the sphere the force decays like ``exp(-sharpness (d - r))``.
    """
    width = 1.0 / sharpness
    distance = jnp.sqrt(jnp.sum(p_from_centre * p_from_centre) + width**2)
    penetration = width * jax.nn.softplus((radius - distance) / width)
    return stiffness * penetration / radius**3 * p_from_centre / distance


def sensor_wrench(force_fts: jax.Array, p_ee_fts: jax.Array) -> tuple[jax.Array, jax.Array]:
    """What the F/T sensor between link 7 and the EE measures when ``force_fts`` (3,) N acts
    at the EE point, ``p_ee_fts`` (3,) m from the sensor, both in sensor axes: the force and
    its moment about the sensor point, ``(f, p x f)`` (N, N m)."""
    return force_fts, cross(p_ee_fts, force_fts)


def wrench_at_ee(force_fts: jax.Array, torque_fts: jax.Array, p_ee_fts: jax.Array) -> jax.Array:
    """Eq 18: the sensor wrench moved from the sensor point to the EE point, ``[f; n]`` (6,)
    in sensor axes. The moment about the EE point is ``n_fts + f x p_ee`` (the paper's
    ``p (x) f`` read with the sign that makes a pure force at the EE point give zero moment
    there, as it must)."""
    return jnp.concatenate([force_fts, torque_fts + cross(force_fts, p_ee_fts)])


def rotate_wrench(R_a_b: jax.Array, wrench_b: jax.Array) -> jax.Array:
    """Eq 19: a wrench ``[f; n]`` (6,) in frame ``b`` axes rotated into frame ``a`` axes."""
    return matvec(R_a_b, wrench_b.reshape(2, 3)).reshape(6)
