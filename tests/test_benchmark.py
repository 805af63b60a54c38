"""``spacegrasp benchmark --quick`` runs every part (ours, MuJoCo, the Pinocchio loop) so the
benchmark never rots. No assertion on time: only that every figure is there and sane, and
that the Pinocchio peer simulated the same closed loop as ours."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import jax
import numpy as np
import pytest

from spacegrasp_jax.benchmarks.suite import KEYS


@pytest.mark.slow
def test_quick_benchmark_writes_every_key(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "spacegrasp_jax.cli", "benchmark", "--quick", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    report = json.loads((tmp_path / "benchmark.json").read_text())
    assert set(KEYS) <= set(report), set(KEYS) - set(report)
    assert set(report["rollout_s"]) == {"admittance", "cartesian"}
    assert set(report["batch_steps_per_s"]) == {"1", "4"}
    assert set(report["gradient_over_forward"]) == {"reverse", "truncated", "forward"}
    numbers = [
        *report["rollout_s"].values(),
        *report["compile_s"].values(),
        *report["flight_over_ideal_step"].values(),
        report["free_target_over_stationary_step"],
        report["schedule_over_constant_step"],
        *report["batch_steps_per_s"].values(),
        *report["gradient_over_forward"].values(),
        report["gradient_peak_mb"]["reverse"],
        report["flops_per_step"],
        report["pinocchio_loop_rollout_s"],
        report["mujoco_mj_step_17s_s"],
        report["mujoco_rollout_steps_per_s"],
    ]
    assert all(math.isfinite(x) and x > 0 for x in numbers), numbers
    assert report["pinocchio_loop_max_pose_difference"] < 1e-6
    assert "spacegrasp-jax" in result.stdout and "ratio" in result.stdout
    assert not any(tmp_path.glob("benchmark-*")), "intermediate files left behind"


def test_batch_efficiency_reports_each_part(tmp_path):
    """``benchmarks.batch_efficiency`` at toy size: a row per requested part with finite
    positive times; an unknown part is refused before anything compiles."""
    base = [sys.executable, "-m", "spacegrasp_jax.benchmarks.batch_efficiency", "--out", str(tmp_path)]
    toy_size = ["--batch", "4", "--iterations", "10", "--repeats", "1"]
    result = subprocess.run(base + ["--parts", "kinematics"] + toy_size, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    report = json.loads((tmp_path / "batch_efficiency.json").read_text())
    assert [row["part"] for row in report["results"]] == ["kinematics"]
    row = report["results"][0]
    numbers = [row["single_us_per_sample"], row["batch_us_per_sample"], row["batch_gain"]]
    assert all(math.isfinite(x) and x > 0 for x in numbers), numbers
    assert math.isclose(row["batch_gain"], row["single_us_per_sample"] / row["batch_us_per_sample"])

    refused = subprocess.run(base + ["--parts", "kinematics,rnea"], capture_output=True, text=True, timeout=60)
    assert refused.returncode == 2 and "unknown ['rnea']" in refused.stderr


@pytest.mark.slow
def test_gradient_parts_reports_each_part(tmp_path):
    """``benchmarks.gradient_parts`` on two states: a row per part with finite positive
    forward and reverse times; bad options are refused before anything compiles."""
    from spacegrasp_jax.benchmarks.gradient_parts import PARTS

    base = [sys.executable, "-m", "spacegrasp_jax.benchmarks.gradient_parts", "--out", str(tmp_path)]
    result = subprocess.run(base + ["--states", "2", "--repeats", "1"], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    report = json.loads((tmp_path / "gradient_parts.json").read_text())
    assert [row["part"] for row in report["results"]] == list(PARTS)
    for row in report["results"]:
        numbers = [row["forward_us"], row["reverse_us"], row["reverse_over_forward"]]
        assert all(math.isfinite(x) and x > 0 for x in numbers), row
        assert math.isclose(row["reverse_over_forward"], row["reverse_us"] / row["forward_us"])

    for option, message in (
        (["--parts", "stage,rnea"], "unknown ['rnea']"),
        (["--states", "5000"], "--states must be"),
    ):
        refused = subprocess.run(base + option, capture_output=True, text=True, timeout=60)
        assert refused.returncode == 2 and message in refused.stderr, refused.stderr


def test_kinematics_by_component_equals_the_package_kinematics():
    """The probe of ``benchmarks.batch_efficiency`` computes the same frames as
    ``kinematics.forward_kinematics``, for one sample and under ``vmap``."""
    import jax
    import numpy as np

    import spacegrasp_jax as sg
    from spacegrasp_jax.benchmarks.batch_efficiency import forward_kinematics_by_component
    from spacegrasp_jax.core.kinematics import forward_kinematics
    from spacegrasp_jax.core.spatial import rotation_exp

    robot, rng = sg.paper_robot(), np.random.default_rng(3)
    q, p_base = rng.uniform(-np.pi, np.pi, (5, 7)), rng.normal(size=(5, 3))
    R_base = np.stack([np.asarray(rotation_exp(v)) for v in rng.normal(size=(5, 3))])
    expected = jax.vmap(lambda p, R, q: forward_kinematics(robot, p, R, q))(p_base, R_base, q)
    batched = jax.vmap(lambda p, R, q: forward_kinematics_by_component(robot, p, R, q))(p_base, R_base, q)
    single = forward_kinematics_by_component(robot, p_base[0], R_base[0], q[0])
    for name in vars(expected):
        np.testing.assert_allclose(getattr(batched, name), getattr(expected, name), atol=1e-14, err_msg=name)
        np.testing.assert_allclose(getattr(single, name), getattr(expected, name)[0], atol=1e-14, err_msg=name)


def test_compile_benchmark_times_its_calls_in_turn_after_the_warm_up():
    """``benchmarks.compile`` times a gradient and its forward rollout in alternation, after
    untimed rounds: each call is timed once per round, the warm-up's calls are not timed."""
    from spacegrasp_jax.benchmarks.compile import timed_after_warmup

    order = []
    calls = {"run": lambda: order.append("run"), "forward": lambda: order.append("forward")}
    times = timed_after_warmup(calls, warmup=2, repeats=3)
    assert order == ["run", "forward"] * 5
    assert {name: len(t) for name, t in times.items()} == {"run": 3, "forward": 3}
    assert all(t >= 0 for t in times["run"] + times["forward"])


