"""spacegrasp-jax: a differentiable simulator of a free-floating space manipulator capturing
a satellite (Basmadji et al., active 6-DoF force/torque control on the Dynamic Jacobian).

Importing the package enables float64 in JAX (the dynamics need it, DESIGN.md) and asks
XLA:CPU to compile small loops into single kernels (``spacegrasp_jax.compilation``).
"""

from spacegrasp_jax.compilation import request_loop_kernels

request_loop_kernels()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

from spacegrasp_jax.dynamics import (  # noqa: E402
    bias_forces,
    dynamic_jacobian,
    dynamic_jacobian_ee,
    forward_dynamics,
    inverse_dynamics,
    kinetic_energy,
    mass_matrix,
    mass_matrix_and_bias,
    momentum_jacobians,
    momentum_matrix,
    system_com,
    system_momentum,
)
from spacegrasp_jax.kinematics import ee_jacobians, ee_pose, forward_kinematics  # noqa: E402
from spacegrasp_jax.model import (  # noqa: E402
    PAPER_Q_INIT,
    Robot,
    RobotConfigError,
    load_robot,
    make_robot,
    paper_robot,
)

__version__ = "0.1.0"

__all__ = [
    "PAPER_Q_INIT",
    "Robot",
    "RobotConfigError",
    "bias_forces",
    "dynamic_jacobian",
    "dynamic_jacobian_ee",
    "ee_jacobians",
    "ee_pose",
    "forward_dynamics",
    "inverse_dynamics",
    "forward_kinematics",
    "kinetic_energy",
    "load_robot",
    "make_robot",
    "mass_matrix",
    "mass_matrix_and_bias",
    "momentum_jacobians",
    "momentum_matrix",
    "paper_robot",
    "system_com",
    "system_momentum",
]
