"""Tile plans of CCD images and the footprints of tiles on the reference grid.

A CCD image is partitioned into overlapping rectangular tiles whose side covers about
``tile_size_ref_px`` reference pixels on the ground. Each tile's footprint is found by
intersecting the rays of points along its border with the DEM through the initial
camera; the reference window is the footprint's bounding box on the reference grid,
padded by the a-priori uncertainty.

Coordinates: tiles are integer ranges of image lines and samples; footprints are in
reference pixels ``(col, row)`` with the first pixel centre at ``(0.5, 0.5)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.camera.base import Camera, Terrain
from planetref.camera.mapping import image_gsd_m, image_to_ref_pixel
from planetref.errors import InputError
from planetref.frontend.config import FrontendConfig
from planetref.raster.ortho import ReferenceOrtho, RefWindow

__all__ = ["Footprint", "Tile", "TilePlan", "plan_tiles", "tile_footprint"]


@dataclass(frozen=True)
class Tile:
    """A rectangle of a CCD image.

    Attributes:
        tile_id: Stable identifier ``"<ccd>:r<row>c<col>"`` (row/column of the tile grid).
        ccd: CCD name.
        line0: First line (integer index).
        sample0: First sample.
        n_lines: Number of lines.
        n_samples: Number of samples.
        core: ``(line0, sample0, line1, sample1)`` (end exclusive) of the part of the tile
            it owns: tiles of a plan overlap, and each point of the image belongs to the
            core of exactly one tile (the overlap is split in the middle), so that a
            correspondence found in two neighbouring tiles is counted once. None: the
            whole tile.
    """

    tile_id: str
    ccd: str
    line0: int
    sample0: int
    n_lines: int
    n_samples: int
    core: tuple[int, int, int, int] | None = None

    @property
    def centre(self) -> tuple[float, float]:
        """``(line, sample)`` of the tile's centre (continuous image coordinates)."""
        return (self.line0 + self.n_lines / 2.0, self.sample0 + self.n_samples / 2.0)

    @property
    def bounds(self) -> tuple[int, int, int, int]:
        """``(line0, sample0, line1, sample1)``, end exclusive."""
        return (self.line0, self.sample0, self.line0 + self.n_lines, self.sample0 + self.n_samples)

    def contains(self, line: NDArray[np.float64], sample: NDArray[np.float64]) -> NDArray[np.bool_]:
        """True where continuous ``(line, sample)`` lies inside the tile."""
        l0, s0, l1, s1 = self.bounds
        with np.errstate(invalid="ignore"):
            return (line >= l0) & (line < l1) & (sample >= s0) & (sample < s1)

    def owns(self, line: NDArray[np.float64], sample: NDArray[np.float64]) -> NDArray[np.bool_]:
        """True where continuous ``(line, sample)`` lies in the tile's core (see ``core``)."""
        l0, s0, l1, s1 = self.core or self.bounds
        with np.errstate(invalid="ignore"):
            return (line >= l0) & (line < l1) & (sample >= s0) & (sample < s1)

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly form."""
        doc: dict[str, Any] = {
            "tile_id": self.tile_id,
            "ccd": self.ccd,
            "line0": self.line0,
            "sample0": self.sample0,
            "n_lines": self.n_lines,
            "n_samples": self.n_samples,
        }
        if self.core is not None:
            doc["core"] = list(self.core)
        return doc

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> Tile:
        """Inverse of :meth:`to_dict`."""
        return cls(
            str(doc["tile_id"]),
            str(doc["ccd"]),
            int(doc["line0"]),
            int(doc["sample0"]),
            int(doc["n_lines"]),
            int(doc["n_samples"]),
            None if doc.get("core") is None else tuple(int(v) for v in doc["core"]),  # type: ignore[arg-type]
        )


@dataclass(frozen=True)
class TilePlan:
    """The tiles of one CCD image and the scale between image and reference.

    Attributes:
        ccd: CCD name.
        image_size: ``(n_lines, n_samples)``.
        image_gsd_m: Ground sampling distance of the image at its centre (m).
        ref_gsd_m: Ground sampling distance of the reference (m, geometric mean of both
            axes at the image centre).
        tiles: The tiles, row by row.
    """

    ccd: str
    image_size: tuple[int, int]
    image_gsd_m: float
    ref_gsd_m: float
    tiles: tuple[Tile, ...]

    @property
    def ratio(self) -> float:
        """Image pixels per reference pixel (about 10 for HiRIC over CTX)."""
        return self.ref_gsd_m / self.image_gsd_m


@dataclass(frozen=True)
class Footprint:
    """A tile's footprint on the reference grid through the initial camera and the DEM.

    Attributes:
        tile: The tile.
        border_px: ``(N, 2)`` reference ``(col, row)`` of the tile's border points
            (NaN where a ray missed the DEM).
        window: Full-resolution window covering the footprint (unpadded), or None when
            no border ray met the DEM.
        gsd_m: ``(along columns, along rows)`` ground size of a reference pixel there (m).
    """

    tile: Tile
    border_px: NDArray[np.float64]
    window: RefWindow | None
    gsd_m: tuple[float, float]

    def pad_px(self, metres: float) -> int:
        """A ground distance in whole reference pixels (rounded up, finer axis)."""
        return math.ceil(metres / min(self.gsd_m))


def _starts(n: int, size: int, step: int) -> list[int]:
    if n <= size:
        return [0]
    out = list(range(0, n - size, step))
    # The last tile ends on the image edge instead of sticking out of it.
    if out[-1] + size < n:
        out.append(n - size)
    return out


def _cores(starts: list[int], size: int, n: int) -> list[tuple[int, int]]:
    """The owned range of each tile: neighbours split their overlap in the middle."""
    ends = [min(s + size, n) for s in starts]
    lo = [0] + [(ends[i] + starts[i + 1]) // 2 for i in range(len(starts) - 1)]
    return list(zip(lo, [*lo[1:], n], strict=True))


def plan_tiles(
    camera: Camera, ccd: str, ref: ReferenceOrtho, terrain: Terrain, config: FrontendConfig
) -> TilePlan:
    """Partition a CCD image into tiles sized in reference pixels.

    Args:
        camera: The initial camera.
        ccd: CCD name.
        ref: The reference orthoimage.
        terrain: The reference DEM.
        config: Front-end settings (tile size and overlap in reference pixels).

    Returns:
        The plan; tile sides are ``tile_size_ref_px`` times the GSD ratio in image pixels
        (less where the image is smaller).

    Raises:
        GeometryError: If no ray of the image meets the DEM.
    """
    n_lines, n_samples = camera.image_size(ccd)
    gsd_img = image_gsd_m(camera, ccd, terrain)
    col, row = image_to_ref_pixel(camera, ccd, [n_lines / 2.0], [n_samples / 2.0], ref, terrain)
    if np.isfinite(col[0]) and np.isfinite(row[0]):
        gx, gy = ref.ground_sampling_m(float(col[0]), float(row[0]))
    else:  # the centre's ray falls in a DEM hole: the ortho's own centre will do
        gx, gy = ref.ground_sampling_m()
    gsd_ref = math.sqrt(gx * gy)
    ratio = gsd_ref / gsd_img
    size = max(16, round(config.tile_size_ref_px * ratio))
    overlap = round(config.tile_overlap_ref_px * ratio)
    step = max(1, size - overlap)
    tiles = []
    line_starts, sample_starts = _starts(n_lines, size, step), _starts(n_samples, size, step)
    line_cores, sample_cores = (
        _cores(line_starts, size, n_lines),
        _cores(sample_starts, size, n_samples),
    )
    for i, l0 in enumerate(line_starts):
        for j, s0 in enumerate(sample_starts):
            (cl0, cl1), (cs0, cs1) = line_cores[i], sample_cores[j]
            tiles.append(
                Tile(
                    f"{ccd}:r{i:03d}c{j:03d}",
                    ccd,
                    l0,
                    s0,
                    min(size, n_lines),
                    min(size, n_samples),
                    (cl0, cs0, cl1, cs1),
                )
            )
    return TilePlan(ccd, (n_lines, n_samples), gsd_img, gsd_ref, tuple(tiles))


def tile_footprint(
    camera: Camera, tile: Tile, ref: ReferenceOrtho, terrain: Terrain, points_per_edge: int = 5
) -> Footprint:
    """Project a tile's border onto the reference grid.

    Args:
        camera: The initial camera.
        tile: The tile.
        ref: The reference orthoimage.
        terrain: The reference DEM.
        points_per_edge: Points per edge (corners included).

    Returns:
        The footprint; ``window`` is None when no border ray met the DEM.
    """
    if points_per_edge < 2:
        raise InputError(f"points_per_edge must be >= 2, got {points_per_edge}")
    l0, s0, l1, s1 = tile.bounds
    t = np.linspace(0.0, 1.0, points_per_edge)
    lines = np.concatenate(
        [np.full_like(t, l0), l0 + t * (l1 - l0), np.full_like(t, l1), l1 - t * (l1 - l0)]
    )
    samples = np.concatenate(
        [s0 + t * (s1 - s0), np.full_like(t, s1), s1 - t * (s1 - s0), np.full_like(t, s0)]
    )
    col, row = image_to_ref_pixel(camera, tile.ccd, lines, samples, ref, terrain)
    border = np.column_stack([col, row])
    ok = np.all(np.isfinite(border), axis=1)
    if not ok.any():
        return Footprint(tile, border, None, ref.ground_sampling_m())
    window = RefWindow.around(col[ok].min(), row[ok].min(), col[ok].max(), row[ok].max())
    gsd = ref.ground_sampling_m(float(np.mean(col[ok])), float(np.mean(row[ok])))
    return Footprint(tile, border, window, gsd)