@pytest.mark.slow
def test_worstcase_benchmark_writes_its_rows_resumes_and_refuses_bad_options(tmp_path):
    """``benchmarks.worstcase`` on one seed of a 0.1 s approach and a budget of 12: one row
    whose ratio and verdicts follow from its two worst values, a summary of it; run again,
    it runs nothing (the row is there); bad options are refused before anything compiles."""
    base = [sys.executable, "-m", "spacegrasp_jax.benchmarks.worstcase", "--out", str(tmp_path)]
    toy = ["--seeds", "0", "--budgets", "12", "--realisms", "ideal", "--durations", "0.1", "--methods", "cem"]
    result = subprocess.run(base + toy, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    rows = [json.loads(line) for line in (tmp_path / "rows.jsonl").read_text().splitlines()]
    assert len(rows) == 1 and rows[0]["rollouts"] == 12
    row = rows[0]
    assert math.isclose(row["ratio"], row["search_worst"] / row["campaign_worst"])
    assert row["at_least_as_bad"] == (row["search_worst"] >= row["campaign_worst"])
    summary = json.loads((tmp_path / "summary.json").read_text())["summary"]
    assert summary["0.1 s, ideal, budget 12, cem"]["seeds"] == 1
    again = subprocess.run(base + toy, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0 and "seed 0" not in again.stdout
    assert len((tmp_path / "rows.jsonl").read_text().splitlines()) == 1
    for option, message in (
        (["--methods", "anneal"], "--methods: 'anneal' is not one of cem, ascent"),
        (["--durations", "20"], "--durations: 20 s is outside (0, 17]"),
        (["--budgets", "12", "--methods", "ascent"], "--budgets: ascent: budget: must be an integer of at least 20"),
    ):
        refused = subprocess.run(base + option, capture_output=True, text=True, timeout=60)
        assert refused.returncode == 2 and message in refused.stderr, refused.stderr


@pytest.mark.parametrize(
    "module, argv, named",
    [
        ("truncation", ["--cuts", "20"], "--cuts"),
        ("truncation", ["--cuts", "x"], "--cuts"),
        ("truncation", ["--gains", "nope"], "--gains"),
        ("truncation", ["--n", "1"], "--n"),
        ("worstcase_settings", ["--budget", "32"], "--budget"),
        ("worstcase_settings", ["--realism", "nope"], "--realism"),
        ("worstcase_settings", ["--seeds", "a-b"], "--seeds"),
        ("worstcase_settings", ["--duration", "0"], "--duration"),
        ("worstcase_settings", ["--lines", "--subspace"], "argument --subspace"),
        ("gradient", ["--gradient-from", "20"], "--gradient-from"),
        ("gradient", ["--modes", "forward,nope"], "unknown mode(s)"),
    ],
)
def test_the_gradient_probes_refuse_bad_options_before_anything_runs(module, argv, named, capsys):
    """``benchmarks.truncation``, ``benchmarks.worstcase_settings`` and ``benchmarks.gradient``:
    a bad option exits 2 naming it, before the package is configured or anything compiles."""
    import importlib

    main = importlib.import_module(f"spacegrasp_jax.benchmarks.{module}").main
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2 and f"error: {named}:" in capsys.readouterr().err


def test_the_gradient_chosen_coordinate_search_scans_the_steepest_coordinate_and_keeps_the_best():
    """``worstcase_settings --coordinates`` on a measure of known shape: a hump in the first
    joint's initial angle (``U`` 0.5, width 0.1) and a gentle slope in the second's. From the
    best screened sample (near the hump) the first round scans the first joint's coordinate
    towards the hump and keeps the scan's best point (computed here); the second scans the
    second joint's up to its bound."""
    import jax.numpy as jnp
    from jax.flatten_util import ravel_pytree

    from spacegrasp_jax.analysis import worstcase
    from spacegrasp_jax.benchmarks.worstcase_settings import COORDINATE_FRACTIONS, gradient_coordinates

    def measure(units, key):
        return jnp.exp(-(((units.dq_init[0] - 0.5) / 0.1) ** 2)) + 0.01 * units.dq_init[1]

    programs = (jax.value_and_grad(measure), jax.vmap(measure))
    seed, budget = 3, 64
    units = worstcase.units_of_samples(seed, range(budget // 4))
    values = np.asarray(jax.vmap(measure)(units, None)).copy()
    start = int(np.argmax(values))
    flat = np.asarray(ravel_pytree(jax.tree.map(lambda x: x[start], units))[0])
    u0, u1 = flat[0], flat[1]
    side = np.sign(0.5 - u0)  # the hump's side: where the first coordinate's derivative points
    scanned = u0 + side * (1.0 - side * u0) * np.asarray(COORDINATE_FRACTIONS)
    best_first = max(float(values[start]), *(float(np.exp(-(((x - 0.5) / 0.1) ** 2)) + 0.01 * u1) for x in scanned))
    found = gradient_coordinates(programs, seed, values, budget)
    assert found["coordinates_rollouts"] == budget // 4 + 4 * (4 + len(COORDINATE_FRACTIONS))
    np.testing.assert_allclose(found["coordinates_rounds"][1], best_first, rtol=1e-12)
    assert found["coordinates_rounds"][2] == pytest.approx(best_first + 0.01 * (1.0 - u1), rel=1e-12)
    assert found["coordinates"] == max(found["coordinates_rounds"])


def test_the_gradient_subspace_search_spends_its_budget_moving_the_steepest_coordinates():
    """``worstcase_settings --subspace`` on a bowl upside down in the first joint's initial
    angle (top 0 at ``U`` 0.3) plus a ramp in the radius, which is outside the bowl's
    coordinates but among the 8 steepest: the search climbs from its start, never above the
    top the two reach together, and spends exactly the budget."""

    from spacegrasp_jax.analysis import worstcase
    from spacegrasp_jax.benchmarks.worstcase_settings import gradient_subspace

    def measure(units, key):
        return -((units.dq_init[0] - 0.3) ** 2) + 0.1 * units.radius_scale

    programs = (jax.value_and_grad(measure), jax.vmap(measure))
    seed, budget = 5, 64
    values = np.asarray(jax.vmap(measure)(worstcase.units_of_samples(seed, range(budget // 4)), None)).copy()
    found = gradient_subspace(programs, seed, values, budget)
    assert found["subspace_rollouts"] == budget
    assert found["subspace_start"] == values.max()
    assert found["subspace_start"] + 0.02 < found["subspace"] <= 0.1


@pytest.mark.parametrize(
    "module, argv, said",
    [
        ("equivalence", ["--save", "a.npz", "--tolerance", "-1"], "--tolerance: must be a non-negative number"),
        ("equivalence", ["--against", "nowhere.npz"], "--against: no such file: nowhere.npz"),
        ("equivalence", [], "one of the arguments --save --against is required"),
        ("version_timings", ["--out", "t.json", "--repeats", "0"], "--repeats: must be at least 1"),
        ("config_walk", ["--method", "nelder-mead"], "argument --method: invalid choice"),
        ("config_walk", ["--realism", "mars"], "argument --realism: invalid choice"),
    ],
)
def test_the_version_checks_refuse_bad_options_before_anything_runs(module, argv, said, capsys, tmp_path, monkeypatch):
    """``benchmarks.equivalence``, ``version_timings`` and ``config_walk``: a bad option exits 2
    naming it, before the package is configured or anything runs."""
    import importlib

    monkeypatch.chdir(tmp_path)
    main = importlib.import_module(f"spacegrasp_jax.benchmarks.{module}").main
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2 and said in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_a_runs_compile_estimate_counts_what_its_first_row_evaluated(tmp_path):
    """A CMA-ES run's first row evaluates the start on one batch (32 rollouts), each later
    step a generation of 16 candidates (512): its compile is the first row's wall time less a
    sixteenth of a step's, not less a whole step's. A gradient run's first row is a step."""
    from spacegrasp_jax.benchmarks.tuning import compile_estimate

    history = tmp_path / "history.csv"
    history.write_text("step,wall_s\n0,17.2\n1,29.0\n2,29.5\n3,30.0\n")
    cmaes = {"5": {"steps": 9, "rollouts": 32 + 9 * 512}, "15": {"steps": 29, "rollouts": 32 + 29 * 512}}
    assert math.isclose(compile_estimate(history, cmaes), 17.2 - 29.5 / 16, rel_tol=1e-12)
    gradient = {"5": {"steps": 30, "gradients": 31 * 32}, "15": {"steps": 98, "gradients": 99 * 32}}
    assert math.isclose(compile_estimate(history, gradient), 17.2 - 29.5, rel_tol=1e-12)
    assert math.isclose(compile_estimate(history), 17.2 - 29.5, rel_tol=1e-12)  # no counts: a step


def test_the_timing_study_pairs_each_gain_set_with_itself_across_timings():
    """``benchmarks.timing``'s summary on made-up successes of 1,000 captures: a set that loses
    12 captures and wins 2 back with the timing drawn changes by -1.0 points, and each set is
    compared with the clock's schedule on the drawn timing."""
    from spacegrasp_jax.benchmarks.timing import timing_summary

    nominal = {"time_schedule": np.ones(1000, bool), "contact_time_schedule": np.ones(1000, bool)}
    nominal["contact_time_schedule"][:2] = False
    drawn = {"time_schedule": np.ones(1000, bool), "contact_time_schedule": np.ones(1000, bool)}
    drawn["time_schedule"][100:150] = False
    drawn["contact_time_schedule"][10:22] = False
    summary = timing_summary(nominal, drawn, "time_schedule")
    change = summary["contact_time_schedule"]["timing_change"]
    assert (change["only_reference"], change["only_candidate"]) == (12, 2)
    assert change["rate_difference"] == pytest.approx(-0.010)
    assert change["rate_difference_low"] < -0.010 < change["rate_difference_high"]
    assert summary["time_schedule"]["drawn"]["rate"] == pytest.approx(0.95)
    versus = summary["versus_time_schedule"]["contact_time_schedule"]
    assert (versus["only_reference"], versus["only_candidate"]) == (12, 50)
    assert list(summary["versus_time_schedule"]) == ["contact_time_schedule"]
    with pytest.raises(ValueError, match="other gain sets"):
        timing_summary(nominal, {"time_schedule": drawn["time_schedule"]}, "time_schedule")


def test_the_compile_probes_digest_tells_numbers_apart_bit_for_bit():
    from spacegrasp_jax.benchmarks.compile import output_digest

    outputs = {"a": np.linspace(0.0, 1.0, 7), "b": (np.arange(3), np.float64(2.5))}
    same = {"a": np.linspace(0.0, 1.0, 7), "b": (np.arange(3), np.float64(2.5))}
    assert output_digest(outputs) == output_digest(same)
    nudged = {"a": outputs["a"].copy(), "b": outputs["b"]}
    nudged["a"][3] = np.nextafter(nudged["a"][3], 2.0)  # one unit in the last place
    assert output_digest(nudged) != output_digest(outputs)
    reshaped = {"a": outputs["a"].reshape(7, 1), "b": outputs["b"]}
    assert output_digest(reshaped) != output_digest(outputs)
