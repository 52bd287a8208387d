"""The package's layout rules: no import cycles, no module over ~600 lines.

Both read the source with :mod:`ast` only (nothing is imported), so they are fast and
see every module, including those whose dependencies are missing.
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import planetref

ROOT = Path(planetref.__file__).parent

#: Most lines a module may have (the project's "~600 lines at most, one concept").
MAX_LINES = 600
#: Modules allowed to be longer, each with the reason; keep this list short.
LONG_MODULES: dict[str, str] = {}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in sorted(ROOT.rglob("*.py"))}


def _type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING"
    )


def _top_level_imports(tree: ast.Module) -> list[ast.Import | ast.ImportFrom]:
    """Imports executed when the module is imported (not in functions or TYPE_CHECKING)."""
    out: list[ast.Import | ast.ImportFrom] = []
    todo: list[ast.stmt] = list(tree.body)
    while todo:
        node = todo.pop()
        if isinstance(node, ast.Import | ast.ImportFrom):
            out.append(node)
        elif isinstance(node, ast.If) and not _type_checking(node):
            todo += node.body + node.orelse
        elif isinstance(node, ast.Try):
            todo += node.body + node.orelse + node.finalbody
            for h in node.handlers:
                todo += h.body
        elif isinstance(node, ast.With):
            todo += node.body
    return out


def _resolve(name: str, package: str, node: ast.Import | ast.ImportFrom) -> list[str]:
    """Absolute dotted names a module-level import statement refers to."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    base = node.module or ""
    if node.level:
        parts = package.split(".")
        keep = parts[: len(parts) - node.level + 1]
        base = ".".join([*keep, base] if base else keep)
    return [base] + [f"{base}.{a.name}" for a in node.names]


@functools.cache
def import_graph() -> dict[str, set[str]]:
    """Module -> the planetref modules its module-level imports load directly."""
    modules = _modules()
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        deps: set[str] = set()
        for node in _top_level_imports(tree):
            for target in _resolve(name, package, node):
                if target in modules and target != name:
                    deps.add(target)
        graph[name] = deps
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of ``graph`` (as a closed list of modules), or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return [*stack[stack.index(nxt) :], nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state:
            found = visit(node)
            if found:
                return found
    return None


def test_cycle_finder_finds_a_planted_cycle():
    # The check itself can fail: a three-module cycle is found and named in order.
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert find_cycle(graph) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_graph_sees_relative_and_absolute_imports():
    graph = import_graph()
    assert "planetref.adjust.api" in graph["planetref.adjust"]
    assert "planetref.settings" in graph["planetref.adjust.config"]
    assert len(graph) > 100


def test_no_import_cycles():
    cycle = find_cycle(import_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])


def test_no_module_over_600_lines():
    too_long = {}
    for path in _modules().values():
        rel = path.relative_to(ROOT).as_posix()
        n = len(path.read_text(encoding="utf-8").splitlines())
        if n > MAX_LINES and rel not in LONG_MODULES:
            too_long[rel] = n
    assert too_long == {}, f"modules over {MAX_LINES} lines (split them by concept): {too_long}"
    for rel in LONG_MODULES:
        assert (ROOT / rel).exists(), f"{rel} is allowed to be long but no longer exists"
