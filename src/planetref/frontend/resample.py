"""Bilinear block sampling of the orthorectification.

The lattice interpolation is :mod:`planetref.geometry.lattice`'s.


* :func:`bilinear_blocks`: block means and their valid fraction at fractional block
  indices, as scipy's ``map_coordinates(order=1, mode="constant")`` gives, compiled in one
  pass when numba is available (:mod:`planetref.frontend._numba_resample`; the scipy way,
  :func:`bilinear_blocks_numpy`, is its reference).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from planetref.arrays import F64
from planetref.runtime.optional import optional_module

__all__ = ["bilinear_blocks", "bilinear_blocks_numpy"]


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
