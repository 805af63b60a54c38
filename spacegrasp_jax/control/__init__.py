"""Controllers: the admittance (active 6-DoF F/T) law, the Cartesian law, joint PID, gains."""

from spacegrasp_jax.control.gains import (
    GAINS_USED,
    Gains,
    GainsError,
    UnusedGainsWarning,
    load_gains,
    make_gains,
    paper_gains,
    tuned_gains,
)

#: The controllers' names, everywhere (command line, files, tables, figures).
CONTROLLERS = ("admittance", "cartesian")

__all__ = [
    "CONTROLLERS",
    "GAINS_USED",
    "Gains",
    "GainsError",
    "UnusedGainsWarning",
    "load_gains",
    "make_gains",
    "paper_gains",
    "tuned_gains",
]
