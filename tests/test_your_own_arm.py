"""A new user's own arm from the command line and Python: stock URDFs with several leaves
(example-robot-data 6.0.0's Franka Panda, UR10, Kinova Jaco and xArm7, unchanged; the last
three in tests/data/arms, BSD-2-Clause), mounted on the paper's satellite unless told
otherwise, and run folders that keep their robot, so they work from anywhere once moved."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import warnings
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

import spacegrasp_jax as sg
from spacegrasp_jax import cli
from spacegrasp_jax.core.joint_limits import first_crossings, outside_ranges
from spacegrasp_jax.core.model import n_joints, robot_to_toml
from spacegrasp_jax.core.robot_files import load_robot, robot_from_toml
from spacegrasp_jax.core.urdf import URDFError
from spacegrasp_jax.envelope.scenario import load_scenario
from spacegrasp_jax.loop.control import load_gains, paper_gains
from spacegrasp_jax.loop.control.gains import effective_joint_inertia, starting_gains

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
ARMS = Path(__file__).resolve().parent / "data" / "arms"
PANDA = CONFIGS / "arms" / "panda.urdf"
UR10 = ARMS / "ur10_robot.urdf"


def robots_equal(a, b) -> bool:
    return all(np.array_equal(np.asarray(getattr(a, name)), np.asarray(getattr(b, name))) for name in vars(a))


@pytest.mark.parametrize(
    "source",
    ["paper", "ur5_on_satellite.toml", "panda_on_satellite.toml"],
)
def test_a_robot_written_as_toml_reads_back_bit_for_bit(source):
    robot = sg.paper_robot() if source == "paper" else load_robot(CONFIGS / source)
    text = robot_to_toml(robot, "first line\nsecond line")
    assert text.startswith("# first line\n# second line\n")
    assert robots_equal(robot_from_toml(text), robot)


def test_a_urdf_arm_is_mounted_on_the_papers_satellite_unless_told_otherwise(tmp_path):
    """``--mount paper`` (the default for a URDF): the 500 kg satellite with the paper's inertia,
    the arm's base link and what is fixed to it added; ``urdf``: the URDF is the whole servicer
    (the Panda's 0.63 kg link 0 its "satellite"); a mounting file: its satellite. The mounted
    robot is the one a mounting TOML with the paper's satellite describes."""
    paper = sg.paper_robot()
    mounted = load_robot(PANDA, tip_link="panda_hand_tcp")
    assert 500.0 < float(mounted.satellite_mass) < 501.0
    alone = load_robot(PANDA, mount="urdf", tip_link="panda_hand_tcp")
    assert float(alone.satellite_mass) < 1.0
    by_file = tmp_path / "mount.toml"
    by_file.write_text(
        "[satellite]\nmass = 500.0\ninertia = [[79.0, 0.0, 0.0], [0.0, 79.0, 0.0], [0.0, 0.0, 117.0]]\n"
        "mount_position = [0.2, 0.2, 0.2]\n"
    )
    assert robots_equal(load_robot(PANDA, mount=by_file, tip_link="panda_hand_tcp"), mounted)
    assert np.asarray(paper.satellite_mass) == 500.0
    toml = tmp_path / "panda_mount.toml"
    toml.write_text(f'[urdf]\nfile = "{PANDA}"\ntip_link = "panda_hand_tcp"\n' + by_file.read_text())
    assert robots_equal(load_robot(toml), mounted)
    with pytest.raises(URDFError, match=r"mount.toml: \[urdf\]: a mounting file given with the arm holds"):
        load_robot(PANDA, mount=toml, tip_link="panda_hand_tcp")
    with pytest.raises(sg.RobotConfigError, match=r"paper_robot.toml: tip_link: for a URDF arm only"):
        load_robot(CONFIGS / "paper_robot.toml", tip_link="tool0")


def test_a_bad_path_inside_a_mounting_file_names_the_file_and_the_key(tmp_path):
    mount = tmp_path / "mount.toml"
    mount.write_text('[urdf]\nfile = "arms/nowhere.urdf"\n')
    with pytest.raises(URDFError) as error:
        load_robot(mount)
    assert str(error.value).startswith(f"{mount}: urdf.file = 'arms/nowhere.urdf': ")
    assert "nowhere.urdf: no such file" in str(error.value)


def test_info_names_the_tip_link_flag_and_takes_it(capsys):
    assert cli.main(["info", "--robot", str(PANDA)]) == 2
    err = capsys.readouterr().err
    assert "several leaf links below 'panda_link0' (panda_hand_tcp, panda_leftfinger, panda_rightfinger)" in err
    assert "name the tip link (--tip-link on the command line, tip_link in a mounting TOML)" in err
    assert cli.main(["info", "--robot", str(PANDA), "--tip-link", "panda_hand_tcp"]) == 0
    printed = capsys.readouterr()
    assert "robot: " in printed.out and "7 joints" in printed.out
    assert "the arm is mounted on the paper's 500 kg satellite at its mount point" in printed.err
    assert cli.main(["info", "--tip-link", "tool0"]) == 2  # the paper's robot has no links to choose
    assert "--tip-link: for a URDF arm given with --robot" in capsys.readouterr().err
    for arm, tip, joints in ((ARMS / "kinova.urdf", "j2s6s200_end_effector", 6), (ARMS / "xarm7.urdf", "link7", 7)):
        assert cli.main(["info", "--robot", str(arm), "--tip-link", tip]) == 0, capsys.readouterr().err
        assert f"{joints} joints" in capsys.readouterr().out


@pytest.mark.slow
def test_a_ur10_runs_from_its_stock_urdf_and_its_run_folder_moves(tmp_path, capsys, monkeypatch):
    """``simulate --robot ur10_robot.urdf --tip-link tool0``: the stock UR10, its ``world``
    root bolted to the paper's satellite; the run folder keeps the robot it ran
    (``robot.toml``), so ``animate`` works on it from another folder after it is moved and the
    robot's own file is gone."""
    work = tmp_path / "work"
    work.mkdir()
    shutil.copy(UR10, work / "ur10_robot.urdf")
    (work / "short.toml").write_text(
        (CONFIGS / "ur5_scenario.toml").read_text() + "\nduration = 0.05\n[trajectory]\nduration = 0.05\n"
    )
    monkeypatch.chdir(work)
    args = ["simulate", "--compile-cache", "none", "--controller", "admittance", "--robot", "ur10_robot.urdf"]
    args += ["--tip-link", "tool0", "--scenario", "short.toml", "--gains", str(CONFIGS / "ur5_ideal_gains.json")]
    assert cli.main([*args, "--out", "runs/ur10"]) == 0, capsys.readouterr().err
    config = json.loads((work / "runs" / "ur10" / "config.json").read_text())
    sources = config["record"]["sources"]
    assert sources["robot"] == "ur10_robot.urdf" and sources["robot_links"] == {"tip_link": "tool0"}
    assert config["robot_file"] == "robot.toml"
    ran = load_robot(work / "ur10_robot.urdf", tip_link="tool0")
    assert n_joints(ran) == 6 and robots_equal(load_robot(work / "runs" / "ur10" / "robot.toml"), ran)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    shutil.move(work / "runs" / "ur10", elsewhere / "ur10_moved")
    (work / "ur10_robot.urdf").unlink()
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    assert cli.main(["animate", os.path.join("elsewhere", "ur10_moved"), "--fps", "5"]) == 0, capsys.readouterr().err
    assert any(path.suffix == ".gif" for path in (elsewhere / "ur10_moved").iterdir())
    # the folder's own files run the same capture again, bit for bit
    moved = elsewhere / "ur10_moved"
    config = json.loads((moved / "config.json").read_text())
    assert (config["scenario_file"], config["gains_file"], config["realism_file"]) == (
        "scenario.toml",
        "gains.json",
        None,
    )
    again = ["simulate", "--compile-cache", "none", "--controller", "admittance", "--robot", str(moved / "robot.toml")]
    again += ["--scenario", str(moved / "scenario.toml"), "--gains", str(moved / "gains.json"), "--out", "again"]
    assert cli.main(again) == 0, capsys.readouterr().err
    first = json.loads((moved / "summary.json").read_text())["admittance"]
    second = json.loads((tmp_path / "again" / "summary.json").read_text())["admittance"]
    assert second["final_position_error_m"] == first["final_position_error_m"]
    assert second["max_abs_torque_Nm"] == first["max_abs_torque_Nm"]


def test_the_effective_joint_inertia_of_a_hand_worked_two_joint_system():
    """The Schur complement's diagonal, worked by hand: a satellite block diag(10, 10, 10, 2,
    2, 2), joint 1 coupled to the x translation (1) and the z rotation (0.5), joint 2 to the x
    rotation (1). Joint 1: 3 - 1^2/10 - 0.5^2/2 = 2.775; joint 2: 1 - 1^2/2 = 0.5."""
    M = np.zeros((8, 8))
    M[:6, :6] = np.diag([10.0, 10.0, 10.0, 2.0, 2.0, 2.0])
    M[6:, 6:] = [[3.0, 0.2], [0.2, 1.0]]
    for row, joint, value in ((0, 6, 1.0), (5, 6, 0.5), (3, 7, 1.0)):
        M[row, joint] = M[joint, row] = value
    np.testing.assert_allclose(effective_joint_inertia(M), [2.775, 0.5], rtol=1e-15)


@pytest.mark.parametrize("arm", ["ur5", "panda"])
def test_starting_gains_are_the_rule_the_shipped_arms_gains_started_from(arm):
    """``starting_gains`` against the starting gains the shipped arms' tuning runs record,
    worked out by hand at the time and written to two significant digits."""
    robot = load_robot(CONFIGS / f"{arm}_on_satellite.toml")
    scenario = load_scenario(robot, CONFIGS / f"{arm}_scenario.toml")
    start = starting_gains(robot, scenario.initial.q, scenario.initial.R_base)
    recorded = json.loads((CONFIGS / f"{arm}_ideal_gains.settings.json").read_text())["starting_gains"]
    kp = np.asarray(start.kp)
    assert [float(f"{value:.2g}") for value in kp] == recorded["kp"]
    np.testing.assert_allclose(start.ki, 0.05 * kp, rtol=1e-15)
    np.testing.assert_allclose(start.kd, 7e-5 * kp, rtol=1e-15)
    assert {name: np.asarray(getattr(start, name)).tolist() for name in ("Md", "Bd", "Kd", "K_lin", "K_eul")} == {
        name: np.asarray(getattr(paper_gains(), name)).tolist() for name in ("Md", "Bd", "Kd", "K_lin", "K_eul")
    }


def test_gains_start_writes_a_whole_gains_file_for_any_arm(tmp_path, capsys):
    base = ["gains", "--start", "--robot", str(UR10), "--tip-link", "tool0"]
    assert cli.main(base) == 2
    assert "--scenario: required for an arm of 6 joints" in capsys.readouterr().err
    out = tmp_path / "ur10_start.json"
    robot = load_robot(UR10, tip_link="tool0")
    scenario = load_scenario(robot, CONFIGS / "ur5_scenario.toml")
    start = starting_gains(robot, scenario.initial.q)
    for law in ("admittance", "cartesian"):  # the law's groups, each: no --fill-from needed, no notice
        written = tmp_path / f"{law}.json"
        argv = [*base, "--controller", law, "--scenario", str(CONFIGS / "ur5_scenario.toml"), "--out", str(written)]
        assert cli.main(argv) == 0
        assert "kp = 20/s x effective joint inertia" in capsys.readouterr().err
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            gains = load_gains(written, law, n_joints=6)
        assert gains.to_dict(law) == start.to_dict(law)
    out = tmp_path / "admittance.json"
    assert cli.main([*base, "--scenario", str(CONFIGS / "ur5_scenario.toml"), "--out", str(out)]) == 2
    assert "exists; pass --overwrite" in capsys.readouterr().err


def test_first_crossings_finds_when_and_where_each_limit_was_first_crossed():
    """A made-up 4-step log of a 7-joint arm with joint 3 given the range [-1, 1] rad: joint 3
    leaves it at step 2 (t = 0.2 s, 1.2 rad), joint 5 exceeds the paper's 1 rad/s at step 1
    and joint 1 at step 3; non-finite steps do not count."""
    robot = sg.paper_robot()
    limits = np.tile([-np.inf, np.inf], (7, 1))
    limits[2] = [-1.0, 1.0]
    robot = dataclasses.replace(robot, joint_position_limit=jnp.asarray(limits))
    t = np.array([0.0, 0.1, 0.2, 0.3])
    q = np.zeros((4, 7))
    q[2:, 2] = [1.2, 0.5]
    qd = np.zeros((4, 7))
    qd[1:, 4] = [-1.5, 0.0, 0.0]
    qd[3, 0] = 3.0
    qd[3, 6] = np.nan
    crossings = first_crossings(t, q, qd, robot)
    assert crossings["position"] == {
        "t_s": 0.2,
        "joint": 3,
        "value": 1.2,
        "limit": [-1.0, 1.0],
        "joints": [3],
        "worst": pytest.approx(0.2),
    }
    assert crossings["rate"] == {"t_s": 0.1, "joint": 5, "value": -1.5, "limit": 1.0, "joints": [1, 5], "worst": 2.0}
    assert first_crossings(t, np.zeros((4, 7)), np.zeros((4, 7)), robot) == {"position": None, "rate": None}
    assert outside_ranges(robot, q[2]) == [{"joint": 3, "angle_rad": 1.2, "range_rad": [-1.0, 1.0]}]
    assert outside_ranges(sg.paper_robot(), sg.PAPER_Q_INIT) == []  # the paper's arm has no ranges


def test_initial_angles_outside_the_joint_ranges_are_refused_unless_allowed(capsys):
    """The xArm7 with the paper's q_init: joint 2 at -2.386 rad, its range [-2.059, 2.094]."""
    args = ["export", "--format", "json", "--robot", str(ARMS / "xarm7.urdf"), "--tip-link", "link7"]
    assert cli.main(args) == 2
    err = capsys.readouterr().err
    assert (
        "q_init: the scenario's initial joint angles lie outside the robot's joint ranges: joint 2 at -2.386 rad, "
        in err
    )
    assert "its range [-2.059, 2.094] (choose angles inside them, or pass --allow-outside-limits)" in err
    assert cli.main([*args, "--allow-outside-limits"]) == 0
    assert "spacegrasp: warning: q_init: the scenario's initial joint angles lie outside" in capsys.readouterr().err
    assert cli.main(["info", "--robot", str(ARMS / "xarm7.urdf"), "--tip-link", "link7"]) == 0  # info shows it
    assert "the paper's q_init: joint 2 at -2.386 rad is outside its range [-2.059, 2.094]" in capsys.readouterr().err


@pytest.mark.slow
def test_a_kinova_capture_that_runs_away_reports_its_joint_limit_crossing_first(tmp_path, capsys):
    """The Kinova Jaco (6 joints, rate limits 0.63-0.84 rad/s) from its stock URDF with the
    starting gains: the capture runs away; the first joint-limit crossing is reported, in the
    summary and on the line before the verdict, and came before the runaway."""
    scenario = tmp_path / "jaco.toml"
    scenario.write_text("q_init = [4.71, 2.62, 1.57, 4.71, 1.57, 0.0]\nduration = 3.0\n[trajectory]\nduration = 3.0\n")
    arm = ["--robot", str(ARMS / "kinova.urdf"), "--tip-link", "j2s6s200_end_effector", "--scenario", str(scenario)]
    assert cli.main(["gains", "--start", *arm, "--out", str(tmp_path / "start.json")]) == 0
    args = ["simulate", "--compile-cache", "none", "--controller", "admittance", *arm]
    assert cli.main([*args, "--gains", str(tmp_path / "start.json"), "--out", str(tmp_path / "run")]) == 0
    lines = capsys.readouterr().out.splitlines()
    verdict = next(i for i, line in enumerate(lines) if "capture failed (runaway)" in line)
    assert "joint limits: joint " in lines[verdict - 1] and "exceeded its rate limit" in lines[verdict - 1]
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())["admittance"]
    rate = summary["joint_limits"]["rate"]
    limits = np.asarray(load_robot(ARMS / "kinova.urdf", tip_link="j2s6s200_end_effector").joint_rate_limit)
    assert rate["limit"] == limits[rate["joint"] - 1] and abs(rate["value"]) > rate["limit"]
    assert rate["t_s"] < summary["first_runaway_s"]


