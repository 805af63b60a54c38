"""The film of a capture: its frames, where it draws the end-effector, and the command."""

from __future__ import annotations

import json

import matplotlib.pyplot as plt
import numpy as np
import pytest
from PIL import Image

from spacegrasp_jax import cli
from spacegrasp_jax.analysis import animation
from spacegrasp_jax.jobs import experiment
from spacegrasp_jax.loop.simulate import RunSpec

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def run(robot, gains, short_scenario):
    return experiment.run(RunSpec(robot, short_scenario, "admittance"), gains)


@pytest.fixture(scope="module")
def scene(robot, short_scenario, run):
    rows = animation.frame_rows(run.log.t, fps=10.0, speed=1.0)
    return animation.capture_scene(robot, short_scenario, run.log, rows)


def test_the_recovered_satellite_pose_puts_the_arms_end_on_the_logged_ee(scene, run):
    """The arm is drawn from the joint angles through the arm's kinematics on the satellite
    pose recovered from the log; its end must be the EE point of the log itself (its pose in
    the LAR frame, moved by the LAR's pose)."""
    np.testing.assert_allclose(scene.arm[:, -1], scene.ee, rtol=0, atol=1e-9)
    assert len(scene.t) == 20  # 2 s at 10 frames a second: 0, 0.1, ..., 1.9 s (the log's last row is 1.999 s)
    np.testing.assert_allclose(scene.final_position_error_mm, 1e3 * run.summary["final_position_error_m"], rtol=1e-9)


