"""Run folders: claimed under a lock, self-describing, never clobbered, resumable.

A run folder holds ``run.json``, a planetref-specific manifest: its format name
(``"planetref-run"``) and version, what wrote it (planetref's version and the command),
the run's identity (scene, matcher, configuration digest, fingerprints of the input
files and the weights' sha256) and the list of every file the run wrote. The rules:

* A folder that does not exist or is empty is claimed. A non-empty folder without a
  planetref manifest (including one holding another tool's ``run.json``) is refused;
  nothing is written into it.
* Re-running the same command (same identity) resumes. A different run, changed inputs
  ("inputs changed since this run (FILE): rerun with --overwrite"), other weights or
  another planetref version are refused unless ``overwrite``.
* ``overwrite`` removes exactly the files the manifest lists (then the folders left
  empty); every other file (the user's notes, sub-folders) is kept, and a run never
  writes over a file it did not write.
* The folder is locked (``fcntl.flock`` on ``.planetref.lock``) while a process uses it;
  a second process is refused with the holder's pid.
* No input of the command may lie inside the run folder.

Files appear in the list as soon as :meth:`RunDir.file` hands out their path (so a run
killed half-way can still be replaced), before any atomic write
(:mod:`planetref.runtime.atomic`) lands inside the folder while the run is active (so a run that
could not save its manifest, a full disk, wrote nothing unlisted), and, when the run
ends, every file that appeared in the folder during the run. The manifest says whether
the run ended normally (``complete``): an interrupted command that cannot resume
(``simulate``, ``adjust``) starts again on its next run instead of asking for
``--overwrite``.

planetref never follows a link it did not create: the lock, the manifest and the log
must be regular files (a folder where one is a link is refused), every path handed out
must stay inside the folder, and files opened in place are opened with ``O_NOFOLLOW``
(:func:`planetref.runtime.atomic.open_regular`). Names starting with
:data:`planetref.runtime.atomic.TEMP_PREFIX` or :data:`~planetref.runtime.atomic.PENDING_PREFIX` are
planetref's temporaries: never a user's file, never recorded, removed (or adopted) by the
next run.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

from planetref import __version__
from planetref.errors import InputError, OutputError, RunDirError
from planetref.runtime.atomic import (
    TEMP_PREFIX,
    check_regular,
    is_planetref_temporary,
    json_safe,
    open_regular,
    read_only_mode,
    watch_outputs,
    write_json_atomic,
)

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "LOCK_NAME",
    "MARKER",
    "RunDir",
    "check_output_file",
    "config_digest",
    "file_fingerprint",
]

MARKER = "run.json"
LOCK_NAME = ".planetref.lock"
LOG_NAME = "planetref.log"
#: The names planetref opens in place (not by an atomic rename): they must be regular
#: files, never links, before a run claims the folder.
_OWN_NAMES = (LOCK_NAME, MARKER, LOG_NAME)
FORMAT = "planetref-run"
FORMAT_VERSION = 1
SMALL_FILE_BYTES = 8 << 20
"""Files up to this size are fingerprinted with a full sha256."""
HEAD_TAIL_BYTES = 1 << 20
"""Bigger files: sha256 of their first and last MiB (with their size and mtime)."""

_log = logging.getLogger(__name__)


def config_digest(doc: Mapping[str, Any]) -> str:
    """A short stable digest of a JSON-serialisable configuration."""
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def file_fingerprint(path: str | os.PathLike[str], *, full: bool = False) -> dict[str, Any]:
    """What identifies a file's content cheaply.

    Args:
        path: The file.
        full: Hash the whole file whatever its size (weights).

    Returns:
        ``{"size", "mtime_ns", "sha256"}`` (whole file; files up to 8 MiB or ``full``) or
        ``{"size", "mtime_ns", "head_tail_sha256"}`` (first and last MiB).

    Raises:
        InputError: The file cannot be read.
    """
    p = Path(path)
    try:
        st = p.stat()
        h = hashlib.sha256()
        with open(p, "rb") as fh:
            if full or st.st_size <= SMALL_FILE_BYTES:
                for block in iter(lambda: fh.read(1 << 20), b""):
                    h.update(block)
                key = "sha256"
            else:
                h.update(fh.read(HEAD_TAIL_BYTES))
                fh.seek(-HEAD_TAIL_BYTES, os.SEEK_END)
                h.update(fh.read(HEAD_TAIL_BYTES))
                key = "head_tail_sha256"
    except OSError as exc:
        raise InputError(f"cannot read the file ({exc.strerror or exc})", path=p) from None
    return {"size": st.st_size, "mtime_ns": st.st_mtime_ns, key: h.hexdigest()}


def _same_file(a: Path, b: Path) -> bool:
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def check_output_file(
    path: str | os.PathLike[str],
    inputs: Iterable[str | os.PathLike[str]],
    *,
    overwrite: bool,
    option: str = "--out",
) -> Path:
    """Refuse an output file that is an input, a folder, or exists without ``overwrite``.

    Args:
        path: The output file.
        inputs: The command's input files (compared by resolved path and inode).
        overwrite: Whether an existing file may be replaced.
        option: The option that named the output (for the message).

    Returns:
        ``path``.

    Raises:
        InputError: The output is one of the inputs, a folder, or exists.
    """
    p = Path(path)
    for src in inputs:
        if _same_file(p, Path(src)):
            raise InputError(
                f"{option} is an input of this command; planetref never writes over an input",
                path=p,
            )
    if p.is_dir():
        raise InputError(f"{option} is a folder, a file is expected", path=p)
    if (p.exists() or p.is_symlink()) and not overwrite:
        raise InputError(f"{option} exists; pass --overwrite to replace it", path=p)
    mode = read_only_mode(p)
    if mode is not None:  # refused before any work; atomic_path refuses it again
        raise InputError(
            f"{option} is a read-only file (mode {mode:o}); planetref "
            "does not replace it, even with --overwrite",
            path=p,
        )
    return p


def _inside(child: str | os.PathLike[str], folder: str | os.PathLike[str]) -> bool:
    c, f = os.path.realpath(child), os.path.realpath(folder)
    return c == f or c.startswith(f.rstrip(os.sep) + os.sep)


def _read_manifest(marker: Path) -> tuple[dict[str, Any] | None, str]:
    """The manifest, or None and why the file is not one."""
    try:
        doc = json.loads(marker.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        return None, f"unreadable ({type(exc).__name__})"
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        if isinstance(doc, dict) and "kind" in doc and "planetref_version" in doc:
            return None, "written by an older planetref, without the list of its files"
        return None, "not written by planetref (no 'format': 'planetref-run')"
    if not isinstance(doc.get("format_version"), int) or doc["format_version"] > FORMAT_VERSION:
        return None, f"a newer planetref run format ({doc.get('format_version')!r})"
    if not isinstance(doc.get("files"), list):
        return None, "a planetref manifest without its list of files"
    return doc, ""


class _Lock:
    """An exclusive ``flock`` on ``<folder>/.planetref.lock`` holding the holder's pid."""

    def __init__(self, folder: Path) -> None:
        import fcntl

        self.path = folder / LOCK_NAME
        try:  # never through a link: truncating it would destroy the file it names
            fd = open_regular(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        except OutputError as exc:
            raise RunDirError(str(exc)) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                holder = os.read(fd, 64).decode("ascii", "replace").strip() or "unknown"
            finally:
                os.close(fd)
            raise RunDirError(
                f"the run folder is in use by another planetref process (pid {holder}); "
                "wait for it to finish or choose another --out",
                path=folder,
            ) from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self.fd: int | None = fd

    def release(self) -> None:
        if self.fd is not None:
            os.close(self.fd)  # closing the descriptor drops the flock
            self.fd = None


class RunDir:
    """A run's output folder (see the module docstring for the rules).

    Args:
        path: The folder.
        kind: What writes it (``"georef"``, ``"compare"``, ``"simulate"``, ``"adjust"``).
        identity: What must match for a re-run to resume (scene path, matcher, config
            digest...).
        overwrite: Replace a different previous run (only the files its manifest lists).
        inputs: The command's input files: fingerprinted into the identity, and none may
            lie inside the folder.
        weights: Weight files: their sha256 goes into the identity.
        resumable: Whether the same run may be resumed; otherwise an existing run of any
            identity needs ``overwrite``.

    Raises:
        RunDirError: The path is a file, the folder is not a planetref run folder, is in
            use, holds another run, or its run's inputs have changed.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        kind: str,
        identity: Mapping[str, Any],
        *,
        overwrite: bool = False,
        inputs: Iterable[str | os.PathLike[str]] = (),
        weights: Iterable[str | os.PathLike[str]] = (),
        resumable: bool = True,
    ) -> None:
        self.path = Path(path)
        self.kind = kind
        self.identity = json_safe(dict(identity))
        self.resumed = False
        self._complete = False
        self._saving = False
        self._lock: _Lock | None = None
        try:  # paths go into run.json, planetref.log and the reports, all UTF-8
            os.path.abspath(self.path).encode("utf-8")
        except UnicodeEncodeError:
            shown = os.fsencode(os.path.abspath(self.path)).decode("utf-8", "backslashreplace")
            raise RunDirError(
                "the output folder's name is not valid UTF-8 (undecodable bytes shown as "
                "\\x..); planetref writes paths into run.json and its logs as UTF-8: "
                "choose another --out",
                path=shown,
            ) from None
        if self.path.exists() and not self.path.is_dir():
            raise RunDirError("the output path exists and is not a folder", path=self.path)
        inputs = [Path(p) for p in inputs]
        for src in inputs:
            if self.path.exists() and _inside(src, self.path):
                raise RunDirError(
                    f"the output folder holds an input of this command ({src}); "
                    "choose another --out",
                    path=self.path,
                )
        self.inputs = {str(p.resolve()): file_fingerprint(p) for p in inputs}
        self.weights = {Path(w).name: file_fingerprint(w, full=True)["sha256"] for w in weights}
        self._check_own_names()
        self._inspect()  # refuse a foreign folder before creating anything in it
        try:
            self.path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(
                f"cannot create the output folder ({exc.strerror or exc})", path=self.path
            ) from None
        self._lock = _Lock(self.path)
        try:
            previous = self._inspect()
            self._remove_temporaries()
            self._files: set[str] = set()
            if previous is not None:
                self._take_over(previous, overwrite=overwrite, resumable=resumable)
            self._foreign = self._present() - self._files
            self._save()
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ claiming

    def _check_own_names(self) -> None:
        """Refuse a folder whose lock, manifest or log is a link or not a regular file."""
        for name in _OWN_NAMES:
            try:
                check_regular(self.path / name)
            except OutputError as exc:
                raise RunDirError(str(exc)) from None

    def _entries(self) -> list[Path]:
        return [c for c in self.path.iterdir() if c.name != LOCK_NAME] if self.path.is_dir() else []

    def _inspect(self) -> dict[str, Any] | None:
        """The previous manifest, None for a new or empty folder; refuse anything else."""
        if not self._entries():
            return None
        marker = self.path / MARKER
        if not marker.is_file():
            raise RunDirError(
                "the folder is not empty and was not written by planetref (no "
                f"{MARKER}); planetref writes nothing there: choose another --out",
                path=self.path,
            )
        doc, why = _read_manifest(marker)
        if doc is None:
            raise RunDirError(
                f"the folder's {MARKER} is {why}; planetref writes and removes nothing "
                "there: choose another --out",
                path=self.path,
            )
        return doc

    def _take_over(self, previous: dict[str, Any], *, overwrite: bool, resumable: bool) -> None:
        listed = {str(f) for f in previous["files"] if isinstance(f, str)}
        problem = self._difference(previous)
        if problem is None and not resumable and previous.get("complete") is False:
            # The same command, interrupted (Ctrl-C, a kill): nothing of it is worth
            # keeping and everything listed is its own; start again, as it would resume.
            _log.info("%s: replacing the files of an interrupted %s run", self.path, self.kind)
            self._remove(listed)
            return
        if problem is None and resumable and not overwrite:
            for f in sorted(listed):
                try:  # a listed file replaced by a link: resuming would write through it
                    check_regular(self._inside_path(f), folder_ok=True)
                except OutputError as exc:
                    raise RunDirError(str(exc)) from None
            self.resumed = True
            self._files = {f for f in listed if (self.path / f).exists()}
            return
        if not overwrite:
            raise RunDirError(
                (problem or f"the folder holds the outputs of the same {self.kind} command")
                + ": rerun with --overwrite (which replaces only the files that run wrote) "
                "or choose another --out",
                path=self.path,
            )
        self._remove(listed)

    def _difference(self, previous: dict[str, Any]) -> str | None:
        """Why ``previous`` is not this run (None when it is the same run)."""
        if previous.get("kind") != self.kind or previous.get("identity") != self.identity:
            old = previous.get("identity") or {}
            changed = [
                f"{k}: {old.get(k)!r} -> {self.identity.get(k)!r}"
                for k in sorted(set(old) | set(self.identity))
                if old.get(k) != self.identity.get(k)
            ]
            what = "; ".join([str(previous.get("kind")), *changed])
            return f"the folder holds another run ({what})"
        if previous.get("planetref_version") != __version__:
            return (
                f"this run was written by planetref {previous.get('planetref_version')} "
                f"(this is {__version__})"
            )
        old_inputs = previous.get("inputs") or {}
        for name in sorted(set(old_inputs) | set(self.inputs)):
            if old_inputs.get(name) != self.inputs.get(name):
                return f"inputs changed since this run ({name})"
        old_weights = previous.get("weights") or {}
        for name in sorted(set(old_weights) | set(self.weights)):
            if old_weights.get(name) != self.weights.get(name):
                return f"weights changed since this run ({name})"
        return None

    def _inside_path(self, rel: str) -> Path:
        """The listed file ``rel`` (a path that leaves the folder is refused)."""
        p = self.path / rel
        if ".." in Path(rel).parts or Path(rel).is_absolute() or not _inside(p.parent, self.path):
            raise RunDirError(
                f"the manifest lists a file outside the folder ({rel}); planetref writes "
                "and removes nothing there: choose another --out",
                path=self.path,
            )
        return p

    def _remove(self, listed: set[str]) -> None:
        """Remove the listed files (never outside the folder), then emptied folders.

        Nothing is removed when one of them is read-only (no write bit in its mode):
        ``--overwrite`` obeys the rule every planetref write does.
        """
        for rel in sorted(listed):
            p = self.path / rel
            if p.is_symlink() or not _inside(p.parent, self.path):
                continue
            mode = read_only_mode(p)
            if mode is not None:
                raise RunDirError(
                    f"{rel} is read-only (mode {mode:o}); planetref does not replace or "
                    "remove it, even with --overwrite: make it writable or choose another "
                    "--out",
                    path=self.path,
                )
        folders: set[Path] = set()
        for rel in sorted(listed):
            p = self.path / rel
            if not _inside(p.parent, self.path) or p.name in (LOCK_NAME, ""):
                continue
            if p.is_symlink() or p.is_file():
                p.unlink()
                _log.info("overwrite: removed %s", p)
                folders.update(q for q in p.parents if _inside(q, self.path))
            elif p.is_dir():
                folders.add(p)
        root = os.path.realpath(self.path)
        for folder in sorted(folders, key=lambda q: len(q.parts), reverse=True):
            if os.path.realpath(folder) == root:
                continue
            with contextlib.suppress(OSError):  # not empty: it holds the user's files
                folder.rmdir()
        (self.path / MARKER).unlink(missing_ok=True)

    def _remove_temporaries(self) -> None:
        """Remove atomic writes' temporaries an interrupted run left (under the lock).

        Pending worker outputs (:data:`~planetref.runtime.atomic.PENDING_PREFIX`) stay: their
        stage adopts or removes them when it resumes.
        """
        import shutil

        for dirpath, dirnames, filenames in os.walk(self.path):
            if dirpath != str(self.path) and MARKER in filenames:
                dirnames[:] = []  # a nested run folder (its own lock) cleans its own
                continue
            for name in filenames:
                if name.startswith(TEMP_PREFIX):
                    with contextlib.suppress(OSError):
                        os.unlink(os.path.join(dirpath, name))
            for name in [d for d in dirnames if d.startswith(TEMP_PREFIX)]:
                dirnames.remove(name)
                target = os.path.join(dirpath, name)
                if not os.path.islink(target):  # a build folder an interrupted run left
                    shutil.rmtree(target, ignore_errors=True)

    def _present(self) -> set[str]:
        """Every file in the folder (relative, POSIX), outside nested run folders."""
        found: set[str] = set()
        for dirpath, dirnames, filenames in os.walk(self.path):
            here = Path(dirpath)
            if here != self.path and (here / MARKER).is_file():
                dirnames[:] = []  # a nested run folder lists its own files
                continue
            dirnames[:] = [d for d in dirnames if not is_planetref_temporary(d)]
            for name in filenames:
                if name in (LOCK_NAME,) or (here == self.path and name == MARKER):
                    continue
                if is_planetref_temporary(name):
                    continue  # planetref's own, never a user's file nor an output
                found.add((here / name).relative_to(self.path).as_posix())
        return found

    def _save(self) -> None:
        doc = {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "written_by": f"planetref {__version__} ({self.kind})",
            "kind": self.kind,
            "identity": self.identity,
            "planetref_version": __version__,
            "inputs": self.inputs,
            "weights": self.weights,
            "files": sorted(self._files),
            "complete": self._complete,
        }
        self._saving = True
        try:
            write_json_atomic(self.path / MARKER, doc, indent=2, nan_as_null=True)
        finally:
            self._saving = False

    def _relative(self, path: Path) -> str | None:
        if not _inside(path.parent, self.path):
            return None
        rel = Path(os.path.realpath(path.parent)).relative_to(os.path.realpath(self.path))
        return (rel / path.name).as_posix()

    def _check_within(self, path: Path) -> None:
        """Refuse a path named inside the folder whose real folder is outside (a link)."""
        lexical = os.path.normpath(os.path.abspath(path))
        root = os.path.normpath(os.path.abspath(self.path))
        if lexical.startswith(root.rstrip(os.sep) + os.sep) and not _inside(
            os.path.dirname(lexical), self.path
        ):
            raise RunDirError(
                "the path leads out of the run folder through a link; planetref writes "
                "only inside it",
                path=path,
            )

    def _claim(self, path: Path) -> None:
        self._check_within(path)
        rel = self._relative(path)
        if rel is None or rel in (MARKER, LOCK_NAME) or rel in self._files:
            return
        if any(is_planetref_temporary(part) for part in rel.split("/")):
            return  # planetref's own temporary (removed, or renamed and claimed, later)
        if rel in self._foreign:
            raise RunDirError(
                "this file was not written by planetref, so the run does not replace it: "
                "move it away or choose another --out",
                path=path,
            )
        self._files.add(rel)
        self._save()

    # ------------------------------------------------------------------ OutputWatcher

    def check_output(self, path: Path) -> None:
        """Refuse an atomic write over a file the run did not write; record it first."""
        if self._saving:
            return
        # Recorded before it is written: a file that lands in the folder is always in
        # the manifest, even when saving the manifest fails afterwards (a full disk).
        # Otherwise the run's own file would be foreign to every rerun, --overwrite too.
        self._claim(path)  # raises for a file the run did not write

    def output_written(self, path: Path) -> None:
        """Record an atomic write inside the folder."""
        if not self._saving:
            self._claim(path)

    # ------------------------------------------------------------------ use

    def file(self, *parts: str) -> Path:
        """A path inside the run folder, recorded as the run's (parent folders are created).

        Raises:
            RunDirError: The path is a file that planetref did not write.
        """
        for part in parts:
            if part in ("", ".", "..") or "/" in part or os.sep in part:
                raise RunDirError(
                    f"{part!r} is not a file or folder name of the run (a path component); "
                    "planetref writes only inside the run folder",
                    path=self.path,
                )
        p = self.path.joinpath(*parts)
        self._claim(p)
        p.parent.mkdir(parents=True, exist_ok=True)
        self._check_within(p)  # the folders just made may not be links either
        try:
            check_regular(p, folder_ok=True)  # opened in place: never through a link
        except OutputError as exc:
            raise RunDirError(str(exc)) from None
        return p

    def write_json(self, name: str, doc: Any) -> Path:
        """Write ``doc`` as JSON to ``name`` inside the run folder, atomically."""
        return write_json_atomic(self.file(name), doc, indent=2, nan_as_null=True)

    def finish(self, *, complete: bool = True) -> None:
        """Record every file that appeared during the run, and release the lock.

        Args:
            complete: Whether the run ended normally (recorded as ``complete`` in the
                manifest); an interrupted command that cannot resume starts again on
                its next run instead of asking for ``--overwrite``.
        """
        if self._lock is None:
            return
        self._complete = complete
        try:
            if self.path.is_dir():
                self._files |= self._present() - self._foreign
                self._files = {f for f in self._files if (self.path / f).exists()}
                self._save()
        finally:
            self.close()

    def close(self) -> None:
        """Release the lock (idempotent); the manifest stays as last saved."""
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def __del__(self) -> None:
        self.close()

    @contextlib.contextmanager
    def logging_to_file(self, name: str = LOG_NAME) -> Iterator[Path]:
        """The active run: logs copied to a file, outputs recorded; finished on exit.

        planetref's log records (INFO and above) go to ``name``; every atomic write inside
        the folder is checked and recorded; on exit (even on an error) the file list is
        completed and the lock released.
        """
        path = self.file(name)
        try:  # appended in place: never through a link or into a hard-linked file
            fd = open_regular(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
        except OutputError as exc:
            raise RunDirError(str(exc)) from None
        stream = os.fdopen(fd, "a", encoding="utf-8")
        handler = logging.StreamHandler(stream)
        handler.setLevel(logging.INFO)
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        logger = logging.getLogger("planetref")
        previous_level = logger.level
        if logger.level == logging.NOTSET or logger.level > logging.INFO:
            logger.setLevel(logging.INFO)
        # Console handlers keep their own level, so -q still silences the terminal.
        for h in logger.handlers:
            if h.level == logging.NOTSET:
                h.setLevel(previous_level or logging.WARNING)
        logger.addHandler(handler)
        try:
            with watch_outputs(self):
                yield path
        except BaseException as exc:
            # The error's line goes to the run's log only (the CLI prints it once).
            record = logging.LogRecord(
                "planetref", logging.ERROR, __file__, 0, "run failed: %s: %s", None, None
            )
            record.args = (type(exc).__name__, " ".join(str(exc).split()))
            handler.handle(record)
            failed = True
            raise
        else:
            failed = False
        finally:
            logger.removeHandler(handler)
            handler.close()
            stream.close()
            logger.setLevel(previous_level)
            self.finish(complete=not failed)
