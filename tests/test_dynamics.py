"""Dynamics against Pinocchio (an independent model built from the paper's tables), and
the invariants that hold whatever the model: M symmetric positive definite, momentum
rows of M, finite-difference gradients, vmap consistency and no retracing."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pinocchio as pin
import pinocchio_reference as ref
import pytest

import spacegrasp_jax as sg

RTOL = 1e-9


def relative_error(actual, expected) -> float:
    actual, expected = np.asarray(actual), np.asarray(expected)
    return float(np.max(np.abs(actual - expected)) / np.max(np.abs(expected)))


def pin_mass_matrix(model, data, state):
    qp = ref.configuration(state.p_base, state.R_base, state.q, model)
    M = pin.crba(model, data, qp)
    return np.triu(M) + np.triu(M, 1).T  # crba fills the upper triangle


def pin_state(model, state):
    """``(T, configuration, velocity)`` of ``state`` in Pinocchio's conventions, with
    ``v_pin = T x_v`` (``ref.velocity_map``)."""
    T = ref.velocity_map(state.R_base)
    return (
        T,
        ref.configuration(state.p_base, state.R_base, state.q, model),
        T @ np.concatenate([state.V_base, state.qd]),
    )


@pytest.fixture(scope="module")
def jitted():
    return {
        "mass_matrix": jax.jit(sg.mass_matrix),
        "bias_forces": jax.jit(sg.bias_forces),
        "forward_dynamics": jax.jit(sg.forward_dynamics),
        "inverse_dynamics": jax.jit(sg.inverse_dynamics),
        "dynamic_jacobian": jax.jit(sg.dynamic_jacobian),
        "dynamic_jacobian_ee": jax.jit(sg.dynamic_jacobian_ee),
        "system_momentum": jax.jit(sg.system_momentum),
        "momentum_jacobians": jax.jit(sg.momentum_jacobians),
    }


def test_mass_matrix_matches_pinocchio(robot, random_states, pinocchio_model, jitted):
    model, data, _ = pinocchio_model
    for state in random_states:
        T = ref.velocity_map(state.R_base)
        expected = T.T @ pin_mass_matrix(model, data, state) @ T
        actual = jitted["mass_matrix"](robot, state.R_base, state.q)
        assert relative_error(actual, expected) <= RTOL


def test_bias_forces_match_pinocchio(robot, random_states, pinocchio_model, jitted):
    model, data, _ = pinocchio_model
    for state in random_states:
        T, qp, v_pin = pin_state(model, state)
        nle = pin.nonLinearEffects(model, data, qp, v_pin)
        # tau_pin = M_pin (T xdot_v + c) + nle and Q = T^T tau_pin.
        c = ref.frame_acceleration_offset(state.R_base, state.V_base)
        expected = T.T @ (pin_mass_matrix(model, data, state) @ c + nle)
        actual = jitted["bias_forces"](robot, state.R_base, state.q, state.V_base, state.qd)
        assert relative_error(actual, expected) <= RTOL


def test_forward_dynamics_matches_pinocchio_aba(robot, random_states, pinocchio_model, jitted):
    model, data, _ = pinocchio_model
    rng = np.random.default_rng(7)
    for state in random_states:
        Q = np.concatenate([rng.normal(scale=5.0, size=6), rng.normal(scale=2.0, size=7)])
        T, qp, v_pin = pin_state(model, state)
        a_pin = pin.aba(model, data, qp, v_pin, T @ Q)
        expected = T.T @ (a_pin - ref.frame_acceleration_offset(state.R_base, state.V_base))
        actual = jitted["forward_dynamics"](robot, state.R_base, state.q, state.V_base, state.qd, Q)
        assert relative_error(actual, expected) <= RTOL


def test_inverse_dynamics_matches_pinocchio_rnea(robot, random_states, pinocchio_model, jitted):
    model, data, _ = pinocchio_model
    rng = np.random.default_rng(5)
    for state in random_states:
        xdd = np.concatenate([rng.normal(scale=0.5, size=6), rng.normal(scale=2.0, size=7)])
        T, qp, v_pin = pin_state(model, state)
        a_pin = T @ xdd + ref.frame_acceleration_offset(state.R_base, state.V_base)
        expected = T.T @ pin.rnea(model, data, qp, v_pin, a_pin)
        actual = jitted["inverse_dynamics"](robot, state.R_base, state.q, state.V_base, state.qd, xdd)
        assert relative_error(actual, expected) <= RTOL


@pytest.mark.slow
def test_forward_dynamics_derivatives_match_the_solve(robot, random_states):
    """forward_dynamics is differentiated through inverse dynamics (its own rule); both
    autodiff modes must agree with autodiff of ``M^-1 (Q - bias)`` written with a dense
    13x13 solve, for every argument, the robot's masses included."""
    Q = np.linspace(-2.0, 2.0, 13)

    def dense(robot, R_base, q, V_base, qd, Q):
        M = sg.mass_matrix(robot, R_base, q)
        return jnp.linalg.solve(M, Q - sg.bias_forces(robot, R_base, q, V_base, qd))

    def with_masses(function):
        def at(satellite_mass, link_mass, R_base, q, V_base, qd, Q):
            perturbed = sg.Robot(**{**vars(robot), "satellite_mass": satellite_mass, "link_mass": link_mass})
            return function(perturbed, R_base, q, V_base, qd, Q)

        return at

    argnums = tuple(range(7))
    ours_fwd = jax.jit(jax.jacfwd(with_masses(sg.forward_dynamics), argnums=argnums))
    ours_rev = jax.jit(jax.jacrev(with_masses(sg.forward_dynamics), argnums=argnums))
    reference = jax.jit(jax.jacfwd(with_masses(dense), argnums=argnums))
    for state in random_states[:4]:
        arguments = (robot.satellite_mass, robot.link_mass, state.R_base, state.q, state.V_base, state.qd, Q)
        expected = reference(*arguments)
        for got in (ours_fwd(*arguments), ours_rev(*arguments)):
            for g, e in zip(got, expected):
                assert relative_error(g, e) <= 1e-9


