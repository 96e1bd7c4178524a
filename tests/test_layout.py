"""The package's shape (docs/architecture.md): layers that import only downwards, thin
commands, light imports.

Imports are read from the source (every import statement, also those inside functions), so
an import hidden in a function counts as well.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

PACKAGE = Path(__file__).parents[1] / "gst_jax"
# Command modules: argument parsing and printing around one library call.
COMMANDS = {"gst_jax.train", "gst_jax.evaluate", "gst_jax.sweep", "gst_jax.plot", "gst_jax.cli",
            "gst_jax.navigate", "gst_jax.stream_commands"}


# The layers of docs/architecture.md, bottom up: a module may import its own layer and those
# below. A name ending in "." stands for a package's modules (and the package itself).
LAYERS = (
    ("foundation", {"gst_jax.config", "gst_jax.errors", "gst_jax.progress", "gst_jax.compiles",
                    "gst_jax.private_folders", "gst_jax.paired", "gst_jax.resources",
                    "gst_jax.host_devices", "gst_jax.arrays", "gst_jax.regular_files"}),
    ("data", {"gst_jax.data.", "gst_jax.safe_pickle"}),
    ("numerics", {"gst_jax.graph", "gst_jax.noise", "gst_jax.gumbel", "gst_jax.augment",
                  "gst_jax.adaptation",
                  "gst_jax.parallel", "gst_jax.simulate.agents.orca"}),
    ("model", {"gst_jax.model."}),
    ("rollout", {"gst_jax.rollout"}),
    ("outputs", {"gst_jax.losses", "gst_jax.metrics", "gst_jax.predict.", "gst_jax.interop",
                 "gst_jax.predictors",
                 "gst_jax.crowdnav", "gst_jax.conformal.", "gst_jax.stream", "gst_jax.stream_core",
                 "gst_jax.stream_time", "gst_jax.stream_fallback",
                 "gst_jax.stream_file", "gst_jax.stream_checks", "gst_jax.stream_slots",
                 "gst_jax.stream_programs", "gst_jax.stream_output",
                 "gst_jax.prediction_files", "gst_jax.trajnet_metrics", "gst_jax.figures",
                 "gst_jax.simulate",
                 # the simulators' core (but ORCA, numerics), the paper's, CrowdNav++'s
                 "gst_jax.simulate.agents", "gst_jax.simulate.agents.motion",
                 "gst_jax.simulate.agents.predicted", "gst_jax.simulate.paper",
                 "gst_jax.simulate.paper.scenarios", "gst_jax.simulate.paper.measures",
                 "gst_jax.simulate.paper.loop", "gst_jax.simulate.paper.figures",
                 "gst_jax.simulate.paper.encounters", "gst_jax.simulate.crowdnav."}),
    ("evaluation", {"gst_jax.evaluation", "gst_jax.coverage", "gst_jax.coverage_report",
                    "gst_jax.strata",
                    "gst_jax.testing."}),
    ("state", {"gst_jax.io.", "gst_jax.pretrained", "gst_jax.training",
               "gst_jax.training.state", "gst_jax.training.schedules",
               "gst_jax.training.members", "gst_jax.training.step",
               "gst_jax.training.persistence"}),
    ("models by name", {"gst_jax.runs"}),
    ("drivers", {"gst_jax.training.loop", "gst_jax.training.selection",
                 "gst_jax.training.sweep", "gst_jax.run_figures",
                 "gst_jax.simulate.paper.study", "gst_jax.pretrained.export",
                 "gst_jax.pretrained.choose"}),
    ("flags", {"gst_jax.cli"}),
)
# Imports against the layers, each with its reason in docs/architecture.md (none today).
ALLOWED_UPWARD: set[tuple[str, str]] = set()


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in PACKAGE.rglob("*.py")}


def _is_command(module: str) -> bool:
    return module in COMMANDS or module.endswith(".__main__")


def _is_main_block(node: ast.AST) -> bool:
    """`if __name__ == "__main__":`, the block that runs only where the module is the program
    (`python -m gst_jax.stream replay`), never where it is imported."""
    return (isinstance(node, ast.If) and isinstance(node.test, ast.Compare)
            and isinstance(node.test.left, ast.Name) and node.test.left.id == "__name__"
            and any(isinstance(c, ast.Constant) and c.value == "__main__"
                    for c in node.test.comparators))


def _main_blocks(path: Path) -> list[ast.If]:
    return [node for node in ast.parse(path.read_text()).body if _is_main_block(node)]


def _imported_names(path: Path) -> set[str]:
    """Every module named by an import statement of the file, anywhere in it but in its
    top-level `if __name__ == "__main__":` block (a command's, `_main_blocks`)."""
    names = set()
    tree = ast.parse(path.read_text())
    tree.body = [node for node in tree.body if not _is_main_block(node)]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            for alias in node.names:      # `from gst_jax import data` imports gst_jax.data
                submodule = f"{node.module}.{alias.name}"
                names.add(submodule if submodule in MODULES else node.module)
    return names


def import_graph() -> dict[str, set[str]]:
    """Module -> the gst_jax modules importing it executes. Importing a.b.c also runs the
    __init__ of a.b (a subpackage other than the root) unless the importer is inside a.b."""
    graph = {}
    for module, path in MODULES.items():
        targets = set()
        for name in _imported_names(path):
            if name not in MODULES or name == module:
                continue
            targets.add(name)
            parts = name.split(".")
            for depth in range(2, len(parts)):
                package = ".".join(parts[:depth])
                if not (module == package or module.startswith(package + ".")):
                    targets.add(package)
        graph[module] = targets
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    visiting, done = [], set()

    def visit(module):
        if module in visiting:
            return visiting[visiting.index(module):] + [module]
        if module in done:
            return None
        visiting.append(module)
        for target in sorted(graph[module]):
            if (cycle := visit(target)) is not None:
                return cycle
        visiting.pop()
        done.add(module)
        return None

    for module in sorted(graph):
        if (cycle := visit(module)) is not None:
            return cycle
    return None


def test_no_import_cycle_inside_the_package():
    cycle = find_cycle(import_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_the_cycle_check_sees_function_level_imports(tmp_path):
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None
    hidden = tmp_path / "hidden.py"          # the lazy import that hid train <-> evaluate
    hidden.write_text("def fit():\n    from gst_jax import evaluation, runs\n")
    assert {"gst_jax.evaluation", "gst_jax.runs"} <= _imported_names(hidden)


def layer_of(module: str) -> int:
    """The index of a module's layer; commands (and the package root, which imports nothing
    at import time) sit on top."""
    if _is_command(module) or module == "gst_jax":
        return len(LAYERS)
    for index, (_, members) in enumerate(LAYERS):
        if module in members or any(m.endswith(".") and (module + ".").startswith(m)
                                    for m in members):
            return index
    raise AssertionError(f"{module} is in no layer of tests/test_layout.py (docs/architecture.md)")


def upward_imports(graph: dict[str, set[str]]) -> set[tuple[str, str]]:
    return {(module, target) for module, targets in graph.items() for target in targets
            if layer_of(target) > layer_of(module)}


def test_every_import_runs_down_the_layers():
    upward = upward_imports(import_graph()) - ALLOWED_UPWARD
    assert not upward, "imports against the layers: " + ", ".join(
        f"{a} ({LAYERS[layer_of(a)][0]}) -> {b} ({LAYERS[layer_of(b)][0]})"
        for a, b in sorted(upward))


def test_the_allowed_exceptions_are_few_and_explained():
    assert len(ALLOWED_UPWARD) <= 2
    architecture = (PACKAGE.parent / "docs" / "architecture.md").read_text()
    for module, target in ALLOWED_UPWARD:
        assert f"{module} -> {target}" in architecture
    for name, _ in LAYERS:
        assert f"**{name}**" in architecture, f"docs/architecture.md does not name layer {name}"


def test_the_layer_check_sees_an_import_that_runs_up():
    assert upward_imports({"gst_jax.data.batch": {"gst_jax.model.gst"}}) == {
        ("gst_jax.data.batch", "gst_jax.model.gst")}
    assert not upward_imports({"gst_jax.model.gst": {"gst_jax.data.batch"}})


def test_library_modules_import_no_command_and_parse_no_arguments():
    for module, path in MODULES.items():
        if _is_command(module):
            continue
        imported = _imported_names(path)
        commands = sorted(name for name in imported if _is_command(name))
        assert not commands, f"{module} imports the command module(s) {commands}"
        assert "argparse" not in imported, f"{module} parses arguments; commands do that"


def test_a_library_module_run_as_a_program_only_hands_over_to_a_command():
    """A library module's `if __name__ == "__main__":` block (`python -m gst_jax.stream
    replay`) imports nothing but a command module, whose `main` it calls: the layers above
    never run inside the library, and the command stays where commands are checked."""
    for module, path in MODULES.items():
        if _is_command(module):
            continue
        for block in _main_blocks(path):
            imports = [node for node in ast.walk(block)
                       if isinstance(node, (ast.Import, ast.ImportFrom))]
            named = {alias.name if isinstance(node, ast.Import) else node.module
                     for node in imports for alias in node.names}
            assert named and all(_is_command(name) for name in named), (
                f"{module}'s __main__ block imports {sorted(map(str, named))}: only a command "
                "module's main belongs there")


def test_the_main_block_check_sees_a_main_block(tmp_path):
    program = tmp_path / "program.py"
    program.write_text("import numpy\n\nif __name__ == '__main__':\n"
                       "    from gst_jax.train import main\n    main()\n")
    assert _imported_names(program) == {"numpy"}
    assert len(_main_blocks(program)) == 1


def test_commands_are_thin():
    for module, path in MODULES.items():
        if _is_command(module) and module != "gst_jax.cli":
            lines = len(path.read_text().splitlines())
            assert lines <= 70, f"{module} has {lines} lines; move its logic into the library"


def test_a_module_over_400_lines_says_why_it_is_one_job():
    """Issue 91: a module holds one job; one that grows past 400 lines says in its docstring
    why it is still one ("One job, though over 400 lines: ...")."""
    for module, path in MODULES.items():
        text = path.read_text()
        if len(text.splitlines()) > 400:
            docstring = " ".join((ast.get_docstring(ast.parse(text)) or "").split())
            assert "One job, though over 400 lines:" in docstring, (
                f"{module} has {len(text.splitlines())} lines: split it, or say in its "
                "docstring why it is one job")


def _loaded_after(statement: str) -> list[str]:
    """The heavy libraries a fresh interpreter holds after `statement`."""
    code = (f"import sys; {statement}; print([m for m in ('jax', 'flax', 'orbax.checkpoint', "
            "'optax', 'scipy', 'matplotlib') if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    return eval(out)


def test_importing_the_package_and_its_data_layer_loads_no_jax():
    """`import gst_jax` loads nothing heavy until a name is used; the data layer is numpy."""
    assert _loaded_after("import gst_jax") == []
    assert _loaded_after("import gst_jax.data, gst_jax.config, gst_jax.errors, "
                         "gst_jax.safe_pickle") == []


def test_the_data_stats_command_loads_no_jax():
    assert _loaded_after("import gst_jax.data.__main__") == []
