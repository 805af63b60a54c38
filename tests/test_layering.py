"""The package's layers, read from its folders: no module imports one of a higher layer, only
the command line, the tuning and the benchmarks draw figures, the plots run nothing of the package, the laws are listed
once and dispatched on nowhere else, each gain group is declared by its law alone, only
the loop dispatches on the realism, and loops over whole runs go through one helper."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: The package's layers, lowest first, each a folder: a module imports modules of its own
#: layer and of the layers below, never above. ``tuning`` (the repository's ``tuning/``) sits
#: above the analysis; on top, the faces: the command line (whose ``benchmark`` runs the
#: benchmarks) and the benchmarks (which run commands).
LAYERS = ("core", "envelope", "loop", "jobs", "analysis", "tuning", "cli benchmarks")
#: The figures: only the command line, the tuning's figures and the benchmarks draw them.
FIGURES = {"spacegrasp_jax.analysis.plots", "spacegrasp_jax.analysis.animation"}


def module_files(root: Path = ROOT):
    for path in sorted((root / "spacegrasp_jax").rglob("*.py")):
        yield ".".join(path.relative_to(root).with_suffix("").parts).removesuffix(".__init__"), path
    for folder in ("tuning", "benchmarks"):
        for path in sorted((root / folder).glob("*.py")):
            yield f"spacegrasp_jax.{folder}.{path.stem}".removesuffix(".__init__"), path


def imported(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
            names |= {f"{node.module}.{alias.name}" for alias in node.names}
    return {name for name in names if name.startswith("spacegrasp_jax")}


def within(name: str, groups: set[str]) -> bool:
    return any(name == group or name.startswith(group + ".") for group in groups)


def layer(name: str) -> int | None:
    """The layer of a module or of a name in one (its folder's place in ``LAYERS``); ``None``
    for the package's root and the names it exports."""
    parts = name.split(".")
    folders = [folder for layer in LAYERS for folder in layer.split()]
    if len(parts) < 2 or parts[1] not in folders:
        return None
    return next(index for index, layer in enumerate(LAYERS) if parts[1] in layer.split())


def import_targets(path: Path) -> set[str]:
    """What each import statement of the package imports: ``import a.b`` -> ``a.b``, ``from m
    import x`` -> ``m.x`` (a module, a folder or a name in ``m``; ``from spacegrasp_jax import
    __version__`` is the root's)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            names |= {f"{node.module}.{alias.name}" for alias in node.names}
    return {name for name in names if name == "spacegrasp_jax" or name.startswith("spacegrasp_jax.")}


def layer_violations(root: Path = ROOT) -> list[str]:
    """Each module outside a layer folder, and each import from a higher layer (the package's
    root, which exports from ``core`` and ``jobs``, counts as ``jobs``)."""
    found = []
    for module, path in module_files(root):
        if module == "spacegrasp_jax":
            continue
        own = layer(module)
        if own is None:
            found.append(f"{module}: in no layer folder ({', '.join(' '.join(LAYERS).split())})")
            continue
        for name in sorted(import_targets(path)):
            theirs = layer(name)
            theirs = LAYERS.index("jobs") if theirs is None else theirs  # the root
            if theirs > own:
                found.append(f"{module} ({LAYERS[own]}) imports {name} ({LAYERS[theirs]})")
    return sorted(found)


def test_every_module_sits_in_a_layer_folder_and_imports_nothing_above_it():
    assert layer_violations() == []


def test_a_module_left_beside_the_folders_or_importing_upward_is_found(tmp_path):
    """The test of the test: a module at the package's top and a core module that imports a
    job are both named."""
    for folder in ("spacegrasp_jax/core", "spacegrasp_jax/jobs", "tuning", "benchmarks"):
        (tmp_path / folder).mkdir(parents=True)
    (tmp_path / "spacegrasp_jax" / "__init__.py").write_text("")
    (tmp_path / "spacegrasp_jax" / "loose.py").write_text("")
    (tmp_path / "spacegrasp_jax" / "jobs" / "campaign.py").write_text("")
    (tmp_path / "spacegrasp_jax" / "core" / "model.py").write_text("from spacegrasp_jax.jobs import campaign\n")
    assert layer_violations(tmp_path) == [
        "spacegrasp_jax.core.model (core) imports spacegrasp_jax.jobs.campaign (jobs)",
        "spacegrasp_jax.loose: in no layer folder (core, envelope, loop, jobs, analysis, tuning, cli, benchmarks)",
    ]


def test_only_the_command_line_the_tuning_and_the_benchmarks_draw_figures():
    for module, path in module_files():
        if within(module, FIGURES | {"spacegrasp_jax.cli", "spacegrasp_jax.benchmarks", "spacegrasp_jax.tuning"}):
            continue
        wrong = {name for name in imported(path) if within(name, FIGURES)}
        assert not wrong, f"{module} imports {sorted(wrong)}"


def test_the_plots_draw_data_and_run_nothing_of_the_package():
    # The one import: the laws' registry, for each law's line style.
    assert imported(ROOT / "spacegrasp_jax" / "analysis" / "plots.py") == {
        "spacegrasp_jax.loop.control.registry",
        "spacegrasp_jax.loop.control.registry.LAWS",
    }


#: The paper's laws written again in NumPy and Pinocchio, independently of the package, to
#: check it: they must branch on the law themselves, not read it from the package.
INDEPENDENT_REFERENCES = {"spacegrasp_jax.benchmarks.pinocchio_loop"}


def law_names() -> set[str]:
    from spacegrasp_jax.loop.control.registry import LAWS

    return set(LAWS)


def listed_names(node: ast.AST, names: set[str]) -> set[str]:
    """Which of ``names`` a tuple, list, set or dict literal (its keys) writes as strings."""
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        items = node.elts
    elif isinstance(node, ast.Dict):
        items = [key for key in node.keys if key is not None]
    else:
        return set()
    return {item.value for item in items if isinstance(item, ast.Constant) and item.value in names}


def test_the_registry_is_the_only_list_of_laws():
    """No module writes two laws' names in one tuple, list, set or dict: the laws are
    listed once, in ``control.registry`` (which lists their classes, not names)."""
    names = law_names()
    for module, path in module_files():
        if module in INDEPENDENT_REFERENCES:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            listed = listed_names(node, names)
            assert len(listed) < 2, f"{module}, line {node.lineno}: lists the laws {sorted(listed)}"


def test_each_gain_group_is_declared_by_its_law_and_listed_nowhere_else():
    """A ``GainGroup`` is made only in a law's (or the servo's) module under ``control``, and
    no module outside ``control`` writes two groups' names in one tuple, list, set or dict:
    the gain set, the files, tuning and export read the groups from the registry's
    collection (a law lists its own in its class: its loop gain's direction per group)."""
    from spacegrasp_jax.loop.control.registry import GAIN_GROUPS

    for module, path in module_files():
        if module in INDEPENDENT_REFERENCES:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "GainGroup":
                assert within(module, {"spacegrasp_jax.loop.control"}), (
                    f"{module}, line {node.lineno}: declares a gain group"
                )
            if within(module, {"spacegrasp_jax.loop.control"}):
                continue
            listed = listed_names(node, set(GAIN_GROUPS))
            assert len(listed) < 2, f"{module}, line {node.lineno}: lists the gain groups {sorted(listed)}"


def test_no_module_outside_the_laws_dispatches_on_a_laws_name():
    """``controller == "admittance"``, ``controller in ("cartesian", ...)``: a branch on a
    law's name belongs in the law (its class attributes), not beside it."""
    names = law_names()
    for module, path in module_files():
        if within(module, {"spacegrasp_jax.loop.control"}) or module in INDEPENDENT_REFERENCES:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Compare):
                operands = [node.left, *node.comparators]
                constants = [c for o in operands for c in ast.walk(o) if isinstance(c, ast.Constant)]
                named = {c.value for c in constants if isinstance(c.value, str) and c.value in names}
                assert not named, f"{module}, line {node.lineno}: compares with the law name(s) {sorted(named)}"