def test_momentum_matches_pinocchio(robot, random_states, pinocchio_model, jitted):
    model, data, _ = pinocchio_model
    for state in random_states:
        T, qp, v_pin = pin_state(model, state)
        h_com = pin.computeCentroidalMomentum(model, data, qp, v_pin)  # about the system CoM
        linear = h_com.linear
        angular_origin = h_com.angular + np.cross(data.com[0], linear)
        expected = np.concatenate([linear, angular_origin])
        actual = jitted["system_momentum"](robot, state.p_base, state.R_base, state.q, state.V_base, state.qd)
        assert relative_error(actual, expected) <= RTOL
        H2, H3 = jitted["momentum_jacobians"](robot, state.p_base, state.R_base, state.q)
        assert relative_error(H2 @ state.V_base + H3 @ state.qd, expected) <= RTOL


def test_dynamic_jacobian_matches_pinocchio(robot, random_states, pinocchio_model, jitted):
    model, data, ee_frame = pinocchio_model
    for state in random_states:
        expected, _ = ref.dynamic_jacobian(model, data, ee_frame, state)
        actual = jitted["dynamic_jacobian"](robot, state.R_base, state.q)
        assert relative_error(actual, expected) <= RTOL
        R_ee = data.oMf[ee_frame].rotation
        expected_ee = np.vstack([R_ee.T @ expected[:3], R_ee.T @ expected[3:]])
        actual_ee = jitted["dynamic_jacobian_ee"](robot, state.R_base, state.q)
        assert relative_error(actual_ee, expected_ee) <= RTOL


def test_dynamic_jacobian_gives_zero_momentum_twist(robot, random_states, jitted):
    """With V_s chosen so the momentum is zero, J_s V_s + J_m qd == J_dyn qd (eqs 5-8)."""
    for state in random_states:
        H2, H3 = jitted["momentum_jacobians"](robot, state.p_base, state.R_base, state.q)
        V_base = -np.linalg.solve(H2, H3 @ state.qd)
        momentum = jitted["system_momentum"](robot, state.p_base, state.R_base, state.q, V_base, state.qd)
        assert np.max(np.abs(momentum)) <= 1e-12 * np.max(np.abs(H3 @ state.qd))
        J_s, J_m = sg.ee_jacobians(robot, state.R_base, state.q)
        twist = J_s @ V_base + J_m @ state.qd
        J_dyn = jitted["dynamic_jacobian"](robot, state.R_base, state.q)
        assert relative_error(J_dyn @ state.qd, twist) <= RTOL


def test_mass_matrix_symmetric_positive_definite(robot, random_states, jitted):
    for state in random_states:
        M = np.asarray(jitted["mass_matrix"](robot, state.R_base, state.q))
        np.testing.assert_allclose(M, M.T, rtol=0, atol=1e-13 * np.abs(M).max())
        assert np.linalg.eigvalsh(M)[0] > 0.0


def test_mass_matrix_total_mass(robot, jitted):
    M = jitted["mass_matrix"](robot, jnp.eye(3), jnp.asarray(sg.PAPER_Q_INIT))
    np.testing.assert_allclose(np.diag(M)[:3], 587.0, rtol=1e-14)  # 500 + 80 + 7 kg


