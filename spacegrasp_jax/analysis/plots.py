"""Figures, NumPy in and matplotlib figures out: the paper's Figures 4-9 from rollout logs
(``FIGURES``, with the free-floating target's motion beside them), and the figures of the
commands built on the rollout: tuning (loss, peak torques), Monte-Carlo campaigns
(histograms, scatter, failures), gradient health, stability margins, the worst-case search, the EE path and trade-off plots.

Style of the paper: blue dashed line for the admittance law (the paper's "active 6 DoF
force/torque control"), red dotted for the Cartesian law, black solid for the desired
trajectory; each law's style is its own (``ControlLaw.style``). ``logs`` maps a controller
name (``"admittance"``, ``"cartesian"``, any of the registry's) to a log with NumPy fields;
any may be missing.

Every ``figure_*`` function returns a matplotlib figure and leaves the backend alone: a
notebook shows it inline, the command line (which selects the file-only Agg backend) saves
it.
"""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

from spacegrasp_jax.loop.control.registry import LAWS

#: Line styles by name: each law's (the registry's), the desired trajectory's and a tuning's.
STYLES = {name: dict(law.style) for name, law in LAWS.items()} | {
    "desired": dict(color="black", linestyle="-", label="desired"),
    "start": dict(color="tab:gray", linestyle="--", label="starting gains"),
    "tuned": dict(color="tab:green", linestyle="-", label="tuned gains"),
}


#: Line styles of runs that are not one of ``STYLES``' names (``spacegrasp compare``'s
#: runs, labelled by what differs between them), in order.
_RUN_LINESTYLES = ("-", "--", ":", "-.")


def style_of(name: str, index: int = 0) -> dict:
    """The line style of the run ``name``: ``STYLES``' for its names, else the
    ``index``-th colour and line style of a cycle, labelled ``name``."""
    if name in STYLES:
        return STYLES[name]
    return dict(color=f"C{index % 10}", linestyle=_RUN_LINESTYLES[index % len(_RUN_LINESTYLES)], label=name)


def plot_series(ax, t: np.ndarray, values: np.ndarray, style: str, linewidth: float = 1.4, index: int = 0):
    """One time series on ``ax`` in the style of the run ``style`` ([`style_of`][spacegrasp_jax.analysis.plots.style_of]);
    returns the line."""
    (line,) = ax.plot(t, values, linewidth=linewidth, **style_of(style, index))
    return line


def _grid(rows: int, columns: int, title: str, height: float = 2.2, caption: str | None = None):
    fig, axes = plt.subplots(rows, columns, figsize=(5.0 * columns, height * rows), sharex=True, squeeze=False)
    fig.suptitle(title if caption is None else f"{title}\n{caption}", fontsize=11 if caption else None)
    return fig, axes


def _finish(fig, axes, ylabels, caption: str | None = None):
    for ax, label in zip(axes.flat, ylabels):
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("time [s]")
    entries = {}  # label -> handle, over every panel (a panel may carry a line the first lacks)
    for ax in axes.flat:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            entries.setdefault(label, handle)
    fig.legend(list(entries.values()), list(entries), loc="lower center", ncol=min(len(entries), 4), frameon=False)
    top = 0.96 if caption is None else 0.96 - 0.25 / fig.get_figheight()  # room for the caption line
    fig.tight_layout(rect=(0, 0.05, 1, top))
    return fig


def _plot_columns(axes, logs, series, columns, desired=None):
    for index, (name, log) in enumerate(logs.items()):
        for ax, column in zip(axes.flat, columns):
            plot_series(ax, log.t, series(log)[:, column], name, index=index)
    if desired is not None:
        log = next(iter(logs.values()))
        for ax, column in zip(axes.flat, columns):
            plot_series(ax, log.t, desired(log)[:, column], "desired", linewidth=1.0)


def figure_ee_pose(
    logs, title: str = "Fig. 4  End-effector position and orientation in the LAR frame", caption: str | None = None
):
    """Figure 4: EE position (mm) and orientation (deg) in the LAR frame, with the desired.
    ``caption``: a second title line (the command line's: the loop, gains and target)."""
    fig, axes = _grid(3, 2, title, caption=caption)
    scale = np.array([1e3, 1e3, 1e3, np.degrees(1), np.degrees(1), np.degrees(1)])
    order = [0, 3, 1, 4, 2, 5]  # left column positions, right column angles
    _plot_columns(axes, logs, lambda log: log.pose_ee * scale, order, desired=lambda log: log.pose_des * scale)
    labels = ["x [mm]", "roll [deg]", "y [mm]", "pitch [deg]", "z [mm]", "yaw [deg]"]
    return _finish(fig, axes, labels, caption=caption)


def figure_contact_force(logs, caption: str | None = None):
    """Figure 5: the contact model's force on the EE, LAR axes, and its magnitude."""
    fig, axes = _grid(2, 2, "Fig. 5  External forces from the contact model (LAR axes)", caption=caption)
    _plot_columns(
        axes,
        logs,
        lambda log: np.column_stack([log.contact_force, np.linalg.norm(log.contact_force, axis=1)]),
        range(4),
    )
    return _finish(fig, axes, ["F_x [N]", "F_y [N]", "F_z [N]", "|F| [N]"], caption=caption)


def figure_momentum(logs, caption: str | None = None):
    """Figure 6: resultant linear and angular momentum of the whole system (the angular
    momentum about the inertial origin)."""
    fig, axes = _grid(
        1, 2, "Fig. 6  Momentum and angular momentum (about the inertial origin)", height=3.2, caption=caption
    )
    norms = lambda log: np.column_stack(
        [np.linalg.norm(log.momentum[:, :3], axis=1), np.linalg.norm(log.momentum[:, 3:], axis=1)]
    )  # noqa: E731
    _plot_columns(axes, logs, norms, range(2))
    return _finish(fig, axes, ["|P| [N s]", "|L| [N m s]"], caption=caption)


def figure_base_velocity(logs, caption: str | None = None):
    """Figure 7: resultant linear and angular velocity of the servicing satellite."""
    fig, axes = _grid(1, 2, "Fig. 7  Servicing satellite velocities", height=3.2, caption=caption)
    norms = lambda log: np.column_stack(
        [1e3 * np.linalg.norm(log.V_base[:, :3], axis=1), np.degrees(np.linalg.norm(log.V_base[:, 3:], axis=1))]
    )  # noqa: E731
    _plot_columns(axes, logs, norms, range(2))
    return _finish(fig, axes, ["|v_s| [mm/s]", "|w_s| [deg/s]"], caption=caption)


