"""Run directories: never clobbered silently, resumable, self-describing.

A run directory holds ``run.json`` (what kind of run wrote it and its identity: scene,
matcher, configuration digest), ``config.json`` (the resolved configuration),
``planetref.log`` and the run's outputs. Re-running the same command on the same
directory resumes (finished tiles are kept); a directory written by a different run is
refused unless ``overwrite`` is given, and a non-empty directory that planetref did not
write is always refused.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from planetref import __version__
from planetref.atomic import json_safe
from planetref.atomic import write_json_atomic as _write_json
from planetref.errors import InputError

__all__ = ["RunDir", "config_digest", "write_json_atomic"]

MARKER = "run.json"


def config_digest(doc: Mapping[str, Any]) -> str:
    """A short stable digest of a JSON-serialisable configuration."""
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def write_json_atomic(path: str | os.PathLike[str], doc: Any) -> Path:
    """Write JSON (numpy values converted, NaN written as null) atomically."""
    return _write_json(path, json_safe(doc), indent=2)


class RunDir:
    """A run's output directory.

    Args:
        path: The directory.
        kind: What writes it (``"georef"``, ``"compare"``...).
        identity: What must match for a re-run to resume (scene path, matcher, config
            digest...).
        overwrite: Remove a previous run's outputs first (only ever in a directory that
            planetref wrote).

    Raises:
        InputError: The directory is a file, is non-empty without being a planetref run
            directory, or holds a different run and ``overwrite`` is false.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        kind: str,
        identity: Mapping[str, Any],
        *,
        overwrite: bool = False,
    ) -> None:
        self.path = Path(path)
        self.kind = kind
        self.identity = json_safe(dict(identity))
        if self.path.exists() and not self.path.is_dir():
            raise InputError("the output path exists and is not a directory", path=self.path)
        marker = self.path / MARKER
        existing = list(self.path.iterdir()) if self.path.is_dir() else []
        self.resumed = False
        if existing:
            if not marker.is_file():
                raise InputError(
                    "the output directory is not empty and was not written by "
                    "planetref; choose another --out",
                    path=self.path,
                )
            try:
                previous = json.loads(marker.read_text(encoding="utf-8"))
            except (OSError, json.JSONDecodeError):
                previous = {}
            same = previous.get("kind") == kind and previous.get("identity") == self.identity
            if overwrite:
                for child in existing:
                    if child.is_dir() and not child.is_symlink():
                        shutil.rmtree(child)
                    else:
                        child.unlink()
            elif same:
                self.resumed = True
            else:
                raise InputError(
                    f"the output directory holds another run ({previous.get('kind')}: "
                    f"{previous.get('identity')}); use --overwrite to replace it or choose "
                    "another --out",
                    path=self.path,
                )
        self.path.mkdir(parents=True, exist_ok=True)
        write_json_atomic(
            marker, {"kind": kind, "identity": self.identity, "planetref_version": __version__}
        )

    def file(self, *parts: str) -> Path:
        """A path inside the run directory (parent folders are created)."""
        p = self.path.joinpath(*parts)
        p.parent.mkdir(parents=True, exist_ok=True)
        return p

    def write_json(self, name: str, doc: Any) -> Path:
        """Write ``doc`` as JSON to ``name`` inside the run directory, atomically."""
        return write_json_atomic(self.file(name), doc)

    @contextlib.contextmanager
    def logging_to_file(self, name: str = "planetref.log") -> Iterator[Path]:
        """Copy planetref's log records (INFO and above) into a file of the run."""
        path = self.file(name)
        handler = logging.FileHandler(path, mode="a", encoding="utf-8")
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
            yield path
        finally:
            logger.removeHandler(handler)
            handler.close()
            logger.setLevel(previous_level)
