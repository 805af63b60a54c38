"""The closed loop: stability, the paper's findings, momentum without contact, dt
convergence, divergence reporting, vmap and gradients."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spacegrasp_jax.analysis import plots
from spacegrasp_jax.envelope import metrics
from spacegrasp_jax.envelope.scenario import paper_scenario
from spacegrasp_jax.jobs import experiment
from spacegrasp_jax.loop.control import PID, Admittance, Cartesian, chain, law_named, make_gains
from spacegrasp_jax.loop.simulate import RunSpec, first_nonfinite_time, initial_state, rollout

# Table 5 of the paper, N m.
PAPER_TABLE5 = {
    "admittance": np.array([1.50, 2.45, 1.68, 0.86, 1.10, 0.17, 0.036]),
    "cartesian": np.array([1.89, 4.21, 2.72, 0.72, 1.55, 0.35, 0.027]),
}


def test_both_controllers_stable_over_17_s(full_runs):
    for controller, result in full_runs.items():
        assert first_nonfinite_time(result.log) is None
        assert result.log.t[-1] == pytest.approx(17.0 - 1e-3)
        torque = np.array(result.summary["max_abs_torque_Nm"])
        # Same order of magnitude as Table 5 for every joint (within a factor of 2).
        ratio = torque / PAPER_TABLE5[controller]
        assert np.all((ratio > 0.5) & (ratio < 2.0)), (controller, ratio)
        assert result.summary["max_contact_force_N"] > 1.0  # the EE did meet the sphere


def test_paper_findings_hold(full_runs):
    """Section 5's claims, each checkable here: the admittance law reaches the target more
    precisely, with lower torques in the joints where Table 5 says so (1, 2, 3, 5, 6),
    enters the sphere earlier, and keeps lower momentum and satellite velocities."""
    active, cartesian = full_runs["admittance"].summary, full_runs["cartesian"].summary
    assert active["final_position_error_m"] < 0.2 * cartesian["final_position_error_m"]
    assert active["final_position_error_m"] < 5e-3
    lower = np.array(active["max_abs_torque_Nm"]) < np.array(cartesian["max_abs_torque_Nm"])
    assert all(lower[[0, 1, 2, 4, 5]])
    assert active["first_contact_s"] < cartesian["first_contact_s"]
    for key in ("max_linear_momentum_Ns", "max_angular_momentum_Nms", "max_base_speed_mps", "max_base_rate_radps"):
        assert active[key] < cartesian[key], key


@pytest.mark.parametrize("controller", ["admittance", "cartesian"])
def test_without_contact_tracks_and_keeps_zero_momentum(robot, gains, controller):
    """Full 17 s with the sphere removed (k = 0): the EE follows the trajectory and the
    system's momentum stays zero (no external force) to 1e-9 relative to the momentum
    the satellite's own reaction motion carries."""
    scenario = paper_scenario(robot, contact_stiffness=0.0)
    result = experiment.run(RunSpec(robot, scenario, controller), gains)
    log = result.log
    assert result.summary["max_contact_force_N"] == 0.0
    assert np.max(metrics.position_error(log)) < 0.01
    assert result.summary["final_position_error_m"] < 5e-4
    assert result.summary["final_orientation_error_rad"] < 1e-3
    satellite_momentum = float(robot.satellite_mass) * np.max(np.linalg.norm(log.V_base[:, :3], axis=1))
    assert satellite_momentum > 0.1  # the satellite does react to the arm
    assert np.max(np.abs(log.momentum)) <= 1e-9 * satellite_momentum


@pytest.mark.slow
@pytest.mark.parametrize("controller", ["admittance", "cartesian"])
def test_halving_dt_changes_peak_torques_by_less_than_one_percent(robot, gains, full_runs, controller):
    fine = experiment.run(RunSpec(robot, paper_scenario(robot, dt=5e-4), controller), gains)
    coarse = np.array(full_runs[controller].summary["max_abs_torque_Nm"])
    change = np.abs(np.array(fine.summary["max_abs_torque_Nm"]) - coarse) / coarse
    assert np.all(change < 0.01), change


def test_divergence_is_reported_with_its_time(robot, gains):
    wild = make_gains(**{**gains.to_dict(), "kp": [1e7] * 7})
    scenario = paper_scenario(robot, duration=0.5)
    with pytest.raises(experiment.SimulationDiverged, match=r"first non-finite value at t = ") as error:
        experiment.run(RunSpec(robot, scenario, "cartesian"), wild)
    assert 0.0 < error.value.time_s < 0.5


def test_unknown_controller_is_rejected_before_compiling(robot, gains, short_scenario):
    with pytest.raises(ValueError, match="controller: expected one of"):
        rollout(robot, short_scenario, gains, "computed_torque")


