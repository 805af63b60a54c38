"""A law written here, in the test file, with gain groups of its own and a gain set of its
own, runs in the closed loop, in a campaign's batched program and in the tuning gradient with
no change to the package. To have something independent to compare with, it is the
impedance law written again under another name, with its spring and damper as groups of its
own (``Kx``, ``Bx``): each result must be the package's impedance law's with ``Kd``, ``Bd``."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spacegrasp_jax.core import spatial
from spacegrasp_jax.envelope.perturbations import PerturbationRanges
from spacegrasp_jax.envelope.scenario import paper_scenario
from spacegrasp_jax.jobs.montecarlo import FoldedMetrics, evaluate_samples
from spacegrasp_jax.loop import simulate
from spacegrasp_jax.loop.control import ControlInputs, Impedance, Output, load_gains
from spacegrasp_jax.loop.control.admittance import pose_error
from spacegrasp_jax.loop.control.groups import GainGroup, group, groups_of
from spacegrasp_jax.loop.simulate import RunSpec

SPRING = GainGroup(6, "N/m, N m/rad", "a virtual spring, diagonal", "none: a law of a test", 1000.0)
DAMPER = GainGroup(6, "N s/m, N m s/rad", "a virtual damper, diagonal", "none: a law of a test", 100.0)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SpringGains:
    """The law's gains, and the whole gain set its runs take."""

    Kx: jax.Array = group(SPRING)
    Bx: jax.Array = group(DAMPER)


@dataclasses.dataclass(frozen=True)
class SpringThroughTranspose:
    """``u = J_dyn^T R (Kx e + Bx (twist_des - twist))``: torques, no servo after them."""

    name: ClassVar[str] = "spring_through_transpose"
    title: ClassVar[str] = "a law of a test"
    output: ClassVar[Output] = Output.JOINT_TORQUES
    gains_type: ClassVar[type] = SpringGains
    gain_groups: ClassVar[tuple[str, ...]] = tuple(groups_of(SpringGains))
    loop_gain: ClassVar[dict[str, int]] = {"Kx": 1, "Bx": 1}
    style: ClassVar[dict[str, str]] = dict(color="black", linestyle="-", label="a law of a test")
    paper_max_abs_torque_Nm: ClassVar[None] = None

    def init(self, n_joints: int = 7, dtype=jnp.float64):
        return ()

    def update(self, gains: SpringGains, inputs: ControlInputs, state, dt):
        wrench_lar = gains.Kx * pose_error(inputs.pose_des, inputs.pose) + gains.Bx * (inputs.twist_des - inputs.twist)
        wrench_ee = spatial.matvec(inputs.R_lar_ee.T, wrench_lar.reshape(2, 3)).reshape(6)
        return inputs.J_dyn_ee.T @ wrench_ee, state

    def log_fields(self, state) -> dict:
        return {}


@pytest.fixture(scope="module")
def both(robot):
    """The package's impedance law with its shipped file's gains, and this law with the same
    numbers as its own groups."""
    gains = load_gains(Path(__file__).resolve().parents[1] / "configs" / "impedance_gains.json", "impedance")
    return gains, SpringGains(Kx=gains.Kd, Bx=gains.Bd)


def test_a_law_written_here_runs_in_the_closed_loop(robot, both):
    scenario = paper_scenario(robot, duration=0.5, move_duration=0.5)
    gains, own = both
    run = jax.jit(simulate.closed_loop)
    _, theirs = run(RunSpec(robot, scenario, Impedance()), gains, None)
    _, ours = run(RunSpec(robot, scenario, SpringThroughTranspose()), own, None)
    assert np.abs(np.asarray(ours.u)).max() > 1e-3
    for name in ("u", "q", "qd", "pose_ee", "contact_force"):
        np.testing.assert_allclose(getattr(ours, name), getattr(theirs, name), rtol=1e-12, atol=1e-14, err_msg=name)


def test_a_law_written_here_runs_in_a_campaigns_samples(robot, both):
    scenario = paper_scenario(robot, duration=0.5, move_duration=0.5)
    gains, own = both
    indices, ranges = jnp.arange(3, dtype=jnp.uint32), PerturbationRanges()
    program = jax.jit(lambda spec, gains: evaluate_samples(spec, gains, 5, indices, ranges=ranges))
    _, theirs, _ = program(RunSpec(robot, scenario, Impedance(), observer=FoldedMetrics()), gains)
    _, ours, _ = program(RunSpec(robot, scenario, SpringThroughTranspose(), observer=FoldedMetrics()), own)
    for name in ("final_position_error_m", "largest_peak_torque_Nm", "max_contact_force_N"):
        np.testing.assert_allclose(ours[name], theirs[name], rtol=1e-10, err_msg=name)


@pytest.mark.slow
def test_a_law_written_here_has_its_own_groups_tuned_by_the_tuning_gradient(robot, both):
    """Its groups' gradient is the impedance law's for ``Kd``, ``Bd`` and agrees with central
    differences along a random direction of its log-gains."""
    from spacegrasp_jax.tuning.gradients import central_differences, envelope_gradients
    from spacegrasp_jax.tuning.objective import Objective, Weights

    scenario = paper_scenario(robot, duration=0.5, move_duration=0.5, contact_law="smooth")
    gains, own = both
    objective = Objective(Weights(), (1.0,) * 7)
    theirs, _ = envelope_gradients(RunSpec(robot, scenario, Impedance()), gains, objective, n=1, horizons=(1.0,))
    law = SpringThroughTranspose()
    ours, evaluate = envelope_gradients(RunSpec(robot, scenario, law), own, objective, n=1, horizons=(1.0,))
    assert set(ours.gradients) == {"Kx", "Bx"}
    for mine, package in (("Kx", "Kd"), ("Bx", "Bd")):
        np.testing.assert_allclose(ours.gradients[mine], theirs.gradients[package], rtol=1e-9, atol=1e-12)
    (check,) = central_differences(ours, evaluate, own, law, samples=[0])
    assert check["relative_error"] < 1e-4, check
