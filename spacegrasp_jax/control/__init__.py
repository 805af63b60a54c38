"""Controllers: the admittance (active 6-DoF F/T) law, the Cartesian law, joint PID, gains."""

from spacegrasp_jax.control.gains import Gains, GainsError, load_gains, make_gains, paper_gains, tuned_gains

CONTROLLERS = ("admittance", "cartesian")

__all__ = ["CONTROLLERS", "Gains", "GainsError", "load_gains", "make_gains", "paper_gains", "tuned_gains"]
