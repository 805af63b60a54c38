"""Tuning the admittance, Cartesian and joint PID gains: one driver runs every method.

* [`spacegrasp_jax.tuning.objective`][tuning.objective] - the objective (capture margins, or weighted final errors, RMS tracking, smooth peak torque).
* [`spacegrasp_jax.tuning.parameters`][tuning.parameters] - log-gain parameters and the freeze mask.
* [`spacegrasp_jax.tuning.protocol`][tuning.protocol] - what a tuning method is: ask, tell, its state.
* [`spacegrasp_jax.tuning.problem`][tuning.problem] - the training problem that answers a method's requests.
* [`spacegrasp_jax.tuning.driver`][tuning.driver] - the one loop: validation, best point, checkpoints, resume, Ctrl-C.
* [`spacegrasp_jax.tuning.tune`][tuning.tune] - the run's settings, the gradient method and its programs, the method registry.
* [`spacegrasp_jax.tuning.cmaes`][tuning.cmaes] - CMA-ES.
* [`spacegrasp_jax.tuning.run`][tuning.run] - the ``spacegrasp tune`` job: files, evaluation, plots.
* [`spacegrasp_jax.tuning.ceiling`][tuning.ceiling] - what caps a campaign's success: each failed capture tuned alone.
"""

from spacegrasp_jax.tuning.cmaes import CMAESSettings
from spacegrasp_jax.tuning.driver import optimise
from spacegrasp_jax.tuning.objective import Objective, Weights, objective_parts, smooth_max
from spacegrasp_jax.tuning.parameters import GROUPS, gains_from_params, initial_params, make_mask
from spacegrasp_jax.tuning.protocol import Answers, Outcome, Request, TuningMethod
from spacegrasp_jax.tuning.tune import (
    METHODS,
    GradientSettings,
    TuneConfig,
    make_method,
    make_optimizer,
    make_problem,
    setup,
)

__all__ = [
    "GROUPS",
    "METHODS",
    "Answers",
    "CMAESSettings",
    "GradientSettings",
    "Objective",
    "Outcome",
    "Request",
    "TuneConfig",
    "TuningMethod",
    "Weights",
    "gains_from_params",
    "initial_params",
    "make_mask",
    "make_method",
    "make_optimizer",
    "make_problem",
    "objective_parts",
    "optimise",
    "setup",
    "smooth_max",
]
