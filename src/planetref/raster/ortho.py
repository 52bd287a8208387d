"""Windowed reading of the reference orthoimage.

:class:`ReferenceOrtho` wraps one band of a georeferenced orthoimage (a CTX-like mosaic in a
Mars map CRS) and reads :class:`RefWindow` windows of it, at full resolution or averaged
down by an integer factor, with a validity mask.

Pixel convention
----------------
Reference pixel coordinates ``(col, row)`` are continuous with pixel ``(r, c)`` covering
``[c, c + 1) x [r, r + 1)``, so its centre is at ``(c + 0.5, r + 0.5)`` and the map
coordinates of a point are ``transform @ (col, row)`` (GDAL's "area" convention). This is
the matcher convention of :mod:`planetref.matching` (``x = col``, ``y = row``): a keypoint
``(x, y)`` found on a window maps to full-resolution reference pixels with
:meth:`RefWindow.to_ref_pixel`.
"""

from __future__ import annotations

from dataclasses import dataclass
from os import PathLike
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.errors import CrsError, InputError
from planetref.geometry.geodesy import CrsGround
from planetref.raster.image import BandReader, masked_block_mean

__all__ = ["RefWindow", "ReferenceOrtho"]


@dataclass(frozen=True)
class RefWindow:
    """A window on the reference grid, optionally coarsened.

    Attributes:
        col0: Full-resolution column of the window's left edge (integer).
        row0: Full-resolution row of the window's top edge (integer).
        width: Width in window pixels.
        height: Height in window pixels.
        factor: Each window pixel averages ``factor x factor`` reference pixels.
    """

    col0: int
    row0: int
    width: int
    height: int
    factor: int = 1

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0 or self.factor < 1:
            raise InputError(f"bad reference window {self}")

    @property
    def shape(self) -> tuple[int, int]:
        """``(height, width)`` of the window's array."""
        return (self.height, self.width)

    @property
    def bounds_px(self) -> tuple[int, int, int, int]:
        """``(col0, row0, col1, row1)`` in full-resolution reference pixels (end exclusive)."""
        return (
            self.col0,
            self.row0,
            self.col0 + self.width * self.factor,
            self.row0 + self.height * self.factor,
        )

    def to_ref_pixel(
        self, x: ArrayLike, y: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Window pixel coordinates ``(x, y)`` to full-resolution reference ``(col, row)``."""
        return (
            self.col0 + np.asarray(x, float) * self.factor,
            self.row0 + np.asarray(y, float) * self.factor,
        )

    def from_ref_pixel(
        self, col: ArrayLike, row: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Full-resolution reference ``(col, row)`` to window pixel coordinates ``(x, y)``."""
        return (
            (np.asarray(col, float) - self.col0) / self.factor,
            (np.asarray(row, float) - self.row0) / self.factor,
        )

    @classmethod
    def around(
        cls,
        col_min: float,
        row_min: float,
        col_max: float,
        row_max: float,
        pad_px: float = 0.0,
        factor: int = 1,
    ) -> RefWindow:
        """The smallest window of the given factor covering a box plus a margin.

        Args:
            col_min: Left edge of the box (full-resolution reference pixels).
            row_min: Top edge.
            col_max: Right edge.
            row_max: Bottom edge.
            pad_px: Margin added on every side (full-resolution pixels).
            factor: Coarsening factor of the window.
        """
        vals = (col_min, row_min, col_max, row_max, pad_px)
        if not all(np.isfinite(v) for v in vals):
            raise InputError(f"window box must be finite, got {vals}")
        c0 = int(np.floor(col_min - pad_px))
        r0 = int(np.floor(row_min - pad_px))
        c1 = int(np.ceil(col_max + pad_px))
        r1 = int(np.ceil(row_max + pad_px))
        w = max(1, -(-(c1 - c0) // factor))
        h = max(1, -(-(r1 - r0) // factor))
        return cls(c0, r0, w, h, factor)

    def coarsened(self, factor: int) -> RefWindow:
        """A window of the given factor covering (at least) the same area."""
        c0, r0, c1, r1 = self.bounds_px
        return RefWindow(
            c0, r0, max(1, -(-(c1 - c0) // factor)), max(1, -(-(r1 - r0) // factor)), factor
        )

    def shifted(self, dcol: float, drow: float) -> RefWindow:
        """The window moved by whole full-resolution pixels (rounded)."""
        return RefWindow(
            self.col0 + round(dcol), self.row0 + round(drow), self.width, self.height, self.factor
        )

    def padded(self, pad_px: int) -> RefWindow:
        """The window grown by ``pad_px`` full-resolution pixels on every side."""
        pad_w = -(-pad_px // self.factor)
        return RefWindow(
            self.col0 - pad_w * self.factor,
            self.row0 - pad_w * self.factor,
            self.width + 2 * pad_w,
            self.height + 2 * pad_w,
            self.factor,
        )

    def to_tuple(self) -> tuple[int, int, int, int, int]:
        """``(col0, row0, width, height, factor)`` (for serialisation)."""
        return (self.col0, self.row0, self.width, self.height, self.factor)


class ReferenceOrtho(BandReader):
    """One band of a reference orthoimage, read through windows.

    Args:
        source: Raster path, or a 2-D array (then ``transform`` and ``crs`` are required).
        transform: Affine geotransform of an array source (``rasterio.Affine`` or the six
            GDAL coefficients).
        crs: CRS of an array source (anything pyproj accepts).
        band: 1-based band of a file.
        nodata: A pixel value meaning "no data", in addition to the band's own.

    Raises:
        MissingFileError: If the path does not exist.
        UnsupportedFormatError: If GDAL cannot open it.
        CrsError: If the raster has no CRS.
        InputError: Bad band, array or transform.
    """

    def __init__(
        self,
        source: str | PathLike[str] | ArrayLike,
        *,
        transform: Any = None,
        crs: Any = None,
        band: int = 1,
        nodata: float | None = None,
    ) -> None:
        from affine import Affine

        super().__init__(source, band=band, nodata=nodata, what="reference orthoimage")
        if self._ds is not None:
            if self._ds.crs is None:
                self.close()
                raise CrsError("the reference orthoimage has no CRS", path=self.path)
            transform, crs = self._ds.transform, self._ds.crs
        elif transform is None or crs is None:
            raise InputError("an array reference needs a transform and a CRS")
        if not isinstance(transform, Affine):
            coeffs = tuple(float(v) for v in transform)
            if len(coeffs) != 6:
                raise InputError(f"transform needs 6 coefficients, got {len(coeffs)}")
            transform = Affine.from_gdal(*coeffs)
        if abs(transform.determinant) == 0:
            raise InputError(f"singular geotransform {tuple(transform)[:6]}")
        self.transform = transform
        self._inverse = ~transform
        self.ground = CrsGround(crs)
        self.crs = self.ground.crs

    def __enter__(self) -> ReferenceOrtho:
        return self

    def __repr__(self) -> str:
        return f"ReferenceOrtho({self.name!r}, rows={self._shape[0]}, cols={self._shape[1]})"

    # -- geometry ---------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, cols)``."""
        return self._shape

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)`` of the raster extent in map units."""
        rows, cols = self._shape
        pts = [self.transform @ (c, r) for c in (0, cols) for r in (0, rows)]
        xs, ys = [p[0] for p in pts], [p[1] for p in pts]
        return (min(xs), min(ys), max(xs), max(ys))

    def pixel_to_map(
        self, col: ArrayLike, row: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Continuous reference ``(col, row)`` (pixel centre at +0.5) to map ``(x, y)``."""
        t = self.transform
        col, row = np.asarray(col, float), np.asarray(row, float)
        return t.a * col + t.b * row + t.c, t.d * col + t.e * row + t.f

    def map_to_pixel(
        self, x: ArrayLike, y: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Map ``(x, y)`` to continuous reference ``(col, row)`` (pixel centre at +0.5)."""
        t = self._inverse
        x, y = np.asarray(x, float), np.asarray(y, float)
        return t.a * x + t.b * y + t.c, t.d * x + t.e * y + t.f

    def contains_pixel(self, col: ArrayLike, row: ArrayLike) -> NDArray[np.bool_]:
        """True where continuous ``(col, row)`` lies inside the raster extent."""
        col, row = np.asarray(col, float), np.asarray(row, float)
        rows, cols = self._shape
        with np.errstate(invalid="ignore"):
            return (col >= 0) & (col < cols) & (row >= 0) & (row < rows)

    def window_transform(self, window: RefWindow) -> Any:
        """The affine transform of a window's own pixel grid."""
        from affine import Affine

        return (
            self.transform
            @ Affine.translation(window.col0, window.row0)
            @ Affine.scale(window.factor)
        )

    def ground_sampling_m(
        self, col: float | None = None, row: float | None = None
    ) -> tuple[float, float]:
        """Ground size (m) of one reference pixel along columns and rows at a location.

        Map units are not ground metres away from a projection's true-scale line (e.g.
        east-west in equirectangular off its standard parallel), so the size is measured
        on the body between neighbouring pixel centres at height 0.

        Args:
            col: Column of the location (default: the raster centre).
            row: Row of the location.

        Returns:
            ``(gsd_along_columns_m, gsd_along_rows_m)``.
        """
        rows, cols = self._shape
        c = cols / 2.0 if col is None else float(col)
        r = rows / 2.0 if row is None else float(row)
        x, y = self.pixel_to_map([c, c + 1.0, c], [r, r, r + 1.0])
        xyz = self.ground.map_to_xyz(x, y, np.zeros(3))
        return (float(np.linalg.norm(xyz[1] - xyz[0])), float(np.linalg.norm(xyz[2] - xyz[0])))

    # -- reading ----------------------------------------------------------------------
    def read(
        self, window: RefWindow, min_valid_fraction: float = 0.5
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """Read a window; pixels outside the raster or without data come back invalid.

        A coarsened window averages each ``factor x factor`` block over its valid pixels
        (no-data never enters the mean).

        Args:
            window: The window.
            min_valid_fraction: With ``factor > 1``, a block needs at least this fraction
                of valid pixels to be valid.

        Returns:
            ``(data, valid)`` of shape ``window.shape``; data is float32, 0 where invalid.
        """
        f = window.factor
        data, valid = self._read_window(
            window.row0, window.col0, window.height * f, window.width * f
        )
        if f == 1:
            return data, valid
        return masked_block_mean(data, valid, f, min_valid_fraction)
