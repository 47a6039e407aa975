"""The package's layers: the library never imports its command line, and no modules import each other in a circle.

Every ``.py`` of the package is parsed with ``ast`` (nothing is imported). An edge A -> B is an ``import`` or
``from ... import`` statement in A that names module B of the package, at module level or inside a function;
imports under ``if TYPE_CHECKING:`` never run and are not edges. ``from . import x`` is an edge to submodule ``x``
when there is one, else to the package itself. Importing ``proxycodec.x`` runs ``proxycodec/__init__.py`` first,
but that package-parent relation is not an edge (every module would otherwise depend on its package); an explicit
import of a package (``from .. import __version__``) is one. Lazy ``importlib`` lookups are not seen.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
#: pyproject's ``package-dir``: package name -> folder (relative to the repository root).
PACKAGE_DIRS = {"proxycodec": "proxycodec", "proxycodec.formats": "formats", "proxycodec.cli": "cli"}
CLI = "proxycodec.cli"


# ------------------------------------------------------------------------------------------------ the graph
def package_modules(root: Path = REPO_ROOT, package_dirs: dict[str, str] = PACKAGE_DIRS) -> dict[str, Path]:
    """Module name -> file, for every ``.py`` under the package folders (sub-packages included)."""
    mods: dict[str, Path] = {}
    for pkg, folder in package_dirs.items():
        base = root / folder
        for path in sorted(base.rglob("*.py")):
            rel = path.relative_to(base).with_suffix("").parts
            if not all(part.isidentifier() for part in rel):
                continue
            mods[".".join((pkg, *rel[:-1], *(() if rel[-1] == "__init__" else (rel[-1],))))] = path
    return mods


def _runtime_nodes(tree: ast.AST):
    """Every node of ``tree`` except what sits under ``if TYPE_CHECKING:``."""
    stack = [tree]
    while stack:
        node = stack.pop()
        yield node
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and _is_type_checking(child.test):
                stack.extend(child.orelse)
                continue
            stack.append(child)


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def imports_of(name: str, source: str, modules: set[str], is_package: bool = False) -> set[str]:
    """The package modules that module ``name`` (whose code is ``source``) imports."""
    package = name if is_package else name.rpartition(".")[0]
    out: set[str] = set()

    def nearest_module(dotted: str) -> str | None:  # "a.b.c" -> the longest prefix that is a module
        parts = dotted.split(".")
        for k in range(len(parts), 0, -1):
            if ".".join(parts[:k]) in modules:
                return ".".join(parts[:k])
        return None

    for node in _runtime_nodes(ast.parse(source)):
        if isinstance(node, ast.Import):
            for alias in node.names:
                target = nearest_module(alias.name)
                if target:
                    out.add(target)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                up = package.split(".")
                if node.level > 1:
                    up = up[:-(node.level - 1)]
                base = ".".join(up + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                target = sub if sub in modules else nearest_module(base)
                if target:
                    out.add(target)
    out.discard(name)
    return out


def import_graph(mods: dict[str, Path] | None = None) -> dict[str, set[str]]:
    mods = package_modules() if mods is None else mods
    names = set(mods)
    return {m: imports_of(m, p.read_text(), names, is_package=p.name == "__init__.py") for m, p in mods.items()}


def cycle_components(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components (Tarjan) with more than one module, and the modules that import
    themselves: each sorted, in sorted order."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def strongconnect(v: str) -> None:  # recursion depth <= module count (about a hundred)
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                strongconnect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1 or v in graph.get(v, ()):
                components.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            strongconnect(v)
    return sorted(components)


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle (``[a, b, ..., a]``) per component of :func:`cycle_components`, through its smallest module."""
    return [cycle_in(comp, graph) for comp in cycle_components(graph)]


def cycle_in(component: list[str], graph: dict[str, set[str]]) -> list[str]:
    """A shortest cycle through the component's smallest module (breadth-first within the component)."""
    start, members = component[0], set(component)
    prev: dict[str, str] = {}
    frontier = [start]
    while frontier:
        nxt = []
        for v in frontier:
            for w in sorted(graph.get(v, ())):
                if w not in members:
                    continue
                if w == start:
                    path = [v]
                    while path[-1] != start:
                        path.append(prev[path[-1]])
                    return path[::-1] + [start]
                if w not in prev:
                    prev[w] = v
                    nxt.append(w)
        frontier = nxt
    raise AssertionError(f"no cycle through {start} in {component}")  # pragma: no cover - an SCC has one


