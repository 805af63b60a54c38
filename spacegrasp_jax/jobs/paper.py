"""The paper's reference numbers that results are compared with (Basmadji et al., section 5).

Keys are the paper's two controllers' names (``"admittance"``, the paper's "active 6 DoF
force/torque control"; ``"cartesian"``, its "classical Cartesian control"); each law holds
its own row ([`ControlLaw.paper_max_abs_torque_Nm`][spacegrasp_jax.loop.control.law.ControlLaw]).
"""

from __future__ import annotations

from spacegrasp_jax.loop.control.registry import LAWS, PAPER_CONTROLLERS

#: Table 5: maximal absolute joint torques, joints 1-7 (N m).
MAX_ABS_TORQUE_NM = {name: LAWS[name].paper_max_abs_torque_Nm for name in PAPER_CONTROLLERS}

__all__ = ["MAX_ABS_TORQUE_NM"]
