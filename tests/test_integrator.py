"""Physical invariants of the simulated free-floating motion: momentum conservation under
internal (joint) torques, energy conservation without torques and RK4's 4th order, and
the Dynamic Jacobian against the finite-difference EE twist of a simulated motion."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import spacegrasp_jax as sg
from spacegrasp_jax.core import spatial
from spacegrasp_jax.core.integrator import (
    free_floating_derivative,
    plant_state,
    rk4_step,
    simulate_free_floating,
)

_simulate_chunk = jax.jit(simulate_free_floating)
CHUNK = 25  # steps per compiled call: every test reuses the one compilation


def simulate(robot, state, joint_torques, dt):
    """``simulate_free_floating`` in chunks of CHUNK steps (len(joint_torques) % CHUNK == 0)."""
    joint_torques = np.asarray(joint_torques, dtype=np.float64)
    paths = []
    for chunk in joint_torques.reshape(-1, CHUNK, 7):
        state, path = _simulate_chunk(robot, state, chunk, dt)
        paths.append(path if not paths else jax.tree.map(lambda x: x[1:], path))
    return state, jax.tree.map(lambda *xs: jnp.concatenate(xs), *paths)


def momentum_of(robot, state):
    return sg.system_momentum(robot, state.p_base, state.R_base, state.q, state.V_base, state.qd)


def energy_of(robot, state):
    return sg.kinetic_energy(robot, state.R_base, state.q, state.V_base, state.qd)


@pytest.mark.parametrize("index", [0, 1])
def test_momentum_conserved_under_random_joint_torques(robot, random_states, index):
    """2 s of RK4 at 1 ms with random joint torques (internal forces): the total linear
    and angular momentum stay constant to 1e-9 relative."""
    s = random_states[index]
    start = plant_state(s.p_base, s.R_base, s.q, s.V_base, s.qd)
    torques = np.random.default_rng(index).normal(scale=5.0, size=(2000, 7))  # N m
    _, path = simulate(robot, start, torques, 1e-3)
    momenta = jax.vmap(momentum_of, in_axes=(None, 0))(robot, path)
    drift = np.max(np.abs(np.asarray(momenta) - np.asarray(momenta[0])), axis=0)
    scale = np.abs(np.asarray(momenta[0]))
    assert np.max(drift[:3]) <= 1e-9 * np.max(scale[:3])
    assert np.max(drift[3:]) <= 1e-9 * np.max(scale[3:])
    # The torques did move the arm: the test is not vacuous.
    assert np.max(np.abs(np.asarray(path.qd[-1]) - s.qd)) > 1.0


def test_momentum_stays_zero_from_rest(robot):
    """Started at rest, the momentum stays zero while the joint torques move the arm."""
    start = plant_state(np.zeros(3), np.eye(3), np.asarray(sg.PAPER_Q_INIT), np.zeros(6), np.zeros(7))
    torques = np.tile(np.array([1.0, -2.0, 1.5, 0.5, -0.5, 0.2, 0.05]), (2000, 1))
    final, path = simulate(robot, start, torques, 1e-3)
    momenta = np.asarray(jax.vmap(momentum_of, in_axes=(None, 0))(robot, path))
    base_speed = np.max(np.abs(np.asarray(path.V_base)))
    assert base_speed > 1e-3  # the satellite reacts
    # Zero to RK4's error (momentum is not linear in the state, so RK4 does not keep it
    # exactly), relative to the momentum the satellite's own motion carries.
    satellite_momentum = float(robot.satellite_mass) * base_speed
    assert np.max(np.abs(momenta)) <= 1e-9 * satellite_momentum


def test_energy_conserved_with_fourth_order_convergence(robot, random_states):
    """Without torques the kinetic energy is conserved up to RK4's error, which falls as
    dt^4: the log-log slope of the energy error against dt is 4."""
    s = random_states[4]
    start = plant_state(s.p_base, s.R_base, s.q, s.V_base, s.qd)
    energy_0 = float(energy_of(robot, start))
    steps = np.array([0.04, 0.02, 0.01, 0.005])
    errors = []
    for dt in steps:
        final, _ = simulate(robot, start, jnp.zeros((int(round(1.0 / dt)), 7)), dt)
        errors.append(abs(float(energy_of(robot, final)) - energy_0) / energy_0)
    slope = np.polyfit(np.log(steps), np.log(errors), 1)[0]
    assert 3.8 <= slope <= 4.2, (slope, errors)
    final, _ = simulate(robot, start, jnp.zeros((1000, 7)), 1e-3)
    assert abs(float(energy_of(robot, final)) - energy_0) <= 1e-11 * energy_0


@pytest.mark.slow
def test_dynamic_jacobian_matches_simulated_ee_twist(robot, random_states):
    """At zero momentum, J_dyn qd equals the EE twist measured by central differences of
    the EE pose along a simulated free motion (forward and backward in time)."""
    for s in random_states[:4]:
        H2, H3 = sg.momentum_jacobians(robot, s.p_base, s.R_base, s.q)
        V_base = -np.linalg.solve(H2, H3 @ s.qd)  # zero total momentum
        start = plant_state(s.p_base, s.R_base, s.q, V_base, s.qd)
        zero = jnp.zeros(13)
        h = 1e-4

        def advance(dt):
            return rk4_step(lambda x: (), lambda x, _, Q: free_floating_derivative(robot, x, Q), start, dt, zero)[0]

        ahead, behind = advance(h), advance(-h)
        p_ahead, R_ahead = sg.ee_pose(robot, ahead.p_base, ahead.R_base, ahead.q)
        p_behind, R_behind = sg.ee_pose(robot, behind.p_base, behind.R_base, behind.q)
        measured = np.concatenate(
            [(p_ahead - p_behind) / (2 * h), spatial.rotation_log(R_ahead @ R_behind.T) / (2 * h)]
        )
        predicted = np.asarray(sg.dynamic_jacobian(robot, start.R_base, s.q) @ s.qd)
        np.testing.assert_allclose(predicted, measured, rtol=0, atol=1e-7 * np.abs(predicted).max())


def test_quaternion_stays_unit_and_matches_rotation(robot, random_states):
    s = random_states[5]
    start = plant_state(s.p_base, s.R_base, s.q, s.V_base, s.qd)
    assert np.allclose(np.asarray(start.R_base), s.R_base, atol=1e-14)
    final, path = simulate(robot, start, jnp.zeros((500, 7)), 1e-3)
    norms = np.linalg.norm(np.asarray(path.quat_base), axis=1)
    np.testing.assert_allclose(norms, 1.0, atol=1e-14)
    # The fixed target beside the chaser is handed back as it was, bit for bit.
    for name in ("p", "quat", "v", "w"):
        np.testing.assert_array_equal(getattr(final.target, name), getattr(start.target, name))


def test_the_projection_renormalises_a_free_targets_quaternion_only():
    from spacegrasp_jax.core.target import TargetState

    off = jnp.array([1.0, 0.1, -0.2, 0.05]) * 1.001  # a quaternion a step of RK4 left off the unit sphere
    state = plant_state(jnp.zeros(3), jnp.eye(3), jnp.zeros(7), jnp.zeros(6), jnp.zeros(7))
    free = TargetState(jnp.zeros(3), off, jnp.zeros(3), jnp.zeros(3))
    fixed = TargetState(jnp.zeros(3), off, jnp.zeros(3), jnp.zeros(3), free=False)
    moved = dataclasses.replace(state, quat_base=off, target=free).projected()
    np.testing.assert_allclose(np.linalg.norm(moved.quat_base), 1.0, atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(moved.target.quat), 1.0, atol=1e-15)
    np.testing.assert_allclose(moved.target.quat, off / np.linalg.norm(off), atol=1e-15)
    kept = dataclasses.replace(state, target=fixed).projected()
    np.testing.assert_array_equal(kept.target.quat, off)  # a fixed target is left as it is
    with pytest.raises(ValueError, match="free-floating target"):
        free_floating_derivative(sg.paper_robot(), dataclasses.replace(state, target=free), jnp.zeros(13))


# ---- RK4 as one scan of four stages (the forward loops' step) -------------------------------

LAMBDA, DT = -3.0, 0.05


def _affine_rate(state, kinematics, u):
    """``x' = LAMBDA x + u`` on the joint angles and rates, ``LAMBDA x`` on the base's position
    and twist, the attitude and the target at rest: RK4's update has a closed form."""
    scaled = lambda x: LAMBDA * x  # noqa: E731
    return dataclasses.replace(
        state,
        p_base=scaled(state.p_base),
        quat_base=jnp.zeros(4),
        q=scaled(state.q) + u,
        V_base=scaled(state.V_base),
        qd=scaled(state.qd) + u,
        target=state.target.at_rest(),
    )


