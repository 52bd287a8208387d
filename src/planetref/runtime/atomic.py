"""Atomic file writes: a temporary file beside the target, renamed over it on success.

Readers never see a half-written file, and a failed write leaves any previous file
untouched. Every planetref output goes through here.

A run folder (:class:`planetref.pipeline.rundir.RunDir`) watches the writes made while it
is active (:func:`watch_outputs`): it refuses to replace a file it did not write and
records every file it did, so ``--overwrite`` later removes exactly those.
"""

from __future__ import annotations

import contextlib
import contextvars
import json
import os
import tempfile
import urllib.error
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Protocol

from planetref.errors import OutputError, PlanetrefError

__all__ = [
    "OutputWatcher",
    "atomic_path",
    "json_safe",
    "read_only_mode",
    "record_output",
    "watch_outputs",
    "write_bytes_atomic",
    "write_json_atomic",
    "write_text_atomic",
]

#: Modules whose exceptions, raised while an output is written, are write failures
#: (GDAL, OGR, Arrow, SQLite): they are re-raised naming the file.
_WRITER_MODULES = frozenset({"rasterio", "pyogrio", "fiona", "osgeo", "pyarrow", "sqlite3"})


class OutputWatcher(Protocol):
    """Told about atomic writes while :func:`watch_outputs` is active."""

    def check_output(self, path: Path) -> None:
        """Raise if ``path`` (absolute) must not be written."""

    def output_written(self, path: Path) -> None:
        """``path`` (absolute) has just been written."""


_WATCHERS: contextvars.ContextVar[tuple[OutputWatcher, ...]] = contextvars.ContextVar(
    "planetref_output_watchers", default=()
)


@contextlib.contextmanager
def watch_outputs(watcher: OutputWatcher) -> Iterator[None]:
    """Let ``watcher`` check and record every atomic write made inside the block."""
    token = _WATCHERS.set((*_WATCHERS.get(), watcher))
    try:
        yield
    finally:
        _WATCHERS.reset(token)


def record_output(path: str | os.PathLike[str]) -> None:
    """Tell the watchers that ``path`` was written for this process by another one.

    A worker process writes its outputs atomically, but the watchers (a run folder's
    record of its files) live in the process that asked for them; it records them here
    when the worker says they are written.
    """
    absolute = Path(os.path.abspath(path))
    for w in _WATCHERS.get():
        w.check_output(absolute)
        w.output_written(absolute)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def read_only_mode(path: str | os.PathLike[str]) -> int | None:
    """The permission bits of a file that no one may write, else ``None``.

    The mode bits, not ``os.access``: root may replace anything, but a file marked
    read-only for everyone (an archive, shared data) is not planetref's to replace.
    """
    p = Path(path)
    if not p.is_file():
        return None
    mode = p.stat().st_mode & 0o777
    return None if mode & 0o222 else mode


def _write_failed(exc: BaseException) -> bool:
    if isinstance(exc, PlanetrefError):
        return False
    if isinstance(exc, urllib.error.URLError | ConnectionError | TimeoutError):
        return False  # the source failed (a download), not the write
    if isinstance(exc, OSError):
        return True
    return type(exc).__module__.split(".")[0] in _WRITER_MODULES


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

    Raises:
        OutputError: ``path`` is a read-only file (no write bit in its mode, whoever runs
            planetref), or the write failed (disk full, permissions, a GDAL or Arrow
            write error); the message names ``path``.
    """
    target = Path(path)
    absolute = Path(os.path.abspath(target))
    mode = read_only_mode(target)
    if mode is not None:
        raise OutputError(
            f"the file is read-only (mode {mode:o}); planetref does not replace it",
            path=target,
        )
    watchers = _WATCHERS.get()
    for w in watchers:
        w.check_output(absolute)
    try:
        if parents:
            target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(
            prefix=f".{target.stem}.", suffix=f".tmp{target.suffix}", dir=target.parent
        )
    except OSError as exc:
        raise OutputError(f"cannot create the file ({exc.strerror or exc})", path=target) from exc
    os.close(fd)
    tmp_path = Path(tmp)
    if not create:
        tmp_path.unlink()
    try:
        yield tmp_path
        # mkstemp creates 0600 files; outputs get the usual permissions.
        os.chmod(tmp_path, 0o666 & ~_umask())
        os.replace(tmp_path, target)
    except Exception as exc:
        if _write_failed(exc):
            reason = (getattr(exc, "strerror", None) or str(exc) or type(exc).__name__).strip()
            reason = reason.splitlines()[0] if reason else type(exc).__name__
            raise OutputError(
                f"cannot write the file ({type(exc).__name__}: {reason})", path=target
            ) from exc
        raise
    finally:
        tmp_path.unlink(missing_ok=True)
    for w in watchers:
        w.output_written(absolute)


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


def write_json_atomic(
    path: str | os.PathLike[str], doc: Any, *, indent: int = 1, nan_as_null: bool = False
) -> Path:
    """Write JSON atomically (the one JSON writer).

    Args:
        path: The file.
        doc: JSON types, or numpy values and paths when ``nan_as_null``.
        indent: Indentation.
        nan_as_null: Convert with :func:`json_safe` first: numpy values to Python, NaN
            and infinities to ``null`` (reports, where "not measured" is a value). Off, a
            NaN or infinity is refused (``allow_nan=False``: cameras, where it is a bug).
    """
    if nan_as_null:
        doc = json_safe(doc)
    return write_text_atomic(path, json.dumps(doc, indent=indent, allow_nan=False) + "\n")
