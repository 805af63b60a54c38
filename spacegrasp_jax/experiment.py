"""Host-side runs: compile once, time, check for divergence, and write results to disk.

This is the edge of the library where ``jit`` happens (the core never calls it). The CLI,
the tests and the notebooks use :func:`run`, so a rollout of a given controller, shapes and
static settings compiles once per process.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

from spacegrasp_jax import compilation, metrics
from spacegrasp_jax.control.gains import Gains
from spacegrasp_jax.model import Robot
from spacegrasp_jax.scenario import Scenario
from spacegrasp_jax.simulate import Log, first_nonfinite_time, rollout

#: Keys of summary.json and of the timeseries files for each controller.
RESULT_KEYS = {"admittance": "active", "cartesian": "cartesian"}

#: Table 5 of the paper: maximal absolute joint torques (N m).
PAPER_MAX_TORQUE_NM = {
    "admittance": [1.50, 2.45, 1.68, 0.86, 1.10, 0.17, 0.036],
    "cartesian": [1.89, 4.21, 2.72, 0.72, 1.55, 0.35, 0.027],
}


class SimulationDiverged(RuntimeError):
    """The closed loop produced non-finite values; ``time_s`` is the first bad step."""

    def __init__(self, controller: str, time_s: float):
        super().__init__(f"the {controller} rollout diverged: first non-finite value at t = {time_s:.4f} s")
        self.controller = controller
        self.time_s = time_s


@dataclasses.dataclass(frozen=True)
class RunResult:
    """One rollout on the host: its log as NumPy arrays, summary and timings (s)."""

    controller: str
    log: Log
    summary: dict
    compile_time_s: float
    run_time_s: float


_COMPILED: dict = {}


def _compiled_rollout(robot, scenario, gains, controller, pinv_damping):
    """AOT-compiled rollout, cached by controller, static settings and argument shapes.
    Returns ``(executable, compile_time_s)``; the time is that of the original compile."""
    arguments = (robot, scenario, gains)
    key = (
        controller,
        pinv_damping,
        jax.tree.structure(arguments),
        tuple((np.shape(leaf), str(getattr(leaf, "dtype", type(leaf)))) for leaf in jax.tree.leaves(arguments)),
    )
    if key not in _COMPILED:
        start = time.perf_counter()
        function = compilation.jit(rollout, static_argnames=("controller", "pinv_damping"))
        executable = function.lower(robot, scenario, gains, controller=controller, pinv_damping=pinv_damping).compile()
        _COMPILED[key] = (executable, time.perf_counter() - start)
    return _COMPILED[key]


def run(
    robot: Robot, scenario: Scenario, gains: Gains, controller: str, *, pinv_damping: float = 0.0, check: bool = True
) -> RunResult:
    """Run one closed-loop rollout and bring its log back as NumPy arrays.

    Raises:
        SimulationDiverged: (when ``check``) the state became non-finite; the error gives
            the first non-finite time.
    """
    executable, compile_time = _compiled_rollout(robot, scenario, gains, controller, pinv_damping)
    start = time.perf_counter()
    _, log = executable(robot, scenario, gains)
    log = jax.tree.map(np.asarray, jax.block_until_ready(log))
    run_time = time.perf_counter() - start
    bad_time = first_nonfinite_time(log)
    if check and bad_time is not None:
        raise SimulationDiverged(controller, bad_time)
    summary = metrics.summary(log) if bad_time is None else {"first_nonfinite_s": bad_time}
    summary.update(compile_time_s=compile_time, run_time_s=run_time)
    return RunResult(controller, log, summary, compile_time, run_time)


def table5_markdown(results: dict) -> str:
    """Table 5 (peak |u_i| per joint, N m) of ``results`` (controller -> :class:`RunResult`)
    beside the paper's, with the relative difference, as a Markdown table."""
    header = "| joint |" + "".join(f" {RESULT_KEYS[c]} (ours) | {RESULT_KEYS[c]} (paper) | difference |" for c in results)
    lines = [header, "|" + " --- |" * (1 + 3 * len(results))]
    for joint in range(7):
        cells = []
        for controller, result in results.items():
            ours, paper = result.summary["max_abs_torque_Nm"][joint], PAPER_MAX_TORQUE_NM[controller][joint]
            cells.append(f" {ours:.3f} | {paper:.3g} | {100.0 * (ours / paper - 1.0):+.0f}% |")
        lines.append(f"| {joint + 1} |" + "".join(cells))
    return "\n".join(lines)


