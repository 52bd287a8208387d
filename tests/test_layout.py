"""The package's layer contract: the pipeline's order, no cycles, no private imports.

Every import counts: at module level, inside functions and under ``TYPE_CHECKING``
(a deferred import still ties the two modules together). The rules, read from the
source with :mod:`ast` only (nothing is imported, so the test is fast and sees every
module):

1. **Layers.** Each top-level part of the package sits on one floor of :data:`LAYERS`;
   a module may import only from its own floor or the floors below. Parts on the same
   floor are independent unless :data:`ALLOWED_SIDEWAYS` says otherwise (``simulate``
   sits beside ``pipeline`` and neither imports the other).
2. **No cycles between files**, not even through deferred imports.
3. **No private names across modules**: ``from planetref.x import _y`` is allowed
   only inside the module ``x`` itself (a module's ``_private`` helpers are its own).
   Compiled twins (``_numba_*`` modules) are loaded through
   :func:`planetref.runtime.optional.optional_module` by their numpy reference only.

Module length (~600 lines) is advice, not a rule: :func:`test_report_long_modules`
prints the longest modules without failing.
"""

from __future__ import annotations

import ast
import functools
from collections.abc import Mapping
from pathlib import Path

import pytest

import planetref

ROOT = Path(planetref.__file__).parent

#: The floors of the house, lowest first. ``errors`` is the exception root every part uses.
LAYERS: tuple[frozenset[str], ...] = (
    frozenset({"errors", "arrays", "__init__", "py.typed"}),
    frozenset({"runtime"}),
    frozenset({"geometry"}),
    frozenset({"camera", "raster", "matching"}),
    frozenset({"scene"}),
    frozenset({"frontend"}),
    frozenset({"control"}),
    frozenset({"adjust"}),
    frozenset({"products"}),
    frozenset({"report"}),
    frozenset({"pipeline", "simulate"}),
    frozenset({"cli", "__main__"}),
)
#: Same-floor imports that are allowed, as ``(importer part, imported part)``.
ALLOWED_SIDEWAYS: frozenset[tuple[str, str]] = frozenset(
    {
        # The camera models read rasters (RPC GeoTIFF tags, DEM terrain), never the reverse.
        ("camera", "raster"),
        # A matcher's inputs are raster windows.
        ("matching", "raster"),
        # The package's face and ``python -m planetref``.
        ("__init__", "errors"),
        ("__main__", "cli"),
    }
)


def floor_of(part: str) -> int:
    """The floor index of a top-level part (KeyError names an unplaced part)."""
    for i, parts in enumerate(LAYERS):
        if part in parts:
            return i
    raise KeyError(f"{part!r} is on no floor of LAYERS: place it in the house")


def module_name(path: Path, root: Path = ROOT) -> str:
    """Dotted module name of a file under ``root`` (the ``planetref`` folder)."""
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def package_sources(root: Path = ROOT) -> dict[str, tuple[str, bool]]:
    """Module -> (source, is_package) for every module of the package."""
    return {
        module_name(p, root): (p.read_text(encoding="utf-8"), p.name == "__init__.py")
        for p in sorted(root.rglob("*.py"))
    }


