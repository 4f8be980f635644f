"""Imports run one way: the layers of README's layout table, and no import cycle between our modules.

Read statically (``ast`` over every .py of the four packages, nothing imported): every ``import`` counts,
at module level, inside functions (a lazy import still ties two modules) and under ``TYPE_CHECKING``.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# Each package and the packages of ours it may import (README, "Layout"): the lower layers only.
MAY_IMPORT: dict[str, frozenset[str]] = {
    "neudf_core": frozenset(),
    "worker": frozenset({"neudf_core"}),
    "service": frozenset({"worker", "neudf_core"}),
    "web": frozenset({"service"}),
}


def module_files(root: Path) -> dict[str, Path]:
    """Dotted module name -> file, for every .py of the packages in MAY_IMPORT (a package is its __init__)."""
    modules = {}
    for package in MAY_IMPORT:
        for path in sorted((root / package).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return modules


def imported_names(module: str, path: Path) -> Iterator[tuple[str, int]]:
    """(dotted name, line) of everything ``module`` imports: ``import a.b`` gives a.b, ``from a import b`` gives
    a.b (a submodule, or a name in a: the caller resolves it); relative imports are made absolute."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            for alias in node.names:
                yield f"{base}.{alias.name}", node.lineno


def resolve(name: str, modules: dict[str, Path]) -> str | None:
    """The module of ours a dotted import name lands in: the longest prefix that is one; None for others'."""
    parts = name.split(".")
    for end in range(len(parts), 0, -1):
        candidate = ".".join(parts[:end])
        if candidate in modules:
            return candidate
    return None


def import_graph(root: Path) -> dict[str, dict[str, int]]:
    """Module -> {module of ours it imports: first line}."""
    modules = module_files(root)
    graph: dict[str, dict[str, int]] = {}
    for module, path in modules.items():
        edges = graph.setdefault(module, {})
        for name, line in imported_names(module, path):
            target = resolve(name, modules)
            if target is not None and target != module:
                edges.setdefault(target, line)
    return graph


def layer_violations(graph: dict[str, dict[str, int]]) -> list[str]:
    found = []
    for module, edges in sorted(graph.items()):
        layer = module.split(".")[0]
        for target, line in sorted(edges.items()):
            other = target.split(".")[0]
            if other != layer and other not in MAY_IMPORT[layer]:
                found.append(f"{module} (line {line}) imports {target}: {layer} may import "
                             f"{', '.join(sorted(MAY_IMPORT[layer])) or 'nothing of ours'}")
    return found


def cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in graph.get(node, {}):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
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

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return sorted(found)


def test_the_walk_sees_every_package_and_its_imports() -> None:
    graph = import_graph(ROOT)
    assert {m.split(".")[0] for m in graph} == set(MAY_IMPORT)
    assert "worker.store" in graph["worker.tasks"]  # a module-level import
    assert "worker.tasks" in graph["worker.cli"]  # an import inside a function


def test_layers_import_only_the_layers_below() -> None:
    assert layer_violations(import_graph(ROOT)) == []


def test_no_import_cycles() -> None:
    assert cycles(import_graph(ROOT)) == []


def test_the_checks_catch_what_they_look_for() -> None:
    graph = {"service.app": {"web.page": 3}, "web.page": {"service.jobs": 1}, "neudf_core.cli": {"worker.cli": 9},
             "worker.celery_app": {"worker.tasks": 5, "worker.settings": 2}, "worker.tasks": {"worker.celery_app": 7},
             "worker.store": {"service.jobs": 4}}
    assert [v.split(" imports ")[0] for v in layer_violations(graph)] == [
        "neudf_core.cli (line 9)", "service.app (line 3)", "worker.store (line 4)"]
    assert cycles(graph) == [["worker.celery_app", "worker.tasks"]]
