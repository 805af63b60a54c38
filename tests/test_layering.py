"""The package's layers, read from its source: the core imports no host module, nothing
below the faces imports a face, the plots run nothing of the package, the laws are listed
once and dispatched on nowhere else, each gain group is declared by its law alone, only
the loop dispatches on the realism, and loops over whole runs go through one helper."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: The command line, the figures and the benchmarks: they may import anything.
FACES = {"spacegrasp_jax.cli", "spacegrasp_jax.plots", "spacegrasp_jax.benchmarks"}
#: The host side: runs, batches, files, campaigns, sweeps, margins, tuning.
HOST = {
    "spacegrasp_jax.batching",
    "spacegrasp_jax.campaign",
    "spacegrasp_jax.experiment",
    "spacegrasp_jax.margins",
    "spacegrasp_jax.records",
    "spacegrasp_jax.runfiles",
    "spacegrasp_jax.stability",
    "spacegrasp_jax.sweep",
    "spacegrasp_jax.tuning",
    "spacegrasp_jax.worstcase",
}


def module_files():
    for path in sorted((ROOT / "spacegrasp_jax").rglob("*.py")):
        yield ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__"), path
    for folder in ("tuning", "benchmarks"):
        for path in sorted((ROOT / folder).glob("*.py")):
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


def test_the_core_imports_no_host_module_and_no_face():
    for module, path in module_files():
        if within(module, FACES | HOST) or module == "spacegrasp_jax":
            continue
        wrong = {name for name in imported(path) if within(name, FACES | HOST)}
        assert not wrong, f"{module} imports {sorted(wrong)}"


def test_nothing_below_the_faces_imports_a_face():
    for module, path in module_files():
        if within(module, FACES):
            continue
        wrong = {name for name in imported(path) if within(name, FACES)}
        assert not wrong, f"{module} imports {sorted(wrong)}"


def test_the_plots_draw_data_and_run_nothing_of_the_package():
    # The one import: the laws' registry, for each law's line style.
    assert imported(ROOT / "spacegrasp_jax" / "plots.py") == {
        "spacegrasp_jax.control.registry",
        "spacegrasp_jax.control.registry.LAWS",
    }


#: The paper's laws written again in NumPy and Pinocchio, independently of the package, to
#: check it: they must branch on the law themselves, not read it from the package.
INDEPENDENT_REFERENCES = {"spacegrasp_jax.benchmarks.pinocchio_loop"}


def law_names() -> set[str]:
    from spacegrasp_jax.control.registry import LAWS

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
    from spacegrasp_jax.control.registry import GAIN_GROUPS

    for module, path in module_files():
        if module in INDEPENDENT_REFERENCES:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "GainGroup":
                assert within(module, {"spacegrasp_jax.control"}), (
                    f"{module}, line {node.lineno}: declares a gain group"
                )
            if within(module, {"spacegrasp_jax.control"}):
                continue
            listed = listed_names(node, set(GAIN_GROUPS))
            assert len(listed) < 2, f"{module}, line {node.lineno}: lists the gain groups {sorted(listed)}"


def test_no_module_outside_the_laws_dispatches_on_a_laws_name():
    """``controller == "admittance"``, ``controller in ("cartesian", ...)``: a branch on a
    law's name belongs in the law (its class attributes), not beside it."""
    names = law_names()
    for module, path in module_files():
        if within(module, {"spacegrasp_jax.control"}) or module in INDEPENDENT_REFERENCES:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Compare):
                operands = [node.left, *node.comparators]
                constants = [c for o in operands for c in ast.walk(o) if isinstance(c, ast.Constant)]
                named = {c.value for c in constants if isinstance(c.value, str) and c.value in names}
                assert not named, f"{module}, line {node.lineno}: compares with the law name(s) {sorted(named)}"


#: The loop: the modules that decide, from the realism, what runs in a control period.
THE_LOOP = {"spacegrasp_jax.simulate", "spacegrasp_jax.stages", "spacegrasp_jax.realism"}
#: Modules that read one stage's flag for what it means to a result, not to run a loop:
#: the part of the final error the LAR estimate's error explains.
READS_A_STAGES_VALUE = {"spacegrasp_jax.anatomy"}


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
        if module == "spacegrasp_jax.compilation":
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
        if module == "spacegrasp_jax.compilation":
            continue  # where it is defined
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Attribute) and node.attr == "map":
                owner = node.value
                name = owner.attr if isinstance(owner, ast.Attribute) else getattr(owner, "id", None)
                assert name != "lax", f"{module}, line {node.lineno}: lax.map (use compilation.map_one_at_a_time)"


#: The modules a control period is written in.
LOOP_MODULES = {"spacegrasp_jax.simulate", "spacegrasp_jax.stages", "spacegrasp_jax.integrator"}


def test_the_loop_asks_the_process_nothing_while_it_is_traced():
    """How the loop is compiled is a static option the host fills (``LoopOptions``): the
    loop's modules import no process setting and ask no backend."""
    for module, path in module_files():
        if module not in LOOP_MODULES:
            continue
        assert "spacegrasp_jax.compilation" not in imported(path), f"{module} imports compilation"
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
    counts as the module that holds it (``spacegrasp_jax.model.Robot``: the model)."""

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