@pytest.mark.slow
def test_a_campaign_and_a_tuning_run_of_an_arm_move_and_go_on(tmp_path, capsys, monkeypatch):
    """A UR5 campaign and a UR5 tuning run, each moved to another folder and used from a third,
    the arm's files gone: the campaign replays a sample and resumes from the robot it keeps
    (the same robot given by another path counts as the same); the tuning run resumes from the
    robot in its record."""
    work = tmp_path / "work"
    (work / "arms").mkdir(parents=True)
    shutil.copy(CONFIGS / "arms" / "ur5_robot.urdf", work / "arms" / "ur5_robot.urdf")
    shutil.copy(CONFIGS / "ur5_on_satellite.toml", work / "ur5.toml")
    (work / "short.toml").write_text(
        (CONFIGS / "ur5_scenario.toml").read_text() + "\nduration = 0.05\n[trajectory]\nduration = 0.05\n"
    )
    gains = str(CONFIGS / "ur5_ideal_gains.json")
    monkeypatch.chdir(work)
    campaign_args = ["montecarlo", "--compile-cache", "none", "--n", "4", "--chunk", "2", "--controller", "admittance"]
    campaign_args += ["--robot", "ur5.toml", "--scenario", "short.toml", "--gains", gains]
    assert cli.main([*campaign_args, "--out", "campaign"]) == 0, capsys.readouterr().err
    tune_args = ["tune", "--compile-cache", "none", "--robot", "ur5.toml", "--scenario", "short.toml"]
    tune_args += ["--gains", gains, "--steps", "1", "--batch", "1", "--population", "4", "--holdout", "0"]
    assert cli.main([*tune_args, "--out", "tune"]) == 0, capsys.readouterr().err
    limits = np.asarray(load_robot(work / "ur5.toml").joint_rate_limit).tolist()  # a mounting file states them
    assert (
        json.loads((work / "campaign" / "campaign.json").read_text())["record"]["criteria"]["joint_rate_limits_radps"]
        == limits
    )
    assert json.loads((work / "tune" / "run.json").read_text())["config"]["joint_rate_limits_radps"] == limits
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    for name in ("campaign", "tune"):
        shutil.move(work / name, elsewhere / name)
    kept_robot = tmp_path / "kept" / "ur5.toml"  # the same robot by another path, for the resume
    kept_robot.parent.mkdir()
    shutil.copytree(work / "arms", kept_robot.parent / "arms")
    shutil.copy(work / "ur5.toml", kept_robot)
    shutil.rmtree(work / "arms")
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    replay = ["replay", str(elsewhere / "campaign"), "--sample", "1", "--compile-cache", "none", "--out", "replayed"]
    assert cli.main(replay) == 0, capsys.readouterr().err
    with np.load(elsewhere / "campaign" / "samples.npz") as samples:
        summary = json.loads((tmp_path / "replayed" / "summary.json").read_text())
        key = next(iter(summary))
        assert summary[key]["final_position_error_m"] == pytest.approx(
            float(samples[f"{key}/final_position_error_m"][1]), rel=1e-9
        )
    resumed = [*campaign_args[:-6], "--robot", str(kept_robot), "--scenario", str(work / "short.toml")]
    resumed += ["--gains", gains, "--out", str(elsewhere / "campaign"), "--resume"]
    assert cli.main(resumed) == 0, capsys.readouterr().err
    capsys.readouterr()
    assert cli.main(["tune", "--out", str(elsewhere / "tune"), "--resume", "--steps", "2"]) == 0, (
        capsys.readouterr().err
    )
    assert "resuming after generation 1/2" in capsys.readouterr().err


