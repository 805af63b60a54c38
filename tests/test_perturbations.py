"""The seeded scenario sampler: nominal at zero range, reproducible, chunk-independent."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from spacegrasp_jax.perturbations import PerturbationRanges, sample_scenarios
from spacegrasp_jax.scenario import paper_scenario


@pytest.fixture(scope="module")
def nominal(robot):
    return paper_scenario(robot)


def test_zero_ranges_give_the_nominal_scenario_exactly(nominal):
    batch = sample_scenarios(nominal, 7, range(3), PerturbationRanges(0.0, 0.0, 0.0, 1.0))
    for leaf, batched in zip(jax.tree.leaves(nominal), jax.tree.leaves(batch)):
        for i in range(3):
            np.testing.assert_array_equal(batched[i], leaf)


def test_same_seed_same_samples_whatever_the_batch(nominal):
    ranges = PerturbationRanges()
    whole = sample_scenarios(nominal, 3, range(8), ranges)
    tail = sample_scenarios(nominal, 3, range(5, 8), ranges)  # a later chunk on its own
    np.testing.assert_array_equal(whole.initial.q[5:], tail.initial.q)
    np.testing.assert_array_equal(whole.R_lar[5:], tail.R_lar)
    other = sample_scenarios(nominal, 4, range(8), ranges)
    assert not np.allclose(whole.initial.q, other.initial.q)


def test_samples_stay_within_their_ranges(nominal):
    ranges = PerturbationRanges(q_init_rad=0.02, lar_position_m=0.004, lar_angle_rad=0.01, stiffness_factor=3.0)
    batch = sample_scenarios(nominal, 0, range(200), ranges)
    dq = np.asarray(batch.initial.q) - np.asarray(nominal.initial.q)
    assert np.abs(dq).max() <= 0.02 and np.abs(dq).max() > 0.015
    dp_lar = np.einsum("ji,nj->ni", np.asarray(nominal.R_lar), np.asarray(batch.p_lar) - np.asarray(nominal.p_lar))
    assert np.abs(dp_lar).max() <= 0.004 + 1e-15
    k = np.asarray(batch.contact_stiffness) / float(nominal.contact_stiffness)
    assert k.min() >= 1 / 3 - 1e-12 and k.max() <= 3 + 1e-12
    for R in np.asarray(batch.R_lar[:5]):
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)  # still rotations


@pytest.mark.parametrize("change, message", [
    (dict(q_init_rad=-0.1), "q_init_rad: must be non-negative"),
    (dict(lar_position_m=float("nan")), "lar_position_m: must be a finite number"),
    (dict(stiffness_factor=0.5), "stiffness_factor: must be >= 1"),
])
def test_ranges_are_validated(change, message):
    with pytest.raises(ValueError, match=message):
        PerturbationRanges(**change)
