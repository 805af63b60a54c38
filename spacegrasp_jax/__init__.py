"""spacegrasp-jax: a differentiable simulator of a free-floating space manipulator capturing
a satellite (Basmadji et al., active 6-DoF force/torque control on the Dynamic Jacobian).

Importing the package changes no process-wide setting. The package computes in float64 and
runs fastest on a CPU with loops compiled whole: call [`configure()`][spacegrasp_jax.compilation.configure] once, before JAX runs
anything (``spacegrasp_jax.compilation`` says what each setting does)::

    import spacegrasp_jax as sg
    sg.configure()
"""

from spacegrasp_jax.compilation import (
    CacheFolderError,
    Float64Required,
    compile_loops_whole,
    configure,
    enable_float64,
    use_compile_cache,
)
from spacegrasp_jax.dynamics import (
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
from spacegrasp_jax.kinematics import ee_jacobians, ee_pose, forward_kinematics
from spacegrasp_jax.model import (
    PAPER_Q_INIT,
    Robot,
    RobotConfigError,
    make_robot,
    paper_robot,
)
from spacegrasp_jax.robot_files import load_robot

__version__ = "0.1.0"

__all__ = [
    "CacheFolderError",
    "Float64Required",
    "PAPER_Q_INIT",
    "Robot",
    "RobotConfigError",
    "bias_forces",
    "compile_loops_whole",
    "configure",
    "dynamic_jacobian",
    "dynamic_jacobian_ee",
    "ee_jacobians",
    "ee_pose",
    "enable_float64",
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
    "use_compile_cache",
]
