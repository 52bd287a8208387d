"""The fine-stage grid: the reference grid, or a grid ``k`` times finer (``fine_upsample``).

:class:`FineWindow` is a window of the reference grid whose pixels are ``1/k`` reference
pixels; it offers what the orthorectification and the tile algorithm use of a
:class:`~planetref.raster.ortho.RefWindow` (``shape``, ``width``, ``height``, ``factor``,
``to_ref_pixel``, ``from_ref_pixel``, ``bounds_px``, ``to_tuple``), so the CCD tile can be
orthorectified straight onto it, and :func:`read_fine` resamples the reference onto it.

Coordinates: fine pixel ``(x, y)`` (corner convention, first pixel centre at 0.5) is
reference pixel ``(col0 + dcol + x / k, row0 + drow + y / k)``, with ``(dcol, drow)`` the
window's sub-pixel ``shift`` (0 but for a fine pass re-centred on a first pass's offset).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.arrays import F64
from planetref.raster.ortho import ReferenceOrtho, RefWindow

__all__ = ["FineWindow", "read_fine"]

_PAD = 2  # reference pixels read around the window for the bicubic kernel


@dataclass(frozen=True)
class FineWindow:
    """A full-resolution reference window sampled ``up`` times finer.

    Attributes:
        base: The window on the reference grid (``factor`` 1).
        up: Fine pixels per reference pixel (1: the reference grid itself).
        shift: ``(dcol, drow)`` reference px added to the base window's origin, so that
            the window can sit on an offset to a fraction of a pixel (``|shift| <= 0.5``
            in practice: the whole pixels are the base window's); the reference is then
            resampled whatever ``up`` is.
    """

    base: RefWindow
    up: int = 1
    shift: tuple[float, float] = (0.0, 0.0)

    @classmethod
    def at(cls, window: RefWindow, dcol: float, drow: float, up: int) -> FineWindow:
        """``window`` moved by ``(dcol, drow)`` reference px to a fraction of a pixel."""
        moved = window.shifted(dcol, drow)
        return cls(
            moved,
            up,
            (float(dcol) - (moved.col0 - window.col0), float(drow) - (moved.row0 - window.row0)),
        )

    @property
    def width(self) -> int:
        """Fine pixels across."""
        return self.base.width * self.up

    @property
    def height(self) -> int:
        """Fine pixels down."""
        return self.base.height * self.up

    @property
    def shape(self) -> tuple[int, int]:
        """``(height, width)`` in fine pixels."""
        return (self.height, self.width)

    @property
    def factor(self) -> float:
        """Reference pixels per fine pixel (``1 / up``)."""
        return 1.0 / self.up

    @property
    def bounds_px(self) -> tuple[int, int, int, int]:
        """``(col0, row0, col1, row1)`` on the reference grid."""
        return self.base.bounds_px

    def to_ref_pixel(self, x: ArrayLike, y: ArrayLike) -> tuple[F64, F64]:
        """Reference ``(col, row)`` of fine-pixel coordinates."""
        return (
            self.base.col0 + self.shift[0] + np.asarray(x, float) / self.up,
            self.base.row0 + self.shift[1] + np.asarray(y, float) / self.up,
        )

    def from_ref_pixel(self, col: ArrayLike, row: ArrayLike) -> tuple[F64, F64]:
        """Fine-pixel coordinates of reference ``(col, row)``."""
        return (
            (np.asarray(col, float) - self.base.col0 - self.shift[0]) * self.up,
            (np.asarray(row, float) - self.base.row0 - self.shift[1]) * self.up,
        )

    def to_tuple(self) -> tuple[int, int, int, int, int]:
        """The base window's ``(col0, row0, width, height, factor)``."""
        return self.base.to_tuple()


def _interpolate(a: F64, pos: F64, axis: int, *, cubic: bool) -> F64:
    """``a`` sampled at fractional indices ``pos`` along ``axis`` (Keys cubic or linear)."""
    i0 = np.floor(pos).astype(np.intp)
    t = pos - i0
    if cubic:
        k = -0.75  # OpenCV's INTER_CUBIC
        w = [
            ((k * (t + 1) - 5 * k) * (t + 1) + 8 * k) * (t + 1) - 4 * k,
            ((k + 2) * t - (k + 3)) * t * t + 1,
            ((k + 2) * (1 - t) - (k + 3)) * (1 - t) * (1 - t) + 1,
        ]
        w.append(1.0 - w[0] - w[1] - w[2])
        taps = range(-1, 3)
    else:
        w, taps = [1.0 - t, t], range(2)
    n = a.shape[axis]
    shape = [1, 1]
    shape[axis] = len(pos)
    out = np.zeros((*a.shape[:axis], len(pos), *a.shape[axis + 1 :]))
    for m, wm in zip(taps, w, strict=True):
        idx = np.clip(i0 + m, 0, n - 1)
        out += np.take(a, idx, axis=axis) * wm.reshape(shape)
    return out


def read_fine(
    ref: ReferenceOrtho, window: FineWindow
) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """The reference resampled onto a fine window (bicubic).

    With ``up`` 1 and no sub-pixel shift, the reference window itself. A fine pixel is
    valid when the reference pixels its bicubic kernel reaches are.

    Returns:
        ``(data, valid)`` of ``window.shape``; data float32, 0 where invalid.
    """
    shifted = window.shift != (0.0, 0.0)
    if window.up == 1 and not shifted:
        return ref.read(window.base)
    import cv2

    b, k = window.base, window.up
    padded = RefWindow(b.col0 - _PAD, b.row0 - _PAD, b.width + 2 * _PAD, b.height + 2 * _PAD, 1)
    data, valid = ref.read(padded)
    good = cv2.erode(valid.astype(np.uint8), np.ones((3, 3), np.uint8), borderValue=0)
    if shifted:
        # Exact positions: OpenCV's warps quantise them to 1/32 px, as large as the
        # sub-pixel errors this window serves to remove. The same Keys kernel (a = -0.75)
        # as cv2.resize's bicubic, so an unshifted window gives resize's values.
        value = data.astype(np.float64)
        weight = good.astype(np.float64)
        for axis, n, d in ((0, window.height, window.shift[1]), (1, window.width, window.shift[0])):
            # fine pixel j (centre at corner coordinate j + 0.5) samples the padded array
            # at index _PAD + d + (j + 0.5) / k - 0.5
            pos = _PAD + d + (np.arange(n) + 0.5) / k - 0.5
            value = _interpolate(value, pos, axis, cubic=True)
            weight = _interpolate(weight, pos, axis, cubic=False)
        inside = weight > 1.0 - 1e-4
        return np.where(inside, value, 0.0).astype(np.float32), inside
    # cv2.resize maps destination pixel centre x + 0.5 to source x' + 0.5 = (x + 0.5) / k:
    # the same corner convention as FineWindow.to_ref_pixel.
    fine = cv2.resize(data, None, fx=k, fy=k, interpolation=cv2.INTER_CUBIC)
    vfine = cv2.resize(good.astype(np.float32), None, fx=k, fy=k, interpolation=cv2.INTER_LINEAR)
    s = _PAD * k
    out = fine[s : s + window.height, s : s + window.width]
    ok = vfine[s : s + window.height, s : s + window.width] > 1.0 - 1e-4
    return np.where(ok, out, 0.0).astype(np.float32), ok
