"""The generated MJCF describes the same system: MuJoCo's EE position, kinetic energy and
forward dynamics against ours at random states (MuJoCo is the independent reference here;
the benchmarks compare against it)."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

import spacegrasp_jax as sg
from spacegrasp_jax.core import mjcf


@pytest.fixture(scope="module")
def mujoco_model(robot):
    model = mujoco.MjModel.from_xml_string(mjcf.robot_to_mjcf(robot))
    return model, mujoco.MjData(model)


def _load(mujoco_model, state, ctrl=None):
    model, data = mujoco_model
    data.qpos[:] = mjcf.qpos_from_state(state.p_base, state.R_base, state.q)
    data.qvel[:] = mjcf.qvel_from_state(state.R_base, state.V_base, state.qd)
    data.ctrl[:] = np.zeros(7) if ctrl is None else ctrl
    mujoco.mj_forward(model, data)
    return model, data


def test_the_model_has_the_documented_options(mujoco_model):
    model, _ = mujoco_model
    assert (model.nq, model.nv, model.nu) == (14, 13, 7)
    assert model.opt.timestep == 1e-3
    assert model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4
    np.testing.assert_array_equal(model.opt.gravity, 0.0)
    assert model.body_mass.sum() == pytest.approx(500.0 + 87.0)  # Tables 2 and 3, EE included


def test_ee_position_matches(robot, random_states, mujoco_model):
    for state in random_states:
        _, data = _load(mujoco_model, state)
        p_ee, _ = sg.ee_pose(robot, state.p_base, state.R_base, state.q)
        np.testing.assert_allclose(data.site_xpos[0], p_ee, atol=1e-12)


def test_kinetic_energy_matches(robot, random_states, mujoco_model):
    for state in random_states:
        model, data = _load(mujoco_model, state)
        M = np.zeros((model.nv, model.nv))
        mujoco.mj_fullM(model, data, M)
        energy = 0.5 * data.qvel @ M @ data.qvel
        ours = sg.kinetic_energy(robot, state.R_base, state.q, state.V_base, state.qd)
        np.testing.assert_allclose(energy, ours, rtol=1e-12)


def test_forward_dynamics_matches_under_random_torques(robot, random_states, mujoco_model):
    rng = np.random.default_rng(3)
    for state in random_states:
        u = rng.normal(scale=5.0, size=7)
        _, data = _load(mujoco_model, state, ctrl=u)
        Q = np.concatenate([np.zeros(6), u])
        xdd = np.asarray(sg.forward_dynamics(robot, state.R_base, state.q, state.V_base, state.qd, Q))
        # MuJoCo: [dv_s/dt (world), d(R^T w_s)/dt = R^T dw_s/dt (body), qdd]
        expected = np.concatenate([xdd[:3], state.R_base.T @ xdd[3:6], xdd[6:]])
        np.testing.assert_allclose(data.qacc, expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())
