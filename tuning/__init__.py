"""Gradient-based tuning of the admittance, Cartesian and joint PID gains with optax.

* [`spacegrasp_jax.tuning.objective`][tuning.objective] - the objective (final errors, RMS tracking, smooth peak torque).
* [`spacegrasp_jax.tuning.parameters`][tuning.parameters] - log-gain parameters and the freeze mask.
* [`spacegrasp_jax.tuning.tune`][tuning.tune] - loss over a scenario batch, gradients, the resumable optimiser loop.
* [`spacegrasp_jax.tuning.run`][tuning.run] - the ``spacegrasp tune`` job: files, evaluation, plots.
"""

from spacegrasp_jax.tuning.objective import Objective, Weights, objective_parts, smooth_max
from spacegrasp_jax.tuning.parameters import GROUPS, gains_from_params, initial_params, make_mask
from spacegrasp_jax.tuning.tune import TuneConfig, make_optimizer, optimise, setup

__all__ = [
    "GROUPS",
    "Objective",
    "TuneConfig",
    "Weights",
    "gains_from_params",
    "initial_params",
    "make_mask",
    "make_optimizer",
    "objective_parts",
    "optimise",
    "setup",
    "smooth_max",
]
