"""ttompc's imports form a DAG: no import circle among the modules of one package, nor among the packages.

The graph is read statically (``ast``), one edge per ``import``/``from ... import`` of a ttompc module that names a
module of the same package, wherever the statement stands: at module level, under ``if TYPE_CHECKING:`` (a type a
module names is a module it depends on, and a reader follows it) and inside a function (a function-local import that
closes a circle only hides it; one that closes none, e.g. to import plotting late, adds an edge and no circle).
Packages are compared one at a time, as ``farm``-style graphs draw them, and then against each other: one node per
subpackage of ``ttompc`` (its nested packages folded into it) and one per top-level module, an edge wherever a module
of one imports a module of another. No circle is allowed at either level.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import ttompc

ROOT = Path(ttompc.__file__).parent


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in ROOT.rglob("*.py")}


def _package(module: str) -> str:
    return module if MODULES[module].name == "__init__.py" else module.rpartition(".")[0]


def _resolve(name: str) -> str | None:
    """The ttompc module ``name`` refers to: itself, or for ``pkg.mod.Name`` the longest module prefix."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def imports(module: str) -> set[str]:
    """The ttompc modules ``module`` imports, from any statement in its body (module doc)."""
    package = _package(module)
    found: set[str] = set()
    for node in ast.walk(ast.parse(MODULES[module].read_text())):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
            names = [base] + [f"{base}.{a.name}" for a in node.names]
        else:
            continue
        found |= {r for n in names if n.startswith("ttompc") and (r := _resolve(n)) not in (None, module)}
    return found


def package_graph() -> dict[str, set[str]]:
    """module -> the modules of its own package it imports (a package's ``__init__`` left out: it re-exports)."""
    graph: dict[str, set[str]] = defaultdict(set)
    for module in MODULES:
        if MODULES[module].name == "__init__.py":
            continue
        graph[module] = {m for m in imports(module) if _package(m) == _package(module) and m != _package(module)}
    return graph


def top_level(module: str) -> str:
    """The node of ``module`` in the graph of packages: its subpackage of ``ttompc``, or itself at the top level."""
    parts = module.split(".")
    head = ".".join(parts[:2])
    return head if len(parts) > 2 or MODULES[module].name == "__init__.py" else module


def top_level_graph() -> dict[str, set[str]]:
    """subpackage or top-level module -> those it imports (module doc)."""
    graph: dict[str, set[str]] = defaultdict(set)
    for module in MODULES:
        graph[top_level(module)] |= {top_level(m) for m in imports(module)} - {top_level(module)}
    return graph


def circles(graph: dict[str, set[str]]) -> set[frozenset[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    out: set[frozenset[str]] = set()

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = {stack.pop()}
            while v not in component:
                component.add(stack.pop())
            if len(component) > 1:
                out.add(frozenset(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_reader_sees_every_kind_of_import() -> None:
    """The reader finds module-level, TYPE_CHECKING and function-local imports, absolute and relative."""
    assert "ttompc.mpc.providers" in imports("ttompc.mpc.methods")  # module level
    assert "ttompc.policy" in imports("ttompc.mpc.methods")  # under TYPE_CHECKING
    assert "ttompc.config" in imports("ttompc.mpc.settings")  # function-local
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == {frozenset("abc")}
    assert circles({"a": {"b"}, "b": set()}) == set()


def test_no_import_circle_within_a_package() -> None:
    """Every package is a DAG of its modules."""
    found = circles(package_graph())
    assert found == set(), f"import circles: {[sorted(c) for c in found]}"


def test_no_import_circle_between_packages() -> None:
    """The subpackages and top-level modules of ttompc are a DAG (module doc)."""
    assert top_level("ttompc.solvers.backends.qp") == "ttompc.solvers"
    assert top_level("ttompc.mpc") == "ttompc.mpc"
    assert top_level("ttompc.config") == "ttompc.config"
    graph = top_level_graph()
    assert "ttompc.evaluation" in graph["ttompc.training"]  # the closed-loop callback measures with evaluation/
    found = circles(graph)
    assert found == set(), f"import circles between packages: {[sorted(c) for c in found]}"
