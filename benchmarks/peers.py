"""The tools a user would otherwise pick, timed on the same robot and the same 1 ms RK4 steps.

* MuJoCo (``mujoco`` on PyPI) with the MJCF that [`spacegrasp_jax.core.mjcf`][spacegrasp_jax.core.mjcf] generates from the
  package's ``Robot``: free-joint base, no gravity, no contacts, RK4 at 1 ms, zero joint
  torques (open loop: MuJoCo has no controller here). ``mj_step`` in a Python loop on one
  thread, and ``mujoco.rollout`` over a batch of initial states with a thread per core.
* Pinocchio in a Python loop with the same closed loop (``benchmarks.pinocchio_loop``).
"""

from __future__ import annotations

import os
import time

import numpy as np

from spacegrasp_jax.benchmarks.dynamics import timed


def _cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def _mujoco_model(robot, dt: float):
    import mujoco

    from spacegrasp_jax.core import mjcf

    model = mujoco.MjModel.from_xml_string(mjcf.robot_to_mjcf(robot, dt))
    return model, mujoco.MjData(model)


def _initial_state(model, data, scenario):
    import mujoco

    from spacegrasp_jax.core import mjcf

    initial = scenario.initial
    data.qpos[:] = mjcf.qpos_from_state(initial.p_base, initial.R_base, initial.q)
    data.qvel[:] = mjcf.qvel_from_state(initial.R_base, initial.V_base, initial.qd)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    state = np.zeros(mujoco.mj_stateSize(model, spec))
    mujoco.mj_getState(model, data, state, spec)
    return state


def mujoco_mj_step(robot, scenario, repeats: int = 3) -> dict:
    """Median time of ``scenario.n_steps`` calls of ``mj_step`` from the scenario's start."""
    import mujoco

    model, data = _mujoco_model(robot, scenario.dt)
    state = _initial_state(model, data, scenario)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS

    def run():
        mujoco.mj_setState(model, data, state, spec)
        for _ in range(scenario.n_steps):
            mujoco.mj_step(model, data)

    run()  # warm-up
    timing = timed(run, repeats)
    return {
        "run_s": timing["median_s"],
        "run_spread_s": [timing["min_s"], timing["max_s"]],
        "us_per_step": 1e6 * timing["median_s"] / scenario.n_steps,
    }


def mujoco_rollout(robot, scenario, batch: int, segment: int = 250, threads: int | None = None) -> dict:
    """Scenario-steps per second of ``mujoco.rollout`` over ``batch`` copies of the initial
    state (slightly perturbed joint angles), ``scenario.n_steps`` steps each, with a thread
    per core. Run in segments of ``segment`` steps so the returned states stay small."""
    import mujoco
    from mujoco import rollout

    model, data = _mujoco_model(robot, scenario.dt)
    state = _initial_state(model, data, scenario)
    states = np.tile(state, (batch, 1))
    states[:, 1 + 7 : 1 + 14] += np.random.default_rng(0).uniform(
        -0.02, 0.02, size=(batch, 7)
    )  # qpos joints: time, then qpos
    threads = threads or _cores()
    datas = [mujoco.MjData(model) for _ in range(threads)]
    control = np.zeros((batch, segment, model.nu))
    output = np.zeros((batch, segment, states.shape[1]))
    with rollout.Rollout(nthread=threads) as runner:

        def run():
            current = states
            for _ in range(scenario.n_steps // segment):
                runner.rollout(model, datas, current, control, nstep=segment, state=output)
                current = np.ascontiguousarray(output[:, -1])

        start = time.perf_counter()
        run()
        seconds = time.perf_counter() - start
    steps = batch * (scenario.n_steps // segment) * segment
    return {
        "batch": batch,
        "threads": threads,
        "run_s": seconds,
        "scenario_steps_per_s": steps / seconds,
        "finite": bool(np.all(np.isfinite(output))),
    }


def pinocchio_closed_loop(robot, scenario, gains, controller: str = "admittance") -> dict:
    """Time of one closed-loop rollout as a Python loop over Pinocchio, and the largest
    difference of its final EE pose from ``spacegrasp_jax``'s (checked by the caller)."""
    from spacegrasp_jax.benchmarks.pinocchio_loop import PinocchioClosedLoop

    loop = PinocchioClosedLoop(robot, scenario, gains, controller)
    start = time.perf_counter()
    pose, peak = loop.run()
    seconds = time.perf_counter() - start
    return {
        "run_s": seconds,
        "us_per_step": 1e6 * seconds / scenario.n_steps,
        "final_pose": pose.tolist(),
        "peak_abs_torque_Nm": peak.tolist(),
    }