def library_imports_of(graph: dict[str, set[str]], cli: str) -> list[str]:
    """The edges ``module -> target`` from outside package ``cli`` into it."""
    inside = lambda m: m == cli or m.startswith(cli + ".")  # noqa: E731
    return sorted(f"{m} -> {t}" for m, targets in graph.items() if not inside(m) for t in targets if inside(t))


def describe_cycles(graph: dict[str, set[str]]) -> list[str]:
    """Per component: its modules and one cycle through them."""
    return [f"{{{', '.join(comp)}}}, e.g. {' -> '.join(cycle_in(comp, graph))}" for comp in cycle_components(graph)]


# ------------------------------------------------------------------------------------------------ the checks
@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    return import_graph()


def test_the_walked_folders_are_the_packages():
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    with open(REPO_ROOT / "pyproject.toml", "rb") as fh:
        assert tomllib.load(fh)["tool"]["setuptools"]["package-dir"] == PACKAGE_DIRS


def test_the_walk_sees_every_layer(graph):
    for m in ("proxycodec", "proxycodec.model", "proxycodec.formats.container", "proxycodec.cli.main",
              "proxycodec.render.project"):
        assert m in graph, m
    assert "proxycodec.errors" in graph["proxycodec.model"]


def test_the_library_does_not_import_the_command_line(graph):
    bad = library_imports_of(graph, CLI)
    assert not bad, "library modules import the command line: " + ", ".join(bad)


def test_no_import_cycle(graph):
    cycles = describe_cycles(graph)
    assert not cycles, "modules that import each other: " + "; ".join(cycles)


# ------------------------------------------------------------------------------------------------ the checker
def private_imports(mods: dict[str, Path] | None = None) -> list[str]:
    """``from M import _name`` in any package module: a private name crossing a module boundary (dunders such as
    ``__version__`` are public)."""
    out = []
    for name, path in sorted((mods or package_modules()).items()):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom):
                out += [f"{name}:{node.lineno} imports {node.module or '.'}.{a.name}" for a in node.names
                        if a.name.startswith("_") and not a.name.startswith("__")]
    return out


def test_no_private_name_crosses_a_module_boundary(tmp_path):
    bad = private_imports()
    assert not bad, "private names imported from another module: " + "; ".join(bad)
    (tmp_path / "a.py").write_text("from .b import _hidden, public\nfrom . import __version__\n")
    assert private_imports({"p.a": tmp_path / "a.py"}) == ["p.a:1 imports b._hidden"]


def test_cycle_finder_on_a_small_graph():
    g = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set(), "e": {"e"}, "f": {"g"}, "g": {"f"}}
    assert find_cycles(g) == [["a", "b", "c", "a"], ["e", "e"], ["f", "g", "f"]]
    assert find_cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == []
    # two loops through one module: one cycle reported for the component, the shortest through its first module
    g = {"a": {"b", "c"}, "b": {"a"}, "c": {"d"}, "d": {"a"}}
    assert find_cycles(g) == [["a", "b", "a"]]
    assert describe_cycles(g) == ["{a, b, c, d}, e.g. a -> b -> a"]


def test_import_resolution():
    mods = {"p", "p.x", "p.sub", "p.sub.y", "p.sub.z", "p.cli", "p.cli.main"}
    src = """
import os
import p.sub.y
from . import x, helper
from .z import thing
from .. import cli
from ..cli.main import run
from p import __version__
from typing import TYPE_CHECKING
if TYPE_CHECKING:
    from .. import x as never
def later():
    from ..sub import z
"""
    # in p.sub.y: p.sub.x is no module, so "from . import x, helper" is the package p.sub; itself is dropped; the
    # TYPE_CHECKING import is not an edge
    assert imports_of("p.sub.y", src, mods) == {"p.sub", "p.sub.z", "p.cli", "p.cli.main", "p"}
    assert imports_of("p.sub", "from . import y\nfrom .. import x", mods, is_package=True) == {"p.sub.y", "p.x"}
    g = {m: set() for m in mods} | {"p.x": {"p.cli.main"}, "p.cli": {"p.cli.main"}, "p.cli.main": {"p.x"}}
    assert library_imports_of(g, "p.cli") == ["p.x -> p.cli.main"]
