"""The paper's reference numbers that results are compared with (Basmadji et al., section 5).

Keys are the controllers' names (``"admittance"``, the paper's "active 6 DoF force/torque
control"; ``"cartesian"``, its "classical Cartesian control").
"""

from __future__ import annotations

#: Table 5: maximal absolute joint torques, joints 1-7 (N m).
MAX_ABS_TORQUE_NM = {
    "admittance": (1.50, 2.45, 1.68, 0.86, 1.10, 0.17, 0.036),
    "cartesian": (1.89, 4.21, 2.72, 0.72, 1.55, 0.35, 0.027),
}

__all__ = ["MAX_ABS_TORQUE_NM"]
