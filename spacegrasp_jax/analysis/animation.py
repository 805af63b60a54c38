"""A film of a capture from a run's time series: the satellite, the arm, the target's ring and
contact sphere, the contact force, in 3D.

[`capture_scene()`][spacegrasp_jax.analysis.animation.capture_scene] turns a run's log into the points
each frame draws (all in the inertial frame, m): the satellite's pose is not logged, so it is
recovered from what is: the EE pose in the LAR frame, the LAR's pose (fixed, or the free
target's) and the joint angles, through the arm's own kinematics. [`draw_frame()`][spacegrasp_jax.analysis.animation.draw_frame]
and [`write_film()`][spacegrasp_jax.analysis.animation.write_film] draw them with matplotlib from one
fixed camera with equal axes. The ring is drawn, not modelled: the contact is the paper's
sphere (eq 20), and the ring a circle around the LAR origin in its x-y plane.

GIFs are written with Pillow (matplotlib's own dependency); MP4 needs ``imageio-ffmpeg``, a
wheel that brings its own ``ffmpeg`` (``pip install spacegrasp-jax[video]``).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import jax
import numpy as np

from spacegrasp_jax.core import kinematics, spatial
from spacegrasp_jax.core.model import Robot

#: The ring drawn around the LAR origin (m): schematic, the model's contact is the sphere.
RING_RADIUS_M = 0.12
#: Length of the contact force's arrow per newton (m/N).
ARROW_M_PER_N = 0.02
#: The figure's size (inches) and resolution (dots per inch): 560 x 420 pixels.
FIGURE_INCHES, DPI = (5.6, 4.2), 100
#: The end-effector's marker colour (matplotlib's tab:red).
EE_COLOR = "#d62728"
#: The camera: elevation and azimuth (degrees), matplotlib's convention.
ELEVATION_DEG, AZIMUTH_DEG = 22.0, -58.0


class AnimationError(ValueError):
    """A film cannot be made as asked (the file type, the writer, the run); the message says why."""


@dataclasses.dataclass(frozen=True)
class Scene:
    """What each frame draws, one row per logged step (T steps), inertial frame, m.

    Attributes:
        t: (T,) s.
        arm: (T, N + 2, 3) the arm as a polyline: frame 0 (the mount), the joints' frames
            1..N-1 and N, then the EE point.
        satellite_edges: (T, 12, 2, 3) the satellite drawn as a box of its inertia's
            proportions (the uniform box of the same principal moments and mass).
        ring: (T, 48, 3) the LAR ring's circle. sphere: (T, 3) the contact sphere's centre.
        sphere_radius: m.
        ee: (T, 3) the EE point. force: (T, 3) N, the contact force on the EE.
        final_position_error_mm, final_orientation_error_deg: the run's final errors.
        regime: (T,) words saying which regime of a gain schedule each row ran in
            (``schedule.regime_labels``), or ``None`` for constant gains.
    """

    t: np.ndarray
    arm: np.ndarray
    satellite_edges: np.ndarray
    ring: np.ndarray
    sphere: np.ndarray
    sphere_radius: float
    ee: np.ndarray
    force: np.ndarray
    final_position_error_mm: float
    final_orientation_error_deg: float
    regime: tuple[str, ...] | None = None


def _box_edges(robot: Robot) -> np.ndarray:
    """(12, 2, 3) the edges of the uniform box with the satellite's mass and principal moments,
    in its principal axes, about its CoM."""
    inertia = np.asarray(robot.satellite_inertia, dtype=float)
    moments, axes = np.linalg.eigh(inertia)
    mass = float(robot.satellite_mass)
    # I_x = m (b^2 + c^2) / 12 and so on: side^2 = 6 (I_y + I_z - I_x) / m.
    sides = np.sqrt(np.maximum(6.0 * (moments.sum() - 2.0 * moments) / mass, 1e-6))
    corners = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)]) * sides
    pairs = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
    return np.array([[axes @ corners[a], axes @ corners[b]] for a, b in pairs])


def lar_poses(log, scenario) -> tuple[np.ndarray, np.ndarray]:
    """``(p_lar (T, 3), R_lar (T, 3, 3))``: the LAR's pose at each step, the scenario's for the
    paper's fixed target, or the free target's (its CoM and attitude moved by the LAR's place
    in it)."""
    steps = len(np.asarray(log.t))
    if not scenario.free_target:
        p = np.broadcast_to(np.asarray(scenario.p_lar, dtype=float), (steps, 3))
        R = np.broadcast_to(np.asarray(scenario.R_lar, dtype=float), (steps, 3, 3))
        return p, R
    R = np.asarray(jax.vmap(spatial.quat_to_rotation)(np.asarray(log.target_quat)))
    com_in_lar = np.asarray(scenario.target.com_in_lar, dtype=float)
    return np.asarray(log.target_position) - np.einsum("tij,j->ti", R, com_in_lar), R


def capture_scene(robot: Robot, scenario, log, rows=None, regime=None) -> Scene:
    """The [`Scene`][spacegrasp_jax.analysis.animation.Scene] of ``log`` (a run of ``robot`` on
    ``scenario``) at its steps ``rows`` (an index array; ``None``: every step); ``regime``:
    a gain schedule's regime in words at every step of ``log`` (``None``: constant gains)."""
    rows = slice(None) if rows is None else np.asarray(rows)
    if regime is not None and len(regime) != len(np.asarray(log.t)):
        raise AnimationError(f"regime: expected a label for each of the log's {len(log.t)} steps, got {len(regime)}")
    p_lar_all, R_lar_all = lar_poses(log, scenario)
    p_lar, R_lar = p_lar_all[rows], R_lar_all[rows]
    pose_ee = np.asarray(log.pose_ee)[rows]
    q = np.asarray(log.q)[rows]
    # The EE's pose in the inertial frame from the log, and the arm's from its own kinematics
    # on a satellite at the origin: the satellite's pose is what makes the two agree.
    p_ee = p_lar + np.einsum("tij,tj->ti", R_lar, pose_ee[:, :3])
    R_ee = np.einsum("tij,tjk->tik", R_lar, np.asarray(jax.vmap(spatial.euler_zyx_to_rotation)(pose_ee[:, 3:])))
    at_origin = jax.jit(jax.vmap(lambda q: kinematics.forward_kinematics(robot, np.zeros(3), np.eye(3), q)))(q)
    R_base = np.einsum("tij,tkj->tik", R_ee, np.asarray(at_origin.R_ee))
    p_base = p_ee - np.einsum("tij,tj->ti", R_base, np.asarray(at_origin.p_ee))
    to_world = lambda points: p_base[:, None, :] + np.einsum("tij,tkj->tki", R_base, points)  # noqa: E731
    chain = np.concatenate(
        [
            np.asarray(at_origin.joint_origin),
            np.asarray(at_origin.link_origin)[:, -1:],
            np.asarray(at_origin.p_ee)[:, None],
        ],
        axis=1,
    )
    edges = _box_edges(robot)
    satellite = to_world(edges.reshape(1, -1, 3).repeat(len(q), 0)).reshape(len(q), 12, 2, 3)
    angle = np.linspace(0.0, 2.0 * math.pi, 48)
    circle = RING_RADIUS_M * np.stack([np.cos(angle), np.sin(angle), np.zeros_like(angle)], axis=-1)
    ring = p_lar[:, None, :] + np.einsum("tij,kj->tki", R_lar, circle)
    sphere = p_lar + np.einsum("tij,j->ti", R_lar, np.asarray(scenario.sphere_centre, dtype=float))
    force = np.einsum("tij,tj->ti", R_lar, np.asarray(log.contact_force)[rows])
    final = np.asarray(log.pose_ee)[-1] - np.asarray(log.pose_des)[-1]
    R_final = np.asarray(spatial.euler_zyx_to_rotation(np.asarray(log.pose_ee)[-1, 3:]))
    R_wanted = np.asarray(spatial.euler_zyx_to_rotation(np.asarray(log.pose_des)[-1, 3:]))
    return Scene(
        t=np.asarray(log.t)[rows],
        arm=to_world(chain),
        satellite_edges=satellite,
        ring=ring,
        sphere=sphere,
        sphere_radius=float(scenario.sphere_radius),
        ee=p_ee,
        force=force,
        final_position_error_mm=1e3 * float(np.linalg.norm(final[:3])),
        final_orientation_error_deg=math.degrees(float(np.linalg.norm(spatial.rotation_log(R_wanted.T @ R_final)))),
        regime=None if regime is None else tuple(np.asarray(regime, dtype=object)[rows].tolist()),
    )


