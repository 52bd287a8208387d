"""The stage images and matches of a strip's tiles, kept from the matching pass for Fig. 2.

Fig. 2 draws the tiles with the most, the median and the fewest verified matches, which
are known only when every tile is matched. Matching them again to draw them cost more
than the rest of the figures (hiric-strip, SIFT: three tiles, ~10 CPU-s of ~20). A
:class:`PanelStore` instead receives every tile as it is matched (``match_strip``'s
``debug_sink``), writes its stages to a folder (uncompressed ``.npz``, one file per tile,
~1-3 MB, written atomically) and lets them go, so memory does not grow with the strip; the
figure then reads back the three it draws. A run keeps the store in its run folder
(``persistent``), so a resumed run, whose tiles come back from the journal, finds the
stages of the tiles matched before it was stopped; after the figure is drawn, only its
tiles are kept (:meth:`PanelStore.keep_only`). A tile matched by a parallel worker is
written into the same folder by the worker itself (:func:`save_panels`, the store's
:attr:`PanelStore.folder` travels with the task) and adopted by the store when its result
arrives, so no tile is matched again for the figure.
"""

from __future__ import annotations

import re
import tempfile
import zipfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.errors import InputError
from planetref.runtime.atomic import PENDING_PREFIX, adopt_pending, atomic_path, pending_path

__all__ = ["MatchPanel", "PanelStore", "panels_from_tile", "save_panels"]

_FIELDS = ("image0", "valid0", "image1", "valid1", "keypoints0", "keypoints1", "inliers")


@dataclass
class MatchPanel:
    """One image pair with its matches.

    Attributes:
        title: Panel title (e.g. ``"coarse"``).
        image0: Left image (the CCD tile in the common geometry).
        image1: Right image (the reference window).
        keypoints0: ``(N, 2)`` ``(x, y)`` on ``image0``.
        keypoints1: ``(N, 2)`` on ``image1``.
        inliers: ``(N,)`` kept matches (default: all).
        valid0: Validity of ``image0`` (invalid pixels drawn blank).
        valid1: Validity of ``image1``.
    """

    title: str
    image0: NDArray[Any]
    image1: NDArray[Any]
    keypoints0: NDArray[np.float64]
    keypoints1: NDArray[np.float64]
    inliers: NDArray[np.bool_] | None = None
    valid0: NDArray[np.bool_] | None = None
    valid1: NDArray[np.bool_] | None = None


def panels_from_tile(result: Any) -> list[MatchPanel]:
    """Panels of a :class:`~planetref.frontend.result.TileResult` matched with ``debug``.

    Raises:
        InputError: If the result holds no stage images (match it with ``debug=True``).
    """
    stages = getattr(result, "debug", None) or []
    if not stages:
        raise InputError(
            f"tile {getattr(result, 'tile_id', '?')} has no stage images; "
            "match it with debug=True (or list it in debug_tiles)"
        )
    return [
        MatchPanel(
            s.stage, s.image0, s.image1, s.keypoints0, s.keypoints1, s.inliers, s.valid0, s.valid1
        )
        for s in stages
    ]