def figure_joint_torques(logs, caption: str | None = None, torque_limit_Nm=None):
    """Figure 8: joint torques of the N joints (the paper's seven); ``torque_limit_Nm`` (N,) N m:
    each joint's motor limit, drawn at +-limit where the joint's peak reaches half of it, else
    written in the panel's corner (a line far above the curves would flatten them)."""
    joints = np.shape(next(iter(logs.values())).u)[-1]
    fig, axes = _grid((joints + 1) // 2, 2, "Fig. 8  Joint torques", height=2.0, caption=caption)
    _plot_columns(axes, logs, lambda log: log.u, range(joints))
    if torque_limit_Nm is not None:
        for joint, ax in zip(range(joints), axes.flat):
            limit = float(np.asarray(torque_limit_Nm)[joint])
            peak = max(float(np.max(np.abs(np.asarray(log.u)[:, joint]))) for log in logs.values())
            if peak >= 0.5 * limit:
                for sign in (1.0, -1.0):
                    ax.axhline(sign * limit, color="0.4", linestyle="-.", linewidth=0.9, label="motor limit")
            else:
                ax.text(
                    0.99, 0.95, f"motor limit ±{limit:g} N m", transform=ax.transAxes, ha="right", va="top", fontsize=7
                )
    if joints % 2:  # an odd count leaves the last panel empty: the one above it gets the time axis
        axes.flat[joints].set_visible(False)
        axes.flat[joints - 2].xaxis.set_tick_params(labelbottom=True)
        axes.flat[joints - 2].set_xlabel("time [s]")
    return _finish(fig, axes, [f"u_{i + 1} [N m]" for i in range(joints)], caption=caption)


def figure_sensor_loads(logs, caption: str | None = None):
    """Figure 9: loads measured by the F/T sensor between link 7 and the EE (sensor axes)."""
    fig, axes = _grid(3, 2, "Fig. 9  Loads measured between the seventh link and the end-effector", caption=caption)
    both = lambda log: np.column_stack([log.fts_force, log.fts_torque])  # noqa: E731
    _plot_columns(axes, logs, both, [0, 3, 1, 4, 2, 5])
    return _finish(fig, axes, ["f_x [N]", "n_x [N m]", "f_y [N]", "n_y [N m]", "f_z [N]", "n_z [N m]"], caption=caption)


def figure_target_motion(logs, caption: str | None = None):
    """A free-floating target's motion: how far its CoM moved from where it started (mm),
    its speed (mm/s) and angular rate (deg/s), and the impulse the contact gave it (N s,
    the magnitude of the time integral of the contact force on the target). Only the logs
    whose target moves are drawn ([`target_moves()`][spacegrasp_jax.analysis.plots.target_moves])."""
    logs = {name: log for name, log in logs.items() if target_moves(log)}
    fig, axes = _grid(2, 2, "The free-floating target's motion", height=2.6, caption=caption)

    def series(log):
        dt = np.diff(log.t, append=log.t[-1] + (log.t[-1] - log.t[-2] if len(log.t) > 1 else 0.0))
        impulse = np.cumsum(-np.asarray(log.contact_force) * dt[:, None], axis=0)  # on the target, LAR axes
        return np.column_stack(
            [
                1e3 * np.linalg.norm(log.target_position - log.target_position[0], axis=1),
                1e3 * np.linalg.norm(log.target_velocity, axis=1),
                np.degrees(np.linalg.norm(log.target_angular_velocity, axis=1)),
                np.linalg.norm(impulse, axis=1),
            ]
        )

    _plot_columns(axes, logs, series, range(4))
    return _finish(
        fig,
        axes,
        ["CoM displacement [mm]", "speed [mm/s]", "angular rate [deg/s]", "contact impulse [N s]"],
        caption=caption,
    )


def target_moves(log) -> bool:
    """Whether ``log``'s target moves at some step (never the paper's fixed target; a log
    written without target fields: no)."""
    motion = (getattr(log, "target_velocity", None), getattr(log, "target_angular_velocity", None))
    return all(series is not None for series in motion) and bool(
        np.any(np.asarray(motion[0]) != 0.0) or np.any(np.asarray(motion[1]) != 0.0)
    )


FIGURES = {
    "fig4_ee_pose.png": figure_ee_pose,
    "fig5_contact_force.png": figure_contact_force,
    "fig6_momentum.png": figure_momentum,
    "fig7_base_velocity.png": figure_base_velocity,
    "fig8_joint_torques.png": figure_joint_torques,
    "fig9_fts_loads.png": figure_sensor_loads,
}


def save(figures: dict, out_dir, write_atomically) -> list[str]:
    """Write each figure of ``figures`` (file name -> figure) into ``out_dir`` as a PNG with
    ``write_atomically(path, write)`` (``spacegrasp_jax.jobs.runfiles.write_atomically``), then
    close it; returns the file names."""
    for name, fig in figures.items():
        write_atomically(out_dir / name, lambda target: fig.savefig(target, dpi=110, format="png"))
        plt.close(fig)
    return list(figures)


def save_figures(logs, out_dir, write_atomically, caption: str | None = None, torque_limit_Nm=None) -> list[str]:
    """Write Figures 4-9 into ``out_dir``, each with ``caption`` under its title and Fig. 8
    with the motor limits ``torque_limit_Nm`` (N,) N m; with a free-floating target in any
    log that moves, ``target_motion.png`` too ([`figure_target_motion`][spacegrasp_jax.analysis.plots.figure_target_motion]). Returns the file names."""
    figures = {
        name: build(logs, caption=caption, torque_limit_Nm=torque_limit_Nm)
        if build is figure_joint_torques
        else build(logs, caption=caption)
        for name, build in FIGURES.items()
    }
    if any(target_moves(log) for log in logs.values()):
        figures["target_motion.png"] = figure_target_motion(logs, caption=caption)
    return save(figures, out_dir, write_atomically)


def figure_loss_curve(history: list[dict], caption: str | None = None):
    """Tuning: the loss and its main parts against the optimiser step; ``caption``: a
    second title line (the run's loop, starting gains and target)."""
    steps = np.array([row["step"] for row in history])
    fig, axes = plt.subplots(1, 3, figsize=(15, 3.6))
    axes[0].plot(steps, [row["loss"] for row in history], color="black", marker=".")
    axes[0].set_ylabel("loss [-]")
    axes[1].plot(
        steps,
        [1e3 * row["final_position_error_m"] for row in history],
        color="tab:blue",
        marker=".",
        label="final position error",
    )
    axes[1].plot(
        steps,
        [1e3 * row["rms_tracking_m"] for row in history],
        color="tab:orange",
        marker=".",
        label="RMS tracking error",
    )
    axes[1].set_ylabel("error [mm]")
    axes[1].legend()
    axes[2].plot(
        steps,
        [row["peak_torque_smooth"] for row in history],
        color="tab:red",
        marker=".",
        label="smooth max (optimised)",
    )
    axes[2].plot(steps, [row["peak_torque_hard"] for row in history], color="tab:red", linestyle=":", label="hard max")
    axes[2].set_ylabel("peak |u_i| / start peak_i [-]")
    axes[2].legend()
    for ax in axes:
        ax.set_xlabel("optimiser step")
        ax.grid(True, alpha=0.3)
    title = "Tuning: loss and its parts (smooth contact law)"
    fig.suptitle(title if caption is None else f"{title}\n{caption}")
    fig.tight_layout()
    return fig


def figure_peak_torques(before, after, caption: str | None = None, torque_limit_Nm=None):
    """Tuning: per-joint peak |u| before and after (exact contact law); each joint's motor
    limit ``torque_limit_Nm`` (N,) N m as a black mark where given."""
    fig, ax = plt.subplots(figsize=(8, 3.6))
    joints = np.arange(1, len(before) + 1)
    ax.bar(joints - 0.2, before, width=0.4, color=STYLES["start"]["color"], label=STYLES["start"]["label"])
    ax.bar(joints + 0.2, after, width=0.4, color=STYLES["tuned"]["color"], label=STYLES["tuned"]["label"])
    if torque_limit_Nm is not None:
        ax.hlines(np.asarray(torque_limit_Nm), joints - 0.4, joints + 0.4, color="black", label="motor limit")
    ax.set_xlabel("joint")
    ax.set_ylabel("max |u_i| [N m]")
    title = "Peak joint torques, nominal scenario, exact contact law"
    ax.set_title(title if caption is None else f"{title}\n{caption}")
    ax.legend()
    ax.grid(True, axis="y", alpha=0.3)
    fig.tight_layout()
    return fig


def save_tuning_figures(
    history, log_before, log_after, out_dir, write_atomically, caption: str | None = None, torque_limit_Nm=None
) -> None:
    """``loss.png``, ``peak_torques.png`` and ``ee_pose.png`` of a tuning run, each with
    ``caption`` under its title; the motor limits ``torque_limit_Nm`` on the peaks."""
    figures = {
        "loss.png": figure_loss_curve(history, caption=caption),
        "peak_torques.png": figure_peak_torques(
            np.max(np.abs(log_before.u), axis=0),
            np.max(np.abs(log_after.u), axis=0),
            caption=caption,
            torque_limit_Nm=torque_limit_Nm,
        ),
        "ee_pose.png": figure_ee_pose(
            {"start": log_before, "tuned": log_after},
            "EE pose in LAR before and after tuning (exact contact law)",
            caption=caption,
        ),
    }
    save(figures, out_dir, write_atomically)


# ---- Monte-Carlo campaigns: ``metrics`` maps a variant key ("admittance/paper") to its
# per-sample metrics (NumPy arrays, leading axis over samples). ----


def _variant_colour(index: int, key: str):
    controller = key.split("/")[0]
    if index == 0 or key.endswith("/paper"):
        return STYLES.get(controller, STYLES["start"])["color"]
    return plt.get_cmap("tab10")(index % 10)


def _campaign_values(sample_metrics: dict) -> tuple[np.ndarray, np.ndarray]:
    """(final position error in mm, largest peak |u| over the joints in N m) of the samples
    that did not diverge."""
    ok = ~np.isfinite(sample_metrics["first_nonfinite_s"])
    error_mm = 1e3 * np.asarray(sample_metrics["final_position_error_m"])[ok]
    peak = np.asarray(sample_metrics["largest_peak_torque_Nm"])[ok]
    return error_mm, peak


def _spans_decades(values: np.ndarray, decades: float = 2.0) -> bool:
    """True when positive values spread over more than ``decades`` powers of ten: a few
    unstable samples (thousands of N m) would otherwise squeeze the rest into one bin."""
    return bool(values.size and values.min() > 0.0 and np.log10(values.max() / values.min()) > decades)


def _bins(values: np.ndarray, count: int = 30):
    if not values.size or values.max() <= values.min():
        return count
    if _spans_decades(values):
        return np.geomspace(values.min(), values.max(), count + 1)
    return np.linspace(values.min(), values.max(), count + 1)


def figure_campaign_histograms(
    metrics: dict,
    title: str = "Monte-Carlo campaign",
    tolerance_mm: float | None = None,
    torque_threshold_Nm: float | None = None,
):
    """Histograms of the final position error (with the success tolerance, if given) and of
    the largest peak joint torque (with the success criterion's torque threshold, if given: a
    line where it lies within twice the largest peak, else named in the legend)."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    values = {key: _campaign_values(m) for key, m in metrics.items()}
    for column, (ax, xlabel, panel_title) in enumerate(
        zip(
            axes,
            ["final EE position error [mm]", "max over joints of max |u_i| [N m]"],
            ["Final positioning error", "Peak joint torque"],
        )
    ):
        pooled = np.concatenate([v[column] for v in values.values()])
        bins = _bins(pooled)
        if _spans_decades(pooled):
            ax.set_xscale("log")
        for index, (key, v) in enumerate(values.items()):
            n_samples = len(metrics[key]["first_nonfinite_s"])
            ax.hist(
                v[column],
                bins=bins,
                alpha=0.55,
                color=_variant_colour(index, key),
                label=f"{key} ({v[column].size}/{n_samples} finite)",
            )
        if column == 0 and tolerance_mm is not None:
            ax.axvline(
                tolerance_mm, color="black", linestyle="--", linewidth=1, label=f"success tolerance {tolerance_mm:g} mm"
            )
        if column == 1 and torque_threshold_Nm is not None:
            label = f"torque threshold {torque_threshold_Nm:g} N m"
            if pooled.size and torque_threshold_Nm <= 2.0 * np.max(pooled):
                ax.axvline(torque_threshold_Nm, color="black", linestyle="--", linewidth=1, label=label)
            else:
                ax.plot([], [], color="black", linestyle="--", linewidth=1, label=f"{label} (beyond the axis)")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("samples")
        ax.set_title(panel_title)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def figure_campaign_scatter(metrics: dict, title: str = "Monte-Carlo campaign"):
    """Largest peak joint torque against final position error, one point per sample."""
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for index, (key, sample_metrics) in enumerate(metrics.items()):
        error_mm, peak = _campaign_values(sample_metrics)
        ax.scatter(error_mm, peak, s=10, alpha=0.6, color=_variant_colour(index, key), label=key)
    pooled = [_campaign_values(m) for m in metrics.values()]
    if _spans_decades(np.concatenate([error for error, _ in pooled])):
        ax.set_xscale("log")
    if _spans_decades(np.concatenate([peak for _, peak in pooled])):
        ax.set_yscale("log")
    ax.set_xlabel("final EE position error [mm]")
    ax.set_ylabel("max over joints of max |u_i| [N m]")
    ax.set_title(f"Peak joint torque against final positioning error\n{title}", fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


#: The failure classes in the order a campaign assigns them (spacegrasp_jax.jobs.anatomy), and their colours.
_FAILURE_COLOURS = {
    "success": "tab:green",
    "diverged": "black",
    "runaway": "tab:red",
    "joint_range": "tab:pink",
    "joint_rate": "tab:olive",
    "torque_threshold": "tab:orange",
    "position": "tab:blue",
    "orientation": "tab:purple",
    "target_speed": "tab:brown",
}


def figure_campaign_failures(metrics: dict, title: str = "Monte-Carlo campaign"):
    """Why captures fail: per variant, the samples by the first criterion they missed
    (``failure``), and the final position error of the position failures split into its
    approach-axis and cross-axis components and its estimate, compliance and residual parts
    (``final_error_<part>_m``; medians, mm)."""
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.2))
    keys = list(metrics)
    left = np.zeros(len(keys))
    for name, colour in _FAILURE_COLOURS.items():
        counts = np.array([np.sum(np.asarray(metrics[key]["failure"]) == name) for key in keys], dtype=float)
        if counts.any():
            axes[0].barh(keys, counts, left=left, color=colour, label=name)
        left += counts
    axes[0].set_xlabel("samples")
    axes[0].set_title("First criterion missed")
    axes[0].legend(fontsize=8, loc="lower right")
    parts = ("along", "across", "estimate", "compliance", "residual")
    width = 0.8 / max(len(keys), 1)
    for index, key in enumerate(keys):
        m = metrics[key]
        failed = np.asarray(m["failed_position"], dtype=bool)
        values = [np.abs(np.asarray(m[f"final_error_{part}_m"], dtype=float)[failed]) for part in parts]
        medians = [1e3 * np.nanmedian(v) if v.size else 0.0 for v in values]
        axes[1].bar(
            np.arange(len(parts)) + index * width,
            medians,
            width,
            color=_variant_colour(index, key),
            label=f"{key} ({int(failed.sum())} position failures)",
        )
    axes[1].set_xticks(np.arange(len(parts)) + 0.4 - width / 2, [f"|{p}|" for p in parts])
    axes[1].set_ylabel("median over the position failures [mm]")
    axes[1].set_title("Final position error of the position failures")
    axes[1].legend(fontsize=8)
    axes[1].grid(True, axis="y", alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def save_campaign_figures(
    out_dir, metrics: dict, title: str, tolerance_mm: float, write_atomically, torque_threshold_Nm: float | None = None
) -> None:
    """``histograms.png``, ``torque_vs_error.png`` and ``failures.png`` of a Monte-Carlo campaign."""
    figures = {
        "histograms.png": figure_campaign_histograms(metrics, title, tolerance_mm, torque_threshold_Nm),
        "torque_vs_error.png": figure_campaign_scatter(metrics, title),
        "failures.png": figure_campaign_failures(metrics, title),
    }
    save(figures, out_dir, write_atomically)


def figure_requirement_curves(document: dict):
    """Success (95% intervals shaded) against the width of each perturbation group, one panel a
    group and the last all together, one line a gain set, the requirement levels dashed
    (a requirements study's ``requirements.json``)."""
    curves, levels = document["curves"], document["settings"]["levels"]
    names = list(curves)
    columns = min(4, len(names))
    rows = -(-len(names) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(3.6 * columns, 2.9 * rows), squeeze=False, sharey=True)
    for ax, name in zip(axes.flat, names):
        entry = curves[name]
        widths = np.asarray(entry["widths"], dtype=float)
        for label in [key for key in entry if key not in ("widths", "half_widths")]:
            intervals = entry[label]["intervals"]
            rate = 100 * np.array([i["rate"] for i in intervals])
            low, high = (100 * np.array([i[k] for i in intervals]) for k in ("low", "high"))
            (line,) = ax.plot(widths, rate, marker="o", label=label)
            ax.fill_between(widths, low, high, color=line.get_color(), alpha=0.2)
        for level in levels:
            ax.axhline(100 * level, color="grey", linestyle="--", linewidth=0.8)
        ax.set_title(name.replace("_", " "), fontsize=10)
        ax.set_xlabel("width [x reference]")
        ax.grid(True, alpha=0.3)
    for ax in axes[:, 0]:
        ax.set_ylabel("success [%]")
    for ax in list(axes.flat)[len(names) :]:
        ax.set_visible(False)
    axes.flat[0].legend(fontsize=8)
    fig.suptitle("Capture success against the width of each perturbation (95% intervals)")
    fig.tight_layout()
    return fig


def save_requirement_curves(path, document: dict, write_atomically) -> None:
    """``figure_requirement_curves()`` as ``path`` (a PNG)."""
    from pathlib import Path

    path = Path(path)
    save({path.name: figure_requirement_curves(document)}, path.parent, write_atomically)


def figure_gradient_health(norm_ratios, cosines, horizon_norms: list[dict], outlier_factor: float, title: str):
    """Gradient health over the envelope: the gradient norm over the nominal's (log scale,
    the outlier threshold marked), the cosine with the nominal gradient, and the gradient
    norm against the horizon (median, 95th percentile, largest)."""
    fig, axes = plt.subplots(1, 3, figsize=(15, 3.8))
    ratios = np.asarray(norm_ratios, dtype=float)
    ratios = ratios[np.isfinite(ratios) & (ratios > 0.0)]
    if len(ratios):
        axes[0].hist(np.log10(ratios), bins=40, color="tab:blue")
    axes[0].axvline(np.log10(outlier_factor), color="tab:red", linestyle="--", label=f"{outlier_factor:g}x nominal")
    axes[0].set_xlabel("log10 (|gradient| / |nominal gradient|)")
    axes[0].set_ylabel("samples")
    axes[0].legend()
    cos = np.asarray(cosines, dtype=float)
    axes[1].hist(cos[np.isfinite(cos)], bins=40, range=(-1.0, 1.0), color="tab:green")
    axes[1].set_xlabel("cosine with the nominal gradient")
    horizons = [row["horizon_s"] for row in horizon_norms]
    for key, label, style in (
        ("median_norm", "median", "o-"),
        ("p95_norm", "95th percentile", "s--"),
        ("largest_norm", "largest", "^:"),
        ("nominal_norm", "nominal", "k.-"),
    ):
        axes[2].semilogy(horizons, [row[key] for row in horizon_norms], style, label=label)
    axes[2].set_xlabel("horizon [s]")
    axes[2].set_ylabel("|gradient| (log-gains)")
    axes[2].legend()
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def save_gradient_figures(out_dir, norm_ratios, cosines, horizon_norms, outlier_factor, title, write_atomically):
    """``gradients.png`` of ``spacegrasp gradients`` ([`figure_gradient_health()`][spacegrasp_jax.analysis.plots.figure_gradient_health])."""
    figure = figure_gradient_health(norm_ratios, cosines, horizon_norms, outlier_factor, title)
    save({"gradients.png": figure}, out_dir, write_atomically)


def figure_worst_case_search(history: list, campaign_values, screening: int, label: str, title: str):
    """The worst-case search of ``spacegrasp worstcase`` against a campaign of the same
    rollouts: each start's worst measure so far against the rollouts spent (from the end of
    the screening), the campaign's worst so far against its samples, and the worst of the
    whole campaign (dashed)."""
    fig, ax = plt.subplots(figsize=(8.0, 4.5))
    fig.suptitle(title)
    values = np.asarray(campaign_values, dtype=float)
    top = np.nanmax(np.where(np.isfinite(values), values, np.nan)) if np.isfinite(values).any() else 1.0
    rollouts = np.array([row["rollouts"] for row in history])
    best = np.array([row["best"] for row in history], dtype=float)
    for start in range(best.shape[1]):
        ax.plot(rollouts, np.minimum(best[:, start], 3.0 * top), "o-", markersize=3, label=f"ascent from start {start}")
    running = np.maximum.accumulate(np.where(np.isfinite(values), values, 3.0 * top))
    ax.plot(np.arange(1, len(values) + 1), running, color="black", label="campaign: worst so far")
    ax.axhline(running[-1], color="black", linestyle="--", linewidth=1, label=f"campaign of {len(values)}: worst")
    ax.axvline(screening, color="tab:gray", linestyle=":", label="end of the screening")
    ax.set_xlabel("rollouts")
    ax.set_ylabel(label)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def figure_reliability(estimate, points: dict, title: str):
    """A failure probability's evidence (``spacegrasp reliability``): left, the margin of every
    point the estimator evaluated against its distance from the origin of the standard space
    (failures below 0, the most probable failure points circled); right, the perturbations the
    failing captures have in common (``reliability.attribution()``)."""
    fig, (left, right) = plt.subplots(1, 2, figsize=(11.0, 4.5), gridspec_kw={"width_ratios": [3, 2]})
    fig.suptitle(f"{title}\n{estimate.method}: {estimate.summary()}", fontsize=10)
    distance, g = np.asarray(points["distance"]), np.asarray(points["g"])
    failing = g < 0.0
    left.scatter(distance[~failing], g[~failing], s=4, color="tab:blue", alpha=0.4, label="captured")
    left.scatter(distance[failing], g[failing], s=6, color="tab:red", alpha=0.6, label="failed")
    for k, point in enumerate(estimate.design_points):
        left.scatter(
            [point["distance"]],
            [point["g"]],
            s=60,
            facecolors="none",
            edgecolors="black",
            label="most probable failures" if k == 0 else None,
        )
    left.axhline(0.0, color="black", linewidth=1)
    left.set_xlabel("distance |z| from the nominal capture (standard normal units)")
    left.set_ylabel("margin g (below 0: failed)")
    left.grid(True, alpha=0.3)
    left.legend(fontsize=8)
    if estimate.attribution:
        shares = estimate.attribution
        names = list(shares)[::-1]
        right.barh(names, [100.0 * shares[name] for name in names], color="tab:red")
        right.set_xlabel("share of the failures' excess spread (%)")
        right.set_title(f"what the {estimate.failing:,} failing captures have in common", fontsize=9)
    else:
        right.text(0.5, 0.5, "no failing point sampled", ha="center", va="center", transform=right.transAxes)
        right.set_axis_off()
    fig.tight_layout()
    return fig


def _probe_outcome(probe: dict, captured_at_nominal: np.ndarray) -> float:
    """mm: the largest final position error of a probe's samples that capture at the nominal
    gains (all samples if none does); inf if one of them ran away or diverged."""
    errors = np.array([np.nan if e is None else e for e in probe["final_position_error_m"]], dtype=float)
    chosen = captured_at_nominal if captured_at_nominal.any() else np.ones_like(captured_at_nominal)
    if not np.all(np.asarray(probe["bounded"])[chosen]) or not np.all(np.isfinite(errors[chosen])):
        return np.inf
    return 1e3 * float(np.max(errors[chosen]))


def figure_margins(result: dict, tolerance_mm: float, title: str):
    """The margin searches of ``spacegrasp margins`` (``spacegrasp_jax.analysis.margins.find_margins()``'s
    result): for the joint PID's gain factor, the law's gain factor, the extra delay at the
    controller's output and, where it was searched, the delay at the servo's input, each
    probe's outcome (the largest final position error of the samples that capture at the
    nominal gains, log scale; a probe where one ran away drawn at the top), green where the
    loop holds and red where it fails, the tolerance and the margins marked."""
    servo = result.get("servo_delay_margin") is not None
    fig, axes = plt.subplots(1, 4 if servo else 3, figsize=(20 if servo else 15, 4.0), sharey=True)
    fig.suptitle(title)
    captured = np.asarray(result["nominal"]["success"], dtype=bool)
    probes = result["probes"]
    finite = [_probe_outcome(p, captured) for p in probes]
    finite = [v for v in finite if np.isfinite(v)]
    top = 3.0 * max(finite + [tolerance_mm])
    panels = (
        ("pid", "joint PID gain factor", axes[0]),
        ("law", f"{result['controller']} law gain factor", axes[1]),
        (
            "delay",
            f"extra delay at the controller's output [control periods of {result['control_period_s']:g} s]",
            axes[2],
        ),
    )
    if servo:
        label = f"delay at the servo's input [servo ticks of {result['servo_period_s']:g} s]"
        panels += (("servo_delay", label, axes[3]),)
    for loop, label, ax in panels:
        delay = loop in ("delay", "servo_delay")
        chosen = [p for p in probes if p["loop"] in (loop, "nominal")]
        for p in chosen:
            x = (0 if delay else 1.0) if p["loop"] == "nominal" else p["value"]
            y = _probe_outcome(p, captured)
            ax.plot(
                x,
                min(y, top),
                "x" if not np.isfinite(y) else "o",
                color="tab:green" if p["holds"] else "tab:red",
                markersize=7,
            )
        ax.axhline(tolerance_mm, color="black", linestyle="--", linewidth=1, label=f"tolerance {tolerance_mm:g} mm")
        if delay:
            margin = result["delay_margin" if loop == "delay" else "servo_delay_margin"]
            ax.axvline(margin["holds_periods"], color="tab:green", linestyle=":", label="margin (holds)")
            if margin["fails_periods"] is not None:
                ax.axvline(margin["fails_periods"], color="tab:red", linestyle=":", label="fails")
            ax.set_xlim(-0.5, max(p["value"] for p in chosen if p["loop"] == loop) + 1.0 if len(chosen) > 1 else 1.0)
        else:
            for direction in ("increase", "decrease"):
                margin = result["gain_margins"][loop][direction]
                ax.axvline(margin["holds"], color="tab:green", linestyle=":")
                if margin["fails"] is not None:
                    ax.axvline(margin["fails"], color="tab:red", linestyle=":")
            ax.set_xscale("log")
            ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
            ax.xaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
            ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_yscale("log")
        ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.yaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
        ax.yaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel(label)
        ax.grid(True, alpha=0.3)
    axes[0].set_ylabel("largest final position error [mm]\n(x: a sample ran away)")
    handles = [
        plt.Line2D([], [], marker="o", linestyle="", color="tab:green", label="holds"),
        plt.Line2D([], [], marker="o", linestyle="", color="tab:red", label="fails"),
        plt.Line2D([], [], color="black", linestyle="--", label=f"tolerance {tolerance_mm:g} mm"),
        plt.Line2D([], [], color="tab:green", linestyle=":", label="margin: last factor that holds"),
        plt.Line2D([], [], color="tab:red", linestyle=":", label="first that fails"),
    ]
    axes[2].legend(handles=handles, fontsize=8)
    fig.tight_layout()
    return fig


def figure_eigenvalues(linear: dict, title: str):
    """The period map's eigenvalues (``spacegrasp_jax.analysis.stability.linear_analysis()``'s
    result) for the nominal gains and at the first failing factor of each linear gain
    margin: in the unit disc (left; a mode is stable inside the circle) and as poles
    ``s = ln(lambda) / T`` (right): growth rate ``Re s`` against frequency ``|Im s| / 2 pi``,
    where the slow modes a short control period crowds near ``z = 1`` stand apart. The
    growth limit the margins use is the dashed line."""
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.5))
    fig.suptitle(title)
    sets = [("nominal gains", np.asarray([m["eigenvalue"] for m in linear["modes"]]), "k", "o")]
    markers = {"pid": "^", "law": "s"}
    for loop, directions in linear["eigenvalues_at_margins"].items():
        for direction, values in directions.items():
            if values is not None:
                factor = linear["gain_margins"][loop][direction]["fails"]
                colour = "tab:red" if direction == "increase" else "tab:blue"
                sets.append((f"{loop} gain x{factor:.3g} (fails)", np.asarray(values), colour, markers[loop]))
    angle = np.linspace(0.0, 2.0 * np.pi, 721)
    disc, poles = axes
    disc.plot(np.cos(angle), np.sin(angle), color="0.6", lw=1.0)
    period = linear["control_period_s"]
    for label, values, colour, marker in sets:
        disc.plot(values[:, 0], values[:, 1], marker, mfc="none", color=colour, label=label, ms=6)
        z = values[:, 0] + 1j * values[:, 1]
        z = z[np.abs(z) > 0.0]
        s = np.log(z) / period
        poles.plot(s.real, np.abs(s.imag) / (2.0 * np.pi), marker, mfc="none", color=colour, label=label, ms=6)
    disc.set_aspect("equal")
    disc.set(xlabel="Re z", ylabel="Im z", title="eigenvalues of the control-period map")
    disc.legend(fontsize=8, loc="lower left")
    poles.axvline(0.0, color="0.4", lw=1.0)
    poles.axvline(linear["growth_limit_per_s"], color="tab:red", ls="--", lw=1.0, label="growth limit")
    poles.set_xscale("symlog", linthresh=0.01)
    poles.set_yscale("symlog", linthresh=0.01)
    poles.set_ylim(bottom=0.0)
    poles.set(
        xlabel="growth rate Re s [1/s] (right of 0: grows)",
        ylabel="frequency |Im s| / 2 pi [Hz]",
        title="the same modes as poles s = ln(z) / T",
    )
    for ax in axes:
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    return fig


