"""The rules of the tree (docs/architecture.md), so that `make test` keeps them.

- The import contracts in pyproject.toml's ``[tool.importlinter]``, checked by
  ``lint-imports``: analyzer <- sniffer <- tui; inside the analyzer protocol <-
  traffic <- recording <- analysis <- cli; only command modules import click or
  a command module; no circle between the packages (or modules) of one package.
- No circle between modules at all, checked here on the same import graph
  (grimp's, which counts every import: function-local ones and those under
  ``if TYPE_CHECKING:`` too).  import-linter's ``acyclic_siblings`` misses one
  kind: a package's ``__init__`` and a module inside it importing each other.
- No module over 500 lines; no function over 60 lines unless its docstring
  says it is a "hot loop" (and why).
- Every package is listed in ``[tool.setuptools] packages``, or the wheel
  would ship without it.
- Library modules define no helpers that only tests use.
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
import tomllib
from collections.abc import Iterator
from pathlib import Path

import pytest
import grimp

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("analyzer", "sniffer", "tui")
MAX_MODULE_LINES = 500
MAX_FUNCTION_LINES = 60


def _modules(top: Path = ROOT) -> Iterator[Path]:
    for package in PACKAGES:
        yield from sorted((top / package).rglob("*.py"))


def _tree(path: Path) -> ast.Module:
    return ast.parse(path.read_text(encoding="utf-8"), filename=str(path))


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))


def test_the_import_contracts_hold() -> None:
    lint_imports = Path(sys.executable).parent / "lint-imports"
    done = subprocess.run([str(lint_imports), "--no-cache", "--no-logo"], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr


def _cycles(imports: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for start in sorted(imports):
        if start in index:
            continue
        work = [(start, iter(sorted(imports[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(imports[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_cycles_finds_a_circle_and_nothing_else() -> None:
    imports = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set(), "e": {"d"}}
    assert _cycles(imports) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_module_imports_itself_through_others() -> None:
    graph = grimp.build_graph(*(f"whiztap.{p}" for p in PACKAGES), cache_dir=None)
    imports = {module: graph.find_modules_directly_imported_by(module) for module in graph.modules}
    circles = ["\n  ".join(_chain(graph, component)) for component in _cycles(imports)]
    assert not circles, "import circles:\n  " + "\n\n  ".join(circles)


def _chain(graph: grimp.ImportGraph, component: list[str]) -> list[str]:
    """One circle through the component's first module, each import with its line."""
    first, members = component[0], set(component)
    steps = []
    for importer, imported in _circle(graph, first, members):
        lines = sorted(d["line_number"] for d in graph.get_import_details(importer=importer, imported=imported))
        steps.append(f"{importer} -> {imported} (l. {', '.join(map(str, lines))})")
    return steps


def _circle(graph: grimp.ImportGraph, first: str, members: set[str]) -> list[tuple[str, str]]:
    """The shortest path from ``first`` back to itself inside the component (breadth first)."""
    came_from: dict[str, str] = {}
    frontier = [first]
    while frontier:
        following = []
        for module in frontier:
            for imported in sorted(graph.find_modules_directly_imported_by(module) & members):
                if imported == first:
                    path = [(module, first)]
                    while module != first:
                        path.append((came_from[module], module))
                        module = came_from[module]
                    return path[::-1]
                if imported not in came_from:
                    came_from[imported] = module
                    following.append(imported)
        frontier = following
    return []


def test_no_module_is_over_500_lines() -> None:
    long = {str(path.relative_to(ROOT)): n for path in _modules()
            if (n := len(path.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES}
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"


def _long_functions(path: Path) -> Iterator[str]:
    for node in ast.walk(_tree(path)):
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        lines = node.end_lineno - node.lineno + 1
        if lines > MAX_FUNCTION_LINES and "hot loop" not in (ast.get_docstring(node) or ""):
            yield f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({lines} lines)"


@pytest.mark.slow
def test_no_function_is_over_60_lines_unless_it_is_a_documented_hot_loop() -> None:
    long = [found for path in _modules() for found in _long_functions(path)]
    assert not long, (f"functions over {MAX_FUNCTION_LINES} lines (split them, or say \"hot loop\" and why "
                      f"in the docstring):\n  " + "\n  ".join(long))


def test_every_package_is_in_the_wheel() -> None:
    folders = {"whiztap." + ".".join(init.parent.relative_to(ROOT).parts)
               for package in PACKAGES for init in (ROOT / package).rglob("__init__.py")}
    listed = set(_pyproject()["tool"]["setuptools"]["packages"])
    assert folders == listed, (f"not in [tool.setuptools] packages: {sorted(folders - listed)}; "
                               f"listed but not a package: {sorted(listed - folders)}")


def _names_used(paths: list[Path]) -> set[str]:
    """Every name these files use: loaded names, attributes, and names imported from a module."""
    used: set[str] = set()
    for path in paths:
        for node in ast.walk(_tree(path)):
            if isinstance(node, ast.Name) and not isinstance(node.ctx, ast.Store):
                used.add(node.id)
            elif isinstance(node, ast.Attribute):
                used.add(node.attr)
            elif isinstance(node, ast.ImportFrom):
                used.update(alias.name for alias in node.names)
    return used


def _entry_point_names() -> set[str]:
    """The functions pyproject.toml names (the command, subcommands, the plugin's module)."""
    project = _pyproject()["project"]
    targets = list(project.get("scripts", {}).values())
    targets += [t for group in project.get("entry-points", {}).values() for t in group.values()]
    return {target.rpartition(":")[2] for target in targets}


def _documented_names() -> set[str]:
    """The names the docs import from whiztap: public API, for users' code."""
    docs = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    imports = re.compile(r"^\s*from whiztap\.[\w.]+ import ([\w, ]+)$", re.MULTILINE)
    return {name.strip() for doc in docs for found in imports.findall(doc.read_text(encoding="utf-8"))
            for name in found.split(",")}


@pytest.mark.slow
def test_no_library_module_defines_a_helper_only_tests_use() -> None:
    """A top-level function or class of the library that the tests use but no
    library module does (nor pyproject.toml, nor the docs' examples) belongs in
    tests/.  Names are matched by name alone, so this misses a helper that
    shares its name with something the library uses: a cheap check, not a proof."""
    library = list(_modules())
    tests = sorted((ROOT / "tests").rglob("*.py"))
    used_by_library = _names_used(library) | _entry_point_names() | _documented_names()
    used_by_tests = _names_used(tests)
    only_tests = []
    for path in library:
        for node in _tree(path).body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) \
                    and node.name in used_by_tests and node.name not in used_by_library:
                    only_tests.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name}")
    assert not only_tests, "library helpers only tests use (move them to tests/):\n  " + "\n  ".join(only_tests)
