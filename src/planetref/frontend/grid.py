"""The fine-stage grid: the reference grid, or a grid ``k`` times finer (``fine_upsample``).

:class:`FineWindow` is a window of the reference grid whose pixels are ``1/k`` reference
pixels; it offers what the orthorectification and the tile algorithm use of a
:class:`~planetref.raster.ortho.RefWindow` (``shape``, ``width``, ``height``, ``factor``,
``to_ref_pixel``, ``from_ref_pixel``, ``bounds_px``, ``to_tuple``), so the CCD tile can be
orthorectified straight onto it, and :func:`read_fine` resamples the reference onto it.

Coordinates: fine pixel ``(x, y)`` (corner convention, first pixel centre at 0.5) is
reference pixel ``(col0 + x / k, row0 + y / k)``.
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
    """

    base: RefWindow
    up: int = 1

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
            self.base.col0 + np.asarray(x, float) / self.up,
            self.base.row0 + np.asarray(y, float) / self.up,
        )

    def from_ref_pixel(self, col: ArrayLike, row: ArrayLike) -> tuple[F64, F64]:
        """Fine-pixel coordinates of reference ``(col, row)``."""
        return (
            (np.asarray(col, float) - self.base.col0) * self.up,
            (np.asarray(row, float) - self.base.row0) * self.up,
        )

    def to_tuple(self) -> tuple[int, int, int, int, int]:
        """The base window's ``(col0, row0, width, height, factor)``."""
        return self.base.to_tuple()


def read_fine(
    ref: ReferenceOrtho, window: FineWindow
) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """The reference resampled onto a fine window (bicubic; the window itself when ``up`` is 1).

    A fine pixel is valid when the reference pixels its bicubic kernel reaches are.

    Returns:
        ``(data, valid)`` of ``window.shape``; data float32, 0 where invalid.
    """
    if window.up == 1:
        return ref.read(window.base)
    import cv2

    b, k = window.base, window.up
    padded = RefWindow(b.col0 - _PAD, b.row0 - _PAD, b.width + 2 * _PAD, b.height + 2 * _PAD, 1)
    data, valid = ref.read(padded)
    # cv2.resize maps destination pixel centre x + 0.5 to source x' + 0.5 = (x + 0.5) / k:
    # the same corner convention as FineWindow.to_ref_pixel.
    fine = cv2.resize(data, None, fx=k, fy=k, interpolation=cv2.INTER_CUBIC)
    good = cv2.erode(valid.astype(np.uint8), np.ones((3, 3), np.uint8), borderValue=0)
    vfine = cv2.resize(good.astype(np.float32), None, fx=k, fy=k, interpolation=cv2.INTER_LINEAR)
    s = _PAD * k
    out = fine[s : s + window.height, s : s + window.width]
    ok = vfine[s : s + window.height, s : s + window.width] > 1.0 - 1e-4
    return np.where(ok, out, 0.0).astype(np.float32), ok
