"""Atomic file writes: a temporary file beside the target, renamed over it on success.

Readers never see a half-written file, and a failed write leaves any previous file
untouched. Every planetref output goes through here.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

__all__ = [
    "atomic_path",
    "json_safe",
    "write_bytes_atomic",
    "write_json_atomic",
    "write_text_atomic",
]


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(
    path: str | os.PathLike[str], *, create: bool = True, parents: bool = True
) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` when the block ends.

    The temporary name keeps the target's suffix (``.tmp.tif``, ``.tmp.gpkg``...), so
    libraries that pick a format from the name still do.

    Args:
        path: The final file (its folder is created if needed).
        create: Whether the temporary file exists when the block starts. ``False`` suits
            writers that insist on creating the file themselves (GDAL, pyarrow).
        parents: Create missing parent folders (otherwise a missing folder is an
            ``OSError``).

    Yields:
        The temporary path to write to.
    """
    target = Path(path)
    if parents:
        target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{target.stem}.", suffix=f".tmp{target.suffix}", dir=target.parent
    )
    os.close(fd)
    tmp_path = Path(tmp)
    if not create:
        tmp_path.unlink()
    try:
        yield tmp_path
        # mkstemp creates 0600 files; outputs get the usual permissions.
        os.chmod(tmp_path, 0o666 & ~_umask())
        os.replace(tmp_path, target)
    finally:
        tmp_path.unlink(missing_ok=True)


def write_bytes_atomic(path: str | os.PathLike[str], data: bytes, *, parents: bool = True) -> Path:
    """Write bytes atomically (flushed to disk before the rename); see :func:`atomic_path`."""
    with atomic_path(path, parents=parents) as tmp, open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    return Path(path)


def write_text_atomic(
    path: str | os.PathLike[str], text: str, encoding: str = "utf-8", *, parents: bool = True
) -> Path:
    """Write text atomically, encoded with ``encoding``; see :func:`atomic_path`."""
    return write_bytes_atomic(path, text.encode(encoding), parents=parents)


def json_safe(obj: Any) -> Any:
    """A copy of ``obj`` that ``json.dumps(..., allow_nan=False)`` accepts.

    Mappings and sequences are walked; numpy arrays and scalars become Python values,
    paths strings, and NaN or infinite floats ``None``.
    """
    import math
    from collections.abc import Mapping

    import numpy as np

    if isinstance(obj, Mapping):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, np.generic):
        return json_safe(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def write_json_atomic(path: str | os.PathLike[str], doc: Any, *, indent: int = 1) -> Path:
    """Write JSON atomically; NaN and infinities are refused (``allow_nan=False``)."""
    return write_text_atomic(path, json.dumps(doc, indent=indent, allow_nan=False) + "\n")
