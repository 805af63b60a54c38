"""Random states of the system for the reference tests (a module of its own, so that tests
can import it: ``conftest`` is not importable by name once ``notebooks/`` has one too)."""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class RandomState:
    """One random state of the system, NumPy float64, our velocity convention."""

    p_base: np.ndarray  # (3,) m
    R_base: np.ndarray  # (3, 3) satellite to inertial
    q: np.ndarray  # (N,) rad, N the arm's joints (the paper's 7)
    V_base: np.ndarray  # (6,) [v_s, w_s], inertial frame
    qd: np.ndarray  # (N,) rad/s


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


def make_random_states(seed: int, count: int, n_joints: int = 7) -> list[RandomState]:
    rng = np.random.default_rng(seed)
    return [
        RandomState(
            p_base=rng.normal(scale=2.0, size=3),
            R_base=random_rotation(rng),
            q=rng.uniform(-np.pi, np.pi, size=n_joints),
            V_base=np.concatenate([rng.normal(scale=0.2, size=3), rng.normal(scale=0.3, size=3)]),
            qd=rng.normal(scale=1.0, size=n_joints),
        )
        for _ in range(count)
    ]
