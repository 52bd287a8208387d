"""Run numpy's BLAS single-threaded for a while.

Used by the bundle adjustment (normal equations) and by RPC fits (small dense least
squares). The normal equations are accumulated with thousands of small matrix products
(``q x q`` outputs, ``q`` ~ 27). Multi-threaded OpenBLAS gains nothing on them, and on a
machine whose cores are busy with other work (or with torch's threads) its threads wait
for each other: products that take 0.2 ms single-threaded then take up to 300 ms.
:func:`single_threaded_blas` limits the BLAS that numpy loaded to one thread inside a
``with`` block (via threadpoolctl when it is installed, otherwise through OpenBLAS's own
``set_num_threads``), and is a no-op when neither is available.
"""

from __future__ import annotations

import contextlib
import ctypes
from collections.abc import Iterator

__all__ = ["single_threaded_blas"]

_SYMBOLS = (
    ("scipy_openblas_get_num_threads64_", "scipy_openblas_set_num_threads64_"),
    ("scipy_openblas_get_num_threads", "scipy_openblas_set_num_threads"),
    ("openblas_get_num_threads64_", "openblas_set_num_threads64_"),
    ("openblas_get_num_threads", "openblas_set_num_threads"),
)
_handles: list[tuple[object, object]] | None = None


def _openblas() -> list[tuple[object, object]]:
    global _handles
    if _handles is not None:
        return _handles
    found = []
    try:
        with open("/proc/self/maps", encoding="utf-8") as fh:
            paths = sorted(
                {
                    ln.split()[-1]
                    for ln in fh
                    if "openblas" in ln.lower() and ln.split()[-1].startswith("/")
                }
            )
    except OSError:
        paths = []
    for p in paths:
        try:
            lib = ctypes.CDLL(p)
        except OSError:
            continue
        for get_name, set_name in _SYMBOLS:
            if hasattr(lib, get_name) and hasattr(lib, set_name):
                getter, setter = getattr(lib, get_name), getattr(lib, set_name)
                getter.restype = ctypes.c_int
                setter.argtypes = [ctypes.c_int]
                found.append((getter, setter))
                break
    _handles = found
    return found


@contextlib.contextmanager
def single_threaded_blas() -> Iterator[None]:
    """Limit numpy's BLAS to one thread inside the block (restored afterwards)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        threadpool_limits = None
    if threadpool_limits is not None:
        with threadpool_limits(limits=1, user_api="blas"):
            yield
        return
    handles = _openblas()
    saved = []
    for getter, setter in handles:
        try:
            saved.append((setter, int(getter())))  # type: ignore[operator]
            setter(1)  # type: ignore[operator]
        except (OSError, ValueError):  # pragma: no cover - foreign BLAS builds
            continue
    try:
        yield
    finally:
        for setter, n in saved:
            setter(n)  # type: ignore[operator]