def test_rate_limits_are_criteria_where_a_robot_file_states_them(tmp_path):
    """A URDF and a mounting TOML state rate limits (a URDF's <limit velocity> is required), a
    robot TOML when it gives limits.joint_rate; the paper's robot TOML gives none, and reads
    back as the paper's robot with its assumed limits. A run folder keeps a robot without
    stated limits without them, bit for bit."""
    from spacegrasp_jax.core.robot_files import rate_limits_stated

    assert rate_limits_stated(ARMS / "xarm7.urdf") and rate_limits_stated(CONFIGS / "ur5_on_satellite.toml")
    assert not rate_limits_stated(CONFIGS / "paper_robot.toml")
    stated = tmp_path / "stated.toml"
    stated.write_text((CONFIGS / "paper_robot.toml").read_text() + "joint_rate = [0.2, 0.2, 0.2, 0.2, 0.2, 0.2, 0.2]\n")
    assert rate_limits_stated(stated)
    assert np.asarray(load_robot(stated).joint_rate_limit).tolist() == [0.2] * 7
    paper = sg.paper_robot()
    text = robot_to_toml(paper, rate_limits_stated=False)
    assert "\njoint_rate =" not in text and robot_to_toml(robot_from_toml(text)) == robot_to_toml(paper)
    kept = tmp_path / "kept.toml"
    kept.write_text(text)
    assert not rate_limits_stated(kept)
    # Rate limits other than the assumed ones are always written: the file must read back the same.
    assert "\njoint_rate =" in robot_to_toml(load_robot(stated), rate_limits_stated=False)


