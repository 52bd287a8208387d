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

import pytest

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


def test_compile_clock_reports_numba_compiling_apart() -> None:
    """A step that compiles a kernel is charged its own time; the compile goes apart."""
    import time

    import numba

    from planetref.pipeline.job import StripJob
    from planetref.runtime.optional import CompileClock

    clock = CompileClock().start()
    assert clock.seconds() == 0.0

    @numba.njit(cache=False)
    def inner(x: float) -> float:
        return x * 2.0

    @numba.njit(cache=False)
    def outer(x: float) -> float:  # compiles inner too: nested events count once
        return inner(x) + 1.0

    job = object.__new__(StripJob)  # only the timing and the clock are used here
    object.__setattr__(job, "timing", {"adjustment": 0.0})
    object.__setattr__(job, "compile_clock", clock)
    t0, c0 = job.clock()
    w0 = time.perf_counter()
    assert outer(1.0) == 3.0
    wall = time.perf_counter() - w0
    job.charge("adjustment", t0, c0)
    clock.stop()
    compiled = job.timing["compile"]
    assert 0.0 < compiled <= wall + 1e-6
    assert job.timing["adjustment"] == pytest.approx(wall - compiled, abs=0.05)
    before = clock.seconds()
    assert outer(2.0) == 5.0 and clock.seconds() == before  # stopped: nothing more recorded
