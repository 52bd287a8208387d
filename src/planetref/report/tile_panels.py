"""The stage images and matches of a strip's tiles, kept from the matching pass for Fig. 2.

Fig. 2 draws the tiles with the most, the median and the fewest verified matches, which
are known only when every tile is matched. Matching them again to draw them cost more
than the rest of the figures (hiric-strip, SIFT: three tiles, ~10 CPU-s of ~20). A
:class:`PanelStore` instead receives every tile as it is matched (``match_strip``'s
``debug_sink``), writes its stages to a temporary folder (uncompressed ``.npz``, one file
per tile, ~1-3 MB) and lets them go, so memory does not grow with the strip; the figure
then reads back the three it draws. Tiles matched elsewhere (parallel workers, a resumed
run's journal) are not in the store: the figure matches those again, as before.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from planetref.report.figures_matching import MatchPanel

__all__ = ["PanelStore"]

_FIELDS = ("image0", "valid0", "image1", "valid1", "keypoints0", "keypoints1", "inliers")


class PanelStore:
    """Stage images and matches per tile id, on disk in a temporary folder.

    Use as a context manager (or call :meth:`close`): the folder is removed at the end.

    Args:
        folder: Parent of the temporary folder (default: the system's temporary folder).
    """

    def __init__(self, folder: str | Path | None = None) -> None:
        # A TemporaryDirectory removes itself when collected, even if close() is missed.
        self._tmp = tempfile.TemporaryDirectory(prefix="planetref-panels-", dir=folder)
        self._dir = Path(self._tmp.name)
        self._files: dict[str, Path] = {}

    def __enter__(self) -> PanelStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __contains__(self, tile_id: object) -> bool:
        return tile_id in self._files

    def __len__(self) -> int:
        return len(self._files)

    def add(self, result: Any) -> None:
        """Keep the stages of a :class:`~planetref.frontend.result.TileResult` (``debug``).

        Only tiles that ended ``ok`` can be drawn (see
        :func:`~planetref.report.figures_matching.select_tiles`); others are ignored.
        """
        stages = getattr(result, "debug", None) or []
        if getattr(result, "status", "ok") != "ok" or not stages:
            return
        arrays: dict[str, Any] = {"stages": np.array([s.stage for s in stages])}
        for i, s in enumerate(stages):
            for f in _FIELDS:
                arrays[f"{i}_{f}"] = np.asarray(getattr(s, f))
        path = self._dir / f"tile{len(self._files):06d}.npz"
        np.savez(path, **arrays)
        self._files[str(result.tile_id)] = path

    def panels(self, tile_id: str) -> list[MatchPanel] | None:
        """The stages of a tile as figure panels, or None if it was not kept."""
        path = self._files.get(tile_id)
        if path is None:
            return None
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

    def close(self) -> None:
        """Remove the temporary folder."""
        self._files.clear()
        self._tmp.cleanup()