def _rk4_affine(x, u):
    """RK4's step of ``x' = LAMBDA x + u`` from its stability polynomials."""
    z = LAMBDA * DT
    return (1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24) * x + DT * (1 + z / 2 + z**2 / 6 + z**3 / 24) * u


def _start_state():
    rng = np.random.default_rng(8)
    return plant_state(rng.normal(size=3), np.eye(3), rng.normal(size=7), rng.normal(size=6), rng.normal(size=7))


def test_rk4_as_one_scan_of_four_stages_is_rk4():
    """Against RK4's closed form on an affine system; the kinematics returned are those of
    the step's start. The checkpointed step, with and without the start's kinematics handed
    in, is the same step, and so is its derivative (against the unchecked one's)."""
    state, u = _start_state(), jnp.linspace(0.5, -0.5, 7)
    kinematics = lambda s: jnp.concatenate([s.q, s.qd])  # noqa: E731
    step = jax.jit(lambda s, u: rk4_step(kinematics, _affine_rate, s, DT, u))
    moved, held, at_start = step(state, u)
    np.testing.assert_allclose(moved.q, _rk4_affine(state.q, u), rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(moved.qd, _rk4_affine(state.qd, u), rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(moved.V_base, _rk4_affine(state.V_base, 0.0), rtol=1e-14)
    np.testing.assert_allclose(moved.quat_base, state.quat_base, atol=1e-15)
    np.testing.assert_array_equal(at_start, kinematics(state))
    np.testing.assert_array_equal(held, u)
    for start in (None, kinematics(state)):
        checked = jax.jit(
            lambda s, u: rk4_step(kinematics, _affine_rate, s, DT, u, start_kinematics=start, checkpoint=True)
        )
        other, _, nothing = checked(state, u)
        assert nothing is None
        for name in ("p_base", "q", "V_base", "qd"):
            np.testing.assert_allclose(getattr(other, name), getattr(moved, name), rtol=1e-15, atol=1e-16)

    def final_q(u, checkpoint):
        return jnp.sum(rk4_step(kinematics, _affine_rate, state, DT, u, checkpoint=checkpoint)[0].q ** 2)

    np.testing.assert_allclose(jax.grad(final_q)(u, True), jax.grad(final_q)(u, False), rtol=1e-14, atol=1e-16)


def test_what_reads_the_steps_start_runs_once_on_its_kinematics_and_is_held():
    """``at_start`` gives the torque held over the four stages from the start's kinematics:
    the step is RK4's of the affine system with that torque, which it would not be if the
    torque were recomputed at a later stage; its output is the start's."""
    state = _start_state()
    kinematics = lambda s: s.q  # noqa: E731
    at_start = lambda q: (0.3 * q, 2.0 * q)  # noqa: E731
    moved, held, out = jax.jit(lambda s: rk4_step(kinematics, _affine_rate, s, DT, at_start=at_start))(state)
    u = 0.3 * state.q
    np.testing.assert_allclose(held, u, rtol=1e-15)
    np.testing.assert_allclose(out, 2.0 * state.q, rtol=1e-15)
    np.testing.assert_allclose(moved.q, _rk4_affine(state.q, u), rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(moved.qd, _rk4_affine(state.qd, u), rtol=1e-14, atol=1e-15)