def test_bias_is_quadratic_in_velocity(robot, random_states, jitted):
    """Coriolis/centrifugal forces are a quadratic form of x_v: bias(2 x_v) = 4 bias(x_v)."""
    state = random_states[0]
    once = jitted["bias_forces"](robot, state.R_base, state.q, state.V_base, state.qd)
    twice = jitted["bias_forces"](robot, state.R_base, state.q, 2 * state.V_base, 2 * state.qd)
    assert relative_error(twice, 4 * once) <= 1e-12


def test_power_balance_of_bias(robot, random_states):
    """Energy balance (the skew property of dM/dt - 2C along x_v): the bias does no work
    beyond the change of the inertia, x_v^T bias = x_v^T (dM/dt) x_v / 2, with dM/dt
    from a jvp of M along the motion (dR/dt = [w_s]x R, dq/dt = qd)."""
    for state in random_states[:5]:
        x_v = np.concatenate([state.V_base, state.qd])
        R_rate = sg.core.spatial.skew(state.V_base[3:]) @ state.R_base
        _, M_rate = jax.jvp(lambda R, q: sg.mass_matrix(robot, R, q), (state.R_base, state.q), (R_rate, state.qd))
        bias = sg.bias_forces(robot, state.R_base, state.q, state.V_base, state.qd)
        lhs, rhs = x_v @ bias, 0.5 * x_v @ M_rate @ x_v
        assert abs(lhs - rhs) <= 1e-10 * (abs(rhs) + np.abs(bias).max())


# ---- transformations: vmap, grad, jit caching --------------------------------------------

API_CASES = {
    "mass_matrix": (sg.mass_matrix, ("R_base", "q")),
    "bias_forces": (sg.bias_forces, ("R_base", "q", "V_base", "qd")),
    "forward_dynamics": (sg.forward_dynamics, ("R_base", "q", "V_base", "qd", "Q")),
    "inverse_dynamics": (sg.inverse_dynamics, ("R_base", "q", "V_base", "qd", "Q")),
    "ee_pose": (sg.ee_pose, ("p_base", "R_base", "q")),
    "dynamic_jacobian": (sg.dynamic_jacobian, ("R_base", "q")),
    "dynamic_jacobian_ee": (sg.dynamic_jacobian_ee, ("R_base", "q")),
    "system_momentum": (sg.system_momentum, ("p_base", "R_base", "q", "V_base", "qd")),
}


def stacked_arguments(random_states, names):
    rng = np.random.default_rng(3)
    columns = {
        "p_base": np.stack([s.p_base for s in random_states]),
        "R_base": np.stack([s.R_base for s in random_states]),
        "q": np.stack([s.q for s in random_states]),
        "V_base": np.stack([s.V_base for s in random_states]),
        "qd": np.stack([s.qd for s in random_states]),
        "Q": rng.normal(size=(len(random_states), 13)),
    }
    return [columns[name] for name in names]


@pytest.mark.parametrize("name", sorted(API_CASES))
def test_vmap_equals_loop(robot, random_states, name):
    function, names = API_CASES[name]
    batch = stacked_arguments(random_states[:6], names)
    batched = jax.jit(jax.vmap(function, in_axes=(None,) + (0,) * len(names)))(robot, *batch)
    single = jax.jit(function)
    for i in range(len(batch[0])):
        one = single(robot, *[argument[i] for argument in batch])
        for got, want in zip(jax.tree.leaves(batched), jax.tree.leaves(one)):
            np.testing.assert_allclose(got[i], want, rtol=1e-13, atol=1e-13)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(API_CASES))