def test_a_frame_puts_the_ee_at_the_pixel_its_position_projects_to(scene):
    from mpl_toolkits.mplot3d import proj3d

    for k in (0, len(scene.t) // 2, len(scene.t) - 1):
        figure, ax = animation.draw_frame(scene, k)
        figure.canvas.draw()
        image = np.asarray(figure.canvas.buffer_rgba())[..., :3].astype(int)
        x, y, _ = proj3d.proj_transform(*scene.ee[k], ax.get_proj())
        column, row_from_bottom = ax.transData.transform((x, y))
        expected = np.array([image.shape[0] - row_from_bottom, column])
        red = np.argwhere(np.all(np.abs(image - [0xD6, 0x27, 0x28]) <= 8, axis=-1))
        assert len(red) > 20, k  # the marker is there
        np.testing.assert_allclose(red.mean(axis=0), expected, rtol=0, atol=2.0, err_msg=f"frame {k}")
        plt.close(figure)


def test_a_gif_has_the_frames_asked_for_and_consecutive_frames_differ_where_the_arm_moves(scene, tmp_path):
    path = tmp_path / "film.gif"
    assert animation.write_film(scene, path, fps=10.0) == len(scene.t)
    with Image.open(path) as film:
        assert film.n_frames == len(scene.t)
        frames = []
        for k in range(film.n_frames):
            film.seek(k)
            frames.append(np.asarray(film.convert("RGB"), dtype=int))
    height = frames[0].shape[0]
    below_the_text = slice(int(0.12 * height), None)  # the clock and the title change every frame anyway
    moved = np.linalg.norm(np.diff(scene.arm, axis=0), axis=-1).max(axis=-1)
    for k in range(len(frames) - 1):
        changed = np.any(frames[k + 1][below_the_text] != frames[k][below_the_text], axis=-1).sum()
        if moved[k] > 1e-3:  # the arm moved more than a millimetre
            assert changed > 0, k


def test_an_mp4_has_the_frames_asked_for(scene, tmp_path):
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg", reason="MP4 needs the video extra")
    path = tmp_path / "film.mp4"
    assert animation.write_film(scene, path, fps=10.0) == len(scene.t)
    frames, _ = imageio_ffmpeg.count_frames_and_secs(str(path))
    assert frames == len(scene.t)


def test_animate_films_a_run_folder_and_refuses_what_it_cannot_do(robot, tmp_path, capsys):
    scenario = tmp_path / "short.toml"
    scenario.write_text('duration = 2.0\n[trajectory]\nduration = 2.0\n[contact]\nlaw = "smooth"\n')
    out = tmp_path / "run"
    common = ["--scenario", str(scenario), "--fps", "5"]
    assert cli.main(["simulate", "--controller", "admittance", *common, "--animate", "--out", str(out)]) == 0
    assert (out / "capture_admittance.gif").is_file() and (out / "capture_admittance_poster.png").is_file()
    with Image.open(out / "capture_admittance.gif") as film:
        assert film.n_frames == 10
    record = json.loads((out / "config.json").read_text())["record"]
    assert [variant["controller"] for variant in record["variants"]] == ["admittance"]
    capsys.readouterr()
    refused = {
        ("animate", str(out)): "capture_admittance.gif: exists; pass --overwrite",
        ("animate", str(out), "--out", str(tmp_path / "film.avi")): "a film is a .gif or an .mp4",
        ("animate", str(out), "--controller", "cartesian"): "has no run 'cartesian'; it has admittance",
        ("animate", str(tmp_path)): "not a run folder",
    }
    for arguments, message in refused.items():
        assert cli.main(list(arguments)) == 2, arguments
        assert message in capsys.readouterr().err, arguments
    assert cli.main(["animate", str(out), "--out", str(tmp_path / "again.gif"), "--fps", "5", "--speed", "2"]) == 0
    with Image.open(tmp_path / "again.gif") as film:
        assert film.n_frames == 5  # 2 s at 5 frames a second, twice as fast


def test_a_schedules_film_says_the_regime_of_each_frame(robot, gains, short_scenario, run, scene):
    """A time schedule's knots at 0, 0.5 and 1.5 s: each frame's words name the interval of
    the knots that holds its time, and only a schedule's frames carry them (the purple line)."""
    from spacegrasp_jax.loop.control.schedule import regime_labels, schedule_of, variable_series

    schedule = schedule_of(gains, "time", [0.0, 0.5, 1.5], ["Kd"])
    labels = regime_labels(schedule, variable_series("time", run.log))
    rows = animation.frame_rows(run.log.t, fps=10.0, speed=1.0)
    scheduled = animation.capture_scene(robot, short_scenario, run.log, rows, regime=labels)
    words = dict(zip(np.round(scheduled.t, 6), scheduled.regime))
    assert words[0.0] == "time 0 s: regime 1 of 2 (0-0.5 s)"
    assert words[0.7] == "time 0.7 s: regime 2 of 2 (0.5-1.5 s)"
    assert words[1.9] == "time 1.9 s: after the last knot (1.5 s)"
    assert scene.regime is None
    purple = []
    for frame_scene in (scene, scheduled):
        figure, _ = animation.draw_frame(frame_scene, 3)
        figure.canvas.draw()
        image = np.asarray(figure.canvas.buffer_rgba())[..., :3].astype(int)
        purple.append(np.all(np.abs(image - [0x94, 0x67, 0xBD]) <= 8, axis=-1).sum())
        plt.close(figure)
    assert purple[0] == 0 and purple[1] > 50
    with pytest.raises(animation.AnimationError, match="a label for each of the log's"):
        animation.capture_scene(robot, short_scenario, run.log, rows, regime=labels[:-1])


def test_the_film_finds_the_schedule_a_run_folder_ran_with(tmp_path):
    """A kept schedule file, a shipped schedule by name, constant gains: the film's schedule."""
    from spacegrasp_jax.cli.common import _run_schedule
    from spacegrasp_jax.loop.control import paper_gains
    from spacegrasp_jax.loop.control.schedule import GainSchedule, schedule_of

    schedule = schedule_of(paper_gains(), "time", [0.0, 5.0], ["Kd"])
    (tmp_path / "gains.json").write_text(json.dumps(schedule.to_dict("admittance")))
    kept = _run_schedule(tmp_path, {"gains_file": "gains.json"}, "admittance", 7)
    assert isinstance(kept, GainSchedule) and np.array_equal(kept.knots["Kd"], [0.0, 5.0])
    assert isinstance(_run_schedule(tmp_path, {"gains_source": "flight_schedule"}, "admittance", 7), GainSchedule)
    assert _run_schedule(tmp_path, {"gains_source": "flight"}, "admittance", 7) is None
    (tmp_path / "constant.json").write_text(json.dumps(paper_gains().to_dict("admittance")))
    assert _run_schedule(tmp_path, {"gains_file": "constant.json"}, "admittance", 7) is None
