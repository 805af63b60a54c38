"""Right pseudoinverse of the (6, N) Dynamic Jacobian, applied to a twist (eqs 17, 21)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from spacegrasp_jax.core.linalg import solve_spd
from spacegrasp_jax.core.spatial import matmul, matvec
from spacegrasp_jax.loop.control.groups import GainGroup

#: The gain group of a law with a pseudoinverse: the damping a mission sets at design time
#: to keep the pseudoinverse bounded near Dynamic-Jacobian singularities. It adds to the
#: law's own (static) ``pinv_damping``, so the paper's gains keep the exact law.
PINV_DAMPING = GainGroup(
    1,
    "as the Dynamic Jacobian's entries",
    "damping d of the pseudoinverse J^T (J J^T + d^2 1)^-1 (0: the exact pseudoinverse)",
    "eqs (17), (21)",
    default=0.0,
    positive=False,
    optional=True,
)


def pseudoinverse_apply(J: jax.Array, twist: jax.Array, damping=0.0) -> jax.Array:
    """``J^T (J J^T + damping^2 1)^-1 twist`` (N,) for ``J`` (6, N) and ``twist`` (6,).

    With ``damping = 0`` this is the exact Moore-Penrose pseudoinverse, valid (and with
    finite gradients) wherever ``J`` has full row rank, as along the paper's motion; a
    positive ``damping`` (same units as ``J``'s entries) gives the damped least-squares
    inverse, which stays bounded near singular configurations.
    """
    gram = matmul(J, J.T) + damping**2 * jnp.eye(J.shape[0], dtype=J.dtype)
    return matvec(J.T, solve_spd(gram, twist))
