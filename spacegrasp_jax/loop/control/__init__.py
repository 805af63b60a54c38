"""Controllers: the control laws, the joint PID after them, and the gains.

Each law implements [`ControlLaw`][spacegrasp_jax.loop.control.law.ControlLaw] (``init``,
``update``, ``log_fields`` and what it is: name, output, gain groups, style) and is listed
once in [`registry.LAWS`][spacegrasp_jax.loop.control.registry]:
[`Admittance`][spacegrasp_jax.loop.control.admittance.Admittance] and
[`Cartesian`][spacegrasp_jax.loop.control.cartesian.Cartesian], the paper's, command joint rates
to the joint [`PID`][spacegrasp_jax.loop.control.pid.PID];
[`Impedance`][spacegrasp_jax.loop.control.impedance.Impedance] commands joint torques.
[`chain()`][spacegrasp_jax.loop.control.law.chain] makes a law and its servo a
[`Controller`][spacegrasp_jax.loop.control.law.Controller]. Each law and the servo declare their
own gains (``AdmittanceGains``, ``CartesianGains``, ``ImpedanceGains``, ``PIDGains``: one
[`group()`][spacegrasp_jax.loop.control.groups.group] field a gain group), and
[`Gains`][spacegrasp_jax.loop.control.gains.Gains] holds them all in one set.
"""

from spacegrasp_jax.loop.control.admittance import Admittance, AdmittanceGains, AdmittanceState
from spacegrasp_jax.loop.control.cartesian import Cartesian, CartesianGains, CartesianState
from spacegrasp_jax.loop.control.gains import (
    GAINS_USED,
    NAMED_GAINS,
    Gains,
    GainsError,
    UnusedGainsWarning,
    load_gains,
    make_gains,
    missing_groups,
    named_gains,
    paper_gains,
    require_joints,
    required_groups,
    tuned_gains,
)
from spacegrasp_jax.loop.control.groups import GainGroup, group, view
from spacegrasp_jax.loop.control.impedance import Impedance, ImpedanceGains, ImpedanceState
from spacegrasp_jax.loop.control.law import ControlInputs, ControlLaw, Controller, ControllerState, Output, chain
from spacegrasp_jax.loop.control.pid import PID, PIDGains, PIDState
from spacegrasp_jax.loop.control.registry import (
    CONTROLLERS,
    GAIN_GROUPS,
    LAWS,
    PAPER_CONTROLLERS,
    as_controller,
    law_named,
)

__all__ = [
    "CONTROLLERS",
    "GAIN_GROUPS",
    "GAINS_USED",
    "LAWS",
    "NAMED_GAINS",
    "PAPER_CONTROLLERS",
    "PID",
    "Admittance",
    "AdmittanceGains",
    "AdmittanceState",
    "Cartesian",
    "CartesianGains",
    "CartesianState",
    "ControlInputs",
    "ControlLaw",
    "Controller",
    "ControllerState",
    "GainGroup",
    "Impedance",
    "ImpedanceGains",
    "ImpedanceState",
    "Output",
    "PIDGains",
    "PIDState",
    "as_controller",
    "chain",
    "group",
    "view",
    "law_named",
    "Gains",
    "GainsError",
    "UnusedGainsWarning",
    "load_gains",
    "make_gains",
    "missing_groups",
    "named_gains",
    "require_joints",
    "required_groups",
    "paper_gains",
    "tuned_gains",
]