def save_margin_figures(
    out_dir, result: dict, tolerance_mm: float, title: str, write_atomically, bode: dict | None = None
) -> None:
    """``margins.png`` of ``spacegrasp margins`` ([`figure_margins()`][spacegrasp_jax.analysis.plots.figure_margins]) and, with a
    linear analysis in ``result["linear"]``, ``eigenvalues.png`` ([`figure_eigenvalues()`][spacegrasp_jax.analysis.plots.figure_eigenvalues]);
    with its loops' ``bode`` data, ``bode.png`` and ``nichols.png`` ([`figure_bode()`][spacegrasp_jax.analysis.plots.figure_bode],
    [`figure_nichols()`][spacegrasp_jax.analysis.plots.figure_nichols])."""
    figures = {"margins.png": figure_margins(result, tolerance_mm, title)}
    if result.get("linear"):
        figures["eigenvalues.png"] = figure_eigenvalues(result["linear"], title)
    if bode:
        margins_by_loop = result["linear"].get("frequency_response", {}) if result.get("linear") else {}
        figures["bode.png"] = figure_bode(bode, margins_by_loop, title)
        figures["nichols.png"] = figure_nichols(bode, title)
    save(figures, out_dir, write_atomically)


#: The loops' names on the frequency-response figures.
_LOOP_TITLES = {"pid": "broken at the joint PID", "law": "broken at the law"}