def _limits(scene: Scene) -> tuple[np.ndarray, float]:
    """The fixed camera's centre (3,) m and half-width m: everything the film shows, in a cube."""
    points = np.concatenate([scene.arm.reshape(-1, 3), scene.satellite_edges.reshape(-1, 3), scene.ring.reshape(-1, 3)])
    low, high = points.min(axis=0), points.max(axis=0)
    return (low + high) / 2.0, 0.55 * float(np.max(high - low))


class _Frame:
    """The figure and the artists one frame updates."""

    def __init__(self, scene: Scene, title: str):
        import matplotlib.pyplot as plt
        from matplotlib.ticker import MaxNLocator

        self.scene = scene
        self.figure = plt.figure(figsize=FIGURE_INCHES, dpi=DPI)
        ax = self.figure.add_axes([0.0, 0.04, 1.0, 0.84], projection="3d")
        ax.view_init(elev=ELEVATION_DEG, azim=AZIMUTH_DEG)
        centre, half = _limits(scene)
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.set_zlim(centre[2] - half, centre[2] + half)
        ax.set_box_aspect((1.0, 1.0, 1.0))
        ax.grid(False)  # the panes' grid lines cost a third of each frame's drawing
        for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
            axis.set_major_locator(MaxNLocator(4))
        ax.tick_params(labelsize=7)
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_zlabel("z [m]")
        ax.computed_zorder = False  # drawn in the order below: the EE last, always in sight
        self.ax = ax
        self.satellite = [ax.plot([], [], [], color="0.35", linewidth=1.2)[0] for _ in range(12)]
        (self.arm,) = ax.plot([], [], [], color="tab:blue", linewidth=3.0, marker="o", markersize=4)
        (self.ring,) = ax.plot([], [], [], color="tab:orange", linewidth=2.0)
        (self.sphere,) = ax.plot([], [], [], color="tab:orange", linewidth=0.8)
        (self.force,) = ax.plot([], [], [], color="tab:green", linewidth=2.5)
        (self.ee,) = ax.plot([], [], [], linestyle="none", marker="o", markersize=7, color=EE_COLOR)
        self.figure.text(0.5, 0.98, title, ha="center", va="top", fontsize=10)
        self.clock = self.figure.text(0.02, 0.93, "", fontsize=8, family="monospace", va="top")
        self.figure.text(
            0.98,
            0.93,
            f"final error {scene.final_position_error_mm:.2f} mm, {scene.final_orientation_error_deg:.3f} deg",
            ha="right",
            va="top",
            fontsize=8,
        )
        self.regime = None
        if scene.regime is not None:
            self.regime = self.figure.text(0.02, 0.015, "", fontsize=8, family="monospace", color="tab:purple")
        angle = np.linspace(0.0, 2.0 * math.pi, 32)
        self._circle = np.stack([np.cos(angle), np.sin(angle)], axis=-1)

    def draw(self, k: int) -> None:
        s = self.scene
        for line, edge in zip(self.satellite, s.satellite_edges[k]):
            line.set_data_3d(edge[:, 0], edge[:, 1], edge[:, 2])
        self.arm.set_data_3d(s.arm[k, :, 0], s.arm[k, :, 1], s.arm[k, :, 2])
        self.ee.set_data_3d([s.ee[k, 0]], [s.ee[k, 1]], [s.ee[k, 2]])
        self.ring.set_data_3d(s.ring[k, :, 0], s.ring[k, :, 1], s.ring[k, :, 2])
        # The sphere as three great circles.
        r, c = s.sphere_radius, s.sphere[k]
        circles = []
        for a, b in ((0, 1), (1, 2), (0, 2)):
            points = np.repeat(c[None], len(self._circle), 0)
            points[:, a] += r * self._circle[:, 0]
            points[:, b] += r * self._circle[:, 1]
            circles += [points, np.full((1, 3), np.nan)]
        sphere = np.concatenate(circles)
        self.sphere.set_data_3d(sphere[:, 0], sphere[:, 1], sphere[:, 2])
        tip = s.ee[k] + ARROW_M_PER_N * s.force[k]
        self.force.set_data_3d([s.ee[k, 0], tip[0]], [s.ee[k, 1], tip[1]], [s.ee[k, 2], tip[2]])
        self.clock.set_text(f"t = {s.t[k]:6.2f} s   |F| = {np.linalg.norm(s.force[k]):5.2f} N")
        if self.regime is not None:
            self.regime.set_text(f"gain schedule: {s.regime[k]}")


