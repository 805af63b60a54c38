"""Controllers: the control laws, the joint PID after them, and the gains.

Each law implements [`ControlLaw`][spacegrasp_jax.control.law.ControlLaw] (``init``,
``update``, ``log_fields`` and what it is: name, output, gain groups, style) and is listed
once in [`registry.LAWS`][spacegrasp_jax.control.registry]:
[`Admittance`][spacegrasp_jax.control.admittance.Admittance] and
[`Cartesian`][spacegrasp_jax.control.cartesian.Cartesian], the paper's, command joint rates
to the joint [`PID`][spacegrasp_jax.control.pid.PID];
[`Impedance`][spacegrasp_jax.control.impedance.Impedance] commands joint torques.
[`chain()`][spacegrasp_jax.control.law.chain] makes a law and its servo a
[`Controller`][spacegrasp_jax.control.law.Controller].
"""

from spacegrasp_jax.control.admittance import Admittance, AdmittanceState
from spacegrasp_jax.control.cartesian import Cartesian, CartesianState
from spacegrasp_jax.control.gains import (
    GAINS_USED,
    Gains,
    GainsError,
    UnusedGainsWarning,
    load_gains,
    make_gains,
    paper_gains,
    require_joints,
    tuned_gains,
)
from spacegrasp_jax.control.impedance import Impedance, ImpedanceState
from spacegrasp_jax.control.law import ControlInputs, ControlLaw, Controller, ControllerState, Output, chain
from spacegrasp_jax.control.pid import PID, PIDState
from spacegrasp_jax.control.registry import (
    CONTROLLERS,
    LAWS,
    PAPER_CONTROLLERS,
    as_controller,
    law_named,
)

__all__ = [
    "CONTROLLERS",
    "GAINS_USED",
    "LAWS",
    "PAPER_CONTROLLERS",
    "PID",
    "Admittance",
    "AdmittanceState",
    "Cartesian",
    "CartesianState",
    "ControlInputs",
    "ControlLaw",
    "Controller",
    "ControllerState",
    "Impedance",
    "ImpedanceState",
    "Output",
    "PIDState",
    "as_controller",
    "chain",
    "law_named",
    "Gains",
    "GainsError",
    "UnusedGainsWarning",
    "load_gains",
    "make_gains",
    "require_joints",
    "paper_gains",
    "tuned_gains",
]