def figure_bode(bode: dict, margins_by_loop: dict, title: str):
    """The Bode plot of each loop broken at its gain (``spacegrasp_jax.analysis.frequency.bode()``'s
    data a loop): each characteristic locus' magnitude (dB) and phase (deg) of the open loop
    ``L = -g`` against frequency, the 0 dB and -180 deg lines, and the gain margins' and the
    phase margin's frequencies (``loop_margins()``) marked."""
    loops = list(bode)
    fig, axes = plt.subplots(2, len(loops), figsize=(6.5 * len(loops), 7.5), sharex="col", squeeze=False)
    fig.suptitle(f"Frequency response of the linearised loop\n{title}", fontsize=11)
    for column, loop in enumerate(loops):
        data, magnitude_ax, phase_ax = bode[loop], axes[0, column], axes[1, column]
        f = data["frequency_hz"]
        for i in range(data["magnitude_db"].shape[1]):
            magnitude_ax.semilogx(f, data["magnitude_db"][:, i], color=f"C{i % 10}", lw=1.0)
            phase_ax.semilogx(f, data["phase_deg"][:, i], color=f"C{i % 10}", lw=1.0)
        magnitude_ax.axhline(0.0, color="0.3", lw=0.8, ls="--")
        for k in range(-4, 2):
            phase_ax.axhline(-180.0 + 360.0 * k, color="0.3", lw=0.8, ls="--")
        found = margins_by_loop.get(loop, {})
        notes = []
        for direction, entry in (found.get("gain_margins") or {}).items():
            if entry is not None and entry["frequency_hz"] > 0.0:
                magnitude_ax.axvline(entry["frequency_hz"], color="tab:red", lw=0.8, ls=":")
                notes.append(f"gain margin ({direction}) x{entry['factor']:.3g} at {entry['frequency_hz']:.3g} Hz")
        phase = found.get("phase_margin")
        if phase is not None:
            phase_ax.axvline(phase["frequency_hz"], color="tab:blue", lw=0.8, ls=":")
            notes.append(f"phase margin {phase['phase_margin_deg']:.1f} deg at {phase['frequency_hz']:.3g} Hz")
        magnitude_ax.set(
            ylabel="|L| [dB]", title=f"{_LOOP_TITLES.get(loop, loop)}: {data['magnitude_db'].shape[1]} loci"
        )
        phase_ax.set(xlabel="frequency [Hz]", ylabel="phase of L [deg]")
        phase_ax.set_ylim(
            max(-900.0, float(np.nanmin(data["phase_deg"])) - 30.0), float(np.nanmax(data["phase_deg"])) + 30.0
        )
        if notes:
            magnitude_ax.text(0.02, 0.03, "\n".join(notes), transform=magnitude_ax.transAxes, fontsize=7, va="bottom")
        for ax in (magnitude_ax, phase_ax):
            ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    return fig


