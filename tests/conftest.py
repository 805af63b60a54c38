"""Shared fixtures: float64, the paper robot, its Pinocchio twin and random states."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)

import spacegrasp_jax as sg  # noqa: E402

N_RANDOM_STATES = 20


@dataclasses.dataclass(frozen=True)
class RandomState:
    """One random state of the system, NumPy float64, our velocity convention."""

    p_base: np.ndarray  # (3,) m
    R_base: np.ndarray  # (3, 3) satellite to inertial
    q: np.ndarray  # (7,) rad
    V_base: np.ndarray  # (6,) [v_s, w_s], inertial frame
    qd: np.ndarray  # (7,) rad/s


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    quat = rng.normal(size=4)
    w, x, y, z = quat / np.linalg.norm(quat)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def make_random_states(seed: int, count: int) -> list[RandomState]:
    rng = np.random.default_rng(seed)
    return [
        RandomState(
            p_base=rng.normal(scale=2.0, size=3),
            R_base=random_rotation(rng),
            q=rng.uniform(-np.pi, np.pi, size=7),
            V_base=np.concatenate([rng.normal(scale=0.2, size=3), rng.normal(scale=0.3, size=3)]),
            qd=rng.normal(scale=1.0, size=7),
        )
        for _ in range(count)
    ]


@pytest.fixture(scope="session")
def robot() -> sg.Robot:
    return sg.paper_robot()


@pytest.fixture(scope="session")
def random_states() -> list[RandomState]:
    return make_random_states(seed=20261123, count=N_RANDOM_STATES)


@pytest.fixture(scope="session")
def pinocchio_model():
    """``(model, data, ee_frame_id)`` of the paper robot built in Pinocchio from the tables."""
    import pinocchio_reference

    model, ee_frame = pinocchio_reference.build_model()
    return model, model.createData(), ee_frame


# ---- closed loop: each compiled once per session (experiment.run caches executables) ----


@pytest.fixture(scope="session")
def gains():
    from spacegrasp_jax.control import paper_gains

    return paper_gains()


@pytest.fixture(scope="session")
def full_runs(robot, gains):
    """The paper's 17 s scenario with both controllers (exact contact law)."""
    from spacegrasp_jax import experiment
    from spacegrasp_jax.scenario import paper_scenario

    scenario = paper_scenario(robot)
    return {controller: experiment.run(robot, scenario, gains, controller) for controller in ("admittance", "cartesian")}


@pytest.fixture(scope="session")
def short_scenario(robot):
    """2 s with the whole approach compressed into it: contact starts at about 0.9 s."""
    from spacegrasp_jax.scenario import paper_scenario

    return paper_scenario(robot, duration=2.0, move_duration=2.0, contact_law="smooth")
