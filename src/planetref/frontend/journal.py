"""A resumable, crash-safe journal of finished tiles (JSON lines).

Each line is ``{"digest": ..., "attempt": n, "result": TileResult.to_dict()}``. The digest
names the matcher and the front-end settings; a journal of another digest is refused.

Crash safety:

* On open, a torn last line (a run killed mid-write, a full disk) is cut off, so that
  what is appended afterwards starts on a line of its own.
* Every appended line is flushed and fsynced before the tile counts as done.

Resume: a tile whose latest line is ``ok`` or another final status is not matched again;
a tile whose latest line is status ``error`` is matched again until it has failed
``max_attempts`` times (the attempts are counted from the journal itself).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections.abc import Mapping
from os import PathLike
from pathlib import Path
from typing import IO, Any

from planetref.errors import InputError
from planetref.frontend.result import TileResult
from planetref.runtime.atomic import open_regular

__all__ = ["DEFAULT_MAX_ATTEMPTS", "TileJournal", "journal_digest"]

log = logging.getLogger(__name__)

#: How often a tile that errored is tried in all (the first run included).
DEFAULT_MAX_ATTEMPTS = 2


def journal_digest(matcher: str, config: Mapping[str, Any]) -> str:
    """The digest of a matcher name and a front-end configuration (``model_dump()``)."""
    text = json.dumps({"matcher": matcher, "config": dict(config)}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


class TileJournal:
    """The journal of one strip's tiles.

    Use as a context manager: ``with TileJournal(path, digest) as j: done = j.finished``.

    Args:
        path: The JSON-lines file (created with its folder when missing).
        digest: :func:`journal_digest` of this run.
        max_attempts: Attempts a tile that errored gets in all.

    Attributes:
        finished: Tile id -> result of the tiles not to be matched again (read on open).
        attempts: Tile id -> how many times the tile errored so far.
    """

    def __init__(
        self,
        path: str | PathLike[str],
        digest: str,
        *,
        max_attempts: int = DEFAULT_MAX_ATTEMPTS,
    ) -> None:
        if max_attempts < 1:
            raise InputError(f"max_attempts must be >= 1, got {max_attempts}")
        self.path = Path(path)
        self.digest = digest
        self.max_attempts = int(max_attempts)
        self.finished: dict[str, TileResult] = {}
        self.attempts: dict[str, int] = {}
        self._fh: IO[bytes] | None = None

    def __enter__(self) -> TileJournal:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def open(self) -> dict[str, TileResult]:
        """Read the journal, cut a torn tail, open it for appending.

        Returns:
            :attr:`finished`.

        Raises:
            InputError: A line other than the last is not JSON, or the journal was
                written with another matcher or configuration.
        """
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # Read, repaired and appended in place: never through a link (a user's file the
        # link names would be "repaired" as a torn journal) nor a hard-linked file.
        fh = os.fdopen(open_regular(self.path, os.O_RDWR | os.O_CREAT | os.O_APPEND), "a+b")
        try:
            fh.seek(0)
            self._read(fh)
        except BaseException:
            fh.close()
            raise
        self._fh = fh
        return self.finished

    def _read(self, fh: IO[bytes]) -> None:
        data = fh.read()
        lines = data.split(b"\n")  # the last item follows the last newline ("" if intact)
        pos = good_end = 0
        unterminated = False
        latest: dict[str, TileResult] = {}
        for i, raw in enumerate(lines):
            terminated = i < len(lines) - 1
            end = pos + len(raw) + int(terminated)
            if raw.strip():
                try:
                    doc = json.loads(raw.decode("utf-8"))
                    if not isinstance(doc, dict) or "result" not in doc:
                        raise ValueError("not a journal record")
                except (UnicodeDecodeError, ValueError):
                    if not any(rest.strip() for rest in lines[i + 1 :]):
                        break  # a line cut short by an interrupted run: cut off below
                    raise InputError(
                        f"line {i + 1} is not a journal record", path=self.path
                    ) from None
                if doc.get("digest") != self.digest:
                    raise InputError(
                        "the journal was written with another matcher or config "
                        f"(digest {doc.get('digest')}, expected {self.digest}); use a new "
                        "journal file",
                        path=self.path,
                    )
                res = TileResult.from_dict(doc["result"])
                latest[res.tile_id] = res
                if res.status == "error":
                    self.attempts[res.tile_id] = self.attempts.get(res.tile_id, 0) + 1
                unterminated = not terminated
            good_end = end
            pos = end
        if good_end < len(data):
            log.warning(
                "%s: cutting off a torn last line (%d bytes) left by an interrupted run",
                self.path,
                len(data) - good_end,
            )
        if good_end < len(data) or unterminated:
            fh.truncate(good_end)
            if unterminated:  # a whole record without its newline: end the line
                fh.write(b"\n")  # appended: at good_end
            fh.flush()
            os.fsync(fh.fileno())
        for tid, res in latest.items():
            if res.status != "error" or self.attempts.get(tid, 0) >= self.max_attempts:
                self.finished[tid] = res

    def append(self, result: TileResult) -> None:
        """Write one result as a line, flushed and fsynced.

        Raises:
            RuntimeError: The journal is not open.
        """
        if self._fh is None:
            raise RuntimeError("the journal is not open")
        attempt = self.attempts.get(result.tile_id, 0) + 1
        if result.status == "error":
            self.attempts[result.tile_id] = attempt
        line = json.dumps({"digest": self.digest, "attempt": attempt, "result": result.to_dict()})
        self._fh.write((line + "\n").encode("utf-8"))
        self._fh.flush()
        os.fsync(self._fh.fileno())

    def close(self) -> None:
        """Close the file (idempotent)."""
        if self._fh is not None:
            self._fh.close()
            self._fh = None