@pytest.mark.slow
def test_vmap_over_scenarios_equals_loop(robot, gains):
    q_init = np.asarray(paper_scenario(robot).initial.q)
    scenarios = [
        paper_scenario(robot, duration=1.0, move_duration=1.0, contact_stiffness=k, q_init=q_init + 0.01 * k)
        for k in (0.1, 0.2, 0.05)
    ]
    batch = jax.tree.map(lambda *leaves: jnp.stack(leaves), *scenarios)
    batched = jax.jit(jax.vmap(rollout, in_axes=(None, 0, None, None)), static_argnums=3)
    _, logs = batched(robot, batch, gains, "admittance")
    for i, scenario in enumerate(scenarios):
        single = experiment.run(RunSpec(robot, scenario, "admittance"), gains).log
        for name in ("u", "pose_ee", "contact_force", "momentum"):
            np.testing.assert_allclose(
                getattr(logs, name)[i], getattr(single, name), rtol=1e-9, atol=1e-12, err_msg=name
            )
    assert np.max(np.linalg.norm(logs.contact_force, axis=-1)) > 0.0


@pytest.mark.slow
def test_gradient_of_final_position_error_wrt_gains(robot, gains, short_scenario):
    """jax.grad through the whole rollout (smooth contact, no block_steps: the plain path
    a user differentiates): finite, non-zero, and along a random direction in log-gain space
    equal to a central difference. Both laws' gradients, gain group by gain group, are checked
    the same way through the tuning loss (tests/test_tuning.py)."""
    controller = "admittance"

    def final_error(log_gains):
        g = jax.tree.map(jnp.exp, log_gains)
        _, log = rollout(robot, short_scenario, g, controller)
        return metrics.final_position_error(log)

    log_gains = jax.tree.map(jnp.log, gains)
    value, gradient = jax.jit(jax.value_and_grad(final_error))(log_gains)
    leaves = jax.tree.leaves(gradient)
    assert all(np.all(np.isfinite(leaf)) for leaf in leaves)
    assert max(float(np.max(np.abs(leaf))) for leaf in leaves) > 0.0
    rng = np.random.default_rng(1)
    direction = jax.tree.map(lambda leaf: jnp.asarray(rng.normal(size=leaf.shape)), log_gains)
    slope = sum(float(jnp.vdot(g, d)) for g, d in zip(leaves, jax.tree.leaves(direction)))
    h = 1e-5
    evaluate = jax.jit(final_error)
    plus = evaluate(jax.tree.map(lambda x, d: x + h * d, log_gains, direction))
    minus = evaluate(jax.tree.map(lambda x, d: x - h * d, log_gains, direction))
    np.testing.assert_allclose(slope, (plus - minus) / (2 * h), rtol=1e-4, atol=1e-12 * abs(float(value)))


def test_rollout_rejects_a_log_block_that_does_not_divide_the_steps(robot, gains):
    # The same rule in the paper's loop and in the flight-like loop, before anything is traced.
    from spacegrasp_jax.loop.realism import flight

    scenario = paper_scenario(robot, duration=0.1)  # 100 steps
    loops = {"ideal": {}, "flight": dict(realism=flight(), key=jax.random.PRNGKey(0))}
    for segment in (0, 3):
        for loop, settings in loops.items():
            with pytest.raises(ValueError, match="block_steps: .* the 100 steps"):
                rollout(robot, scenario, gains, "admittance", block_steps=segment, **settings)
    # Its name before, with a warning that names the new one: the same check.
    with pytest.warns(DeprecationWarning, match="checkpoint_segment is now block_steps"):
        with pytest.raises(ValueError, match="block_steps: 3 must be a positive divisor of the 100 steps"):
            rollout(robot, scenario, gains, "admittance", checkpoint_segment=3)


@pytest.mark.parametrize(
    "law",
    [Admittance(), pytest.param(Cartesian(pinv_damping=0.01), marks=pytest.mark.slow)],
    ids=["admittance", "cartesian-damped"],
)
def test_a_law_object_runs_the_loop_its_name_runs(robot, gains, short_scenario, law):
    """The law is chosen by its object (static), which carries its settings; the object, the
    object chained with the joint PID and the registry's law of that name and damping are
    the same program, bit for bit."""
    simulate = jax.jit(rollout, static_argnames=("controller",))
    by_object = simulate(robot, short_scenario, gains, controller=law)[1]
    same = [chain(law, PID()), law_named(law.name, law.pinv_damping)]
    if law.pinv_damping == 0.0:
        same.append(law.name)
    for controller in same:
        other = simulate(robot, short_scenario, gains, controller=controller)[1]
        for name, value in vars(other).items():
            np.testing.assert_array_equal(getattr(by_object, name), value, err_msg=f"{controller}: {name}")
    if law.name == "cartesian":  # memoryless: no reference twist carried, zeros logged
        np.testing.assert_array_equal(by_object.V_ref, 0.0)
        assert jax.tree.leaves(initial_state(RunSpec(robot, short_scenario, law)).controller.law) == []
    else:
        assert np.max(np.abs(by_object.V_ref)) > 1e-3


