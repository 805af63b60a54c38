"""The ``spacegrasp tune`` command under the flight preset (noise keys, an unknown satellite,
100 Hz control with a delay, 1 kHz servos, torque limits; the batch's gradients clipped per
sample): the files it writes, that it converges, its option checks, and resume after an
interruption (a real SIGINT to a subprocess) to exactly the uninterrupted run's result. The
ideal loop's tuning is tested through the API (tests/test_tuning.py)."""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from spacegrasp_jax.loop.control import load_gains
from spacegrasp_jax.loop.realism import load_realism

#: Optimiser steps of the tune runs below: the interrupted run gets SIGINT after step 2, and
#: the steps left after it absorb the delay before the signal is handled on a loaded machine.
TUNE_STEPS = 8


def tune_command(tmp_path, out, *extra):
    scenario = tmp_path / "short.toml"
    scenario.write_text("duration = 1.0\n[trajectory]\nduration = 1.0\n")
    return [
        sys.executable,
        "-m",
        "spacegrasp_jax.cli",
        "tune",
        "--out",
        str(out),
        "--scenario",
        str(scenario),
        "--steps",
        str(TUNE_STEPS),
        "--holdout",
        "3",
        "--batch",
        "2",
        "--realism",
        "flight",
        "--method",
        "gradient",
        "--objective",
        "weighted",
        *extra,
    ]


