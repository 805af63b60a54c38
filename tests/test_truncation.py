"""Truncated backpropagation (``LoopOptions.gradient_from_s``, ``TuneConfig.gradient_from_s``,
``spacegrasp tune --gradient-from``): the tuner's truncated gradient against an independent
path to the same derivative, a gain schedule of two knots either side of the cut, whose
second knot's gradient is the gains' effect from the cut on with the state there held; the
loss unchanged; where the cut falls; bad cuts refused before anything compiles."""

from __future__ import annotations

import numpy as np
import pytest

import spacegrasp_jax as sg
from spacegrasp_jax.envelope.scenario import paper_scenario
from spacegrasp_jax.loop.control import paper_gains
from spacegrasp_jax.loop.realism import flight
from spacegrasp_jax.loop.simulate import LoopOptions, gradient_cut
from spacegrasp_jax.tuning.run import tuned_base
from spacegrasp_jax.tuning.tune import TuneConfig, check_gradient_cut, setup

#: The cut (s) in the 1.5 s approach below, after contact begins (about 0.7 s).
CUT_S = 0.9


def _short_approach(robot):
    return paper_scenario(robot, duration=1.5, move_duration=1.5, contact_law="smooth")


def _tuner_gradient(robot, scenario, config):
    """The tuner's ``((loss, aux), gradient)`` at the paper's gains for ``config``."""
    base = tuned_base(paper_gains(), config)
    _, _, params, value_and_grad = setup(robot, scenario, base, config, torque_scale_Nm=np.ones(7))
    return value_and_grad(params)


@pytest.mark.slow
@pytest.mark.parametrize("realism", [None, flight().to_dict()], ids=["ideal", "flight"])
def test_the_truncated_gradient_is_the_schedules_after_the_cut_and_the_loss_is_unchanged(realism):
    robot = sg.paper_robot()
    scenario = _short_approach(robot)
    settings = dict(method="gradient", batch=2, realism=realism, aggregate="mean", seed=3)
    truncated = TuneConfig.of(**settings, gradient_from_s=CUT_S)
    period = 1 if truncated.loop_realism is None else truncated.loop_realism.steps_per_period(scenario.dt)
    period_s = period * scenario.dt
    # Knots one control period apart: every period before the cut runs the first knot's
    # gains, every period from the cut on the second's (the schedule is read at a period's start).
    scheduled = TuneConfig.of(**settings, schedule_variable="time", schedule_knots=(CUT_S - period_s, CUT_S))

    (loss, _), gradient = _tuner_gradient(robot, scenario, truncated)
    (schedule_loss, _), schedule_gradient = _tuner_gradient(robot, scenario, scheduled)
    np.testing.assert_allclose(float(loss), float(schedule_loss), rtol=1e-10)
    for name, knots in schedule_gradient.items():
        if name == "pinv_damping":  # not scheduled (tune --schedule): one knot
            continue
        before, after = np.asarray(knots)
        scale = np.max(np.abs(before + after))  # the whole capture's gradient
        np.testing.assert_allclose(np.asarray(gradient[name]), after, rtol=0, atol=1e-9 * scale, err_msg=name)
    # The part before the cut is not negligible here: the truncation changes the gradient.
    kd = np.asarray(schedule_gradient["Kd"])
    assert np.linalg.norm(kd[0]) > 0.05 * np.linalg.norm(kd[1])


def test_the_cut_is_the_first_block_boundary_at_or_after_the_time():
    assert gradient_cut(None, 0.001, 1, 17_000) == 0
    assert gradient_cut(8.5, 0.001, 1, 17_000) == 8_500
    assert gradient_cut(1.0, 0.001, 1, 17_000) == 1_000  # 1.0 / 0.001 is 999.999...: still 1,000
    assert gradient_cut(0.0, 0.004, 1, 100) == 0
    assert gradient_cut(0.0105, 0.004, 1, 100) == 3  # 2.6 periods: the third's start
    assert gradient_cut(0.0105, 0.004, 2, 100) == 4  # blocks of two periods
    with pytest.raises(ValueError, match="gradient_from_s: 17 s is at or past the run's end"):
        gradient_cut(17.0, 0.001, 1, 17_000)
    with pytest.raises(ValueError, match="gradient_from_s: must be a time"):
        LoopOptions(gradient_from_s=-1.0)


def test_bad_cuts_are_refused_naming_the_setting(robot):
    """(The command line's refusals, before anything compiles: ``tests/test_bad_input.py``.)"""
    with pytest.raises(ValueError, match="gradient_from_s: a setting of the gradient method"):
        TuneConfig.of(method="cmaes", gradient_from_s=3.0)
    with pytest.raises(ValueError, match="gradient_from_s: must be a time of 0 s or more"):
        TuneConfig.of(method="gradient", gradient_from_s=float("nan"))
    with pytest.raises(ValueError, match="at or past the run's end"):
        check_gradient_cut(TuneConfig.of(method="gradient", gradient_from_s=2.0), _short_approach(robot))