def test_the_checkpointed_steps_of_rollout_change_nothing_in_a_forward_run(robot, gains, short_scenario):
    """``rollout`` checkpoints each step's parts (for gradients), with RK4's first
    stage beside the controller; the loop run without checkpointing has the four stages in
    one scan (``integrator.rk4_step``'s ``at_start``): the same operations in the same order,
    compiled as other code, so the two logs agree to rounding (measured: 1.2e-13 of a
    field's largest magnitude here, 3.3e-12 over the paper's 17 s), and the paper's
    reproduction does not depend on checkpointing."""
    from spacegrasp_jax.loop.simulate import LOG_BLOCK, FullLog, RunSpec, closed_loop

    def plain_rollout(robot, scenario, gains):  # the arguments as rollout's: nothing folded in
        spec = RunSpec(robot, scenario, "admittance", observer=FullLog(LOG_BLOCK))
        return closed_loop(spec, gains)[1]

    plain = jax.jit(plain_rollout)(robot, short_scenario, gains)
    checkpointed = jax.jit(rollout, static_argnames="controller")(robot, short_scenario, gains, "admittance")[1]
    for name, value in vars(checkpointed).items():
        if value is not None:
            expected = getattr(plain, name).reshape(value.shape)
            scale = float(np.max(np.abs(expected)))
            np.testing.assert_allclose(value, expected, rtol=0, atol=1e-11 * scale, err_msg=name)


def test_a_diverging_run_writes_what_it_has(robot, gains, tmp_path, capsys):
    """``spacegrasp simulate`` with gains that make the loop blow up: exit 3, and the log up
    to and including the first non-finite step, the summary with the divergence time and
    the state there, and the figures, all written (the same program as the test above)."""
    from spacegrasp_jax import cli

    (tmp_path / "wild.json").write_text(json.dumps({"kp": [1e7] * 7}))
    (tmp_path / "short.toml").write_text("duration = 0.5\n")
    out = tmp_path / "out"
    argv = ["simulate", "--controller", "cartesian", "--gains", str(tmp_path / "wild.json"), "--fill-from", "paper"]
    code = cli.main([*argv, "--scenario", str(tmp_path / "short.toml"), "--out", str(out), "--compile-cache", "none"])
    error = capsys.readouterr().err
    assert code == 3
    assert "the cartesian rollout diverged: first non-finite value at t = " in error and "Traceback" not in error
    summary = json.loads((out / "summary.json").read_text())["cartesian"]
    log = np.load(out / "timeseries_cartesian.npz")
    step = summary["first_nonfinite_step"]
    assert summary["diverged"] and 0 < step < 500
    assert log["t"].shape == (step + 1,) and summary["first_nonfinite_s"] == pytest.approx(log["t"][-1])
    assert not np.all(np.isfinite(log["u"][-1])) or not np.all(np.isfinite(log["q"][-1]))  # the last row is the bad one
    for name in ("q", "qd", "u", "pose_ee", "V_base"):
        assert np.all(np.isfinite(log[name][:-1])), name  # every row before it is finite
    assert summary["nonfinite_fields"] and set(summary["nonfinite_fields"]) <= set(log.files)
    np.testing.assert_array_equal(summary["state_before_divergence"]["q"], log["q"][-2])
    for name in summary["nonfinite_fields"]:
        assert None in np.ravel(np.asarray(summary["state_at_divergence"][name], dtype=object)), name
    assert summary["before_divergence"]["max_abs_torque_Nm"] == pytest.approx(np.max(np.abs(log["u"][:-1]), axis=0))
    assert len(list(out.glob("fig*.png"))) == len(plots.FIGURES)
    assert (out / "config.json").exists() and (out / "table5.csv").exists()


def test_a_run_spec_refuses_a_setting_that_cannot_be_part_of_a_programs_structure(robot, gains, short_scenario):
    """The controller and the observer are the spec's structure (static): one that is not
    hashable is refused when the host looks its program up, naming it, before any compile."""
    from spacegrasp_jax.loop.simulate import FullLog

    @dataclasses.dataclass
    class Unhashable:  # a dataclass that is not frozen has no hash
        block_steps: int | None = None

    with pytest.raises(ValueError, match=r"observer: .* is not hashable"):
        experiment.compiled_loop(RunSpec(robot, short_scenario, "admittance", observer=Unhashable()), gains)
    with pytest.raises(ValueError, match=r"controller: expected a name, a control law or a Controller"):
        RunSpec(robot, short_scenario, 3)
    spec = RunSpec(robot, short_scenario, "cartesian")
    assert spec.controller.name == "cartesian" and spec.observer == FullLog() and not spec.options.checkpoint
    leaves, structure = jax.tree.flatten(spec)
    rebuilt = jax.tree.unflatten(structure, leaves)  # a pytree that rebuilds itself
    assert jax.tree.structure(rebuilt) == structure and rebuilt.controller == spec.controller