#: Rows of :func:`summary_markdown`: label, summary key, scale to the display unit, format.
_SUMMARY_ROWS = [
    ("final EE position error [mm]", "final_position_error_m", 1e3, "{:.2f}"),
    ("final EE orientation error [deg]", "final_orientation_error_rad", math.degrees(1.0), "{:.3f}"),
    ("RMS position tracking error [mm]", "rms_position_error_m", 1e3, "{:.1f}"),
    ("first contact [s]", "first_contact_s", 1.0, "{:.2f}"),
    ("peak contact force [N]", "max_contact_force_N", 1.0, "{:.2f}"),
    ("peak linear momentum [N s]", "max_linear_momentum_Ns", 1.0, "{:.2f}"),
    ("peak angular momentum [N m s]", "max_angular_momentum_Nms", 1.0, "{:.2f}"),
    ("peak satellite speed [mm/s]", "max_base_speed_mps", 1e3, "{:.1f}"),
    ("peak satellite rate [deg/s]", "max_base_rate_radps", math.degrees(1.0), "{:.1f}"),
]


def summary_markdown(results: dict) -> str:
    """The end-of-run errors and the peaks of ``results`` (controller -> :class:`RunResult`)
    side by side, as a Markdown table."""
    lines = ["| |" + "".join(f" {RESULT_KEYS.get(c, c)} |" for c in results), "|" + " --- |" * (1 + len(results))]
    for label, key, scale, number in _SUMMARY_ROWS:
        values = [result.summary.get(key) for result in results.values()]
        lines.append(f"| {label} |" + "".join(" never |" if v is None else f" {number.format(scale * v)} |" for v in values))
    return "\n".join(lines)


class StopRequest:
    """Context manager for long runs: SIGINT/SIGTERM set ``requested``, which the loop checks
    after each unit of work (a tuning step, a Monte-Carlo chunk) before stopping cleanly; a
    second signal interrupts at once (completed units are on disk either way)."""

    def __init__(self, unit: str = "step"):
        self.requested = False
        self.unit = unit
        self._previous = {}

    def __enter__(self):
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame):
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        print(f"\n{signal.Signals(signum).name} received: stopping after this {self.unit} (send again to stop now)", file=sys.stderr, flush=True)

    def __exit__(self, *exc):
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        return False


# ---- files -------------------------------------------------------------------------------


def write_atomically(path: Path, write) -> None:
    """Call ``write(handle_path)`` on a temporary file beside ``path``, then rename it into
    place, so an interrupted run never leaves a half-written file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    descriptor, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=path.suffix)
    os.close(descriptor)
    try:
        write(Path(temporary))
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(temporary, 0o666 & ~umask)  # mkstemp makes 0600; results are ordinary files
        os.replace(temporary, path)
    finally:
        if os.path.exists(temporary):
            os.unlink(temporary)


def write_json(path: Path, document) -> None:
    write_atomically(path, lambda target: target.write_text(json.dumps(document, indent=2) + "\n"))


def write_timeseries(path: Path, log: Log) -> None:
    """The log as a compressed ``.npz`` (one array per :class:`Log` field)."""
    arrays = {name: np.asarray(value) for name, value in vars(log).items()}
    write_atomically(path, lambda target: np.savez_compressed(target, **arrays))


def git_revision() -> str | None:
    """The checkout's commit (with ``-dirty`` for uncommitted changes), or None."""
    here = Path(__file__).resolve().parent
    try:
        revision = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=10)
        if revision.returncode != 0:
            return None
        dirty = subprocess.run(["git", "status", "--porcelain"], cwd=here, capture_output=True, text=True, timeout=10)
        return revision.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return None


def scenario_to_dict(scenario: Scenario) -> dict:
    """The scenario's numbers as plain JSON (initial state, LAR pose, trajectory, contact)."""
    leaves = dataclasses.asdict(scenario)  # nested dataclasses become dicts of arrays

    def plain(value):
        if isinstance(value, dict):
            return {key: plain(item) for key, item in value.items()}
        return np.asarray(value).tolist() if not isinstance(value, (str, float, int)) else value

    return plain(leaves)


def run_config(robot_source: str, scenario: Scenario, gains: Gains, controllers, pinv_damping: float) -> dict:
    """What ``config.json`` records: enough to trace every number back to how it was made."""
    from spacegrasp_jax import __version__

    return {
        "controllers": list(controllers),
        "robot": robot_source,
        "gains": gains.to_dict(),
        "scenario": scenario_to_dict(scenario),
        "pinv_damping": pinv_damping,
        "spacegrasp_jax_version": __version__,
        "jax_version": jax.__version__,
        "numpy_version": np.__version__,
        "backend": jax.default_backend(),
        "git_revision": git_revision(),
    }
