"""Runs that differ only in values share one compiled program: gains, seeds, perturbation
ranges, realism noise levels and the objective's weights are arguments of the programs,
never constants in them, so the process's cache of compiled programs and JAX's persistent
cache (whose key is the program's text) both find the program again. Settings that shape a
program (which ranges are zero, the objective's kind) still make another."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compile_labels import CompileLabels

from spacegrasp_jax.envelope.criteria import CaptureCriteria
from spacegrasp_jax.envelope.perturbations import PerturbationRanges
from spacegrasp_jax.envelope.scenario import paper_scenario
from spacegrasp_jax.jobs import campaign, compilation
from spacegrasp_jax.tuning import run as tuning_run
from spacegrasp_jax.tuning.objective import Objective, Weights
from spacegrasp_jax.tuning.parameters import initial_params, make_mask
from spacegrasp_jax.tuning.tune import TuneConfig, ideal_batch, make_loss, make_value_and_grad, training_scenarios


@pytest.mark.slow
def test_a_campaign_of_another_seed_ranges_and_gains_reuses_its_program(robot, gains):
    scenario = paper_scenario(robot, duration=0.03)
    first = campaign.CampaignConfig(n=2, chunk=2, seed=1)
    other_ranges = dataclasses.replace(first.ranges, q_init_rad=0.05, lar_position_m=0.01, stiffness_factor=3.0)
    second = dataclasses.replace(first, seed=2, ranges=other_ranges)
    other_gains = dataclasses.replace(gains, Kd=2.0 * gains.Kd)
    heard = CompileLabels()
    with compilation.listening(heard):
        a = campaign.evaluate_indices(robot, scenario, campaign.Variant("admittance", gains), first, [0, 1])
        compiled_for_the_first = len(heard.labels)  # 0 if another test of this process compiled it
        b = campaign.evaluate_indices(robot, scenario, campaign.Variant("admittance", other_gains), second, [0, 1])
        assert len(heard.labels) == compiled_for_the_first  # nothing compiled for the second
        # the values were used: the second campaign drew from its own seed and ranges
        assert not np.allclose(a["perturbation.dq_init"], b["perturbation.dq_init"])
        assert np.max(np.abs(b["perturbation.dq_init"])) > 0.02
        # a range switched off changes what the program computes: another program
        still = dataclasses.replace(
            second,
            ranges=dataclasses.replace(other_ranges, satellite_mass_fraction=0.0, satellite_inertia_fraction=0.0),
        )
        campaign.evaluate_indices(robot, scenario, campaign.Variant("admittance", gains), still, [0, 1])
        assert len(heard.labels) == compiled_for_the_first + 1


def test_an_objective_with_other_weights_and_tolerances_reuses_the_evaluation(robot, gains):
    scenarios = jax.tree.map(lambda x: np.stack([x, x]), paper_scenario(robot, duration=0.03))
    first = Objective(Weights(), (1.0,) * 7, kind="weighted")
    second = Objective(
        Weights(peak_torque=2.0, final_position=3.0),
        (2.0,) * 7,
        kind="weighted",
        criteria=CaptureCriteria(position_tolerance_m=0.01),
    )
    heard = CompileLabels()
    with compilation.listening(heard):
        a = tuning_run.evaluate(ideal_batch(robot, scenarios), gains, "admittance", first, chunk=2)
        compiled_for_the_first = len(heard.labels)
        b = tuning_run.evaluate(ideal_batch(robot, scenarios), gains, "admittance", second, chunk=2)
        assert len(heard.labels) == compiled_for_the_first
    np.testing.assert_allclose(b["final_position_error_m"], a["final_position_error_m"], rtol=0, atol=0)
    assert not np.allclose(b["weighted_loss"], a["weighted_loss"])  # the new weights were used
    np.testing.assert_allclose(b["position_margin"], a["position_margin"] / 2.0, rtol=1e-12)


@pytest.mark.slow
def test_the_tuning_gradient_is_one_program_for_other_seeds_gains_and_weights(robot, gains):
    """The persistent cache's key is a hash of the lowered program's text: equal texts are
    one compile, for this process and the next."""
    scenario = paper_scenario(robot, contact_law="smooth", duration=0.02)
    texts, programs = [], []
    for seed, scale, weights in ((0, 1.0, Weights()), (5, 1.5, Weights(peak_torque=3.0, rms_tracking=0.0))):
        config = TuneConfig(batch=2, seed=seed, objective="weighted", weights=weights, method="gradient")
        base = dataclasses.replace(gains, Kd=scale * gains.Kd)
        objective = Objective(weights, (scale,) * 7)
        mask = make_mask(base, "admittance")
        loss = make_loss(robot, training_scenarios(scenario, config), base, mask, config, objective, 2)
        params = initial_params(base, "admittance")
        value_and_grad = make_value_and_grad(loss, params, "reverse")
        programs.append(value_and_grad.program)
        texts.append(value_and_grad.lower(params).as_text())
    assert programs[0] is programs[1]  # one jitted function: this process compiles it once
    assert texts[0] == texts[1]  # one text: the persistent cache finds it in the next process
    assert "stablehlo.constant dense<5.000000e-03>" not in texts[0]  # no range or tolerance baked in


def test_ranges_travel_as_values_with_their_zero_pattern_as_structure():
    ranges = PerturbationRanges()
    leaves, structure = jax.tree.flatten(ranges)
    assert len(leaves) == len(dataclasses.fields(ranges))
    rebuilt = jax.tree.unflatten(structure, leaves)
    assert rebuilt == ranges and rebuilt.perturbs_robot and rebuilt.draws_estimate_errors
    quiet = PerturbationRanges(
        satellite_mass_fraction=0.0,
        satellite_inertia_fraction=0.0,
        lar_estimate_position_m=0.0,
        lar_estimate_angle_rad=0.0,
    )
    assert jax.tree.structure(quiet) != structure
    assert jax.tree.structure(dataclasses.replace(ranges, q_init_rad=0.3)) == structure


def _scaled_sum(offset, block, *, scale):
    return scale * (block + offset)


def test_a_programs_settings_are_its_key_so_another_setting_is_another_program():
    """``batching`` keys a program by the function and every setting a ``functools.partial``
    fixes: the same settings in a fresh partial reuse the program, another value of any of
    them makes a new one (a key written by hand that forgot one would run the old program)."""
    import functools

    from spacegrasp_jax.jobs import batching

    block = np.arange(4.0)
    listener = CompileLabels()
    with compilation.listening(listener):
        twice = batching.map_in_chunks(
            "settings test", functools.partial(_scaled_sum, scale=2.0), (1.0,), block, chunk=4, progress=None
        )
        again = batching.map_in_chunks(
            "settings test", functools.partial(_scaled_sum, scale=2.0), (5.0,), block, chunk=4, progress=None
        )
        thrice = batching.map_in_chunks(
            "settings test", functools.partial(_scaled_sum, scale=3.0), (1.0,), block, chunk=4, progress=None
        )
    np.testing.assert_array_equal(twice, 2.0 * (block + 1.0))
    np.testing.assert_array_equal(again, 2.0 * (block + 5.0))  # a value: the same program
    np.testing.assert_array_equal(thrice, 3.0 * (block + 1.0))  # a setting: another program
    assert len(listener.labels) == 2, listener.labels
    with pytest.raises(batching.BatchingError, match="not hashable"):
        batching.program_settings(functools.partial(_scaled_sum, scale=np.ones(2)))


def test_a_runs_program_is_looked_up_by_its_spec_structure_and_shapes(robot, gains, short_scenario):
    """``experiment.program_key`` is derived from the spec, never written by hand: numbers
    (gains, a realism's noise, the scenario's, a servo delay's ticks, the noise key) leave it
    as it is; every setting that shapes the program (the law's damping, the observer, the
    checkpointing, a realism stage, the scenario's steps, a believed robot, a delay line's
    length) makes another."""
    from spacegrasp_jax.jobs.experiment import program_key
    from spacegrasp_jax.jobs.montecarlo import FoldedMetrics
    from spacegrasp_jax.loop.control import Admittance
    from spacegrasp_jax.loop.realism import Stage, flight
    from spacegrasp_jax.loop.simulate import FullLog, LoopOptions, RunSpec
    from spacegrasp_jax.loop.stages import DelayLine

    def servo_delay(capacity, ticks):
        return (DelayLine(capacity, jnp.int32(ticks), "servo_joints"),)

    key = jax.random.PRNGKey(0)
    base = RunSpec(robot, short_scenario, "admittance", realism=flight(), stages=servo_delay(4, 1))
    reference = program_key(base, gains, key)
    noisier = dataclasses.replace(base.realism, force_noise_std=3.0 * np.asarray(base.realism.force_noise_std))
    same_program = [
        (base, dataclasses.replace(gains, Kd=2.0 * gains.Kd), key),
        (dataclasses.replace(base, realism=noisier), gains, key),
        (
            dataclasses.replace(
                base,
                scenario=dataclasses.replace(short_scenario, contact_stiffness=2.0 * short_scenario.contact_stiffness),
            ),
            gains,
            key,
        ),
        (dataclasses.replace(base, stages=servo_delay(4, 3)), gains, key),
        (base, gains, jax.random.PRNGKey(7)),
        (
            RunSpec(robot, short_scenario, Admittance(), realism=flight(), stages=servo_delay(4, 2)),
            gains,
            key,
        ),
    ]
    for arguments in same_program:
        assert program_key(*arguments) == reference
    other_programs = [
        dataclasses.replace(base, controller=Admittance(pinv_damping=0.01)),
        dataclasses.replace(base, controller="cartesian"),
        dataclasses.replace(base, observer=FoldedMetrics()),
        dataclasses.replace(base, observer=FullLog(4)),
        dataclasses.replace(base, options=LoopOptions(checkpoint=True)),
        dataclasses.replace(base, options=LoopOptions(checkpoint=True, reuse_start_kinematics=True)),
        dataclasses.replace(base, realism=dataclasses.replace(base.realism, stages=base.realism.stages & ~Stage.MODEL)),
        dataclasses.replace(base, scenario=paper_scenario(robot, duration=0.05)),
        dataclasses.replace(base, model_robot=robot),
        dataclasses.replace(base, stages=servo_delay(8, 1)),
        dataclasses.replace(base, stages=(DelayLine(4, jnp.int32(1), "command"),)),
        dataclasses.replace(base, stages=()),
    ]
    keys = [program_key(spec, gains, key) for spec in other_programs]
    assert all(other != reference for other in keys)
    assert len(set(keys)) == len(keys)


@pytest.mark.slow
def test_runs_that_differ_in_numbers_compile_one_program(robot, gains):
    """Two ``experiment.run`` calls whose specs differ only in numbers (the realism's noise,
    the gains, the noise key) compile once, and the second used its numbers."""
    from spacegrasp_jax.jobs import experiment
    from spacegrasp_jax.loop.realism import flight
    from spacegrasp_jax.loop.simulate import RunSpec

    scenario = paper_scenario(robot, duration=0.02, move_duration=2.0)
    quiet = dataclasses.replace(flight(), force_noise_std=0.1 * np.asarray(flight().force_noise_std))
    heard = CompileLabels()
    with compilation.listening(heard):
        first = experiment.run(RunSpec(robot, scenario, "admittance", realism=flight()), gains)
        compiled_for_the_first = len(heard.labels)  # 0 if another test of this process compiled it
        other_gains = dataclasses.replace(gains, kp=2.0 * np.asarray(gains.kp))
        second = experiment.run(
            RunSpec(robot, scenario, "admittance", realism=quiet), other_gains, key=jax.random.PRNGKey(5)
        )
        assert len(heard.labels) == compiled_for_the_first
    assert not np.allclose(first.log.fts_force_measured, second.log.fts_force_measured)