def figure_nichols(bode: dict, title: str):
    """The Nichols chart of each loop broken at its gain: each locus' open-loop magnitude (dB)
    against its phase (deg), the critical points (-180 deg + k 360 deg, 0 dB) marked."""
    loops = list(bode)
    fig, axes = plt.subplots(1, len(loops), figsize=(6.5 * len(loops), 5.5), squeeze=False)
    fig.suptitle(f"Nichols chart of the linearised loop\n{title}", fontsize=11)
    for ax, loop in zip(axes[0], loops):
        data = bode[loop]
        for i in range(data["magnitude_db"].shape[1]):
            ax.plot(data["phase_deg"][:, i], data["magnitude_db"][:, i], color=f"C{i % 10}", lw=1.0)
        low, high = ax.get_xlim()
        for k in range(-4, 2):
            critical = -180.0 + 360.0 * k
            if low <= critical <= high:
                ax.plot(critical, 0.0, "r+", ms=12, mew=2)
        ax.axhline(0.0, color="0.3", lw=0.8, ls="--")
        ax.set(xlabel="phase of L [deg]", ylabel="|L| [dB]", title=_LOOP_TITLES.get(loop, loop))
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    return fig


# ---- the EE path around the contact sphere, and gain sweeps ----------------------------


def figure_gain_schedule(curves: dict[str, dict], variable: str, unit: str, caption: str | None = None):
    """Each scheduled group's gains against the scheduling variable (one panel a group, one
    line an axis or joint, each over its value at the first knot, log scale; the knots
    marked): ``curves`` as ``control.schedule.schedule_curves()`` gives them."""
    names = list(curves) or ["(no scheduled group)"]
    fig, axes = plt.subplots(len(names), 1, figsize=(6.5, 2.3 * len(names)), sharex=True, squeeze=False)
    title = f"Gain schedule on {variable}"
    fig.suptitle(title if caption is None else f"{title}\n{caption}", fontsize=11 if caption else None)
    for ax, name in zip(axes[:, 0], names):
        curve = curves.get(name)
        if curve is None:
            ax.text(0.5, 0.5, "every group is constant", ha="center", va="center", transform=ax.transAxes)
            continue
        first = curve["at_knots"][0]
        for j in range(curve["gains"].shape[1]):
            ax.plot(curve["x"], curve["gains"][:, j] / first[j], color=f"C{j % 10}", linewidth=1.2, label=f"{j + 1}")
            ax.plot(curve["knots"], curve["at_knots"][:, j] / first[j], "o", color=f"C{j % 10}", markersize=3)
        for knot in curve["knots"]:
            ax.axvline(knot, color="0.8", linewidth=0.8, zorder=0)
        ax.set_yscale("log")
        ax.set_ylabel(f"{name} / first knot's")
        ax.grid(True, which="both", alpha=0.3)
    axes[0, 0].legend(title="axis or joint", fontsize=7, ncol=7, loc="best")
    axes[-1, 0].set_xlabel(f"{variable} [{unit}]")
    fig.tight_layout()
    return fig


