"""Run files on the host, written once for every job (``reproduce``, ``simulate``,
``montecarlo``, ``tune``): atomic writes, JSON, time series, the provenance of a run, and
interrupts that stop a long run at a safe point.

Missing values: a metric that has no value (no contact, no divergence) is NaN in arrays and
``null`` in JSON files ([`write_json()`][spacegrasp_jax.jobs.runfiles.write_json] converts every non-finite float).
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import jax
import numpy as np

from spacegrasp_jax import __version__
from spacegrasp_jax.core.model import robot_to_toml


class OutputFolderError(ValueError):
    """An output folder that cannot be created or written; names the folder."""


#: The file every command writes first in its output folder: which command made the run,
#: when, and with which arguments. A folder that holds it belongs to a run of this tool.
RUN_MARKER = ".spacegrasp-run.json"


def _listing(paths: list[Path], most: int = 3) -> str:
    names = sorted(path.name + ("/" if path.is_dir() else "") for path in paths)
    return ", ".join(names[:most]) + (f" and {len(names) - most} more" if len(names) > most else "")


def read_run_marker(out: Path) -> dict | None:
    """The run marker of ``out`` (``RUN_MARKER``), or None where there is none (or it
    cannot be read)."""
    try:
        return json.loads((Path(out) / RUN_MARKER).read_text())
    except (OSError, ValueError):
        return None


def claim_output_folder(
    out: Path, command: str, *, overwrite: bool = False, resume: bool = False, write: bool = True
) -> None:
    """Make ``out`` the output folder of a new run of ``command`` (its run marker written),
    or refuse it before anything is computed.

    The rule, the same for every command: a folder that holds anything (another run, or
    files this tool did not write) is refused, naming what it holds, unless

    * ``resume``: the command continues its own run there (``out`` must hold a run of the
      same command; the command checks that the run is the same);
    * ``overwrite``: the previous run's files are deleted first; files that were in the
      folder before any run of this tool (the marker lists them) are kept, and the new
      run's files are written beside them (a file of the same name is replaced).

    ``write=False`` only checks (nothing deleted, no marker): what every process but the
    first of a multi-host run does before the first claims the folder.

    Raises:
        OutputFolderError: ``out`` is occupied (as above), is a file, or is not writable.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise OutputFolderError(f"{out}: is a file, not a folder")
    held = [path for path in out.iterdir() if not path.name.startswith(".write-test.")] if out.is_dir() else []
    marker = read_run_marker(out)
    what = (
        f"a {marker.get('command', '?')} run (started {marker.get('started', '?')})"
        if marker
        else f"files this tool did not write ({_listing(held)})"
    )
    if resume and overwrite:
        raise OutputFolderError(f"{out}: --resume continues the run there and --overwrite replaces it: give one")
    if resume:
        if marker is not None and marker.get("command") != command:
            raise OutputFolderError(f"{out}: --resume: it holds {what}, not a {command} run")
    elif held and not overwrite:
        raise OutputFolderError(
            f"{out} already holds {what}: pass --overwrite to replace it, or choose another output folder"
        )
    if not write:
        return
    if resume:  # the command checks that the folder holds its run; nothing is written here
        if out.exists():
            check_output_folder(out)
        return
    kept = set(marker.get("kept_files", [])) if marker else {path.name for path in held}
    for path in held:
        if path.name in kept:
            continue
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()
    check_output_folder(out)
    write_json(
        out / RUN_MARKER,
        {
            "command": command,
            "argv": sys.argv[1:],
            "started": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "kept_files": sorted(kept & {path.name for path in held}),
        },
    )


def check_output_folder(out: Path) -> None:
    """Create ``out`` if needed and check that files can be written in it, so that a run
    fails before it computes anything rather than after.

    Raises:
        OutputFolderError: ``out`` (or a parent) is a file, or the folder is not writable.
    """
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        descriptor, probe = tempfile.mkstemp(dir=out, prefix=".write-test.")
        os.close(descriptor)
        os.unlink(probe)
    except OSError as error:
        raise OutputFolderError(f"{out}: cannot write results there ({error.strerror or error})") from None


def write_atomically(path: Path, write) -> None:
    """Call ``write(handle_path)`` on a temporary file beside ``path``, then rename it into
    place, so an interrupted run never leaves a half-written file."""
    path = Path(path)
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


