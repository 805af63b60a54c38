"""The loop's frequency response (``analysis.frequency``): gain and phase margins of loops
whose margins are analytic, and the closed loop at a critical factor having its pole on
the circle the response is taken on. Its agreement with the eigenvalue margins of the
paper's linearised loop is in tests/test_stability.py."""

from __future__ import annotations

import math

import numpy as np
import pytest

from spacegrasp_jax.analysis.frequency import BrokenLoop, FrequencyError, bode, break_loop, loop_margins


def joint_velocity_loop(J=0.5, b=0.2, T=0.01, kp=2.0) -> tuple[BrokenLoop, float, float, float]:
    """One joint of inertia J (kg m^2) and viscous friction b (N m s/rad) under a velocity P
    gain kp (N m s/rad), torque held over T: ``qd' = a qd + (T / J) u``, ``a = 1 - b T / J``,
    ``u = -kp qd``. ``L(z) = k / (z - a)``, ``k = kp T / J``: the closed-loop pole ``a - c k``
    leaves the unit circle at ``-1`` for ``c = (1 + a) / k``, and ``|L| = 1`` where
    ``cos(w T) = (1 + a^2 - k^2) / (2 a)``, the phase margin ``180 deg - arg(e^{jwT} - a)``."""
    a, k = 1.0 - b * T / J, kp * T / J
    loop = BrokenLoop("joint", np.array([[a]]), np.array([[T / J]]), np.array([[-kp]]), T)
    theta = math.acos((1.0 + a * a - k * k) / (2.0 * a))
    phase_margin = 180.0 - math.degrees(math.atan2(math.sin(theta), math.cos(theta) - a))
    return loop, (1.0 + a) / k, phase_margin, theta / (2.0 * math.pi * T)


def test_a_joints_velocity_loop_has_its_analytic_gain_and_phase_margins():
    loop, gain_margin, phase_margin, crossover_hz = joint_velocity_loop()
    found = loop_margins(loop)
    assert found["gain_margins"]["increase"]["factor"] == pytest.approx(gain_margin, rel=1e-9)
    assert found["gain_margins"]["increase"]["frequency_hz"] == pytest.approx(50.0)  # the Nyquist frequency
    assert found["gain_margins"]["decrease"] is None  # the open loop is stable: no gain too low
    assert found["phase_margin"]["phase_margin_deg"] == pytest.approx(phase_margin, rel=1e-6)
    assert found["phase_margin"]["frequency_hz"] == pytest.approx(crossover_hz, rel=1e-6)
    # the closed loop at the margin has its pole on the unit circle
    assert np.max(np.abs(np.linalg.eigvals(loop.closed(gain_margin)))) == pytest.approx(1.0, abs=1e-12)


def test_a_delayed_loop_crosses_at_an_interior_frequency():
    """``L(z) = k / (z (z - a))`` (one period more of delay): the closed loop
    ``z^2 - a z + c k`` has complex poles of modulus ``sqrt(c k)``, on the circle at
    ``c = 1 / k``, at ``cos(w T) = a / 2``."""
    a, k = 0.5, 0.3
    loop = BrokenLoop("delayed", np.array([[a, 0.0], [1.0, 0.0]]), np.array([[1.0], [0.0]]), np.array([[0.0, -k]]), 1.0)
    found = loop_margins(loop)
    assert found["gain_margins"]["increase"]["factor"] == pytest.approx(1.0 / k, rel=1e-6)
    assert found["gain_margins"]["increase"]["frequency_hz"] == pytest.approx(
        math.acos(a / 2) / (2 * math.pi), rel=1e-6
    )
    assert found["phase_margin"] is None  # |L| < 1 everywhere: k < 1 - a


def test_an_unstable_open_loop_has_a_gain_too_low_as_well_as_one_too_high():
    """``L(z) = 1 / (z - 1.2)``: the closed-loop pole ``1.2 - c`` is inside for ``0.2 < c < 2.2``."""
    loop = BrokenLoop("unstable", np.array([[1.2]]), np.array([[1.0]]), np.array([[-1.0]]), 1.0)
    found = loop_margins(loop)
    assert found["gain_margins"]["increase"]["factor"] == pytest.approx(2.2, rel=1e-12)
    assert found["gain_margins"]["decrease"]["factor"] == pytest.approx(0.2, rel=1e-12)
    assert found["gain_margins"]["decrease"]["frequency_hz"] == 0.0


def test_a_loop_broken_from_its_jacobian_and_gain_sensitivity_is_the_loop():
    """A two-channel loop ``A(c) = A0 + c B C`` given as its Jacobian at ``c = 1`` and its
    derivative ``d A / d ln c = B C``: the broken loop closes back to ``A(c)`` at every ``c``,
    its critical factors put a closed-loop eigenvalue on the circle, and the Bode data are
    ``L = -g`` of the loci."""
    rng = np.random.default_rng(4)
    A0 = 0.6 * np.linalg.qr(rng.normal(size=(6, 6)))[0]
    B, C = rng.normal(size=(6, 2)), 0.3 * rng.normal(size=(2, 6))
    loop = break_loop(A0 + B @ C, B @ C, "two", 0.01, radius=1.0)
    assert loop.channels == 2
    for c in (0.3, 1.0, 2.5):
        np.testing.assert_allclose(loop.closed(c), A0 + c * B @ C, atol=1e-12)
    found = loop_margins(loop)
    for item in found["critical_factors"]:
        radius = np.max(np.abs(np.linalg.eigvals(loop.closed(item["factor"]))))
        assert radius >= 1.0 - 1e-6
        assert np.min(np.abs(np.abs(np.linalg.eigvals(loop.closed(item["factor"]))) - 1.0)) < 1e-6
    data = bode(loop, np.array([1.0, 10.0]))
    g = np.linalg.eigvals(loop.transfer(10.0))
    assert np.sort(data["magnitude_db"][1]) == pytest.approx(np.sort(20 * np.log10(np.abs(g))), rel=1e-9)
    with pytest.raises(FrequencyError, match="does not change the loop"):
        break_loop(A0, np.zeros((6, 6)), "none", 0.01)