def figure_schedule_regime(
    t: np.ndarray, x: np.ndarray, knots: dict, gains: dict, variable: str, unit: str, caption: str | None = None
):
    """Which regime a capture was in: the scheduling variable along the run ``x`` (T,) at
    times ``t`` (T,) s, each scheduled group's knots as horizontal lines (``knots``: group ->
    (K,)), and below each group's gains along the run (``gains``: group -> (T, n)), each over
    its value at the start."""
    names = list(gains)
    fig, axes = plt.subplots(1 + len(names), 1, figsize=(6.5, 2.2 * (1 + len(names))), sharex=True, squeeze=False)
    title = f"The schedule's regime along the capture ({variable})"
    fig.suptitle(title if caption is None else f"{title}\n{caption}", fontsize=11 if caption else None)
    top = axes[0, 0]
    top.plot(t, x, color="black", linewidth=1.2)
    for index, name in enumerate(names):
        for knot in knots[name]:
            top.axhline(knot, color=f"C{index % 10}", linestyle=":", linewidth=0.9)
        top.plot([], [], color=f"C{index % 10}", linestyle=":", label=f"{name} knots")
    top.set_ylabel(f"{variable} [{unit}]")
    if names:
        top.legend(fontsize=7, loc="best")
    for ax, name in zip(axes[1:, 0], names):
        series = gains[name]
        for j in range(series.shape[1]):
            ax.plot(t, series[:, j] / series[0, j], color=f"C{j % 10}", linewidth=1.1)
        ax.set_yscale("log")
        ax.set_ylabel(f"{name} / at start")
    for ax in axes[:, 0]:
        ax.grid(True, alpha=0.3)
    axes[-1, 0].set_xlabel("time [s]")
    fig.tight_layout()
    return fig


