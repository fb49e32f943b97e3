"""The import direction of `pa_cli`'s packages (docs/architecture.md), checked over the AST.

Every import of a `pa_cli` module counts, at module level or inside a function, except those
under `if TYPE_CHECKING:` (names for annotations only). A package may import its own modules
and those of the layers below it; packages of one layer do not import each other.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[2] / "pa_cli"

# bottom to top; a unit is a subpackage or a top-level module of pa_cli
LAYERS: list[set[str]] = [
    {"errors"},
    {"runtime"},
    {"core"},
    {"io"},
    {"config"},
    {"sources"},
    {"planes", "adjust", "loops"},
    {"evaluation"},
    {"refine"},
    {"calibration", "simulate"},
    {"cli"},
    {"__main__"},
]
LAYER_OF = {unit: level for level, units in enumerate(LAYERS) for unit in units}


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _imports(tree: ast.AST) -> list[str]:
    """The pa_cli names a tree imports (`from pa_cli.x import y` gives pa_cli.x.y)."""
    found: list[str] = []

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _is_type_checking(node):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 and (
                node.module == "pa_cli" or node.module.startswith("pa_cli.")):
            # `from pa_cli.x import y`: module pa_cli.x.y if y is one, else pa_cli.x (resolved in _graph)
            found.extend(f"{node.module}.{alias.name}" for alias in node.names)
        elif isinstance(node, ast.Import):
            found.extend(alias.name for alias in node.names if alias.name.startswith("pa_cli."))
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return found


def _graph() -> dict[str, set[str]]:
    modules = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        targets = set()
        for target in _imports(ast.parse(path.read_text())):
            while target not in modules and "." in target:  # a function or class of module pa_cli.x
                target = target.rsplit(".", 1)[0]
            if target in modules and target != name:
                targets.add(target)
        graph[name] = targets
    return graph


def _unit(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "pa_cli"


GRAPH = _graph()


def test_every_unit_has_a_layer():
    units = {_unit(m) for m in GRAPH} - {"pa_cli"}
    assert units <= set(LAYER_OF), f"add {sorted(units - set(LAYER_OF))} to LAYERS (and docs/architecture.md)"


@pytest.mark.parametrize("module", sorted(GRAPH))
def test_imports_point_down(module):
    unit = _unit(module)
    if unit == "pa_cli":  # pa_cli/__init__.py: the version only
        assert not GRAPH[module]
        return
    wrong = [t for t in sorted(GRAPH[module]) if _unit(t) != unit and _unit(t) != "pa_cli"
             and LAYER_OF[_unit(t)] >= LAYER_OF[unit]]
    assert not wrong, f"{module} imports {wrong}: same or higher layer (tests/unit/test_architecture.py LAYERS)"


@pytest.mark.parametrize("module", sorted(GRAPH))
def test_private_modules_stay_in_their_package(module):
    package = module.rsplit(".", 1)[0]
    private = [t for t in GRAPH[module] if t.rsplit(".", 1)[-1].startswith("_") and not t.endswith("__init__")
               and t.rsplit(".", 1)[0] != package]
    assert not private, f"{module} imports private modules of another package: {private}"


def test_no_import_cycles():
    state: dict[str, int] = {}  # 1: on the path, 2: done
    path: list[str] = []

    def visit(module: str) -> list[str] | None:
        state[module] = 1
        path.append(module)
        for target in sorted(GRAPH[module]):
            if state.get(target) == 1:
                return path[path.index(target):] + [target]
            if target not in state and (cycle := visit(target)):
                return cycle
        path.pop()
        state[module] = 2
        return None

    for module in sorted(GRAPH):
        if module not in state:
            cycle = visit(module)
            assert cycle is None, " -> ".join(cycle)


def test_library_imports_no_pa_cli_module_inside_functions():
    """Lazy imports of pa_cli modules belong to the CLI (so a command loads only what it uses)."""
    lazy = []
    for path in PACKAGE.rglob("*.py"):
        module = _module_name(path)
        if _unit(module) == "cli":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lazy += [f"{module}:{n.lineno}" for n in ast.walk(node)
                         if isinstance(n, ast.ImportFrom) and (n.module or "").startswith("pa_cli")]
    assert not lazy, f"imports of pa_cli inside functions: {lazy}"


def test_the_check_catches_a_wrong_import(tmp_path):
    """The walker sees imports inside functions and skips TYPE_CHECKING blocks."""
    tree = ast.parse("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pa_cli.cli import app\n"
                     "def f():\n    from pa_cli.refine import pipeline\n")
    assert _imports(tree) == ["pa_cli.refine.pipeline"]