def _resolve(module: str, is_package: bool, node: ast.Import | ast.ImportFrom) -> list[str]:
    """Absolute dotted names an import statement refers to (module and imported names)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    base = node.module or ""
    if node.level:
        package = module if is_package else module.rpartition(".")[0]
        parts = package.split(".")
        keep = parts[: len(parts) - node.level + 1]
        base = ".".join([*keep, base] if base else keep)
    return [base] + [f"{base}.{a.name}" for a in node.names]


def import_edges(
    sources: Mapping[str, tuple[str, bool]],
) -> dict[str, list[tuple[str, ast.Import | ast.ImportFrom]]]:
    """Module -> [(imported planetref module, statement)] over every import in its body."""
    edges: dict[str, list[tuple[str, ast.Import | ast.ImportFrom]]] = {}
    for name, (text, is_package) in sources.items():
        tree = ast.parse(text)
        out: list[tuple[str, ast.Import | ast.ImportFrom]] = []
        for node in ast.walk(tree):
            if not isinstance(node, ast.Import | ast.ImportFrom):
                continue
            for target in _resolve(name, is_package, node):
                # ``from a import b``: b is a module when the package has one by that name.
                while target and target not in sources:
                    target = target.rpartition(".")[0]
                if target.startswith("planetref") and target != name:
                    out.append((target, node))
        edges[name] = out
    return edges


def _part(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def layer_violations(sources: Mapping[str, tuple[str, bool]]) -> list[str]:
    """Every import from a higher floor, or sideways without an allowance."""
    bad = []
    for name, targets in import_edges(sources).items():
        src = _part(name)
        for target, node in targets:
            dst = _part(target)
            if src == dst or target == "planetref":
                continue
            fs, fd = floor_of(src), floor_of(dst)
            if fd > fs or (fd == fs and (src, dst) not in ALLOWED_SIDEWAYS):
                bad.append(f"{name} (line {node.lineno}) imports {target}: {src} -> {dst}")
    return sorted(set(bad))


def cycles(sources: Mapping[str, tuple[str, bool]]) -> list[list[str]]:
    """Strongly connected components of more than one file (Tarjan's algorithm)."""
    graph = {m: sorted({t for t, _ in ts}) for m, ts in import_edges(sources).items()}
    # A package's __init__ re-exporting its modules is its face, not a tie between files.
    graph = {
        m: [t for t in ts if not (sources[m][1] and t.startswith(m + "."))]
        for m, ts in graph.items()
    }
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, []):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def private_imports(sources: Mapping[str, tuple[str, bool]]) -> list[str]:
    """``from planetref.x import _y`` (a private name) outside module ``x``."""
    bad = []
    for name, (text, is_package) in sources.items():
        for node in ast.walk(ast.parse(text)):
            if not isinstance(node, ast.ImportFrom):
                continue
            base = _resolve(name, is_package, node)[0]
            if not base.startswith("planetref") or base == name:
                continue
            for alias in node.names:
                full = f"{base}.{alias.name}"
                private = alias.name.startswith("_") and not alias.name.endswith("__")
                if private and full not in sources:
                    bad.append(f"{name} (line {node.lineno}) imports {full}")
    return sorted(bad)


@functools.cache
def _real() -> dict[str, tuple[str, bool]]:
    return package_sources()


def test_every_part_has_a_floor() -> None:
    parts = {_part(m) for m in _real()}
    for part in parts:
        floor_of(part)


def test_no_import_from_a_later_stage() -> None:
    assert layer_violations(_real()) == []


def test_no_cycle_between_files() -> None:
    assert cycles(_real()) == []


def test_no_private_import_across_modules() -> None:
    assert private_imports(_real()) == []


# ---------------------------------------------------------------- planted violations
def _planted(extra: dict[str, str]) -> dict[str, tuple[str, bool]]:
    base = {
        "planetref": ("", True),
        "planetref.errors": ("class PlanetrefError(Exception): ...\n", False),
        "planetref.frontend": ("", True),
        "planetref.frontend.tile": ("def _helper(): ...\n", False),
        "planetref.adjust": ("", True),
        "planetref.adjust.api": ("from planetref.frontend.tile import match\n", False),
        "planetref.pipeline": ("", True),
        "planetref.simulate": ("", True),
    }
    base.update({k: (v, False) for k, v in extra.items()})
    return base


def test_planted_upward_import_is_caught() -> None:
    src = _planted({"planetref.frontend.strip": "def f():\n    from planetref.adjust import api\n"})
    assert any("frontend -> adjust" in v for v in layer_violations(src))


def test_planted_type_checking_upward_import_is_caught() -> None:
    text = "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import planetref.adjust.api\n"
    assert layer_violations(_planted({"planetref.frontend.strip": text}))


def test_planted_sideways_import_is_caught() -> None:
    src = _planted({"planetref.pipeline.georef": "import planetref.simulate\n"})
    assert any("pipeline -> simulate" in v for v in layer_violations(src))


def test_planted_cycle_is_caught() -> None:
    src = _planted(
        {
            "planetref.frontend.a": "from planetref.frontend.b import x\n",
            "planetref.frontend.b": "def f():\n    from planetref.frontend.a import y\n",
        }
    )
    assert cycles(src) == [["planetref.frontend.a", "planetref.frontend.b"]]


def test_planted_private_import_is_caught() -> None:
    src = _planted({"planetref.frontend.strip": "from planetref.frontend.tile import _helper\n"})
    assert private_imports(src) == [
        "planetref.frontend.strip (line 1) imports planetref.frontend.tile._helper"
    ]


def test_unplaced_part_is_caught() -> None:
    with pytest.raises(KeyError, match="no floor"):
        floor_of("misc")


def test_report_long_modules(capsys: pytest.CaptureFixture[str]) -> None:
    """~600 lines is advice: the longest modules are printed, never failed."""
    sizes = sorted(((text.count("\n"), name) for name, (text, _) in _real().items()), reverse=True)
    with capsys.disabled():
        long = [f"{name} {n}" for n, name in sizes if n > 600]
        if long:
            print("\nmodules over ~600 lines (advice):", ", ".join(long))
    assert sizes  # the package was read
