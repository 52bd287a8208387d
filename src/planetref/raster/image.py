"""Windowed reading of CCD images with no-data masking.

A :class:`CcdImage` reads rectangular windows of one band of a raw (not map-projected)
CCD image, from any raster GDAL reads (GeoTIFF, ISIS3 cube, PDS) or from an in-memory
array, and returns the pixels as float32 together with a boolean validity mask.

Pixel convention
----------------
Windows are addressed by integer ``(line0, sample0)`` (the index of the first line and
sample read) and a size. Continuous image coordinates follow
:mod:`planetref.camera.base`: pixel ``(i, j)`` covers ``[i, i + 1) x [j, j + 1)`` in
``(line, sample)``, so its centre is ``(i + 0.5, j + 0.5)``.

No data
-------
A pixel is invalid when it is

* outside the image (windows may extend beyond it; such pixels read as 0),
* equal to the band's GDAL nodata value, or to an explicitly given nodata value,
* not finite (NaN, +-inf),
* an ISIS special pixel (NULL, LRS, LIS, HIS, HRS). For floating-point data the ISIS
  special values (all below ``-3.4028e38`` for 4-byte reals) are always masked: no real
  radiance takes them. For integer data they are masked for ISIS cubes, or when
  ``isis_special=True``.

Invalid pixels are set to 0 in the returned data; never use them without the mask.
"""

from __future__ import annotations

import functools
import warnings
from collections import OrderedDict
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.errors import InputError, MissingFileError, UnsupportedFormatError

__all__ = ["ISIS_VALID_RANGE", "BandReader", "CcdImage", "isis_valid_mask", "masked_block_mean"]

# Smallest valid 4- and 8-byte reals of ISIS (VALID_MIN4 = 0xFF7FFFFA, VALID_MIN8 =
# 0xFFEFFFFFFFFFFFFA); every special pixel value lies below them.
_VALID_MIN4 = float(np.array([0xFF7FFFFA], dtype=np.uint32).view(np.float32)[0])
_VALID_MIN8 = float(np.array([0xFFEFFFFFFFFFFFFA], dtype=np.uint64).view(np.float64)[0])

ISIS_VALID_RANGE: dict[str, tuple[float, float]] = {
    "uint8": (1.0, 254.0),
    "int16": (-32752.0, 32767.0),
    "uint16": (3.0, 65522.0),
    "float32": (_VALID_MIN4, float(np.finfo(np.float32).max)),
    "float64": (_VALID_MIN8, float(np.finfo(np.float64).max)),
}
"""Inclusive range of valid (non-special) pixel values per ISIS pixel type."""

_ISIS_DRIVERS = frozenset({"ISIS3", "ISIS2", "PDS", "PDS4"})


def isis_valid_mask(
    data: NDArray[Any], dtype: np.dtype[Any] | str | None = None
) -> NDArray[np.bool_]:
    """True where ``data`` holds no ISIS special pixel value.

    Args:
        data: Pixel values as stored (any numeric dtype).
        dtype: The storage type whose special values apply (default: ``data.dtype``).
            Types without ISIS special pixels give an all-True mask.

    Returns:
        Boolean array of ``data.shape``.
    """
    name = np.dtype(dtype if dtype is not None else data.dtype).name
    rng = ISIS_VALID_RANGE.get(name)
    if rng is None:
        return np.ones(data.shape, dtype=bool)
    lo, hi = rng
    with np.errstate(invalid="ignore"):
        return (data >= lo) & (data <= hi)


