"""The figures, on synthetic logs whose curves are known: runs of any name get a style of
their own, every figure carries its caption and no label runs into a title, the motor
limits are drawn on Fig. 8, the campaign histogram names its torque threshold, and the target's
figure draws the displacement, speed, rate and impulse that the log implies."""

from __future__ import annotations

import dataclasses

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from spacegrasp_jax.analysis import plots
from spacegrasp_jax.loop.simulate import Log  # noqa: E402

N, DT = 200, 0.01


def synthetic_log(scale: float = 1.0, target: bool = False) -> Log:
    """A log of N rows with smooth made-up curves; with a target drifting at constant
    velocity (1, 2, 2) mm/s, turning at 0.5 deg/s, pushed by a constant 0.3 N contact."""
    t = DT * np.arange(N)
    wave = scale * np.sin(t)[:, None]
    fields = {
        "t": t,
        "pose_ee": wave * np.ones(6) * 1e-3,
        "pose_des": np.zeros((N, 6)),
        "twist_ee": np.zeros((N, 6)),
        "contact_force": np.tile([0.0, 0.0, 0.3], (N, 1)),
        "momentum": wave * np.ones(6),
        "V_base": wave * np.ones(6) * 1e-3,
        "u": wave * np.arange(1, 8),
        "fts_force": wave * np.ones(3),
        "fts_torque": wave * np.ones(3),
        "V_ref": np.zeros((N, 6)),
        "qd_des": np.zeros((N, 7)),
        "q": np.zeros((N, 7)),
        "qd": np.zeros((N, 7)),
    }
    if target:
        velocity = np.array([1.0, 2.0, 2.0]) * 1e-3
        fields |= {
            "target_position": np.array([0.1, 0.2, 0.3]) + t[:, None] * velocity,
            "target_quat": np.tile([1.0, 0.0, 0.0, 0.0], (N, 1)),
            "target_velocity": np.tile(velocity, (N, 1)),
            "target_angular_velocity": np.tile([0.0, 0.0, np.radians(0.5)], (N, 1)),
        }
    return Log(**{f.name: fields.get(f.name) for f in dataclasses.fields(Log)})


def _overlaps(a, b) -> bool:
    return not (a.x1 <= b.x0 or b.x1 <= a.x0 or a.y1 <= b.y0 or b.y1 <= a.y0)


def test_runs_of_any_name_get_their_own_style():
    assert plots.style_of("admittance") == plots.STYLES["admittance"]
    first, second = plots.style_of("loop flight", 0), plots.style_of("loop ideal", 1)
    assert first["label"] == "loop flight" and second["label"] == "loop ideal"
    assert (first["color"], first["linestyle"]) != (second["color"], second["linestyle"])


@pytest.mark.parametrize("build", list(plots.FIGURES.values()), ids=list(plots.FIGURES))
def test_every_figure_carries_its_caption_and_no_label_runs_into_its_title(build):
    logs = {"loop ideal": synthetic_log(), "loop flight": synthetic_log(2.0)}
    fig = build(logs, caption="ideal loop (the paper's), the paper's gains, fixed target")
    assert fig.get_suptitle().endswith("\nideal loop (the paper's), the paper's gains, fixed target")
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    title = fig._suptitle.get_window_extent(renderer)
    for ax in fig.axes:
        if ax.get_visible():
            assert not _overlaps(ax.yaxis.label.get_window_extent(renderer), title), ax.get_ylabel()
            assert not _overlaps(ax.get_window_extent(renderer), title), ax.get_ylabel()
    labels = {text.get_text() for legend in fig.legends for text in legend.get_texts()}
    assert {"loop ideal", "loop flight"} <= labels
    plt.close(fig)


def test_fig6_names_the_origin_in_its_title_and_keeps_short_labels():
    fig = plots.figure_momentum({"admittance": synthetic_log()})
    assert "about the inertial origin" in fig.get_suptitle()
    assert [ax.get_ylabel() for ax in fig.axes] == ["|P| [N s]", "|L| [N m s]"]
    plt.close(fig)


def test_fig8_shows_each_joints_motor_limit():
    """Joint j's torque peaks near j N m (the synthetic log): the limits of joints 4-7 (5, 5,
    2, 2 N m) are reached by half and drawn as lines; those of joints 1-3 (10 N m) would
    flatten the curves and are written in the panel instead."""
    limits = np.array([10.0, 10.0, 10.0, 5.0, 5.0, 2.0, 2.0])
    fig = plots.figure_joint_torques({"admittance": synthetic_log()}, torque_limit_Nm=limits)
    for joint, ax in zip(range(7), fig.axes):
        horizontal = sorted(
            float(line.get_ydata()[0]) for line in ax.lines if np.ptp(np.asarray(line.get_ydata(), dtype=float)) == 0
        )
        written = [text.get_text() for text in ax.texts]
        if joint < 3:
            assert horizontal == [] and written == ["motor limit ±10 N m"], (joint, horizontal, written)
        else:
            assert horizontal == [-limits[joint], limits[joint]] and written == [], (joint, horizontal, written)
    assert "motor limit" in [text.get_text() for text in fig.legends[0].get_texts()]
    plt.close(fig)


def test_the_campaign_histogram_names_its_torque_threshold():
    metrics = {
        "admittance/paper": {
            "final_position_error_m": np.array([0.002, 0.004, 0.006]),
            "largest_peak_torque_Nm": np.array([1.0, 2.0, 3.0]),
            "first_nonfinite_s": np.full(3, np.nan),
        }
    }
    near = plots.figure_campaign_histograms(metrics, tolerance_mm=5.0, torque_threshold_Nm=4.0)
    far = plots.figure_campaign_histograms(metrics, tolerance_mm=5.0, torque_threshold_Nm=100.0)
    near_labels = [text.get_text() for text in near.axes[1].get_legend().get_texts()]
    far_labels = [text.get_text() for text in far.axes[1].get_legend().get_texts()]
    assert "torque threshold 4 N m" in near_labels and "torque threshold 100 N m (beyond the axis)" in far_labels
    assert any(np.allclose(line.get_xdata(), 4.0) for line in near.axes[1].lines)
    plt.close(near)
    plt.close(far)


def test_the_target_figure_draws_what_the_log_implies():
    fig = plots.figure_target_motion({"admittance": synthetic_log(target=True), "no target": synthetic_log()})
    displacement, speed, rate, impulse = (ax.lines[0] for ax in fig.axes[:4])
    t = DT * np.arange(N)
    assert all(len(ax.lines) == 1 for ax in fig.axes[:4])  # the log without a target is left out
    np.testing.assert_allclose(displacement.get_ydata(), 1e3 * 3e-3 * t, atol=1e-12)  # |(1, 2, 2)| mm/s
    np.testing.assert_allclose(speed.get_ydata(), 3.0, rtol=1e-12)
    np.testing.assert_allclose(rate.get_ydata(), 0.5, rtol=1e-12)
    np.testing.assert_allclose(impulse.get_ydata(), 0.3 * (t + DT), rtol=1e-12)  # 0.3 N over each step
    plt.close(fig)
