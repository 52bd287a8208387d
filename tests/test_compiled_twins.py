"""The compiled twins: one naming rule, one loader, one switch, every twin enumerated.

Every ``_numba_*.py`` module of the package is a compiled twin of a numpy reference in
the same package, loaded only through :func:`planetref.runtime.optional.optional_module`
by name (never imported directly, so a missing numba never breaks an import), and the
switch ``PLANETREF_COMPILED=0`` turns them all off.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import planetref
from planetref.runtime.optional import SWITCH

ROOT = Path(planetref.__file__).parent
TWINS = sorted(ROOT.rglob("_numba_*.py"))


def _dotted(path: Path) -> str:
    return ".".join(path.relative_to(ROOT.parent).with_suffix("").parts)


def _loaders() -> dict[str, list[str]]:
    """Twin module -> the modules that load it through optional_module(NAME, ...)."""
    out: dict[str, list[str]] = {}
    for path in sorted(ROOT.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Call)
                and getattr(node.func, "id", getattr(node.func, "attr", None)) == "optional_module"
                and node.args
                and isinstance(node.args[0], ast.Constant)
            ):
                out.setdefault(node.args[0].value, []).append(_dotted(path))
    return out


def test_every_twin_is_loaded_by_optional_module_from_its_own_package() -> None:
    assert len(TWINS) >= 8  # the line-scan kernel, normal equations, Schur, ..., NCC
    loaders = _loaders()
    for twin in TWINS:
        name = _dotted(twin)
        assert name in loaders, f"{name} is not loaded through optional_module"
        package = name.rpartition(".")[0]
        assert all(m.rpartition(".")[0] == package for m in loaders[name]), loaders[name]


def test_no_twin_is_imported_directly() -> None:
    names = {_dotted(t) for t in TWINS}
    for path in sorted(ROOT.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.module:
                hit = {node.module, *(f"{node.module}.{a.name}" for a in node.names)} & names
                assert not hit, f"{_dotted(path)} imports {hit} directly"
            if isinstance(node, ast.Import):
                assert not {a.name for a in node.names} & names


def test_the_switch_turns_every_twin_off() -> None:
    """With PLANETREF_COMPILED=0 every loader returns None: the numpy references run."""
    code = (
        "import sys; from planetref.runtime.optional import optional_module;"
        f"names = {sorted(_dotted(t) for t in TWINS)!r};"
        "print(sum(optional_module(n, n) is None for n in names), len(names));"
        "print('numba' in sys.modules)"
    )
    env = {"PLANETREF_COMPILED": "0", "PATH": "/usr/bin:/bin"}
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True
    ).stdout.split()
    assert out[0] == out[1]  # every twin off
    assert out[2] == "False"  # and numba never imported
    assert SWITCH == "PLANETREF_COMPILED"