#: The loop: the modules that decide, from the realism, what runs in a control period.
THE_LOOP = {"spacegrasp_jax.loop.simulate", "spacegrasp_jax.loop.stages", "spacegrasp_jax.loop.realism"}
#: Modules that read one stage's flag for what it means to a result, not to run a loop:
#: the part of the final error the LAR estimate's error explains.
READS_A_STAGES_VALUE = {"spacegrasp_jax.jobs.anatomy"}


def test_no_module_outside_the_loop_dispatches_on_the_realism():
    """What runs in a control period is decided in one place: no module outside the loop
    asks whether a realism is the paper's loop (``is_ideal``) or tests a stage's flag
    (``Stage.X in realism.stages``)."""
    for module, path in module_files():
        if module in THE_LOOP:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
                assert node.func.attr != "is_ideal", f"{module}, line {node.lineno}: asks is_ideal()"
            if isinstance(node, ast.Compare) and module not in READS_A_STAGES_VALUE:
                flags = [o for o in node.comparators if isinstance(o, ast.Attribute) and o.attr == "stages"]
                tested = any(isinstance(op, (ast.In, ast.NotIn)) for op in node.ops)
                assert not (flags and tested), f"{module}, line {node.lineno}: tests a realism stage's flag"


#: The target's state and the log's target fields are always there: no module asks
#: whether they are (``x.target is None``, ``log.target_velocity is not None``).
TARGET_FIELDS = {"target", "frame_twist", "target_position", "target_quat", "target_velocity", "momentum_total"}


