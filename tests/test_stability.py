"""Linear stability of the closed loop (``spacegrasp_jax.analysis.stability``).

The eigen-analysis is checked on loops whose poles are known in closed form (a sampled
oscillator; a velocity PID, the project's own, on a rigid inertia), then on the paper's
arm: the period map's Jacobian and its gain derivatives against central differences, the
momentum and centre of mass as conserved quantities of the map out of contact, and the
linear gain margin against the same loop run in the time domain.
"""

from __future__ import annotations

import dataclasses
import math
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from compile_labels import CompileLabels

from spacegrasp_jax.analysis import margins, stability
from spacegrasp_jax.envelope.scenario import paper_scenario
from spacegrasp_jax.jobs import compilation
from spacegrasp_jax.loop.control import paper_gains
from spacegrasp_jax.loop.control.pid import PIDState, pid_torque
from spacegrasp_jax.loop.realism import flight
from spacegrasp_jax.loop.simulate import RunSpec


def _linearisation(jacobian, sensitivity=None, period_s=1e-3):
    n = jacobian.shape[0]
    return stability.Linearisation(
        jacobian=np.asarray(jacobian),
        sensitivity=np.zeros((2, n, n)) if sensitivity is None else np.asarray(sensitivity),
        names=tuple(f"x[{i}]" for i in range(n)),
        period_s=period_s,
        residual=0.0,
        invariant_rows=np.zeros((0, n)),
        contact_force_N=0.0,
        clearance_m=1.0,
        free=False,
        largest_rate_radps=0.0,
    )