def plain(value):
    """``value`` as plain JSON data: arrays and NumPy numbers as lists and floats, non-finite
    floats as ``None``, dataclasses and mappings as dicts."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = dataclasses.asdict(value)
    if isinstance(value, dict):
        return {str(key): plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(item) for item in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, (np.ndarray, jax.Array)):
        return plain(np.asarray(value).tolist())
    return value


def write_json(path: Path, document) -> None:
    """``document`` as indented JSON ([`plain()`][spacegrasp_jax.jobs.runfiles.plain]: non-finite numbers become ``null``)."""
    text = json.dumps(plain(document), indent=2, allow_nan=False) + "\n"
    write_atomically(path, lambda target: target.write_text(text))


def write_text(path: Path, text: str) -> None:
    write_atomically(path, lambda target: target.write_text(text))


#: The file, in a run, campaign or tuning folder, of the robot it ran (written when the robot
#: came from a file): the folder then needs nothing outside it, wherever it is moved.
ROBOT_FILE = "robot.toml"


def write_robot(folder: Path, robot, source: str, links: dict | None = None, *, rate_limits_stated: bool = True) -> str:
    """Write ``robot`` to ``folder / ROBOT_FILE`` as a robot TOML that reads back bit for bit
    ([`robot_to_toml()`][spacegrasp_jax.core.model.robot_to_toml]), its first lines naming the file it
    came from (``source``) and, for a URDF arm, its mount and links (``links``); its rate
    limits stated only where the run judged by them (``rate_limits_stated``). Returns the
    file's name, which the folder's record keeps."""
    said = ", ".join(f"{name} {value}" for name, value in (links or {}).items())
    comment = f"The robot of this run, read from {source}" + (f" ({said})" if said else "") + "."
    comment += "\nEvery field as the run used it; spacegrasp reads it with --robot."
    write_text(folder / ROBOT_FILE, robot_to_toml(robot, comment, rate_limits_stated=rate_limits_stated))
    return ROBOT_FILE


def write_arrays(path: Path, arrays: dict, *, compressed: bool = True) -> None:
    """A ``.npz`` file of ``arrays`` (name -> array)."""
    save = np.savez_compressed if compressed else np.savez
    write_atomically(path, lambda target: save(target, **{name: np.asarray(value) for name, value in arrays.items()}))


def write_timeseries(path: Path, log) -> None:
    """A log ([`Log`][spacegrasp_jax.loop.simulate.Log]) as a compressed ``.npz``, one array per
    field (fields a loop does not fill, ``None``, are left out)."""
    write_arrays(path, {name: value for name, value in vars(log).items() if value is not None})


def csv_columns(arrays: dict) -> dict[str, np.ndarray]:
    """``arrays`` (name -> array with a leading axis N) as flat columns: a (N,) array keeps
    its name, a (N, k, ...) array becomes ``name[0]`` ... ``name[k-1]`` (C order, each
    index in its own brackets)."""
    columns = {}
    for name, value in arrays.items():
        value = np.asarray(value)
        if value.ndim == 1:
            columns[name] = value
            continue
        flat = value.reshape(value.shape[0], -1)
        for column, index in enumerate(np.ndindex(*value.shape[1:])):
            columns[name + "".join(f"[{i}]" for i in index)] = flat[:, column]
    return columns


def write_csv(path: Path, arrays: dict) -> None:
    """A CSV file of ``arrays`` ([`csv_columns`][spacegrasp_jax.jobs.runfiles.csv_columns]), one row per index of the leading
    axis: floats with 17 significant digits (read back bit for bit), missing values empty."""
    columns = csv_columns(arrays)
    names = list(columns)
    rows = len(next(iter(columns.values()))) if columns else 0

    def cell(value) -> str:
        if isinstance(value, (float, np.floating)):
            return repr(float(value)) if math.isfinite(value) else ("" if math.isnan(value) else repr(float(value)))
        return str(value.item() if isinstance(value, np.generic) else value)

    def write(target: Path) -> None:
        with open(target, "w", newline="") as handle:
            handle.write(",".join(names) + "\n")
            for row in range(rows):
                handle.write(",".join(cell(columns[name][row]) for name in names) + "\n")

    write_atomically(path, write)


def write_timeseries_csv(path: Path, log) -> None:
    """A log as a CSV file, one row per log row ([`write_csv`][spacegrasp_jax.jobs.runfiles.write_csv]; fields a loop does not
    fill are left out)."""
    write_csv(path, {name: value for name, value in vars(log).items() if value is not None})


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


def provenance() -> dict:
    """Versions, backend and git revision: what every ``config.json`` records beside the
    run's own settings."""
    return {
        "spacegrasp_jax_version": __version__,
        "jax_version": jax.__version__,
        "numpy_version": np.__version__,
        "backend": jax.default_backend(),
        "git_revision": git_revision(),
    }