def _block_sums(d: NDArray[np.float32], factor: int) -> NDArray[np.float64]:
    """Block means of ``d`` over ``factor x factor`` blocks, zero-padded at the bottom/right.

    The blocks that lie wholly in ``d`` are averaged in place (an OpenCV view, no copy); only
    a trailing partial row or column of blocks is padded with zeros (so its mean is its sum
    over ``factor**2``).
    """
    import cv2

    h, w = d.shape
    hb, wb = -(-h // factor), -(-w // factor)
    hf, wf = h // factor, w // factor
    out = np.zeros((hb, wb))

    def area(a: NDArray[np.float32]) -> NDArray[np.float64]:
        # INTER_AREA with an integer factor is the exact block mean, computed in float32
        # by OpenCV much faster than numpy reductions.
        ph, pw = (-a.shape[0]) % factor, (-a.shape[1]) % factor
        if ph or pw:
            a = np.pad(a, ((0, ph), (0, pw)))
        size = (a.shape[1] // factor, a.shape[0] // factor)
        return cv2.resize(a, size, interpolation=cv2.INTER_AREA).astype(np.float64)

    if hf and wf:
        out[:hf, :wf] = area(d[: hf * factor, : wf * factor])
    if hb > hf:
        out[hf:, :] = area(d[hf * factor :, :])
    if wb > wf and hf:
        out[:hf, wf:] = area(d[: hf * factor, wf * factor :])
    return out


@functools.cache
def _unit_block(factor: int) -> bool:
    """Whether OpenCV's area mean of a ``factor x factor`` block of ones is exactly 1."""
    return bool(_block_sums(np.ones((factor, factor), np.float32), factor)[0, 0] == 1.0)


def masked_block_mean(
    data: NDArray[np.floating],
    valid: NDArray[np.bool_],
    factor: int,
    min_valid_fraction: float = 0.5,
) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """Average non-overlapping ``factor x factor`` blocks over their valid pixels only.

    Invalid pixels never enter the mean (so no-data cannot bias the statistics). A
    trailing partial block (when a side is not a multiple of ``factor``) is averaged over
    the pixels it has.

    Args:
        data: 2-D array.
        valid: Validity mask of the same shape.
        factor: Block side in pixels (1 returns the input as float32).
        min_valid_fraction: A block is valid when at least this fraction of its pixels is.

    Returns:
        ``(mean, valid)`` of shape ``ceil(shape / factor)``; invalid blocks hold 0.
    """
    if factor < 1:
        raise InputError(f"block factor must be >= 1, got {factor}")
    if factor == 1:
        return np.where(valid, data, 0).astype(np.float32), valid.copy()
    h, w = data.shape
    hb, wb = -(-h // factor), -(-w // factor)
    all_valid = bool(valid.all())
    hf, wf = h // factor, w // factor
    if (
        all_valid
        and data.dtype == np.float32
        and hf
        and wf
        and _unit_block(factor)
        and min_valid_fraction <= 1.0 + 1e-6
    ):
        # Whole blocks of valid pixels: their count is exactly 1, so their mean is the
        # area resize itself (the float64 division below by 1.0 returns it unchanged);
        # only a trailing partial row or column of blocks takes the general way.
        import cv2

        mean = np.empty((hb, wb), np.float32)
        ok = np.ones((hb, wb), bool)
        mean[:hf, :wf] = cv2.resize(
            data[: hf * factor, : wf * factor], (wf, hf), interpolation=cv2.INTER_AREA
        )
        if hb > hf:
            mean[hf:], ok[hf:] = masked_block_mean(
                data[hf * factor :], valid[hf * factor :], factor, min_valid_fraction
            )
        if wb > wf:
            mean[:hf, wf:], ok[:hf, wf:] = masked_block_mean(
                data[: hf * factor, wf * factor :],
                valid[: hf * factor, wf * factor :],
                factor,
                min_valid_fraction,
            )
        return mean, ok
    if all_valid and data.dtype == np.float32:
        d = data  # nothing to zero: no copy
    else:
        d = np.where(valid, data, 0).astype(np.float32)
    s = _block_sums(d, factor)
    if all_valid:
        # Every whole block has the validity mean of a block of ones (1 or within an ulp
        # of it in float32); only the trailing partial blocks need their own resize.
        n = np.full((hb, wb), _block_sums(np.ones((factor, factor), np.float32), factor)[0, 0])
        if hb * factor != h or wb * factor != w:
            ones = np.ones((h - (hb - 1) * factor, w), np.float32)
            n[-1:] = _block_sums(ones, factor)
            ones = np.ones((h, w - (wb - 1) * factor), np.float32)
            n[:, -1:] = _block_sums(ones, factor)
    else:
        n = _block_sums(valid.astype(np.float32), factor)
    # The pixels a trailing block really has, for its valid fraction.
    rows = np.minimum(factor, h - np.arange(hb) * factor)
    cols = np.minimum(factor, w - np.arange(wb) * factor)
    size = rows[:, None] * cols[None, :] / float(factor * factor)
    ok = (n > 1e-6 / factor**2) & (n >= min_valid_fraction * size - 1e-6)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(ok, s / np.maximum(n, 1e-12), 0.0)
    return mean.astype(np.float32), ok


class BandReader:
    """One band of a raster (file or array) read through windows, with a validity mask.

    The common machinery of :class:`CcdImage` and
    :class:`~planetref.raster.ortho.ReferenceOrtho`: opening, the no-data rules of this
    module, and boundless integer windows.

    Args:
        source: A raster path (anything GDAL opens) or a 2-D array (kept by reference).
        band: 1-based band index of a file.
        nodata: A pixel value meaning "no data", in addition to the band's own nodata.
        isis_special: Mask ISIS special pixels of integer data. ``None`` (default):
            only for ISIS/PDS files.
        name: A label for messages (default: the path or ``"<array>"``).
        what: What the raster is, for messages ("CCD image"...).

    Raises:
        MissingFileError: If the path does not exist.
        UnsupportedFormatError: If GDAL cannot open it.
        InputError: If the band does not exist or an array is not 2-D numeric.
    """

    def __init__(
        self,
        source: str | PathLike[str] | ArrayLike,
        *,
        band: int = 1,
        nodata: float | None = None,
        isis_special: bool | None = None,
        name: str | None = None,
        what: str = "raster",
    ) -> None:
        self._ds: Any = None
        self._array: NDArray[Any] | None = None
        self.band = int(band)
        self.path: Path | None = None
        self._nodata: list[float] = []
        if nodata is not None and np.isfinite(nodata):
            self._nodata.append(float(nodata))
        if isinstance(source, str | PathLike):
            import rasterio
            from rasterio.errors import NotGeoreferencedWarning, RasterioIOError

            self.path = Path(source)
            if not self.path.exists():
                raise MissingFileError(f"{what} not found", path=self.path)
            try:
                # Raw CCD images have no geotransform; that is expected, not a warning.
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", NotGeoreferencedWarning)
                    self._ds = rasterio.open(self.path)
            except RasterioIOError as exc:
                raise UnsupportedFormatError(
                    f"cannot read raster ({exc})", path=self.path
                ) from None
            if not 1 <= self.band <= self._ds.count:
                n = self._ds.count
                self.close()
                raise InputError(f"band {band} does not exist (the file has {n})", path=self.path)
            own = self._ds.nodatavals[self.band - 1]
            if own is not None and np.isfinite(own):
                self._nodata.append(float(own))
            self.dtype = np.dtype(self._ds.dtypes[self.band - 1])
            self._shape = (int(self._ds.height), int(self._ds.width))
            driver = str(self._ds.driver)
            self.name = name or str(self.path)
        else:
            arr = np.asarray(source)
            if arr.ndim != 2 or not (
                np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)
            ):
                raise InputError(
                    f"a {what} array must be 2-D numeric, got shape "
                    f"{arr.shape} and dtype {arr.dtype}"
                )
            self._array = arr
            self.dtype = arr.dtype
            self._shape = (int(arr.shape[0]), int(arr.shape[1]))
            driver = ""
            self.name = name or "<array>"
        self._isis = (driver in _ISIS_DRIVERS) if isis_special is None else bool(isis_special)

    def close(self) -> None:
        """Close the underlying file (no-op for arrays)."""
        if self._ds is not None:
            self._ds.close()
            self._ds = None

    def __enter__(self) -> Any:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def nodata_values(self) -> tuple[float, ...]:
        """The explicit no-data values that are masked (besides NaN and ISIS specials)."""
        return tuple(self._nodata)

    def _valid(self, raw: NDArray[Any]) -> NDArray[np.bool_]:
        valid = np.ones(raw.shape, dtype=bool)
        if np.issubdtype(raw.dtype, np.floating):
            valid &= np.isfinite(raw)
            valid &= isis_valid_mask(raw)
        elif self._isis:
            valid &= isis_valid_mask(raw)
        for nd in self._nodata:
            valid &= raw != nd
        return valid

    def _raw(self, r0: int, c0: int, r1: int, c1: int) -> NDArray[Any]:
        """The stored pixels of rows ``[r0, r1)``, columns ``[c0, c1)`` (inside the raster)."""
        if self._array is not None:
            return self._array[r0:r1, c0:c1]
        from rasterio.windows import Window

        return self._ds.read(self.band, window=Window(c0, r0, c1 - c0, r1 - r0))

    def _read_window(
        self, row0: int, col0: int, height: int, width: int
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """Rows ``row0 + [0, height)``, columns ``col0 + [0, width)``; outside: invalid."""
        row0, col0, height, width = int(row0), int(col0), int(height), int(width)
        if height <= 0 or width <= 0:
            raise InputError(f"window size must be positive, got {height} x {width}")
        rows, cols = self._shape
        r0, r1 = max(row0, 0), min(row0 + height, rows)
        c0, c1 = max(col0, 0), min(col0 + width, cols)
        if (r0, c0, r1, c1) == (row0, col0, row0 + height, col0 + width):
            # Wholly inside: the converted pixels are the output (no zeroed copy).
            raw = self._raw(r0, c0, r1, c1)
            v = self._valid(raw)
            with np.errstate(invalid="ignore", over="ignore"):
                data = raw if v.all() else np.where(v, raw, 0)
                return data.astype(np.float32), v
        out = np.zeros((height, width), np.float32)
        valid = np.zeros((height, width), bool)
        if r0 >= r1 or c0 >= c1:
            return out, valid
        raw = self._raw(r0, c0, r1, c1)
        v = self._valid(raw)
        dst = (slice(r0 - row0, r1 - row0), slice(c0 - col0, c1 - col0))
        with np.errstate(invalid="ignore", over="ignore"):
            out[dst] = raw if v.all() else np.where(v, raw, 0)
        valid[dst] = v
        return out, valid


class CcdImage(BandReader):
    """One band of a raw CCD image, read through windows.

    Args:
        source: A raster path (anything GDAL opens) or a 2-D array (kept by reference).
        band: 1-based band index of a file.
        nodata: A pixel value meaning "no data", in addition to the band's own nodata.
        isis_special: Mask ISIS special pixels of integer data. ``None`` (default):
            only for ISIS/PDS files.
        name: A label for messages (default: the path or ``"<array>"``).

    Raises:
        MissingFileError: If the path does not exist.
        UnsupportedFormatError: If GDAL cannot open it.
        InputError: If the band does not exist or an array is not 2-D numeric.
    """

    def __init__(
        self,
        source: str | PathLike[str] | ArrayLike,
        *,
        band: int = 1,
        nodata: float | None = None,
        isis_special: bool | None = None,
        name: str | None = None,
    ) -> None:
        super().__init__(
            source, band=band, nodata=nodata, isis_special=isis_special, name=name, what="CCD image"
        )
        # Block means of bands of whole block rows, per (factor, min_valid_fraction), least
        # recently used first; see read_block_mean_cached.
        self._bands: OrderedDict[tuple[int, float, int], tuple[NDArray[Any], NDArray[Any]]] = (
            OrderedDict()
        )
        self._band_pixels = 0
        # Decoded raw lines (the file's own dtype) in bands of whole lines, least recently
        # used first; see _raw_lines.
        self._raw_bands: OrderedDict[int, NDArray[Any]] = OrderedDict()
        self._raw_bytes = 0
        #: Caches that belong with this reader (e.g. the front end's orthorectification
        #: lattices), keyed by their owner; they live and die with the reader.
        self.caches: dict[Any, Any] = {}

    def __enter__(self) -> CcdImage:
        return self

    def __repr__(self) -> str:
        return f"CcdImage({self.name!r}, lines={self._shape[0]}, samples={self._shape[1]})"

    @property
    def shape(self) -> tuple[int, int]:
        """``(n_lines, n_samples)``."""
        return self._shape

    def read(
        self, line0: int, sample0: int, n_lines: int, n_samples: int
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """Read a window; parts outside the image come back invalid.

        Args:
            line0: First line (integer index, may be negative).
            sample0: First sample (may be negative).
            n_lines: Number of lines (> 0).
            n_samples: Number of samples (> 0).

        Returns:
            ``(data, valid)``, both ``(n_lines, n_samples)``; data is float32 with 0 at
            invalid pixels.
        """
        return self._read_window(line0, sample0, n_lines, n_samples)

    def read_block_mean(
        self,
        line0: int,
        sample0: int,
        n_lines: int,
        n_samples: int,
        factor: int,
        min_valid_fraction: float = 0.5,
        max_pixels: int = 1 << 22,
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """Read a window averaged over ``factor x factor`` blocks of valid pixels.

        The window is read in strips of whole block rows of at most about ``max_pixels``
        raw pixels, so memory stays bounded whatever the factor and the window size.

        Args:
            line0: First line of the window (integer, may be negative).
            sample0: First sample.
            n_lines: Lines of the window.
            n_samples: Samples of the window.
            factor: Block side in raw pixels.
            min_valid_fraction: See :func:`masked_block_mean`.
            max_pixels: Raw pixels per strip.

        Returns:
            ``(mean, valid)`` of shape ``ceil((n_lines, n_samples) / factor)``; block
            ``(i, j)`` covers raw lines ``line0 + [i k, (i + 1) k)``.
        """
        return self._block_mean(
            line0, sample0, n_lines, n_samples, factor, min_valid_fraction, max_pixels, self.read
        )

    @staticmethod
    def _block_mean(
        line0: int,
        sample0: int,
        n_lines: int,
        n_samples: int,
        factor: int,
        min_valid_fraction: float,
        max_pixels: int,
        read: Any,
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """:meth:`read_block_mean` with the window reader ``read(line0, sample0, n, m)``."""
        k = int(factor)
        if k < 1:
            raise InputError(f"block factor must be >= 1, got {factor}")
        hb, wb = -(-int(n_lines) // k), -(-int(n_samples) // k)
        out = np.zeros((hb, wb), np.float32)
        ok = np.zeros((hb, wb), bool)
        rows_per_strip = max(1, int(max_pixels) // max(1, int(n_samples) * k))
        for i in range(0, hb, rows_per_strip):
            j = min(hb, i + rows_per_strip)
            n = min(int(n_lines) - i * k, (j - i) * k)
            data, valid = read(line0 + i * k, sample0, n, n_samples)
            out[i:j], ok[i:j] = masked_block_mean(data, valid, k, min_valid_fraction)
        return out, ok

    #: Block rows per cached band of :meth:`read_block_mean_cached`.
    BAND_ROWS = 64
    #: Most block pixels :meth:`read_block_mean_cached` keeps per reader (5 bytes each: ~40 MB).
    MAX_CACHED_PIXELS = 1 << 23
    #: Raw lines per decoded band of :meth:`read_block_mean_cached` (rounded up to whole
    #: blocks of the file).
    RAW_BAND_LINES = 512
    #: Most bytes of decoded raw lines :meth:`read_block_mean_cached` keeps per reader.
    MAX_RAW_BYTES = 32 << 20

    def read_block_mean_cached(
        self,
        line0: int,
        sample0: int,
        n_lines: int,
        n_samples: int,
        factor: int,
        min_valid_fraction: float = 0.5,
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """:meth:`read_block_mean` on the image's own block grid, from a cache of block rows.

        The image is averaged once per factor, in bands of :attr:`BAND_ROWS` block rows
        over the whole width (the blocks of ``(0, 0)``-anchored ``factor x factor`` cells,
        the last row and column partial where the image ends), read when first needed and
        kept while they fit :attr:`MAX_CACHED_PIXELS`: one decimated level per factor (the
        coarse and the fine stages' pre-filters), built once per reader. The raw lines
        under them are decoded once for all factors (:attr:`RAW_BAND_LINES` lines at a
        time, kept while they fit :attr:`MAX_RAW_BYTES`). Windows that start on the block grid
        get the same blocks as :meth:`read_block_mean` of the same window, except that a
        block the window cuts short is whole here; other windows are read directly.

        Returns:
            ``(mean, valid)`` of shape ``ceil((n_lines, n_samples) / factor)``; blocks
            outside the image are invalid.
        """
        k = int(factor)
        if k < 1:
            raise InputError(f"block factor must be >= 1, got {factor}")
        if line0 % k or sample0 % k:
            return self.read_block_mean(line0, sample0, n_lines, n_samples, k, min_valid_fraction)
        hb, wb = -(-int(n_lines) // k), -(-int(n_samples) // k)
        out = np.zeros((hb, wb), np.float32)
        ok = np.zeros((hb, wb), bool)
        rows, cols = self._shape
        nbr, nbc = -(-rows // k), -(-cols // k)
        bi0, bj0 = line0 // k, sample0 // k
        i0, i1 = max(bi0, 0), min(bi0 + hb, nbr)
        j0, j1 = max(bj0, 0), min(bj0 + wb, nbc)
        if i0 >= i1 or j0 >= j1:
            return out, ok
        n = self.BAND_ROWS
        for b in range(i0 // n, (i1 - 1) // n + 1):
            data, valid = self._band(k, float(min_valid_fraction), b)
            a0, a1 = max(i0, b * n), min(i1, (b + 1) * n)
            dst = slice(a0 - bi0, a1 - bi0), slice(j0 - bj0, j1 - bj0)
            src = slice(a0 - b * n, a1 - b * n), slice(j0, j1)
            out[dst], ok[dst] = data[src], valid[src]
        return out, ok

    def _band(self, k: int, frac: float, b: int) -> tuple[NDArray[Any], NDArray[Any]]:
        key = (k, frac, b)
        hit = self._bands.get(key)
        if hit is not None:
            self._bands.move_to_end(key)
            return hit
        rows, cols = self._shape
        l0 = b * self.BAND_ROWS * k
        n = min(rows - l0, self.BAND_ROWS * k)
        got = self._block_mean(l0, 0, n, cols, k, frac, 1 << 22, self._read_lines)
        self._bands[key] = got
        self._band_pixels += got[0].size
        while self._band_pixels > self.MAX_CACHED_PIXELS and len(self._bands) > 1:
            _, old = self._bands.popitem(last=False)
            self._band_pixels -= old[0].size
        return got

    def _read_lines(
        self, line0: int, sample0: int, n_lines: int, n_samples: int
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """:meth:`read` of whole lines inside the image, from the decoded-line cache."""
        raw = self._raw_lines(int(line0), int(line0) + int(n_lines))
        v = self._valid(raw)
        # The conversion of _read_window's window wholly inside the image.
        with np.errstate(invalid="ignore", over="ignore"):
            data = raw if v.all() else np.where(v, raw, 0)
            return data.astype(np.float32), v

    def _raw_lines(self, l0: int, l1: int) -> NDArray[Any]:
        """Stored pixels of lines ``[l0, l1)``, whole width, each band decoded once."""
        rows, cols = self._shape
        if self._array is not None:
            return self._raw(l0, 0, l1, cols)
        block_h = int(self._ds.block_shapes[self.band - 1][0]) or 1
        h = -(-self.RAW_BAND_LINES // block_h) * block_h
        parts = []
        for b in range(l0 // h, (l1 - 1) // h + 1):
            band = self._raw_bands.get(b)
            if band is None:
                band = self._raw(b * h, 0, min(rows, (b + 1) * h), cols)
                self._raw_bands[b] = band
                self._raw_bytes += band.nbytes
            else:
                self._raw_bands.move_to_end(b)
            parts.append(band[max(l0, b * h) - b * h : min(l1, (b + 1) * h) - b * h])
        while self._raw_bytes > self.MAX_RAW_BYTES and len(self._raw_bands) > 1:
            _, old = self._raw_bands.popitem(last=False)
            self._raw_bytes -= old.nbytes
        return parts[0] if len(parts) == 1 else np.concatenate(parts)
