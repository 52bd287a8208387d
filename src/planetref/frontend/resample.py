"""Bilinear resampling of the orthorectification: lattice interpolation and block sampling.

* :func:`separable_bilinear`: a lattice (raw line or sample at nodes) at every pixel of a
  grid, separably (rows first, then columns of the result);
* :func:`bilinear_blocks`: block means and their valid fraction at fractional block
  indices, as scipy's ``map_coordinates(order=1, mode="constant")`` gives, compiled in one
  pass when numba is available (:mod:`planetref.frontend._numba_resample`; the scipy way,
  :func:`bilinear_blocks_numpy`, is its reference).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from planetref._optional import optional_module

__all__ = ["bilinear_blocks", "bilinear_blocks_numpy", "separable_bilinear"]

F64 = NDArray[np.float64]


def _linear_weights(f: F64, n: int) -> tuple[NDArray[np.intp], NDArray[np.intp], F64]:
    """Lower and upper node and the upper weight of fractional indices.

    Node indices beyond the ends are clamped to them, as scipy's ``mode="nearest"`` does.
    """
    lo = np.floor(f)
    i0 = lo.astype(np.intp)
    return np.clip(i0, 0, n - 1), np.clip(i0 + 1, 0, n - 1), f - lo


def separable_bilinear(grid: F64, fy: F64, fx: F64) -> F64:
    """Bilinear values of ``grid`` at every ``(fy[i], fx[j])`` (fractional node indices).

    Both neighbours of a point enter with their weights, so a NaN node makes every value
    around it NaN, as in scipy's ``map_coordinates(order=1, mode="nearest")``.
    """
    ny, nx = grid.shape
    y0, y1, ty = _linear_weights(fy, ny)
    x0, x1, tx = _linear_weights(fx, nx)
    rows = grid[:, x0] * (1.0 - tx) + grid[:, x1] * tx  # (ny, len(fx))
    return rows[y0] * (1.0 - ty)[:, None] + rows[y1] * ty[:, None]


def bilinear_blocks_numpy(
    block: NDArray[np.float32], valid: NDArray[np.bool_], u: F64, v: F64
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Bilinear block means and valid fractions at fractional block ``(row, col)`` indices.

    scipy's ``map_coordinates(order=1, mode="constant", cval=0)``: 0 outside the blocks'
    centres (and at NaN). The reference of the compiled twin.
    """
    finite = np.isfinite(u) & np.isfinite(v)
    coords = np.vstack([np.where(finite, u, -10.0).ravel(), np.where(finite, v, -10.0).ravel()])
    out = ndimage.map_coordinates(
        block, coords, order=1, mode="constant", cval=0.0, prefilter=False
    ).reshape(u.shape)
    vfrac = ndimage.map_coordinates(
        valid.astype(np.float32), coords, order=1, mode="constant", cval=0.0, prefilter=False
    ).reshape(u.shape)
    return out, vfrac


def bilinear_blocks(
    block: NDArray[np.float32], valid: NDArray[np.bool_], u: F64, v: F64
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """:func:`bilinear_blocks_numpy`, compiled in one pass when numba is available (same values)."""
    mod = optional_module("planetref.frontend._numba_resample", "compiled resampling")
    if mod is None:
        return bilinear_blocks_numpy(block, valid, u, v)
    out = np.empty(u.shape, np.float32)
    vfrac = np.empty(u.shape, np.float32)
    mod.bilinear_pair(
        np.ascontiguousarray(block, np.float32),
        np.ascontiguousarray(valid, np.bool_),
        np.ascontiguousarray(u, np.float64).reshape(-1),
        np.ascontiguousarray(v, np.float64).reshape(-1),
        out.reshape(-1),
        vfrac.reshape(-1),
    )
    return out, vfrac