def _sphere_outline(centre_mm, radius_mm, axes_pair, n: int = 181):
    angle = np.linspace(0.0, 2.0 * np.pi, n)
    i, j = axes_pair
    return centre_mm[i] + radius_mm * np.cos(angle), centre_mm[j] + radius_mm * np.sin(angle)


def figure_ee_path(
    logs, sphere_centre, sphere_radius, title: str = "End-effector path around the contact sphere (LAR frame)"
):
    """The EE position in the LAR frame in 3-D, and its side (x-z) and top (x-y) views, with
    the desired path and the contact sphere (eq 20).

    Args:
        logs: controller or style name -> log (NumPy fields).
        sphere_centre: (3,) m, LAR frame. sphere_radius: m.
    """
    centre, radius = 1e3 * np.asarray(sphere_centre, dtype=float), 1e3 * float(sphere_radius)
    fig = plt.figure(figsize=(15, 4.8))
    ax3d = fig.add_subplot(1, 3, 1, projection="3d")
    side, top = fig.add_subplot(1, 3, 2), fig.add_subplot(1, 3, 3)
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 25), np.linspace(0, np.pi, 13))
    ax3d.plot_wireframe(
        centre[0] + radius * np.cos(u) * np.sin(v),
        centre[1] + radius * np.sin(u) * np.sin(v),
        centre[2] + radius * np.cos(v),
        color="tab:gray",
        linewidth=0.4,
        alpha=0.5,
    )
    desired = 1e3 * next(iter(logs.values())).pose_des[:, :3]
    paths = {name: 1e3 * log.pose_ee[:, :3] for name, log in logs.items()} | {"desired": desired}
    for name, p in paths.items():
        style = dict(STYLES[name], linewidth=1.0 if name == "desired" else 1.6)
        ax3d.plot(p[:, 0], p[:, 1], p[:, 2], **style)
        side.plot(p[:, 0], p[:, 2], **style)
        top.plot(p[:, 0], p[:, 1], **style)
        if name != "desired":
            for ax, (a, b) in ((side, (0, 2)), (top, (0, 1))):
                ax.plot(p[-1, a], p[-1, b], marker="o", color=style["color"], markersize=4)
    for ax, pair, xlabel, ylabel, view in (
        (side, (0, 2), "x [mm]", "z [mm]", "side view (x-z)"),
        (top, (0, 1), "x [mm]", "y [mm]", "top view (x-y)"),
    ):
        ax.fill(*_sphere_outline(centre, radius, pair), color="tab:gray", alpha=0.15, label="contact sphere")
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.set_title(f"{view}; dots: final position", fontsize=10)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
    ax3d.set_xlabel("x [mm]")
    ax3d.set_ylabel("y [mm]")
    ax3d.set_zlabel("z [mm]")
    ax3d.set_title("3-D, LAR frame", fontsize=10)
    side.legend(fontsize=8, loc="best")
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def figure_tradeoff(
    peak_torque_Nm,
    final_error_m,
    contact_force_N,
    front,
    highlights: dict | None = None,
    title: str = "Peak joint torque against final positioning error",
):
    """One point per gain set: largest peak joint torque against final EE position error
    (log axes), coloured by peak contact force, the Pareto front joined by a line.

    Args:
        peak_torque_Nm, final_error_m, contact_force_N: (N,) per gain set; non-finite
            (diverged) points are left out and counted in the title.
        front: (N,) bool, the Pareto-optimal points ([`spacegrasp_jax.analysis.sweep.pareto_front()`][spacegrasp_jax.analysis.sweep.pareto_front]).
        highlights: label -> (peak torque N m, final error m), drawn as large markers
            (e.g. the paper's and the tuned gains).
    """
    torque, error_mm, force = np.asarray(peak_torque_Nm), 1e3 * np.asarray(final_error_m), np.asarray(contact_force_N)
    finite = np.isfinite(torque) & np.isfinite(error_mm) & np.isfinite(force)
    fig, ax = plt.subplots(figsize=(8, 5.5))
    points = ax.scatter(error_mm[finite], torque[finite], c=force[finite], cmap="viridis", s=22, edgecolors="none")
    fig.colorbar(points, ax=ax, label="peak contact force [N]")
    order = np.argsort(error_mm[front])
    ax.plot(
        error_mm[front][order],
        torque[front][order],
        color="black",
        linewidth=1.2,
        drawstyle="steps-post",
        label="Pareto front",
    )
    for (label, (peak, error)), marker in zip((highlights or {}).items(), ["*", "P", "D", "X", "s"]):
        ax.plot(
            1e3 * error,
            peak,
            marker=marker,
            markersize=14,
            markeredgecolor="black",
            color="white",
            linestyle="none",
            label=label,
        )
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("final EE position error [mm]")
    ax.set_ylabel("max over joints of max |u_i| [N m]")
    dropped = int(np.sum(~finite))
    ax.set_title(
        title + (f"\n({dropped} diverged gain set{'s' if dropped != 1 else ''} not shown)" if dropped else ""),
        fontsize=11,
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=9)
    fig.tight_layout()
    return fig