def _file_name(tile_id: str) -> str:
    """A tile's file name (tile ids such as ``ccd1:r001c000`` hold a colon)."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", tile_id) + ".npz"


def save_panels(folder: str | Path, result: Any, *, pending: bool = False) -> Path | None:
    """Write the stages of a tile result (matched with ``debug``) into ``folder``.

    The file a :class:`PanelStore` on ``folder`` reads (written atomically); parallel
    workers call this for the tiles they match, with ``pending``: they write the pending
    name (:func:`~planetref.runtime.atomic.pending_path`) that the parent adopts when it records
    the tile. Only tiles that ended ``ok`` can be drawn (see
    :func:`~planetref.report.figures_matching.select_tiles`); others are ignored.

    Returns:
        The file, or None when the result has no stages to keep.
    """
    stages = getattr(result, "debug", None) or []
    if getattr(result, "status", "ok") != "ok" or not stages:
        return None
    tile_id = str(result.tile_id)
    arrays: dict[str, Any] = {
        "tile_id": np.array(tile_id),
        "stages": np.array([s.stage for s in stages]),
    }
    for i, s in enumerate(stages):
        for f in _FIELDS:
            arrays[f"{i}_{f}"] = np.asarray(getattr(s, f))
    path = Path(folder) / _file_name(tile_id)
    if pending:
        path = pending_path(path)
    with atomic_path(path) as tmp:
        np.savez(tmp, **arrays)
    return path


class PanelStore:
    """Stage images and matches per tile id, on disk.

    Use as a context manager (or call :meth:`close`): a temporary folder is removed at the
    end; a persistent one is left as it is.

    Args:
        folder: Parent of the temporary folder (default: the system's temporary folder).
        persistent: A folder that outlives the store (a run folder's): tiles already in it
            (kept by an earlier, stopped run) are found again, and nothing is removed at
            :meth:`close`.
    """

    def __init__(
        self, folder: str | Path | None = None, *, persistent: str | Path | None = None
    ) -> None:
        self._files: dict[str, Path] = {}
        self._tmp: tempfile.TemporaryDirectory[str] | None = None
        if persistent is None:
            # A TemporaryDirectory removes itself when collected, even if close() is missed.
            self._tmp = tempfile.TemporaryDirectory(prefix="planetref-panels-", dir=folder)
            self._dir = Path(self._tmp.name)
            return
        self._dir = Path(persistent)
        # Tiles that workers of an interrupted run wrote but the run never recorded: a
        # valid one is adopted (its tile is in the journal or is matched again), a
        # damaged one removed; neither blocks the run.
        for path in sorted(self._dir.glob(PENDING_PREFIX + "*.npz")) if self._dir.is_dir() else []:
            final = path.with_name(path.name[len(PENDING_PREFIX) :])
            tile_id = self._stored_id(path) if not path.is_symlink() else None
            if tile_id is not None and _file_name(tile_id) == final.name:
                adopt_pending(final)
            elif not path.is_symlink():
                path.unlink(missing_ok=True)
        for path in sorted(self._dir.glob("*.npz")) if self._dir.is_dir() else []:
            if path.name.startswith("."):
                continue  # an atomic write's temporary file cut short
            tile_id = self._stored_id(path)
            if tile_id is not None and _file_name(tile_id) == path.name:
                self._files[tile_id] = path

    @staticmethod
    def _stored_id(path: Path) -> str | None:
        try:
            with np.load(path) as z:
                return str(z["tile_id"])
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
            return None

    def __enter__(self) -> PanelStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __contains__(self, tile_id: object) -> bool:
        return tile_id in self._files

    def __len__(self) -> int:
        return len(self._files)

    @property
    def folder(self) -> Path:
        """Where the tiles' files are (a worker writes its tiles here, see :func:`save_panels`)."""
        return self._dir

    def add(self, result: Any) -> None:
        """Keep the stages of a :class:`~planetref.frontend.result.TileResult` (``debug``).

        A result without stage images (matched by a parallel worker) adopts the pending
        file the worker wrote into :attr:`folder`, if there is one: renamed to its final
        name and recorded as written for this process
        (:func:`~planetref.runtime.atomic.adopt_pending`). Only tiles that ended ``ok`` are kept.
        """
        if getattr(result, "status", "ok") != "ok":
            return
        tile_id = str(result.tile_id)
        if getattr(result, "debug", None):
            path = save_panels(self._dir, result)
        else:
            path = self._dir / _file_name(tile_id)
            pending = pending_path(path)
            regular = pending.is_file() and not pending.is_symlink()
            if regular and self._stored_id(pending) == tile_id:
                adopt_pending(path)
            else:
                path = None
        if path is not None:
            self._files[tile_id] = path

    def panels(self, tile_id: str) -> list[MatchPanel] | None:
        """The stages of a tile as figure panels, or None if it was not kept."""
        path = self._files.get(tile_id)
        if path is None:
            return None
        try:
            return self._read(path)
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
            return None  # damaged: the figure matches the tile again

    @staticmethod
    def _read(path: Path) -> list[MatchPanel]:
        with np.load(path) as z:
            return [
                MatchPanel(
                    str(stage),
                    z[f"{i}_image0"],
                    z[f"{i}_image1"],
                    z[f"{i}_keypoints0"],
                    z[f"{i}_keypoints1"],
                    z[f"{i}_inliers"],
                    z[f"{i}_valid0"],
                    z[f"{i}_valid1"],
                )
                for i, stage in enumerate(z["stages"])
            ]

    def keep_only(self, tile_ids: Iterable[str]) -> None:
        """Remove the files of every tile but ``tile_ids`` (e.g. those a figure drew)."""
        keep = set(tile_ids)
        for tile_id in [t for t in self._files if t not in keep]:
            self._files.pop(tile_id).unlink(missing_ok=True)

    def close(self) -> None:
        """Remove a temporary folder (a persistent one keeps its files)."""
        self._files.clear()
        if self._tmp is not None:
            self._tmp.cleanup()
