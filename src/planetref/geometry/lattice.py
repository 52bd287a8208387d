"""Bilinear interpolation of a lattice of projected nodes (raw line or sample at nodes).

One implementation for every lattice of the package: the front end's orthorectified tiles
(:class:`planetref.frontend.orthorectify.OrthoTile`) and the orthoimages
(:mod:`planetref.products.orthoimage`, whose compiled twin is
:mod:`planetref.products._numba_ortho`).

* :func:`lattice_cell`: positions in lattice units (node ``i`` at ``i``) -> cell and
  fraction, linear extrapolation beyond the end nodes;
* :func:`bilinear_lattice`: the lattice at every (row, column) of a grid, separably:
  along the first axis first, then along the second (``a (1 - f) + b f`` each time).

NaN rule: a value is NaN exactly when a node with a non-zero weight is NaN, so a position
on a node (or on a lattice line) beside a NaN node keeps the node's (line's) value.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from planetref.arrays import F64

__all__ = ["bilinear_lattice", "lattice_cell", "lerp"]


def lattice_cell(pos: F64, n: int) -> tuple[NDArray[np.intp], F64]:
    """Lattice cell ``i0`` and fraction ``f`` of positions in lattice units (0..n-1).

    Positions beyond the lattice fall in its first or last cell, with ``f < 0`` or
    ``f > 1`` (linear extrapolation); the last node is the last cell's ``f = 1``.
    """
    i0 = np.clip(np.floor(pos).astype(np.intp), 0, max(0, n - 2))
    return i0, pos - i0


def lerp(a: F64, b: F64, f: F64) -> F64:
    """``a (1 - f) + b f``; a zero weight ignores its end, so a NaN there does not spread."""
    out = a * (1.0 - f) + b * f
    on_a, on_b = f == 0.0, f == 1.0
    if on_a.any() or on_b.any():
        out = np.where(on_a, a, np.where(on_b, b, out))
    return out


def bilinear_lattice(lat: F64, ir: NDArray[np.intp], fr: F64, ic: NDArray[np.intp], fc: F64) -> F64:
    """Bilinear interpolation of a lattice at rows ``(ir, fr)`` and columns ``(ic, fc)``.

    Separable, along the rows first, then along the columns: the value at row
    ``r = ir + fr`` and column ``c = ic + fc`` (from :func:`lattice_cell`) is
    ``sum w_r w_c lat`` over the cell's four nodes, with ``w_r`` = ``1 - fr`` and ``fr``,
    ``w_c`` likewise (linear extrapolation outside the lattice). NaN semantics: the value
    is NaN exactly when a node with a non-zero weight is NaN, so a position on a node (or
    on a lattice line) next to a NaN node keeps the node's (line's) value; a lattice of
    one row or column is constant along it. (Columns first: pass ``lat.T`` and swap the
    row and column arguments, then transpose the result.)

    Args:
        lat: Lattice values, ``(n_r, n_c)``.
        ir: Cell row of each output row, ``(R,)``.
        fr: Fraction within the cell, ``(R,)``.
        ic: Cell column of each output column, ``(C,)``.
        fc: Fraction within the cell, ``(C,)``.

    Returns:
        ``(R, C)`` values.
    """
    if lat.shape[0] == 1:
        tmp = lat[np.zeros_like(ir)]
    else:
        tmp = lerp(lat[ir], lat[ir + 1], fr[:, None])
    if lat.shape[1] == 1:
        return tmp[:, np.zeros_like(ic)]
    return lerp(tmp[:, ic], tmp[:, ic + 1], fc[None, :])
