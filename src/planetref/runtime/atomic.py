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
    "PENDING_PREFIX",
    "TEMP_PREFIX",
    "OutputWatcher",
    "adopt_pending",
    "atomic_path",
    "check_regular",
    "is_planetref_temporary",
    "json_safe",
    "open_regular",
    "pending_path",
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


#: Every temporary name planetref writes starts with this (atomic writes, worker
#: outputs waiting to be adopted): a run folder knows them as its own debris.
TEMP_PREFIX = ".planetref-tmp."
#: A worker process's finished output, waiting for the parent to adopt it (rename it to
#: its final name and record it); an interrupted run's are adopted or removed next time.
PENDING_PREFIX = ".planetref-pending."


def is_planetref_temporary(name: str) -> bool:
    """Whether a file name is one of planetref's temporaries or pending worker outputs."""
    return name.startswith((TEMP_PREFIX, PENDING_PREFIX))


def _not_regular(path: Path, st: os.stat_result) -> OutputError:
    import stat

    what = "a symbolic link" if stat.S_ISLNK(st.st_mode) else "not a regular file"
    return OutputError(
        f"planetref's file is {what}; planetref never follows or writes through a link "
        "it did not create: remove it or choose another folder",
        path=path,
    )


def check_regular(path: str | os.PathLike[str], *, folder_ok: bool = False) -> Path:
    """Refuse a path that exists and is not a regular file (a link, a folder, a FIFO).

    ``lstat``, so a symbolic link is seen as itself, never as what it names.

    Args:
        path: The path.
        folder_ok: Also accept a real folder (not a link to one).

    Raises:
        OutputError: The path exists and is not a regular file.
    """
    import stat

    p = Path(path)
    try:
        st = os.lstat(p)
    except (FileNotFoundError, NotADirectoryError):
        return p
    except OSError as exc:
        raise OutputError(f"cannot inspect the file ({exc.strerror or exc})", path=p) from None
    if not (stat.S_ISREG(st.st_mode) or (folder_ok and stat.S_ISDIR(st.st_mode))):
        raise _not_regular(p, st)
    return p


def open_regular(
    path: str | os.PathLike[str], flags: int, mode: int = 0o666, *, single_link: bool = True
) -> int:
    """``os.open`` that never follows a symbolic link and opens only a regular file.

    ``O_NOFOLLOW`` refuses a link in the last component; ``O_NONBLOCK`` keeps a FIFO
    from blocking the open before ``fstat`` refuses it. A file opened for writing must
    have no other hard link (``single_link``): writing into it would change the other
    name's content (a user's file linked into the run folder).

    Args:
        path: The file.
        flags: ``os.O_*`` flags (``O_NOFOLLOW`` is added).
        mode: Permission bits of a created file.
        single_link: Refuse a file with more than one hard link.

    Returns:
        The open descriptor (blocking mode restored).

    Raises:
        OutputError: The path is a link, not a regular file, has other hard links, or
            cannot be opened.
    """
    import stat

    p = Path(path)
    try:
        fd = os.open(p, flags | os.O_NOFOLLOW | os.O_NONBLOCK, mode)
    except OSError as exc:
        with contextlib.suppress(OSError):
            st = os.lstat(p)
            if not stat.S_ISREG(st.st_mode):
                raise _not_regular(p, st) from None
        raise OutputError(f"cannot open the file ({exc.strerror or exc})", path=p) from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise _not_regular(p, st)
        if single_link and st.st_nlink > 1:
            raise OutputError(
                f"planetref's file has {st.st_nlink} hard links (another name shares its "
                "content); planetref does not write into it: remove it or choose another "
                "folder",
                path=p,
            )
        os.set_blocking(fd, True)
    except BaseException:
        os.close(fd)
        raise
    return fd


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


def pending_path(path: str | os.PathLike[str]) -> Path:
    """The name a worker process writes ``path`` under, until its parent adopts it.

    A worker never writes an output's final name: a run killed before it recorded the
    output would find an unrecorded file there, which is not the run's to replace. The
    pending name (:data:`PENDING_PREFIX`) is planetref's own; :func:`adopt_pending` gives
    it its final name.
    """
    p = Path(path)
    return p.with_name(PENDING_PREFIX + p.name)


def adopt_pending(path: str | os.PathLike[str]) -> Path | None:
    """Rename the pending output of ``path`` (:func:`pending_path`) onto ``path``.

    The rename is checked and recorded like an atomic write (the watchers, the read-only
    rule); the pending file is opened by nobody and never followed if it is a link.

    Returns:
        ``path``, or None when there is no pending regular file.

    Raises:
        OutputError: ``path`` is read-only, or the rename failed.
    """
    import stat

    target = Path(path)
    pending = pending_path(target)
    try:
        if not stat.S_ISREG(os.lstat(pending).st_mode):
            return None
    except OSError:
        return None
    mode = read_only_mode(target)
    if mode is not None:
        raise OutputError(
            f"the file is read-only (mode {mode:o}); planetref does not replace it",
            path=target,
        )
    absolute = Path(os.path.abspath(target))
    watchers = _WATCHERS.get()
    for w in watchers:
        w.check_output(absolute)
    try:
        os.replace(pending, target)
    except OSError as exc:
        raise OutputError(f"cannot write the file ({exc.strerror or exc})", path=target) from exc
    for w in watchers:
        w.output_written(absolute)
    return target


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

    The temporary name (``.planetref-tmp.<stem>.<random><suffix>``, see
    :data:`TEMP_PREFIX`) keeps the target's suffix (``.tif``, ``.gpkg``...), so
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
            prefix=f"{TEMP_PREFIX}{target.stem}.", suffix=f"{target.suffix}", dir=target.parent
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
