"""Internal GeoTIFF overviews computed while the full resolution is written.

GDAL's ``build_overviews`` reads the finished file back, decoding every tile, and
averages it in a generic loop (nodata handling); for a strip's orthoimages that was
~45 % of their time (hiric-strip: 3.8 of 8.4 CPU-s with one thread). Here each block of
rows, as it is written, is also halved into the first overview level, that one into the
next, and so on; the levels go into the file's overview directories once the full
resolution is complete.

Semantics: GDAL's ``AVERAGE``, bit for bit (tested against ``build_overviews``): a pixel
of level ``k + 1`` is the mean of the valid pixels among its 2 x 2 pixels of level ``k``
(level 0 is the full resolution; each level from the previous, rounded one, as GDAL
cascades); integer types round the mean half away from zero; a block without a valid
pixel is nodata. The width and height must be multiples of the largest factor (the
callers pad their grids): every overview pixel then covers exactly its ``2^k x 2^k``
block, as the overview's georeferencing says (GDAL stretches the last pixels otherwise).

Storage: the rows of each level go to an anonymous temporary file beside the output
(unlinked when created, so a crash leaves nothing behind) while the full resolution is
written, and are copied into the overview directories at the end
(``rasterio.open(path, "r+", overview_level=k)``); memory stays at one block of rows.
"""

from __future__ import annotations

import os
import tempfile
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["OverviewPyramid", "halve_reference", "overview_factors", "padded_size"]

#: Rows copied into an overview level per write.
_COPY_ROWS = 256


def overview_factors(width: int, height: int, min_side: int = 256) -> list[int]:
    """Factors 2, 4, 8, ... while the smaller side of the level keeps ``min_side`` pixels."""
    out, f = [], 2
    while min(width, height) // f >= min_side:
        out.append(f)
        f *= 2
    return out


def padded_size(width: int, height: int) -> tuple[int, int]:
    """``width``, ``height`` rounded up to a multiple of their largest overview factor.

    Every overview pixel then covers exactly its block of full-resolution pixels; the
    caller fills the added columns and rows with nodata. Padding can admit one more
    factor (4090 x 5000 -> 4096 x 5000 has a level at 16), so it repeats until the
    factors of the padded size divide it.
    """
    while True:
        top = max(overview_factors(width, height), default=1)
        w, h = -(-width // top) * top, -(-height // top) * top
        if (w, h) == (width, height):
            return w, h
        width, height = w, h


def halve_reference(src: NDArray[Any], nodata: float) -> NDArray[Any]:
    """The next overview level of ``src`` (even shape) in numpy; see the module doc.

    The reference of the compiled ``_ortho_kernel.halve_rows``.
    """
    h, w = src.shape
    v = src.astype(np.float64)
    ok = (v == v) & (v != nodata)
    s = np.where(ok, v, 0.0).reshape(h // 2, 2, w // 2, 2).sum(axis=(1, 3))
    n = ok.reshape(h // 2, 2, w // 2, 2).sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        m = s / n
    if not np.issubdtype(src.dtype, np.floating):
        m = np.where(m >= 0.0, np.floor(m + 0.5), -np.floor(0.5 - m))
    return np.where(n > 0, m, nodata).astype(src.dtype)


class _Level:
    """One overview level: the odd row waiting for its pair and the spooled rows."""

    def __init__(self, width: int, height: int, folder: str) -> None:
        self.width, self.height = width, height
        self.rows = 0
        self.carry: NDArray[Any] | None = None
        self.spool = tempfile.TemporaryFile(dir=folder, prefix=".planetref-ovr-")

    def take(self, rows: NDArray[Any], halve: Any) -> NDArray[Any]:
        """This level's rows made from ``rows`` of the level below (spooled, returned)."""
        if self.carry is not None:
            rows = np.concatenate([self.carry, rows], axis=0)
            self.carry = None
        n = (len(rows) // 2) * 2
        if n < len(rows):
            self.carry = rows[n:].copy()
        out = halve(rows[:n])
        if len(out):
            self.spool.write(np.ascontiguousarray(out).data)
            self.rows += len(out)
        return out


class OverviewPyramid:
    """Overview levels of one output, fed with its full-resolution rows in order.

    Args:
        width: Full-resolution width (a multiple of the largest factor).
        height: Full-resolution height (likewise).
        factors: ``[2, 4, ..., 2^n]``.
        dtype: The output's data type.
        nodata: Its nodata value (NaN for floats).
        folder: Where the temporary spool files go (the output's folder).
        kernel: The compiled kernels (``_ortho_kernel``), or None for numpy.
    """

    def __init__(
        self,
        width: int,
        height: int,
        factors: list[int],
        dtype: Any,
        nodata: float,
        folder: str | os.PathLike[str],
        kernel: Any = None,
    ) -> None:
        if factors != [2**k for k in range(1, len(factors) + 1)]:
            raise ValueError(f"overview factors must be 2, 4, 8, ...; got {factors}")
        top = factors[-1] if factors else 1
        if width % top or height % top:
            raise ValueError(f"{width} x {height} pixels is not a multiple of {top}")
        self.dtype = np.dtype(dtype)
        self.nodata = float(nodata)
        self._kernel = kernel
        self.levels = [_Level(width // f, height // f, os.fspath(folder)) for f in factors]

    def _halve(self, rows: NDArray[Any]) -> NDArray[Any]:
        if self._kernel is None:
            return halve_reference(rows, self.nodata)
        out = np.empty((len(rows) // 2, rows.shape[1] // 2), self.dtype)
        if len(out):
            is_int = not np.issubdtype(self.dtype, np.floating)
            self._kernel.halve_rows(rows, self.nodata, is_int, out)
        return out

    def push(self, rows: NDArray[Any]) -> None:
        """The next full-resolution rows (the output's type, top to bottom)."""
        x = np.asarray(rows, self.dtype)
        for level in self.levels:
            x = level.take(x, self._halve)
            if not len(x):
                break

    def write_into(self, path: str | os.PathLike[str]) -> None:
        """Copy the levels into the overview directories of the closed file ``path``.

        Raises:
            ValueError: A level did not receive all its rows (the full resolution was
                not pushed to its end).
        """
        import rasterio
        from rasterio.windows import Window

        for k, level in enumerate(self.levels):
            if level.rows != level.height or level.carry is not None:
                raise ValueError(
                    f"overview level {k + 1}: {level.rows} of {level.height} rows were made"
                )
            level.spool.seek(0)
            row_bytes = level.width * self.dtype.itemsize
            with rasterio.open(path, "r+", overview_level=k) as ovr:
                if (ovr.width, ovr.height) != (level.width, level.height):
                    raise ValueError(
                        f"overview level {k + 1} of {path} is {ovr.width} x {ovr.height}, "
                        f"not {level.width} x {level.height}"
                    )
                for r0 in range(0, level.height, _COPY_ROWS):
                    n = min(_COPY_ROWS, level.height - r0)
                    buf = level.spool.read(n * row_bytes)
                    block = np.frombuffer(buf, self.dtype).reshape(n, level.width)
                    ovr.write(block, 1, window=Window(0, r0, level.width, n))

    def close(self) -> None:
        """Release the spool files."""
        for level in self.levels:
            level.spool.close()
