"""Optional compiled modules: imported once, or ``None`` so the caller runs its numpy twin."""

from __future__ import annotations

import importlib
import logging
from functools import cache
from typing import Any

__all__ = ["optional_module"]

log = logging.getLogger("planetref")


@cache
def optional_module(name: str, what: str) -> Any:
    """Import ``name``, or log one warning naming ``what`` and return ``None``.

    Any failure counts (numba missing, a broken llvmlite, a compile error at import): the
    caller then uses its numpy reference, which gives the same results more slowly.
    """
    try:
        return importlib.import_module(name)
    except Exception as exc:  # any failure: the numpy twin is used
        log.warning("%s unavailable (%s): numpy is used", what, exc)
        return None