def test_no_module_tests_the_target_for_none():
    """Every scenario has a target body and every state and log its fields (the paper's
    fixed target by a static flag): a ``None`` test on them would be a second path."""
    for module, path in module_files():
        for node in ast.walk(ast.parse(path.read_text())):
            if not (isinstance(node, ast.Compare) and any(isinstance(op, (ast.Is, ast.IsNot)) for op in node.ops)):
                continue
            sides = [node.left, *node.comparators]
            none = any(isinstance(side, ast.Constant) and side.value is None for side in sides)
            named = [side for side in sides if isinstance(side, ast.Attribute) and side.attr in TARGET_FIELDS]
            assert not (none and named), f"{module}, line {node.lineno}: tests {named[0].attr} for None"


def test_every_compiled_program_is_looked_up_by_a_key_derived_from_its_arguments():
    """``compilation.compile_once`` finds a program by its key: each call in the package
    builds that key in the same function from the arguments themselves
    (``argument_signature``, which ``experiment.program_key`` and the batched jobs' keys
    use), never from a tuple of settings written by hand, which a new setting could miss."""
    calls = 0
    for module, path in module_files():
        if module == "spacegrasp_jax.jobs.compilation":
            continue  # where it is defined
        tree = ast.parse(path.read_text())
        for function in ast.walk(tree):
            if not isinstance(function, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            compiles = [
                node
                for node in ast.walk(function)
                if isinstance(node, ast.Call)
                and isinstance(node.func, (ast.Attribute, ast.Name))
                and getattr(node.func, "attr", getattr(node.func, "id", None)) == "compile_once"
            ]
            if not compiles:
                continue
            calls += len(compiles)
            source = ast.unparse(function)
            assert "argument_signature(" in source or "program_key(" in source, (
                f"{module}.{function.name} looks a compiled program up by a key not derived from its arguments"
            )
    assert calls >= 3  # the rollouts, the batched jobs, the tuning gradient


def test_every_loop_over_runs_goes_through_map_one_at_a_time():
    """A ``jax.lax.map`` over short runs is compiled whole on a CPU, which can triple its
    program's compile (``compilation.map_one_at_a_time``): the package maps only through
    that helper."""
    for module, path in module_files():
        if module == "spacegrasp_jax.jobs.compilation":
            continue  # where it is defined
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Attribute) and node.attr == "map":
                owner = node.value
                name = owner.attr if isinstance(owner, ast.Attribute) else getattr(owner, "id", None)
                assert name != "lax", f"{module}, line {node.lineno}: lax.map (use compilation.map_one_at_a_time)"


#: The modules a control period is written in.
LOOP_MODULES = {"spacegrasp_jax.loop.simulate", "spacegrasp_jax.loop.stages", "spacegrasp_jax.core.integrator"}


def test_the_loop_asks_the_process_nothing_while_it_is_traced():
    """How the loop is compiled is a static option the host fills (``LoopOptions``): the
    loop's modules import no process setting and ask no backend."""
    for module, path in module_files():
        if module not in LOOP_MODULES:
            continue
        assert "spacegrasp_jax.jobs.compilation" not in imported(path), f"{module} imports compilation"
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Attribute):
                assert node.attr not in {"default_backend", "devices"}, (
                    f"{module}, line {node.lineno}: asks the backend"
                )


def test_no_function_of_the_loop_is_over_100_lines():
    """The loop reads as the order of its stages and the integrator's call, not as one body."""
    for module, path in module_files():
        if module not in LOOP_MODULES:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = node.end_lineno - node.lineno + 1
                assert lines <= 100, f"{module}.{node.name}: {lines} lines"


