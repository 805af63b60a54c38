"""Where a tuning run's settings go: the walk of its ``TuneConfig`` through the package.

    python -m spacegrasp_jax.benchmarks.config_walk [--method cmaes|gradient] [--realism ideal|flight]
        [--out walk.json]

Runs a one-step tuning run (``tuning.run.tune``, what ``spacegrasp tune`` enters by) on a
0.1 s scenario under a profiler and lists, in call order, every function of the package
called with the run's settings: the ``TuneConfig`` itself, or one of its fields' values that
is an object of its own (its realism's table, its ranges, its weights, a non-empty tuple),
by identity. From that walk it reports the modules visited and the climbs: the steps of the
walk from a module to one of a higher layer (the layer folders' order, ``tuning`` above
them). Runs with versions from before the layer folders too (their modules are placed in
the folders they moved to).
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import sys
import tempfile
from pathlib import Path

import spacegrasp_jax as sg

#: The layers, lowest first (the package's folders, then the tuning, the command line).
LAYERS = ("core", "envelope", "loop", "jobs", "analysis", "tuning", "cli")


def layer_of(module: str) -> int:
    """The layer of a module of the package, by its folder (a flat module of a version from
    before the folders: by the folder it moved to)."""
    name = module.split(".")[1] if "." in module else ""
    name = getattr(sg, "MOVED_MODULES", {}).get(name, name)
    return LAYERS.index(name) if name in LAYERS else LAYERS.index("jobs")


def walk_of_tune(method: str, realism: str, folder: Path) -> list[tuple[str, str, str]]:
    """``(module, function, argument)`` of each call of the package given the settings, in
    order, during a one-step run of ``method`` in the ``realism`` loop written to ``folder``."""
    from spacegrasp_jax.tuning.run import tune
    from spacegrasp_jax.tuning.tune import TuneConfig

    try:
        from spacegrasp_jax.loop.realism import flight
    except ImportError:  # a version from before the layer folders
        from spacegrasp_jax.realism import flight

    walk, tracked = [], {}

    def track(config):
        tracked[id(config)] = config
        for field in dataclasses.fields(config):  # its settings as given
            value = getattr(config, field.name)
            empty = isinstance(value, (tuple, list, dict)) and not value  # every empty one is shared
            if value is not None and not empty and not isinstance(value, (bool, int, float, str)):
                tracked[id(value)] = value

    def profile(frame, event, arg):
        module = frame.f_globals.get("__name__", "")
        if event != "call" or not module.startswith("spacegrasp_jax"):
            return
        code = frame.f_code
        for name in code.co_varnames[: code.co_argcount + code.co_kwonlyargcount]:
            value = frame.f_locals.get(name)
            if isinstance(value, TuneConfig):
                track(value)
            if id(value) in tracked and tracked[id(value)] is value:
                walk.append((module, code.co_name, name))
                return

    scenario = folder / "short.toml"
    scenario.write_text("duration = 0.1\n[trajectory]\nduration = 0.1\n")
    loop = flight().to_dict() if realism == "flight" else None
    config = TuneConfig.of(steps=1, batch=2, population=4, method=method, realism=loop)
    sys.setprofile(profile)
    try:
        tune(folder / "run", config=config, scenario_file=str(scenario), holdout=0, progress=io.StringIO())
    finally:
        sys.setprofile(None)
    return walk


def summary(walk: list[tuple[str, str, str]]) -> dict:
    """The modules the walk visits, in order, and its climbs to a higher layer."""
    modules, climbs = [], 0
    for before, step in zip([None, *walk], walk):
        if step[0] not in modules:
            modules.append(step[0])
        if before is not None and layer_of(step[0]) > layer_of(before[0]):
            climbs += 1
    calls = [step for before, step in zip([None, *walk], walk) if before is None or before[:2] != step[:2]]
    return {
        "modules": modules,
        "module_count": len(modules),
        "climbs": climbs,
        "calls": [f"{module}.{function}({argument})" for module, function, argument in calls],
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--method", choices=("cmaes", "gradient"), default="cmaes")
    parser.add_argument("--realism", choices=("ideal", "flight"), default="ideal")
    parser.add_argument("--out", type=Path, help="write the walk and its summary to this JSON file")
    args = parser.parse_args(argv)
    sg.configure(compile_cache=False)
    with tempfile.TemporaryDirectory() as folder:
        found = summary(walk_of_tune(args.method, args.realism, Path(folder)))
    found |= {"method": args.method, "realism": args.realism, "package": str(Path(sg.__file__).parent)}
    if args.out is not None:
        args.out.write_text(json.dumps(found, indent=1) + "\n")
    print("\n".join(found["calls"]))
    print(f"{found['module_count']} modules ({', '.join(found['modules'])}), {found['climbs']} climbs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
