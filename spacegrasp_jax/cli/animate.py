"""``spacegrasp animate``: a film of a run's capture."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from spacegrasp_jax.cli.common import _file_name, _films, _run_schedule
from spacegrasp_jax.cli.options import UsageError, _add_command, _add_film_options, _add_overwrite_option
from spacegrasp_jax.core.model import n_joints
from spacegrasp_jax.jobs import campaign, experiment


def _animate(args: argparse.Namespace) -> int:
    """``spacegrasp animate RUN_DIR``: a film of a run's capture (and a poster of its key frame)."""
    folder = Path(args.run_dir)
    if not (folder / "config.json").is_file() or not (folder / "summary.json").is_file():
        raise UsageError(
            f"{folder}: not a run folder of simulate, reproduce or replay (no config.json and summary.json)"
        )
    config = json.loads((folder / "config.json").read_text())
    keys = [
        key
        for key in json.loads((folder / "summary.json").read_text())
        if (folder / f"timeseries_{_file_name(key)}.npz").is_file()
    ]
    if args.controller is not None:
        if args.controller not in keys:
            raise UsageError(f"--controller: {folder} has no run {args.controller!r}; it has {', '.join(keys)}")
        keys = [args.controller]
    if not keys:
        raise UsageError(f"{folder}: holds no time series (timeseries_*.npz) to animate")
    if args.out is not None:
        if len(keys) > 1:
            raise UsageError(
                f"--out: {folder} holds {len(keys)} runs ({', '.join(keys)}); choose one with --controller"
            )
        if Path(args.out).suffix.lower() not in (".gif", ".mp4"):
            raise UsageError(f"--out {args.out}: a film is a .gif or an .mp4")
    targets = [Path(args.out)] if args.out else [folder / f"capture_{_file_name(key)}.gif" for key in keys]
    for target in targets:
        for path in (target, target.with_name(target.stem + "_poster.png")):
            if path.exists() and not args.overwrite:
                raise UsageError(f"{path}: exists; pass --overwrite to replace it")
    if args.out and Path(args.out).suffix.lower() == ".mp4":
        try:
            import imageio_ffmpeg  # noqa: F401
        except ImportError:
            raise UsageError(
                "--out: an MP4 needs imageio-ffmpeg (pip install spacegrasp-jax[video]); a .gif needs nothing more"
            ) from None
    try:
        robot, scenario = campaign.robot_and_scenario_of_run(folder, config)
    except experiment.RunFolderError as error:
        raise UsageError(str(error)) from None
    logs = {key: experiment.read_log(folder / f"timeseries_{_file_name(key)}.npz") for key in keys}
    laws = {key.split("/", 1)[0] for key in keys}
    schedule = _run_schedule(folder, config, laws.pop(), n_joints(robot)) if len(laws) == 1 else None
    written = _films(args, folder, keys, robot, scenario, logs, Path(args.out) if args.out else None, schedule)
    print(f"wrote {', '.join(str(path) for path in written)}")
    return 0


def add_parsers(commands) -> None:
    """The command's parser, added to ``commands``."""
    animate = _add_command(commands, "animate", help="film a run's capture in 3D: a GIF or an MP4, and a poster PNG")
    animate.add_argument("run_dir", metavar="RUN_DIR", help="a run folder of simulate, reproduce or replay")
    animate.add_argument("--controller", help="which of the folder's runs (default: each, one film apiece)")
    animate.add_argument(
        "--out", help="the film, .gif or .mp4 (default: RUN_DIR/capture_<run>.gif; the poster beside it, _poster.png)"
    )
    _add_film_options(animate)
    _add_overwrite_option(animate)
    animate.set_defaults(run=_animate)