def frame_rows(t: np.ndarray, fps: float, speed: float) -> np.ndarray:
    """The rows of a log's times ``t`` (T,) s a film shows: one every ``speed / fps`` s of
    simulated time, from the first to the last."""
    if not (fps > 0.0 and speed > 0.0):
        raise AnimationError(f"fps and speed must be positive, got {fps} and {speed}")
    t = np.asarray(t)
    times = np.arange(t[0], t[-1] + 1e-12, speed / fps)
    return np.searchsorted(t, times - 1e-9).clip(0, len(t) - 1)


def draw_frame(scene: Scene, k: int, title: str = ""):
    """The figure of row ``k`` of ``scene`` (close it with ``matplotlib.pyplot.close``)."""
    frame = _Frame(scene, title)
    frame.draw(k)
    return frame.figure, frame.ax


def write_film(scene: Scene, out: Path, fps: float = 30.0, title: str = "") -> int:
    """Write ``scene``, one frame a row (``capture_scene(..., rows=frame_rows(...))``), to
    ``out`` (``.gif`` or ``.mp4``) at ``fps`` frames a second; returns the number of frames."""
    import matplotlib
    import matplotlib.animation as animation
    import matplotlib.pyplot as plt

    suffix = out.suffix.lower()
    if suffix not in (".gif", ".mp4"):
        raise AnimationError(f"{out}: a film is a .gif or an .mp4, not {suffix or 'a file without a suffix'}")
    indices = range(len(scene.t))
    settings = {}
    if suffix == ".mp4":
        try:
            import imageio_ffmpeg
        except ImportError:
            raise AnimationError(
                "an MP4 needs imageio-ffmpeg (pip install spacegrasp-jax[video]); a .gif needs nothing more"
            ) from None
        settings["animation.ffmpeg_path"] = imageio_ffmpeg.get_ffmpeg_exe()
        writer = animation.FFMpegWriter(fps=fps, codec="libx264", extra_args=["-pix_fmt", "yuv420p"])
    else:
        writer = animation.PillowWriter(fps=fps)
    frame = _Frame(scene, title)
    try:
        with matplotlib.rc_context(settings), writer.saving(frame.figure, str(out), dpi=DPI):
            for k in indices:
                frame.draw(int(k))
                writer.grab_frame()
    finally:
        plt.close(frame.figure)
    return len(indices)


def write_poster(scene: Scene, out, title: str = "") -> None:
    """Write the frame of [`key_frame()`][spacegrasp_jax.analysis.animation.key_frame] to ``out`` as a PNG."""
    import matplotlib.pyplot as plt

    figure, _ = draw_frame(scene, key_frame(scene), title)
    try:
        figure.savefig(out, dpi=DPI, format="png")
    finally:
        plt.close(figure)


def key_frame(scene: Scene) -> int:
    """The row a poster shows: the largest contact force, else the last."""
    norms = np.linalg.norm(scene.force, axis=-1)
    return int(np.argmax(norms)) if norms.max() > 0.0 else len(scene.t) - 1


__all__ = [
    "ARROW_M_PER_N",
    "AnimationError",
    "RING_RADIUS_M",
    "Scene",
    "capture_scene",
    "draw_frame",
    "frame_rows",
    "key_frame",
    "lar_poses",
    "write_film",
    "write_poster",
]