@pytest.mark.parametrize("frequency_hz, damping", [(3.0, 0.2), (40.0, 0.7), (0.5, -0.05)])
def test_a_sampled_oscillator_has_its_frequency_and_damping(frequency_hz, damping):
    """``x'' + 2 zeta w x' + w^2 x = 0`` sampled exactly at T: lambda = exp(s T)."""
    w, period = 2 * math.pi * frequency_hz, 2e-3
    A = scipy.linalg.expm(period * np.array([[0.0, 1.0], [-(w**2), -2 * damping * w]]))
    found = stability.modes(_linearisation(A, period_s=period))
    np.testing.assert_allclose(found.frequency_hz, frequency_hz, rtol=1e-9)
    np.testing.assert_allclose(found.damping_ratio, damping, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(found.growth_rate_per_s, -damping * w, rtol=1e-9)
    assert (found.fastest_growth_per_s > 0) == (damping < 0)


# ---- the project's PID on a rigid inertia: the closed loop's characteristic polynomial ----------

DT, INERTIA = 1e-3, 0.5  # s, kg m^2


def _pid_on_an_inertia(kp, ki, kd):
    """The period map of the joint-rate PID (``pid_torque``, after its ramp) driving a rigid
    inertia (``J w' = u``, exact over the held step) towards rest; state ``(angle, rate,
    integral, previous error)``."""
    gains = types.SimpleNamespace(kp=kp, ki=ki, kd=kd)

    def advance(x):
        angle, rate, integral, previous = x
        torque, pid = pid_torque(gains, PIDState(integral, previous), -rate, 2.0, DT)
        angle = angle + rate * DT + torque * DT**2 / (2 * INERTIA)
        return jnp.stack([angle, rate + torque * DT / INERTIA, pid.integral, pid.previous_error])

    return advance


def _characteristic_roots(kp, ki, kd):
    """By the z-transform, ``z (z - 1)^2 + a (kp z (z - 1) + ki T z^2 + kd (z - 1)^2 / T) = 0``
    with ``a = T / J``, and the angle's own pole at 1."""
    a = DT / INERTIA
    cubic = [1.0, -2 + a * kp + a * ki * DT + a * kd / DT, 1 - a * kp - 2 * a * kd / DT, a * kd / DT]
    return np.concatenate([[1.0], np.roots(cubic)])


def _matched(found, expected):
    """``found`` reordered to ``expected`` by nearest neighbour (each used once)."""
    found, order = list(found), []
    for value in expected:
        nearest = int(np.argmin([abs(f - value) for f in found]))
        order.append(found.pop(nearest))
    return np.asarray(order)


PID_CASES = {"stable": (40.0, 150.0, 0.02), "oscillating": (100.0, 30000.0, 0.02), "unstable": (2100.0, 500.0, 0.1)}


@pytest.mark.parametrize("case", PID_CASES)
def test_a_velocity_pid_on_an_inertia_has_the_analytic_poles(case):
    kp, ki, kd = PID_CASES[case]
    jacobian = jax.jacfwd(_pid_on_an_inertia(kp, ki, kd))(jnp.zeros(4))
    # d jacobian / d ln c, the three gains times c, as Linearizer takes it (forward mode).
    pid_of = lambda log_c: jax.jacfwd(_pid_on_an_inertia(*(g * jnp.exp(log_c) for g in (kp, ki, kd))))(jnp.zeros(4))
    _, derivative = jax.jvp(pid_of, (0.0,), (1.0,))
    found = stability.modes(_linearisation(jacobian, np.stack([derivative, 0 * derivative]), period_s=DT))
    expected = _characteristic_roots(kp, ki, kd)
    np.testing.assert_allclose(_matched(found.eigenvalues, expected), expected, atol=1e-10)
    assert (found.spectral_radius > 1.0) == (case == "unstable")
    assert found.neutral_removed == 0
    # Each pole's sensitivity against central differences of the analytic roots.
    h = 1e-6
    up, down = (_characteristic_roots(*(g * math.exp(s) for g in (kp, ki, kd))) for s in (h, -h))
    slopes = (_matched(up, expected) - _matched(down, expected)) / (2 * h)
    sensitivity = dict(zip(found.eigenvalues, found.sensitivity[0], strict=True))
    got = np.asarray([sensitivity[value] for value in _matched(found.eigenvalues, expected)])
    np.testing.assert_allclose(got, slopes, atol=1e-6 * max(1.0, np.max(np.abs(slopes))))


# ---- the paper's arm ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def flight_loop_at_2s(robot, short_scenario):
    """The flight-like loop (F/T low-pass, a period's delay, its own model, servo ticks
    inside the period) linearised at the end of a 2 s capture."""
    realism = flight()
    point, periods = stability.settled_state(
        RunSpec(robot, short_scenario, "admittance", realism=realism), paper_gains()
    )
    held = stability.holding(robot, short_scenario, point)
    return stability.Linearizer(robot, held, "admittance", realism, point, periods)


@pytest.mark.slow
def test_the_period_maps_jacobian_and_its_gain_derivatives_match_central_differences(flight_loop_at_2s):
    linearizer, gains = flight_loop_at_2s, paper_gains()
    found = linearizer(gains)
    n = len(found.names)
    assert n == 3 + 3 + 7 + 6 + 7 + 6 + 7 + 7 + 6 + 7  # plant, law (V_ref), PID, F/T reading, delay line
    advance = jax.jit(linearizer.advance)
    h = 1e-6
    columns = [
        (np.asarray(advance(jnp.zeros(n).at[i].set(h), gains)) - np.asarray(advance(jnp.zeros(n).at[i].set(-h), gains)))
        / (2 * h)
        for i in range(n)
    ]
    differences = np.stack(columns, axis=1)
    scale = np.max(np.abs(found.jacobian), axis=0, keepdims=True)  # per column: its coordinate's unit
    assert np.max(np.abs(found.jacobian - differences) / scale) < 1e-6
    step = 1e-5
    for index, loop in enumerate(margins.LOOPS):
        up, down = (
            linearizer(stability.scaled_gains(gains, "admittance", stability.factors(loop, math.exp(s))))
            for s in (step, -step)
        )
        derivative = (up.jacobian - down.jacobian) / (2 * step)
        assert np.max(np.abs(derivative)) > 0.0, f"the {loop} gain moves nothing"
        error = np.max(np.abs(found.sensitivity[index] - derivative)) / np.max(np.abs(derivative))
        assert error < 1e-5, loop


@pytest.fixture(scope="module")
def paper_capture_loop(robot):
    """The paper's loop at the end of its 17 s capture (admittance law, paper's gains)."""
    scenario, gains = paper_scenario(robot), paper_gains()
    point, periods = stability.settled_state(RunSpec(robot, scenario, "admittance"), gains)
    held = stability.holding(robot, scenario, point)
    linearizer = stability.Linearizer(robot, held, "admittance", None, point, periods)
    return robot, held, gains, point, periods, linearizer


@pytest.mark.slow
def test_another_operating_point_of_the_same_loop_reuses_the_linearisations_program(paper_capture_loop):
    """The point, the scenario's numbers, the period and the gains are the program's
    arguments: linearising the loop elsewhere compiles nothing, and gives the other point's
    Jacobian (one period of the map from the moved point, against central differences)."""
    robot, held, gains, point, periods, linearizer = paper_capture_loop
    heard = CompileLabels()
    with compilation.listening(heard):
        linearizer(gains)
        compiled_for_the_first = len(heard.labels)  # 0 if another test of this process compiled it
        plant = point.plant
        moved = dataclasses.replace(point, plant=dataclasses.replace(plant, q=plant.q + 0.05, qd=plant.qd + 0.01))
        elsewhere = stability.Linearizer(
            robot, stability.holding(robot, held, moved), "admittance", None, moved, periods - 100
        )
        other_gains = dataclasses.replace(gains, Kd=1.5 * gains.Kd)
        # JAX's own records, independent of the package's announcements: nothing is traced
        # or compiled for the second point (a program closing over its point would be).
        built = []

        def heard_build(event, duration_s, **_):
            if event in ("/jax/core/compile/jaxpr_trace_duration", "/jax/core/compile/backend_compile_duration"):
                built.append(event)

        jax.monitoring.register_event_duration_secs_listener(heard_build)
        try:
            found = elsewhere(other_gains)
        finally:
            jax.monitoring.unregister_event_duration_listener(heard_build)
        assert built == []
        assert len(heard.labels) == compiled_for_the_first
    assert heard.labels.count("the linearisation of the admittance law's loop") <= 1
    advance = jax.jit(elsewhere.advance)
    h, n = 1e-6, len(found.names)
    for name in ("plant.p_base[0]", "plant.attitude[1]", "plant.q[3]", "plant.qd[5]"):
        step = jnp.zeros(n).at[found.names.index(name)].set(h)
        column = (advance(step, other_gains) - advance(-step, other_gains)) / (2 * h)
        scale = np.max(np.abs(column))
        np.testing.assert_allclose(found.jacobian[:, found.names.index(name)], column, atol=1e-6 * scale, err_msg=name)


@pytest.mark.slow
def test_out_of_contact_the_map_conserves_momentum_and_centre_of_mass(paper_capture_loop):
    """The chaser's momentum and centre of mass are the map's invariants when nothing
    touches it (W A = M W), and removing them takes out exactly the 9 eigenvalues at 1."""
    _, _, gains, _, _, linearizer = paper_capture_loop
    linearisation = linearizer(gains)
    assert linearisation.free and linearisation.contact_force_N == 0.0 and linearisation.clearance_m > 0.0
    found = stability.modes(linearisation)
    assert found.neutral_removed == 9
    assert found.invariance_residual < 1e-4
    everything = np.linalg.eigvals(linearisation.jacobian)
    removed = list(everything)
    for value in found.eigenvalues:
        removed.pop(int(np.argmin(np.abs(np.asarray(removed) - value))))
    assert len(removed) == 9
    # Jordan blocks of the eigenvalue 1 split numerically into 1 +- sqrt(eps).
    assert np.max(np.abs(np.asarray(removed) - 1.0)) < 1e-3


@pytest.mark.slow
def test_the_linear_gain_margin_agrees_with_the_loop_run_in_the_time_domain(paper_capture_loop):
    """Where a mode starts to grow as a loop's gain is scaled, by eigenvalues and by running
    the same loop from the same point: the two brackets within one bisection step."""
    robot, held, gains, point, periods, linearizer = paper_capture_loop
    settings = margins.MarginSettings()
    linear = stability.LinearProber(linearizer, gains, "admittance", settings)
    timed = stability.HoldProber(robot, held, "admittance", None, point, periods, gains, settings)
    for loop in margins.LOOPS:
        for direction in ("increase", "decrease"):
            by_eigenvalues = margins.gain_margin(linear, loop, direction)
            by_running = margins.gain_margin(timed, loop, direction)
            if by_eigenvalues["fails"] is None or by_running["fails"] is None:
                assert by_eigenvalues["fails"] is None and by_running["fails"] is None, (loop, direction)
                continue
            low = max(by_eigenvalues["holds"], by_running["holds"], key=lambda x: abs(math.log(x)))
            high = min(by_eigenvalues["fails"], by_running["fails"], key=lambda x: abs(math.log(x)))
            assert abs(math.log(high / low)) <= math.log(settings.factor_resolution) + 1e-12, (loop, direction)
    pid_up = margins.gain_margin(linear, "pid", "increase")
    assert pid_up["fails"] is not None, "the check needs a crossing"
    # At the nominal gains, the slowest mode's growth by both (the self-motion's drift).
    nominal = stability.modes(linearizer(gains)).fastest_growth_per_s
    timed.holds("pid", 1.0)
    assert timed.probes[-1]["growth_rate_per_s"] == pytest.approx(nominal, rel=0.3)


@pytest.mark.slow
def test_the_frequency_responses_gain_margins_agree_with_the_eigenvalue_margins(paper_capture_loop):
    """Each loop of the paper's linearised loop broken at its gain: the gain margins read
    from its frequency response (the characteristic loci on ``|z| = e^{sigma T}``) lie in
    the bracket the eigenvalue search finds on the same linearisation, within one bisection
    step, and where the response finds none within the search's limit the eigenvalues hold
    there too; at each, the broken loop closed at that factor has its least stable mode on
    the circle."""
    from spacegrasp_jax.analysis import frequency

    _, _, gains, _, _, linearizer = paper_capture_loop
    settings = margins.MarginSettings()
    growth_limit = 1.0
    linear = stability.LinearProber(linearizer, gains, "admittance", settings, growth_limit)
    broken = stability.broken_loops(linearizer(gains), growth_limit)
    crossings = 0
    for loop in margins.LOOPS:
        response = frequency.loop_margins(broken[loop])
        for direction in ("increase", "decrease"):
            by_eigenvalues = margins.gain_margin(linear, loop, direction)
            by_response = response["gain_margins"][direction]
            inside = by_response is not None and 1 / settings.max_factor < by_response["factor"] < settings.max_factor
            if by_eigenvalues["fails"] is None:
                assert not inside, (loop, direction, by_response)
                continue
            assert inside, (loop, direction, by_eigenvalues)
            low, high = sorted((by_eigenvalues["holds"], by_eigenvalues["fails"]))
            resolution = settings.factor_resolution
            assert low / resolution <= by_response["factor"] <= high * resolution, (loop, direction)
            closed = np.abs(np.linalg.eigvals(broken[loop].closed(by_response["factor"])))
            assert np.max(closed) == pytest.approx(broken[loop].radius, abs=1e-6)
            crossings += 1
    assert crossings >= 1, "the check needs a margin inside the search's limit"
