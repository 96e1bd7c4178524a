"""The package's shape (docs/ARCHITECTURE.md): one direction of flow, thin commands.

Imports are read from the source (every import statement, also those inside functions), so
a cycle hidden behind a function-level import fails as well.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

PACKAGE = Path(__file__).parents[1] / "gst_jax"
# Command modules: argument parsing and printing around one library call.
COMMANDS = {"gst_jax.train", "gst_jax.evaluate", "gst_jax.sweep", "gst_jax.plot", "gst_jax.cli"}


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in PACKAGE.rglob("*.py")}


def _is_command(module: str) -> bool:
    return module in COMMANDS or module.endswith(".__main__")


def _imported_names(path: Path) -> set[str]:
    """Every module named by an import statement of the file, anywhere in it."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
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


def test_library_modules_import_no_command_and_parse_no_arguments():
    for module, path in MODULES.items():
        if _is_command(module):
            continue
        imported = _imported_names(path)
        commands = sorted(name for name in imported if _is_command(name))
        assert not commands, f"{module} imports the command module(s) {commands}"
        assert "argparse" not in imported, f"{module} parses arguments; commands do that"


def test_commands_are_thin():
    for module, path in MODULES.items():
        if _is_command(module) and module != "gst_jax.cli":
            lines = len(path.read_text().splitlines())
            assert lines <= 70, f"{module} has {lines} lines; move its logic into the library"


def test_importing_the_package_is_light():
    """`import gst_jax` loads no checkpointing library until a checkpoint is read."""
    code = ("import sys, gst_jax; heavy = [m for m in ('orbax.checkpoint', 'optax', "
            "'matplotlib') if m in sys.modules]; print(heavy)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "[]"
