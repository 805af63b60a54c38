"""The whole closed loop against an independent one: the benchmark's peer, written in NumPy
with Pinocchio's ``aba`` for the dynamics (``benchmarks/pinocchio_loop.py``), runs the same
controllers, contact and RK4, and must end where our rollout ends. A 2 s scenario with the
approach compressed into it (contact from about 0.9 s) and a desired rotation, so the
Euler-rate terms of eqs 10-13 are exercised."""

from __future__ import annotations

import numpy as np
import pytest

from spacegrasp_jax.benchmarks.pinocchio_loop import PinocchioClosedLoop
from spacegrasp_jax.envelope.scenario import paper_scenario
from spacegrasp_jax.jobs import experiment
from spacegrasp_jax.loop.simulate import RunSpec


@pytest.mark.parametrize("controller", ["admittance", "cartesian"])
def test_pinocchio_closed_loop_ends_where_ours_does(robot, gains, controller):
    scenario = paper_scenario(robot, duration=2.0, move_duration=2.0, end_pose=(0.01, -0.005, 0.015, 0.05, -0.03, 0.02))
    ours = experiment.run(RunSpec(robot, scenario, controller), gains)
    # The contact is part of the check: the summary holds NaN for a run that never touched.
    assert 0.0 < ours.summary["first_contact_s"] < 2.0
    pose, peak = PinocchioClosedLoop(robot, scenario, gains, controller).run()
    np.testing.assert_allclose(pose, ours.log.pose_ee[-1], atol=1e-12)
    np.testing.assert_allclose(peak, ours.summary["max_abs_torque_Nm"], rtol=1e-10)
