"""spacegrasp-jax: a differentiable simulator of a free-floating space manipulator capturing
a satellite (Basmadji et al., active 6-DoF force/torque control on the Dynamic Jacobian).

Importing the package changes no process-wide setting. The package computes in float64 and
runs fastest on a CPU with loops compiled whole: call [`configure()`][spacegrasp_jax.jobs.compilation.configure] once, before JAX runs
anything (``spacegrasp_jax.jobs.compilation`` says what each setting does)::

    import spacegrasp_jax as sg
    sg.configure()
"""

import importlib
import warnings

from spacegrasp_jax.core.dynamics import (
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
from spacegrasp_jax.core.kinematics import ee_jacobians, ee_pose, forward_kinematics
from spacegrasp_jax.core.model import (
    PAPER_Q_INIT,
    Robot,
    RobotConfigError,
    make_robot,
    paper_robot,
)
from spacegrasp_jax.core.precision import Float64Required, enable_float64
from spacegrasp_jax.core.robot_files import load_robot
from spacegrasp_jax.jobs.compilation import (
    CacheFolderError,
    compile_loops_whole,
    configure,
    use_compile_cache,
)

__version__ = "0.1.0"

#: The modules that moved into the layer folders, and their folder: ``spacegrasp_jax.simulate``
#: is now ``spacegrasp_jax.loop.simulate``.
MOVED_MODULES = {
    **dict.fromkeys(
        (
            "spatial linalg tangents precision inputs model robot_files urdf mjcf kinematics dynamics contact "
            "target integrator trajectory joint_limits"
        ).split(),
        "core",
    ),
    **dict.fromkeys("scenario perturbations metrics statistics criteria plausibility".split(), "envelope"),
    **dict.fromkeys("simulate stages realism control".split(), "loop"),
    **dict.fromkeys(
        ("compilation executable_store runfiles batching paper anatomy experiment montecarlo records campaign").split(),
        "jobs",
    ),
    **dict.fromkeys("margins stability worstcase sweep plots animation export".split(), "analysis"),
}


def __getattr__(name: str):
    """A module by the name it had before the layer folders (``spacegrasp_jax.campaign``, or
    ``from spacegrasp_jax import campaign``): the module, with a ``DeprecationWarning`` naming
    where it lives now. ``import spacegrasp_jax.campaign`` itself no longer works."""
    if name not in MOVED_MODULES:
        raise AttributeError(f"module 'spacegrasp_jax' has no attribute {name!r}")
    where = f"spacegrasp_jax.{MOVED_MODULES[name]}.{name}"
    warnings.warn(f"spacegrasp_jax.{name} is now {where}", DeprecationWarning, stacklevel=2)
    return importlib.import_module(where)


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
