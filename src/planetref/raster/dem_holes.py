"""Holes in a DEM (nodata cells) found when it is read: small ones filled, large refused.

A *hole* is a connected group of nodata (or NaN) cells that does not touch the raster's
edge: the DEM covers the area around it but not the cells themselves. Nodata that touches
the edge is the limit of the DEM's coverage, not a hole; it stays NaN (unknown terrain:
rays that reach it miss, see :mod:`planetref.geometry.terrain`).

Rule (never silently degrade):

* Holes of at most :attr:`DemHoles.max_hole_cells` cells, together at most
  :attr:`DemHoles.max_fraction` of the raster, are filled by harmonic interpolation
  (the smooth surface that solves Laplace's equation with the surrounding heights as
  boundary values: exact on planes, no new extremes), and a warning names the file and
  the number of cells and holes filled.
* A larger hole, or more hole cells in total, is refused with one line naming the file,
  the hole's size and position and what to do.
* ``DemHoles(fill=False)`` keeps holes as NaN (unknown terrain), e.g. to inspect them.

Filling changes only the nodata cells; every valid height is kept bit for bit.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from planetref.errors import InputError

__all__ = ["DemHoleReport", "DemHoleWarning", "DemHoles", "fill_dem_holes"]


@dataclass(frozen=True)
class DemHoles:
    """How a DEM's holes are treated when it is read.

    Attributes:
        fill: Fill small holes (True) or keep every hole as NaN (False).
        max_hole_cells: The largest hole (connected nodata cells, 8-connectivity) that is
            filled; a larger one is an error.
        max_fraction: The largest share of the raster's cells that holes may take
            together (0-1); more is an error.
    """

    fill: bool = True
    max_hole_cells: int = 64
    max_fraction: float = 0.01

    def __post_init__(self) -> None:
        if self.max_hole_cells < 0 or not 0.0 <= self.max_fraction <= 1.0:
            raise InputError(
                f"DEM hole limits must be max_hole_cells >= 0 and 0 <= max_fraction <= 1, "
                f"got {self.max_hole_cells} and {self.max_fraction}"
            )


@dataclass(frozen=True)
class DemHoleReport:
    """What :func:`fill_dem_holes` found and did.

    Attributes:
        n_holes: Number of holes (interior groups of nodata cells).
        n_cells: Cells in them.
        filled: True if they were filled.
        edge_nodata_cells: Nodata cells connected to the raster's edge (not filled).
    """

    n_holes: int
    n_cells: int
    filled: bool
    edge_nodata_cells: int


class DemHoleWarning(UserWarning):
    """Nodata holes of a DEM were filled (the message names the file and the count)."""


def fill_dem_holes(
    heights: NDArray[np.floating],
    policy: DemHoles,
    path: str | os.PathLike[str] | None = None,
) -> tuple[NDArray[np.floating], DemHoleReport]:
    """Find a DEM's holes and fill the small ones (see the module's rule).

    Args:
        heights: Heights in metres, NaN at nodata, shape ``(rows, cols)``; not modified.
        policy: The limits and whether to fill.
        path: The file the DEM came from (for the warning and errors).

    Returns:
        The heights (a copy if anything was filled; same dtype) and a report.

    Raises:
        InputError: A hole or all holes together exceed the policy's limits.
    """
    from scipy import ndimage

    nan = ~np.isfinite(heights)
    if not nan.any():
        return heights, DemHoleReport(0, 0, False, 0)
    labels, n = ndimage.label(nan, structure=np.ones((3, 3), dtype=bool))
    edge = np.unique(
        np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]).astype(np.intp)
    )
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    interior = np.ones(n + 1, dtype=bool)
    interior[0] = False
    interior[edge] = False
    edge_cells = int(sizes[edge[edge > 0]].sum())
    hole_ids = np.flatnonzero(interior)
    n_cells = int(sizes[hole_ids].sum())
    if hole_ids.size == 0:
        return heights, DemHoleReport(0, 0, False, edge_cells)
    if not policy.fill:
        return heights, DemHoleReport(int(hole_ids.size), n_cells, False, edge_cells)
    biggest = int(hole_ids[np.argmax(sizes[hole_ids])])
    if sizes[biggest] > policy.max_hole_cells:
        rows, cols = np.nonzero(labels == biggest)
        raise InputError(
            f"the DEM has a hole of {int(sizes[biggest])} nodata cells around row "
            f"{int(np.median(rows))}, column {int(np.median(cols))} (planetref fills holes "
            f"of at most {policy.max_hole_cells} cells): fill it (e.g. gdal_fillnodata.py) "
            "or use another DEM",
            path=path,
        )
    if n_cells > policy.max_fraction * heights.size:
        raise InputError(
            f"the DEM has {n_cells} nodata cells in {hole_ids.size} holes "
            f"({100.0 * n_cells / heights.size:.2f}% of it, planetref fills at most "
            f"{100.0 * policy.max_fraction:.2f}%): fill them (e.g. gdal_fillnodata.py) or "
            "use another DEM",
            path=path,
        )
    hole = interior[labels]
    out = heights.copy()
    out[hole] = _harmonic_fill(heights.astype(np.float64), hole).astype(heights.dtype)
    name = os.fspath(path) if path is not None else "the DEM"
    warnings.warn(
        f"{name}: filled {n_cells} nodata cells in {hole_ids.size} holes of the DEM by "
        "harmonic interpolation",
        DemHoleWarning,
        stacklevel=3,
    )
    return out, DemHoleReport(int(hole_ids.size), n_cells, True, edge_cells)


def _harmonic_fill(h: NDArray[np.float64], hole: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Heights of the ``hole`` cells that solve Laplace's equation (4-neighbour stencil).

    Every hole cell is interior (not on the raster's edge), so all four neighbours exist;
    neighbours outside the hole are known heights (boundary values).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import spsolve

    rows, cols = np.nonzero(hole)
    n = rows.size
    index = np.full(h.shape, -1, dtype=np.intp)
    index[rows, cols] = np.arange(n)
    ii, jj, vv = [np.arange(n)], [np.arange(n)], [np.full(n, 4.0)]
    rhs = np.zeros(n)
    for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        nr, nc = rows + dr, cols + dc
        k = index[nr, nc]
        inside = k >= 0
        ii.append(np.flatnonzero(inside))
        jj.append(k[inside])
        vv.append(np.full(int(inside.sum()), -1.0))
        rhs[~inside] += h[nr[~inside], nc[~inside]]
    a = coo_matrix((np.concatenate(vv), (np.concatenate(ii), np.concatenate(jj))), (n, n))
    return np.asarray(spsolve(a.tocsc(), rhs), dtype=np.float64)