def run_until_step(command, history, step, timeout=600):
    """Start ``command``, send SIGINT once ``history`` shows ``step`` completed steps."""
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + timeout
    while time.time() < deadline and process.poll() is None:
        if history.exists() and len(history.read_text().splitlines()) >= step + 2:  # header + step 0
            process.send_signal(signal.SIGINT)
            break
        time.sleep(0.05)
    _, err = process.communicate(timeout=timeout)
    return process.returncode, err


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    tmp_path = tmp_path_factory.mktemp("tune")
    out = tmp_path / "full"
    result = subprocess.run(tune_command(tmp_path, out), capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr
    return tmp_path, out, result


@pytest.mark.slow
def test_tune_writes_every_file(uninterrupted):
    _, out, result = uninterrupted
    assert f"step {TUNE_STEPS}/{TUNE_STEPS}" in result.stderr  # the progress bar
    for name in (
        "gains.json",
        "history.csv",
        "summary.json",
        "run.json",
        "checkpoint.npz",
        "loss.png",
        "peak_torques.png",
        "ee_pose.png",
    ):
        assert (out / name).stat().st_size > 0, name
    gains = load_gains(out / "gains.json", "admittance")  # loadable as simulate --gains takes it
    assert gains.kp.shape == (7,)
    rows = list(csv.DictReader((out / "history.csv").open()))
    assert [int(row["step"]) for row in rows] == list(range(TUNE_STEPS + 1))
    assert {
        "loss",
        "final_position_error_m",
        "peak_torque_smooth",
        "peak_torque_hard",
        "peak_torque_gap",
        "gradient_norm",
        "step_size",
    } <= set(rows[0])
    summary = json.loads((out / "summary.json").read_text())
    for key in ("paper_gains", "tuned_gains"):
        assert {
            "max_abs_torque_Nm",
            "final_position_error_m",
            "final_orientation_error_rad",
            "rms_position_error_m",
            "max_contact_force_N",
        } <= set(summary[key])
    assert summary["holdout"]["scenarios"] == 3
    with np.load(out / "holdout.npz") as samples:
        assert samples["start_loss"].shape == (3,) and samples["tuned_final_position_error_m"].shape == (3,)
    assert summary["evaluated_with"].startswith("exact contact law")


@pytest.mark.slow
def test_tuning_under_flight_converges(uninterrupted):
    _, out, _ = uninterrupted
    run = json.loads((out / "run.json").read_text())
    assert run["config"]["realism"] == json.loads(json.dumps(load_realism("flight").to_dict()))
    history = list(csv.DictReader((out / "history.csv").open()))
    losses = [float(row["loss"]) for row in history]
    assert all(np.isfinite(losses)) and "clipped_samples" in history[0]
    assert losses[-1] < 0.75 * losses[0]  # 55.4 -> 38.0 when written
    holdout = json.loads((out / "summary.json").read_text())["holdout"]  # under flight too
    assert holdout["mean_objective_tuned"] < holdout["mean_objective_start"]
    assert holdout["tuned_better_fraction"] >= 2 / 3


@pytest.mark.slow
def test_interrupted_run_resumes_to_the_same_result(uninterrupted):
    tmp_path, full, _ = uninterrupted
    out = tmp_path / "interrupted"
    code, err = run_until_step(tune_command(tmp_path, out), out / "history.csv", step=2)
    assert code == 130, err
    assert "--resume" in err
    steps_done = len((out / "history.csv").read_text().splitlines()) - 2
    assert 2 <= steps_done < TUNE_STEPS
    resume = [sys.executable, "-m", "spacegrasp_jax.cli", "tune", "--out", str(out), "--resume"]
    result = subprocess.run(resume, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr
    assert f"resuming after step {steps_done}/{TUNE_STEPS}" in result.stderr
    assert json.loads((out / "gains.json").read_text()) == json.loads((full / "gains.json").read_text())
    history = list(csv.DictReader((out / "history.csv").open()))
    reference = list(csv.DictReader((full / "history.csv").open()))
    assert [row["loss"] for row in history] == [row["loss"] for row in reference]
    # A finished gradient run given more steps continues: its steps so far stay as they were
    result = subprocess.run([*resume, "--steps", str(TUNE_STEPS + 2)], capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr
    assert f"resuming after step {TUNE_STEPS}/{TUNE_STEPS + 2}" in result.stderr
    extended = [row["loss"] for row in csv.DictReader((out / "history.csv").open())]
    assert len(extended) == TUNE_STEPS + 3 and extended[: TUNE_STEPS + 1] == [row["loss"] for row in reference]
    assert json.loads((out / "run.json").read_text())["config"]["steps"] == TUNE_STEPS + 2


@pytest.mark.slow
def test_fresh_batches_draw_each_steps_samples_and_an_interrupted_run_resumes_to_the_same_gains(uninterrupted):
    """``--fresh-batches``: step 0 runs on the run's batch (its loss is the one-batch run's),
    every later step on a batch of its own; a run stopped after step 2 resumes to exactly the
    uninterrupted run's gains and losses (each step's batch follows from its number)."""
    tmp_path, one_batch, _ = uninterrupted
    extra = ("--fresh-batches", "--aggregate", "median_of_means")
    full = tmp_path / "fresh"
    result = subprocess.run(tune_command(tmp_path, full, *extra), capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr
    fresh = list(csv.DictReader((full / "history.csv").open()))
    fixed = list(csv.DictReader((one_batch / "history.csv").open()))
    assert fresh[0]["loss"] == fixed[0]["loss"]
    assert len({row["loss"] for row in fresh}) == len(fresh)
    assert json.loads((full / "run.json").read_text())["config"]["fresh_batches"] is True

    out = tmp_path / "fresh_interrupted"
    code, err = run_until_step(tune_command(tmp_path, out, *extra), out / "history.csv", step=2)
    assert code == 130, err
    resume = [sys.executable, "-m", "spacegrasp_jax.cli", "tune", "--out", str(out), "--resume"]
    result = subprocess.run(resume, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr
    assert json.loads((out / "gains.json").read_text()) == json.loads((full / "gains.json").read_text())
    assert [row["loss"] for row in csv.DictReader((out / "history.csv").open())] == [row["loss"] for row in fresh]


@pytest.mark.slow
def test_tune_refuses_to_overwrite_and_rejects_bad_options(uninterrupted, tmp_path):
    _, full, _ = uninterrupted
    result = subprocess.run(tune_command(tmp_path, full), capture_output=True, text=True, timeout=300)
    assert result.returncode == 2 and "already holds a tune run (started" in result.stderr
    # A resume is the recorded run: each option given that differs is named, nothing runs.
    before = sorted((path.name, path.stat().st_mtime_ns) for path in full.iterdir())
    changed = ["--batch", "8", "--lr", "0.5", "--steps", "12", "--realism", "flight"]
    result = subprocess.run(
        [sys.executable, "-m", "spacegrasp_jax.cli", "tune", "--out", str(full), "--resume", *changed],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 2, result.stderr
    line = result.stderr.strip().splitlines()[-1]
    assert "--batch 8 (the run's: 2)" in line and "--lr 0.5 (the run's: 0.15)" in line, line
    assert "--steps 12" not in line and "--realism" not in line, line  # more steps continue a run
    assert sorted((path.name, path.stat().st_mtime_ns) for path in full.iterdir()) == before
    result = subprocess.run(
        tune_command(tmp_path, tmp_path / "x", "--weights", "speed=1"), capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 2 and "unknown weight 'speed'" in result.stderr
    result = subprocess.run(
        [sys.executable, "-m", "spacegrasp_jax.cli", "tune", "--out", str(tmp_path / "none"), "--resume"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 2 and "holds no tuning run" in result.stderr


def test_tune_draws_from_the_envelope_it_is_given(tmp_path):
    from spacegrasp_jax.cli import build_parser
    from spacegrasp_jax.cli.tune import _tune_config
    from spacegrasp_jax.envelope.perturbations import PerturbationRanges
    from spacegrasp_jax.tuning.tune import TUNING_RANGES

    def config(*options):
        return _tune_config(build_parser().parse_args(["tune", "--out", str(tmp_path / "x"), *options]), None)

    assert config().ranges == TUNING_RANGES
    assert config("--ranges", "montecarlo").ranges == PerturbationRanges()  # the campaigns' defaults
    ranges_file = tmp_path / "ranges.toml"
    ranges_file.write_text("q_init_rad = 0.04\n")
    from_file = config("--ranges", str(ranges_file), "--range", "lar_position_m=0.007").ranges
    assert (from_file.q_init_rad, from_file.lar_position_m) == (0.04, 0.007)
    assert from_file.base_speed_mps == TUNING_RANGES.base_speed_mps  # the rest: the tuning envelope
    wide = config("--ranges", "lar_wide", "--scale", "2", "--range", "q_init_rad=0.05").ranges
    assert (wide.lar_position_m, wide.lar_estimate_angle_rad, wide.q_init_rad) == (0.02, 0.02, 0.05)  # --range last
    assert wide.stiffness_factor == PerturbationRanges().stiffness_factor ** 2
    for options, message in (
        (["--range", "q_init=0.1"], "unknown perturbation range 'q_init'"),
        (["--ranges", str(tmp_path / "missing.toml")], "missing.toml: no such file"),
        (["--method", "cmaes", "--realism", "flight", "--noise-handling"], "--noise-handling: measures the noise"),
        (["--realism", "flight", "--separable"], "--separable: a setting of CMA-ES"),
        (["--ranges", "montecarlo", "--scale", "10"], "--scale 10: radius_fraction: 0.1 times 10 reaches 1"),
    ):
        result = subprocess.run(
            [sys.executable, "-m", "spacegrasp_jax.cli", "tune", "--out", str(tmp_path / "y"), *options],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert result.returncode == 2 and message in result.stderr and "Traceback" not in result.stderr


def cmaes_command(tmp_path, out, steps):
    """CMA-ES on the default objective (capture), tiny."""
    command = tune_command(tmp_path, out)
    cut = command.index("--method")
    command = command[:cut] + ["--method", "cmaes", "--population", "3"]
    command[command.index("--steps") + 1] = str(steps)
    return command


RACES = Path(__file__).parent.parent / "notebooks" / "data"

#: The options of a race's command that choose its method (the recipe); the rest state the problem.
RECIPE_OPTIONS = {"--method": 1, "--fresh-batches": 0, "--aggregate": 1, "--steps": 1, "--batch": 1}


def _problem_and_recipe(command: str) -> tuple[list[str], list[str]]:
    """A race's ``spacegrasp tune`` command split into the problem's options and the method's."""
    words, problem, recipe = command.split()[2:], [], []
    while words:
        word = words.pop(0)
        if word in RECIPE_OPTIONS:
            recipe += [word, *[words.pop(0) for _ in range(RECIPE_OPTIONS[word])]]
        elif word != "--out":
            problem.append(word)
        else:
            words.pop(0)
    return problem, recipe


@pytest.mark.parametrize("race", ["race", "race_schedule_time"])
def test_without_method_tune_runs_the_recipe_that_won_the_race_on_its_problem(race, tmp_path, capsys):
    """The race's record (committed data) names the winner at 15 minutes, held out; tune
    given only the race's problem must build the winner's configuration, option for option."""
    from spacegrasp_jax.cli import build_parser
    from spacegrasp_jax.cli.tune import _say_recipe, _tune_config

    record = json.loads((RACES / race / "race.json").read_text())
    winner = record["heldout"]["gradient_fresh_15min"]
    assert winner["vs_cmaes_same_mark"]["p_value"] < 0.05
    assert winner["success"]["rate"] > record["heldout"]["cmaes_15min"]["success"]["rate"]
    problem, recipe = _problem_and_recipe(record["methods"]["gradient_fresh"]["command"])
    assert "--method" in recipe and "--realism" in problem

    def config(*options):
        return _tune_config(build_parser().parse_args(["tune", "--out", str(tmp_path / "x"), *options]), None)

    # A race holds out the run's checkpoint at each mark, its last step: --keep last.
    assert config(*problem) == config(*problem, *recipe, "--keep", "last")
    overridden = config(*problem, "--batch", "8", "--no-fresh-batches", "--steps", "3")
    assert (overridden.method, overridden.batch, overridden.fresh_batches, overridden.steps) == (
        "gradient",
        8,
        False,
        3,
    )
    explicit = config(*problem, "--method", "gradient")  # an explicit method keeps its own defaults
    assert (explicit.settings.aggregate, explicit.fresh_batches, explicit.batch) == ("clip", False, 4)
    assert config(*problem, "--method", "cmaes").method == "cmaes"
    ideal = [word for word in problem if word not in ("--realism", "flight")]
    assert (config(*ideal).method, config(*ideal).batch, config(*ideal).steps) == ("cmaes", 4, 60)
    assert config(*ideal, "--realism", "ideal").method == "cmaes"  # the paper's loop under the realism code: not raced
    # The races held out each run's last step (its checkpoint at the mark): the recipe hands it back.
    assert config(*problem).keep == "last" and config(*problem, "--keep", "best").keep == "best"
    assert explicit.keep == "best" and config(*ideal).keep == "best"
    _say_recipe(config(*problem))
    assert "gradient method, fresh batches of 32, median_of_means, 75 steps, the last step's gains" in (
        capsys.readouterr().err
    )


@pytest.mark.slow
def test_a_cmaes_run_writes_its_files_and_resumes_to_the_same_gains(tmp_path, capsys):
    """A CMA-ES run interrupted after its first generation: its check (``--check``) writes the
    summary, held-out captures included, of an uninterrupted run of as many generations; it
    then resumes to the means of an uninterrupted run, and a finished run given more
    generations continues to exactly the run of that many from the start: its history and
    its gains."""
    from spacegrasp_jax import cli

    six = tmp_path / "cmaes_six"
    result = subprocess.run(cmaes_command(tmp_path, six, 6), capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr
    assert "CMA-ES on the admittance capture objective over 2 scenario(s), 40 numbers" in result.stderr
    rows = list(csv.DictReader((six / "history.csv").open()))
    assert [int(row["step"]) for row in rows] == list(range(7))  # the mean after 0..6 generations
    assert {"loss", "capture_loss", "position_margin", "torque_margin", "best_candidate_loss", "sigma"} <= set(rows[0])
    summary = json.loads((six / "summary.json").read_text())
    assert summary["method"] == "cmaes" and summary["objective_kind"] == "capture"
    assert load_gains(six / "gains.json", "admittance").pinv_damping.shape == (1,)
    out = tmp_path / "cmaes_interrupted"
    code, err = run_until_step(cmaes_command(tmp_path, out, 4), out / "history.csv", step=1)
    assert code == 130, err
    assert f"check the gains so far with: spacegrasp tune --out {out} --check" in err
    # Its check: the summary that a run of as many generations writes, held-out captures and all
    steps_done = json.loads((out / "run.json").read_text())["config"]["steps"]
    done = len(list(csv.DictReader((out / "history.csv").open()))) - 1
    assert 1 <= done < steps_done
    assert cli.main(["tune", "--out", str(out), "--check", "--compile-cache", "none"]) == 0
    err = capsys.readouterr().err
    assert f"checking the run as it stands after generation {done}/4" in err and "resuming" not in err
    assert f"checked the run as it stands after step {done} of 4" in err
    stopped_there = tmp_path / "cmaes_as_many"
    assert cli.main([*cmaes_command(tmp_path, stopped_there, done)[3:], "--compile-cache", "none"]) == 0
    checked, uninterrupted = (json.loads((folder / "summary.json").read_text()) for folder in (out, stopped_there))
    assert checked["checked_after"] == {"step": done, "of": 4} and checked["status"] == "interrupted"
    assert checked["holdout"] == uninterrupted["holdout"] and checked["holdout"]["scenarios"] == 3
    assert checked["tuned_gains"] == uninterrupted["tuned_gains"]  # the nominal run's numbers
    assert json.loads((out / "gains.json").read_text()) == json.loads((stopped_there / "gains.json").read_text())
    assert cli.main(["tune", "--out", str(out), "--check", "--steps", "9"]) == 2
    assert "--check: checks the run in --out as it was set up; it takes --holdout only, not --steps" in (
        capsys.readouterr().err
    )
    resume = [sys.executable, "-m", "spacegrasp_jax.cli", "tune", "--out", str(out), "--resume"]
    result = subprocess.run(resume, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr
    assert "resuming after generation" in result.stderr
    # A generation's mean does not depend on how many follow it: the four-generation run's
    # means are the six-generation run's first.
    assert [row["loss"] for row in csv.DictReader((out / "history.csv").open())] == [row["loss"] for row in rows[:5]]
    # More generations are the one option a CMA-ES resume may change: the finished run
    # continues to exactly a run of that many generations from the start.
    result = subprocess.run([*resume, "--steps", "6"], capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr
    assert "resuming after generation 4/6" in result.stderr
    assert json.loads((out / "gains.json").read_text()) == json.loads((six / "gains.json").read_text())
    extended = [row["loss"] for row in csv.DictReader((out / "history.csv").open())]
    assert extended == [row["loss"] for row in rows] and len(extended) == 7
    assert json.loads((out / "run.json").read_text())["config"]["steps"] == 6
    result = subprocess.run([*resume, "--population", "5"], capture_output=True, text=True, timeout=300)
    assert result.returncode == 2 and "--population 5 (the run's: 3)" in result.stderr


@pytest.mark.slow
def test_a_run_that_ends_worse_than_it_started_hands_back_the_start_and_says_so(tmp_path, capsys):
    """A tuning run whose result is worse than its start on the held-out captures (one CMA-ES
    generation of a wide step on one capture, the final mean kept): ``gains.json`` holds the
    starting gains, the tuned ones lie beside it in ``gains_tuned.json``, one line says so, and
    the summary records it. With ``--keep best`` (the default) the run hands back the least
    training objective it saw."""
    from spacegrasp_jax import cli
    from spacegrasp_jax.loop.control import paper_gains

    scenario = tmp_path / "short.toml"
    scenario.write_text("duration = 1.0\n[trajectory]\nduration = 1.0\n")
    base = ["tune", "--compile-cache", "none", "--scenario", str(scenario), "--objective", "weighted"]
    base += ["--steps", "1", "--step-size", "1.5", "--population", "4", "--batch", "1", "--holdout", "8"]
    out = tmp_path / "last"
    assert cli.main([*base, "--keep", "last", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    holdout = summary["holdout"]
    assert holdout["mean_objective_tuned"] > holdout["mean_objective_start"]  # the case: a worse result
    assert summary["gains_file"] == "start" and summary["kept"]["what"] == "the mean after generation 1"
    assert json.loads((out / "gains.json").read_text()) == paper_gains().to_dict("admittance")
    assert json.loads((out / "gains_tuned.json").read_text()) != paper_gains().to_dict("admittance")
    err = capsys.readouterr().err
    assert "the tuned gains are not better than the starting gains on the 8 held-out captures" in err
    assert "gains.json holds the starting gains, the tuned ones are in gains_tuned.json" in err
    out = tmp_path / "best"
    assert cli.main([*base, "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    told = [float(row["best_candidate_loss"]) for row in csv.DictReader((out / "history.csv").open())][1:]
    assert summary["kept"]["training_objective"] == min([*told, summary["kept"]["training_objective"]])


@pytest.mark.slow
def test_early_stopping_from_the_command_line(tmp_path, capsys):
    """``--patience``: the run evaluates each mean on its validation captures, stops once they
    stall, hands back the mean with the best validation objective and records it; a setting
    of early stopping without it is refused."""
    from spacegrasp_jax import cli

    scenario = tmp_path / "short.toml"
    scenario.write_text("duration = 1.0\n[trajectory]\nduration = 1.0\n")
    base = ["tune", "--compile-cache", "none", "--scenario", str(scenario), "--population", "4", "--batch", "1"]
    base += ["--holdout", "0", "--step-size", "0.5"]
    out = tmp_path / "early"
    assert cli.main([*base, "--steps", "8", "--patience", "1", "--validation-size", "2", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    kept = summary["kept"]
    assert kept["rule"] == "best by validation" and kept["what"] == f"the mean after generation {kept['step']}"
    record = np.load(out / "checkpoint.npz")
    validation = [row["validation_loss"] for row in json.loads(str(record["meta"]))["history"]]
    assert kept["validation_objective"] == min(validation)
    # this run's validation objective stalls after generation 4 of 8 (seed 0)
    assert summary["status"] == "stopped_early" and len(validation) - 1 == kept["step"] + 1 < 8
    assert "stopped early: the validation objective has not improved for 1 generations" in capsys.readouterr().err
    assert cli.main([*base, "--validation-size", "4", "--out", str(tmp_path / "refused")]) == 2
    assert "--validation-size: the validation set of early stopping (choose --patience)" in capsys.readouterr().err