def test_gradients_match_central_differences(robot, random_states, name):
    """Directional derivative along a random direction of every real-valued argument
    (joint angles, rates, twist, forces; R_base moved on SO(3)) against central
    differences, through a random scalar projection of the output."""
    function, names = API_CASES[name]
    state = random_states[2]
    rng = np.random.default_rng(11)
    arguments = dict(zip(names, stacked_arguments([state], names)))
    arguments = {key: value[0] for key, value in arguments.items()}
    directions = {key: rng.normal(size=np.shape(value)) for key, value in arguments.items() if key != "R_base"}
    rotation_direction = rng.normal(size=3)
    weights = [rng.normal(size=np.shape(leaf)) for leaf in jax.tree.leaves(function(robot, *arguments.values()))]

    def scalar(eps):
        moved = {key: value + eps * directions[key] if key in directions else value for key, value in arguments.items()}
        if "R_base" in arguments:
            moved["R_base"] = sg.core.spatial.euler_zyx_to_rotation(eps * rotation_direction) @ arguments["R_base"]
        leaves = jax.tree.leaves(function(robot, *[moved[key] for key in names]))
        return sum(jnp.sum(w * leaf) for w, leaf in zip(weights, leaves))

    analytic = jax.jit(jax.grad(scalar))(0.0)
    forward = jax.jit(lambda e: jax.jvp(scalar, (e,), (1.0,))[1])(0.0)
    h = 1e-6
    value = jax.jit(scalar)
    numeric = (value(h) - value(-h)) / (2 * h)
    assert np.isfinite(analytic)
    np.testing.assert_allclose(analytic, numeric, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(forward, analytic, rtol=1e-12, atol=1e-12)


def test_gradients_with_respect_to_robot_parameters(robot, random_states):
    """d(forward dynamics)/d(satellite mass and link masses) against central differences:
    the robot is a pytree of arrays, so model uncertainty is differentiable too."""
    state = random_states[3]
    Q = np.linspace(-1.0, 1.0, 13)

    def scalar(satellite_mass, link_mass):
        perturbed = sg.Robot(**{**vars(robot), "satellite_mass": satellite_mass, "link_mass": link_mass})
        return jnp.sum(sg.forward_dynamics(perturbed, state.R_base, state.q, state.V_base, state.qd, Q) ** 2)

    grad_sat, grad_links = jax.jit(jax.grad(scalar, argnums=(0, 1)))(robot.satellite_mass, robot.link_mass)
    scalar = jax.jit(scalar)
    h = 1e-4 * robot.satellite_mass  # steps relative to the parameter: round-off stays small
    numeric_sat = (
        scalar(robot.satellite_mass + h, robot.link_mass) - scalar(robot.satellite_mass - h, robot.link_mass)
    ) / (2 * h)
    np.testing.assert_allclose(grad_sat, numeric_sat, rtol=1e-6)
    for i in range(7):
        e = np.zeros(7)
        e[i] = h = 1e-4 * robot.link_mass[i]
        numeric = (
            scalar(robot.satellite_mass, robot.link_mass + e) - scalar(robot.satellite_mass, robot.link_mass - e)
        ) / (2 * h)
        np.testing.assert_allclose(grad_links[i], numeric, rtol=1e-6, atol=1e-10)


@pytest.mark.parametrize("name", sorted(API_CASES))
def test_no_retrace_on_new_values(robot, random_states, name):
    function, names = API_CASES[name]
    traces = []

    def counted(*arguments):
        traces.append(None)
        return function(*arguments)

    compiled = jax.jit(counted)
    for state in random_states[:3]:
        arguments = [a[0] for a in stacked_arguments([state], names)]
        jax.block_until_ready(compiled(robot, *arguments))
    assert len(traces) == 1


# ---- property-based: any configuration, not just the 20 seeded states ----------------------

from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

angles = st.floats(min_value=-np.pi, max_value=np.pi, allow_nan=False)
rates = st.floats(min_value=-3.0, max_value=3.0, allow_nan=False)

_mass_matrix = jax.jit(sg.mass_matrix)
_forward = jax.jit(sg.forward_dynamics)
_bias = jax.jit(sg.bias_forces)


@settings(max_examples=40, deadline=None)
@given(q=st.lists(angles, min_size=7, max_size=7), euler=st.lists(angles, min_size=3, max_size=3))
def test_property_mass_matrix_spd_and_matches_pinocchio(robot, pinocchio_model, q, euler):
    model, data, _ = pinocchio_model
    R_base = np.asarray(sg.core.spatial.euler_zyx_to_rotation(jnp.asarray(euler)))
    M = np.asarray(_mass_matrix(robot, R_base, np.asarray(q)))
    assert np.linalg.eigvalsh(M)[0] > 0.0
    T = ref.velocity_map(R_base)
    M_pin = pin.crba(model, data, ref.configuration(np.zeros(3), R_base, q, model))
    expected = T.T @ (np.triu(M_pin) + np.triu(M_pin, 1).T) @ T
    assert relative_error(M, expected) <= RTOL


@settings(max_examples=40, deadline=None)
@given(
    q=st.lists(angles, min_size=7, max_size=7),
    velocity=st.lists(rates, min_size=13, max_size=13),
    acceleration=st.lists(rates, min_size=13, max_size=13),
)
def test_property_forward_dynamics_inverts_the_equation_of_motion(robot, q, velocity, acceleration):
    """forward_dynamics(Q = M a + bias) returns a, for any state and acceleration."""
    R_base = np.eye(3)
    V_base, qd, a = np.asarray(velocity[:6]), np.asarray(velocity[6:]), np.asarray(acceleration)
    Q = _mass_matrix(robot, R_base, np.asarray(q)) @ a + _bias(robot, R_base, np.asarray(q), V_base, qd)
    recovered = _forward(robot, R_base, np.asarray(q), V_base, qd, Q)
    np.testing.assert_allclose(recovered, a, rtol=0, atol=1e-9 * (1.0 + np.abs(a).max()))