def test_a_simulate_run_fails_a_joint_faster_than_its_files_rate_limit(tmp_path, capsys, monkeypatch):
    """The paper's arm with rate limits of 0.2 rad/s stated in its robot TOML, 1 s of the
    Cartesian law: the verdict is joint_rate, naming the joint whose peak rate (read from the
    log) is the largest over its limit; the same arm from the paper's robot TOML (no stated
    rates) is judged as before, by its final errors."""
    monkeypatch.chdir(tmp_path)
    Path("short.toml").write_text("duration = 1.0\n[trajectory]\nduration = 1.0\n")
    Path("tight.toml").write_text(
        (CONFIGS / "paper_robot.toml").read_text() + "joint_rate = [0.2, 0.2, 0.2, 0.2, 0.2, 0.2, 0.2]\n"
    )
    run = ["simulate", "--compile-cache", "none", "--controller", "cartesian", "--scenario", "short.toml"]
    assert cli.main([*run, "--robot", "tight.toml", "--out", "tight"]) == 0
    out = capsys.readouterr().out
    with np.load("tight/timeseries_cartesian.npz") as log:
        peaks = np.max(np.abs(log["qd"]), axis=0)
    joint = int(np.argmax(peaks)) + 1
    assert f"capture failed (joint_rate): joint {joint} turned at {peaks[joint - 1]:.3g} rad/s > its limit 0.2" in out
    summary = json.loads(Path("tight/summary.json").read_text())["cartesian"]
    assert summary["capture_failure"] == "joint_rate"
    assert summary["capture_criteria"]["joint_rate_limits_radps"] == [0.2] * 7
    assert summary["capture_margins"]["joint_rate_margin"] == pytest.approx(np.max(peaks) / 0.2, rel=1e-12)
    assert "\njoint_rate = " in Path("tight/robot.toml").read_text()  # the folder's robot judges the same
    assert cli.main([*run, "--robot", str(CONFIGS / "paper_robot.toml"), "--out", "paper"]) == 0
    summary = json.loads(Path("paper/summary.json").read_text())["cartesian"]
    assert summary["capture_failure"] == "position" and "joint_rate" not in summary["capture_missed"]
    assert summary["capture_criteria"]["joint_rate_limits_radps"] is None
    assert summary["capture_margins"]["joint_rate_margin"] is None