class StopRequest:
    """Context manager for long runs: the first SIGINT/SIGTERM sets ``requested``, which the
    loop checks after each unit of work (a tuning step, a Monte-Carlo chunk) before stopping
    cleanly; the next one stops at once (completed units are on disk either way: every file
    is written atomically).

    Args:
        unit: what the loop finishes before a clean stop (for the message).
        patience: how many signals ask for a clean stop before one stops at once (1 for
            runs with safe points; 0 for runs without: the first signal stops them).
        hard_exit: how "at once" stops. ``False``: ``KeyboardInterrupt`` in the main
            thread (what a notebook expects; Python runs it only between bytecodes, so not
            during a compile). ``True``, the command line's: the process ends with exit
            code 130 and a one-line message, even in the middle of a compile: the signal is
            written to a pipe (``signal.set_wakeup_fd()``) that a watcher thread reads,
            which ends the process with ``os._exit()`` (no interpreter shutdown racing
            the compiler's threads). ``None``: as the enclosing [`StopRequest`][spacegrasp_jax.jobs.runfiles.StopRequest]
            (``False`` outside any).
    """

    _active: list[StopRequest] = []  # the contexts entered, innermost last

    def __init__(self, unit: str = "step", *, patience: int = 1, hard_exit: bool | None = None):
        self.requested = False
        self.unit = unit
        self.patience = patience
        self.hard_exit = hard_exit
        self._received = 0
        self._previous = {}
        self._previous_wakeup = None
        self._pipe = None
        self._watcher = None

    def __enter__(self):
        if self.hard_exit is None:
            self.hard_exit = bool(StopRequest._active) and StopRequest._active[-1].hard_exit
        if self.hard_exit:
            read_end, write_end = os.pipe()
            os.set_blocking(write_end, False)
            self._pipe = (read_end, write_end)
            self._watcher = threading.Thread(target=self._watch, args=(read_end,), name="stop-request", daemon=True)
            self._watcher.start()
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._previous[sig] = signal.signal(sig, self._handle)
        if self.hard_exit:
            self._previous_wakeup = signal.set_wakeup_fd(self._pipe[1], warn_on_full_buffer=False)
        StopRequest._active.append(self)
        return self

    def _handle(self, signum, frame):
        if self.hard_exit:
            return  # the watcher thread acts on the signal, at once even during a compile
        self._received += 1
        if self._received > self.patience:
            raise KeyboardInterrupt
        self._request(signal.Signals(signum).name, lambda text: print(text, file=sys.stderr, end="", flush=True))

    def _request(self, name: str, write) -> None:
        self.requested = True
        write(f"\n{name} received: stopping after this {self.unit} (send again to stop now)\n")

    def _watch(self, read_end: int) -> None:
        while True:
            try:
                received = os.read(read_end, 64)
            except OSError:
                return
            if not received:  # the pipe closed: the context ended
                return
            for signum in received:
                if signum not in (signal.SIGINT, signal.SIGTERM):
                    continue
                self._received += 1
                name = signal.Signals(signum).name
                if self._received > self.patience:
                    os.write(2, f"\n{name} received: stopped at once; finished files are on disk\n".encode())
                    os._exit(130)
                self._request(name, lambda text: os.write(2, text.encode()))

    def __exit__(self, *exc):
        StopRequest._active.remove(self)
        if self.hard_exit:
            signal.set_wakeup_fd(self._previous_wakeup)
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        if self.hard_exit:
            read_end, write_end = self._pipe
            os.close(write_end)  # the watcher reads the end of the pipe and returns
            self._watcher.join(timeout=5.0)
            os.close(read_end)
        return False


def progress_bar(done: int, total: int, text: str, width: int = 24) -> str:
    """``"\\r[####....] text"``: one line of a progress display that rewrites itself."""
    filled = int(width * done / total) if total else width
    return f"\r[{'#' * filled}{'.' * (width - filled)}] {text}"


def _on_terminal(stream) -> bool:
    isatty = getattr(stream, "isatty", None)
    try:
        return bool(isatty and isatty())
    except (OSError, ValueError):  # a closed or detached stream
        return False


def show_progress(stream, line: str) -> None:
    """Show one progress ``line`` (a [`progress_bar()`][spacegrasp_jax.jobs.runfiles.progress_bar])
    on ``stream``: on a terminal it rewrites the line before it; into a pipe or a log file,
    where a carriage return would run the lines together, it is a line of its own."""
    text = line.lstrip("\r")
    if _on_terminal(stream):
        stream.write("\r" + text)
    else:
        stream.write(text + "\n")
    stream.flush()


def end_progress(stream) -> None:
    """End a rewritten progress line on a terminal (a pipe's lines are ended already)."""
    if _on_terminal(stream):
        stream.write("\n")
        stream.flush()


__all__ = [
    "OutputFolderError",
    "RUN_MARKER",
    "StopRequest",
    "check_output_folder",
    "claim_output_folder",
    "csv_columns",
    "git_revision",
    "plain",
    "progress_bar",
    "provenance",
    "show_progress",
    "end_progress",
    "read_run_marker",
    "write_arrays",
    "write_atomically",
    "write_json",
    "write_text",
    "write_csv",
    "write_timeseries",
    "write_timeseries_csv",
]
