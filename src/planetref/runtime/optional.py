"""Optional compiled modules: the one loader and the one switch of the compiled twins.

Every compiled (numba) kernel is a private module ``_numba_<name>.py`` beside the module
that holds its numpy reference, and only that module loads it, through
:func:`optional_module`. A twin that cannot be loaded (numba missing, a broken llvmlite,
a failed compile or smoke test) is ``None``: the caller runs its numpy reference, which
gives the same results more slowly (the tests bind each pair).

The switch: ``PLANETREF_COMPILED=0`` in the environment turns every twin off for the
process (for checking the numpy path, or where numba misbehaves).
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import os
from collections.abc import Callable
from functools import cache
from typing import Any

__all__ = ["SWITCH", "CompileClock", "compiled_enabled", "optional_module"]

log = logging.getLogger("planetref")

#: The environment variable that turns the compiled twins off (``0``, ``false``, ``no``).
SWITCH = "PLANETREF_COMPILED"


def compiled_enabled() -> bool:
    """Whether compiled twins may be used (the :data:`SWITCH` is not off)."""
    return os.environ.get(SWITCH, "1").strip().lower() not in ("0", "false", "no", "off")


@cache
def optional_module(name: str, what: str, check: Callable[[Any], None] | None = None) -> Any:
    """Import ``name``, or log one warning naming ``what`` and return ``None``.

    Args:
        name: The twin's module (``planetref.<package>._numba_<name>``).
        what: What it is, for the one warning line.
        check: A smoke test run on the module once (it compiles or loads numba's cache);
            any failure there also falls back to numpy.

    Any failure counts (numba missing, a broken llvmlite, a compile error at import): the
    caller then uses its numpy reference, which gives the same results more slowly.
    """
    if not compiled_enabled():
        log.info("%s off (%s=0): numpy is used", what, SWITCH)
        return None
    try:
        mod = importlib.import_module(name)
        if check is not None:
            check(mod)
    except Exception as exc:  # any failure: the numpy twin is used
        log.warning("%s unavailable (%s): numpy is used", what, exc)
        return None
    return mod


class CompileClock:
    """Seconds numba spent compiling in this process since :meth:`start` (a recorder).

    The one-off compile of the compiled twins (tens of seconds on a fresh install, none
    once numba's cache holds them) happens inside whichever stage first calls a kernel;
    a run reads this clock around its stages to report that time apart
    (``timing_s.compile``) instead of charging it to, say, the first adjustment. Nested
    compile events (a kernel compiling its callees) count once. Without numba the clock
    reads 0.
    """

    def __init__(self) -> None:
        self._stack: contextlib.ExitStack | None = None
        self._recorder: Any = None

    def start(self) -> CompileClock:
        """Begin recording numba's compile events (a no-op without numba)."""
        if self._stack is None and compiled_enabled():
            try:
                from numba.core import event
            except Exception:  # no numba: nothing compiles
                return self
            self._stack = contextlib.ExitStack()
            self._recorder = self._stack.enter_context(event.install_recorder("numba:compile"))
        return self

    def stop(self) -> None:
        """Stop recording."""
        if self._stack is not None:
            self._stack.close()
            self._stack = None

    def seconds(self) -> float:
        """Compile seconds recorded so far (outermost events only)."""
        if self._recorder is None:
            return 0.0
        total, depth, begin = 0.0, 0, 0.0
        for stamp, ev in list(self._recorder.buffer):
            if ev.is_start:
                if depth == 0:
                    begin = stamp
                depth += 1
            elif depth:
                depth -= 1
                if depth == 0:
                    total += stamp - begin
        return total