@pytest.mark.parametrize("arm", ["ur5", "panda"])
def test_a_shipped_arms_flight_gains_are_the_ones_checked_and_capture_more_than_their_start(arm):
    """``configs/<arm>_flight_gains.json`` (tuned in the flight-like loop) are bit for bit the
    gains its check campaign ran (``notebooks/data/arms/<arm>_flight_check``: flight-like
    captures of a seed fixed before it ran), against a baseline that is the documented starting
    rule worked out afresh; the settings' rates and McNemar test are that campaign's per-sample
    flags recounted, and the flight gains capture significantly more (exact McNemar p < 0.05)."""
    from spacegrasp_jax.envelope import statistics
    from spacegrasp_jax.jobs.campaign import load_samples

    settings = json.loads((CONFIGS / f"{arm}_flight_gains.settings.json").read_text())
    data = ROOT / settings["check"]["data"]
    record = json.loads((data / "campaign.json").read_text())["record"]
    variants = {variant["label"]: variant for variant in record["variants"]}
    shipped, start = variants[f"{arm}_flight_gains"], variants[f"{arm}_gains_start"]
    shipped_file = json.loads((CONFIGS / f"{arm}_flight_gains.json").read_text())
    assert {name: shipped["gains"][name] for name in shipped_file} == shipped_file
    robot = load_robot(CONFIGS / f"{arm}_on_satellite.toml")
    scenario = load_scenario(robot, CONFIGS / f"{arm}_scenario.toml")
    rule = starting_gains(robot, scenario.initial.q, scenario.initial.R_base).to_dict("admittance")
    for name, value in rule.items():
        np.testing.assert_allclose(start["gains"][name], value, rtol=1e-12, err_msg=name)
    assert record["realism"]["timing"]["control_period"] > 0.0  # the flight-like loop, not the ideal one
    _, by_variant = load_samples(data / "samples.npz")
    flags = {key.split("/", 1)[1]: np.asarray(value["success"], bool) for key, value in by_variant.items()}
    tuned, started = flags[f"{arm}_flight_gains"], flags[f"{arm}_gains_start"]
    assert tuned.size == settings["check"]["samples"] >= 256
    assert settings["check"]["success"][f"{arm}_flight_gains"]["successes"] == int(tuned.sum())
    assert settings["check"]["success"][f"{arm}_gains_start"]["successes"] == int(started.sum())
    paired = statistics.compare_success(started, tuned)
    stated = settings["check"]["mcnemar"][f"admittance/{arm}_flight_gains vs admittance/{arm}_gains_start"]
    assert stated["p_value"] == pytest.approx(paired["p_value"], rel=1e-12)
    assert paired["only_candidate"] > paired["only_reference"] and paired["p_value"] < 0.05
