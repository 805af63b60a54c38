"""Controllers: the admittance (active 6-DoF F/T) law, the Cartesian law, joint PID, gains.

Each law is an object with ``init`` and ``update`` ([`spacegrasp_jax.control.law`][spacegrasp_jax.control.law]):
[`Admittance`][spacegrasp_jax.control.admittance.Admittance], [`Cartesian`][spacegrasp_jax.control.cartesian.Cartesian], and the joint [`PID`][spacegrasp_jax.control.pid.PID] stage after them.
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
from spacegrasp_jax.control.law import ControlInputs, law_named
from spacegrasp_jax.control.pid import PID, PIDState

#: The controllers' names, everywhere (command line, files, tables, figures).
CONTROLLERS = ("admittance", "cartesian")

__all__ = [
    "CONTROLLERS",
    "GAINS_USED",
    "PID",
    "Admittance",
    "AdmittanceState",
    "Cartesian",
    "CartesianState",
    "ControlInputs",
    "PIDState",
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