def import_graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    """Which of ``modules`` (name -> file) each imports, by every import statement in its
    file: at the top, in a function body or under ``TYPE_CHECKING`` alike. An imported name
    counts as the module that holds it (``spacegrasp_jax.core.model.Robot``: the model)."""

    def module_of(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    graph = {}
    for module, path in modules.items():
        targets = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [f"{node.module}.{alias.name}" for alias in node.names]
            else:
                continue
            targets |= {module_of(name) for name in names} - {None, module}
        graph[module] = targets
    return graph


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The groups of modules that import one another, directly or round a circle (the
    strongly connected components of more than one module; Tarjan's algorithm)."""
    index, low, on_stack, stack, circles = {}, {}, set(), [], []

    def visit(module):
        index[module] = low[module] = len(index)
        stack.append(module)
        on_stack.add(module)
        for target in graph[module]:
            if target not in index:
                visit(target)
                low[module] = min(low[module], low[target])
            elif target in on_stack:
                low[module] = min(low[module], index[target])
        if low[module] == index[module]:
            group = []
            while not group or group[-1] != module:
                group.append(stack.pop())
                on_stack.discard(group[-1])
            if len(group) > 1:
                circles.append(sorted(group))

    for module in sorted(graph):
        if module not in index:
            visit(module)
    return circles


def test_no_import_circle_anywhere_in_the_package():
    """No two modules import one another, round a circle of any length, including the
    imports written in a function body or under ``TYPE_CHECKING`` to dodge one."""
    assert import_circles(import_graph(dict(module_files()))) == []


def test_an_import_circle_hidden_in_a_function_body_is_found(tmp_path):
    files = {
        "spacegrasp_jax.low": "import math\n",
        "spacegrasp_jax.model": "from spacegrasp_jax.low import x\n",
        "spacegrasp_jax.urdf": "from spacegrasp_jax.kinematics import joint_transforms\n",
        "spacegrasp_jax.kinematics": "from spacegrasp_jax.model import Robot\n",
        "spacegrasp_jax.top": "from spacegrasp_jax import low, model\n",
    }
    modules = {}
    for name, text in files.items():
        modules[name] = tmp_path / f"{name}.py"
        modules[name].write_text(text)
    assert import_circles(import_graph(modules)) == []
    modules["spacegrasp_jax.model"].write_text("def load():\n    from spacegrasp_jax import urdf\n")
    assert import_circles(import_graph(modules)) == [
        ["spacegrasp_jax.kinematics", "spacegrasp_jax.model", "spacegrasp_jax.urdf"]
    ]
    typing_only = "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from spacegrasp_jax.top import T\n"
    modules["spacegrasp_jax.low"].write_text(typing_only)
    assert len(import_circles(import_graph(modules))) == 2


def test_a_module_by_its_name_before_the_folders_comes_with_a_warning_naming_its_folder():
    """``spacegrasp_jax.MOVED_MODULES`` names every module of the layer folders below the
    tuning with its folder (read from the folders), but those written there after the move, and ``from spacegrasp_jax import campaign``
    gives ``spacegrasp_jax.jobs.campaign`` with a ``DeprecationWarning`` saying so."""
    import importlib
    import warnings

    import pytest

    import spacegrasp_jax

    on_disk = {}
    for folder in LAYERS[: LAYERS.index("tuning")]:
        for path in (ROOT / "spacegrasp_jax" / folder).iterdir():
            if path.suffix == ".py" and path.stem != "__init__":
                on_disk[path.stem] = folder
            elif path.is_dir() and (path / "__init__.py").exists():
                on_disk[path.name] = folder
    # modules written in their folder, never at the old place
    added_since = {"frequency": "analysis", "sensitivity": "analysis", "requirements": "analysis"}
    added_since |= {"reliability": "analysis", "limit_state": "analysis", "standard_space": "envelope"}
    assert spacegrasp_jax.MOVED_MODULES == {name: folder for name, folder in on_disk.items() if name not in added_since}
    assert {name: on_disk[name] for name in added_since} == added_since
    with pytest.warns(DeprecationWarning, match=r"spacegrasp_jax.campaign is now spacegrasp_jax.jobs.campaign"):
        from spacegrasp_jax import campaign
    assert campaign is importlib.import_module("spacegrasp_jax.jobs.campaign")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        from spacegrasp_jax import configure  # noqa: F401  (a name at the top: no warning)
    with pytest.raises(AttributeError, match="has no attribute 'nowhere'"):
        spacegrasp_jax.nowhere
