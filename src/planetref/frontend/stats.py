"""Counting and distribution metrics of matched points: NCP and SDU.

* **NCP** (number of correct points): the count of kept matches (MCPs), per CCD image
  and per tile.
* **SDU** (spatial distribution uniformity), as the seed defines it: for each ``s`` in
  ``{32, 64, 128}`` the image is divided into an ``s x s`` grid of equal cells (``s``
  cells along the lines and ``s`` along the samples, whatever the image's aspect
  ratio); the fraction of cells holding at least one point is taken, the fractions are
  averaged over the three grids and given in percent.

Image coordinates are ``(line, sample)`` with the top-left corner of the image at
``(0, 0)`` (first pixel centre at ``(0.5, 0.5)``); a point at ``line`` falls in grid row
``floor(line * s / n_lines)``. Points outside ``[0, n_lines) x [0, n_samples)`` or not
finite are ignored.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from planetref.errors import InputError

__all__ = ["SDU_GRIDS", "ncp", "ncp_per_ccd", "ncp_per_tile", "sdu_per_ccd", "sdu_percent"]

SDU_GRIDS: tuple[int, ...] = (32, 64, 128)
"""Grid sizes ``s`` of the SDU (cells per side)."""


def sdu_percent(
    lines: ArrayLike,
    samples: ArrayLike,
    n_lines: int,
    n_samples: int,
    grids: Sequence[int] = SDU_GRIDS,
) -> float:
    """Spatial distribution uniformity of points over an image, in percent.

    Args:
        lines: Line coordinates of the points (continuous, first pixel centre at 0.5).
        samples: Sample coordinates, same length.
        n_lines: Lines of the image.
        n_samples: Samples of the image.
        grids: Grid sizes ``s`` (``s x s`` cells each).

    Returns:
        The mean over ``grids`` of the percentage of cells with at least one point
        (0 for no point, 100 when every cell of every grid is occupied).

    Raises:
        InputError: Mismatched lengths, a non-positive image size or grid size, or no grid.
    """
    ln = np.asarray(lines, np.float64).ravel()
    sm = np.asarray(samples, np.float64).ravel()
    if ln.shape != sm.shape:
        raise InputError(f"lines and samples differ in length ({ln.size} vs {sm.size})")
    if int(n_lines) <= 0 or int(n_samples) <= 0:
        raise InputError(f"image size must be positive, got {n_lines} x {n_samples}")
    gs = [int(s) for s in grids]
    if not gs or min(gs) <= 0:
        raise InputError(f"grid sizes must be positive and at least one, got {list(grids)}")
    with np.errstate(invalid="ignore"):
        inside = (
            np.isfinite(ln)
            & np.isfinite(sm)
            & (ln >= 0)
            & (ln < n_lines)
            & (sm >= 0)
            & (sm < n_samples)
        )
    ln, sm = ln[inside], sm[inside]
    fractions = []
    for s in gs:
        # The min() guards against rounding pushing a point just below the edge to s.
        r = np.minimum((ln * s / n_lines).astype(np.int64), s - 1)
        c = np.minimum((sm * s / n_samples).astype(np.int64), s - 1)
        occupied = np.unique(r * s + c).size
        fractions.append(occupied / float(s * s))
    return 100.0 * float(np.mean(fractions))


def _column(table: Any, name: str) -> np.ndarray:
    try:
        return np.asarray(table[name])
    except (KeyError, IndexError, TypeError):
        raise InputError(f"the point table has no column {name!r}") from None


def ncp(values: Iterable[Any]) -> dict[str, int]:
    """Count points per key (e.g. the ``ccd`` or ``tile_id`` column of an MCP table)."""
    return dict(Counter(str(v) for v in values))


def ncp_per_ccd(table: Any, ccds: Sequence[str] | None = None) -> dict[str, int]:
    """NCP per CCD image of an MCP table (anything indexable by column name).

    Args:
        table: An :class:`~planetref.control.McpTable` or a mapping with a ``ccd`` column.
        ccds: CCDs to report even when they have no point (default: those present).
    """
    out = dict.fromkeys(ccds or (), 0)
    out.update(ncp(_column(table, "ccd")))
    return out


def ncp_per_tile(table: Any, tile_ids: Sequence[str] | None = None) -> dict[str, int]:
    """NCP per tile of an MCP table (``tile_id`` column); listed tiles default to 0."""
    out = dict.fromkeys(tile_ids or (), 0)
    out.update(ncp(_column(table, "tile_id")))
    return out


def sdu_per_ccd(
    table: Any, image_sizes: dict[str, tuple[int, int]], grids: Sequence[int] = SDU_GRIDS
) -> dict[str, float]:
    """SDU (percent) of the points of each CCD image.

    Args:
        table: MCP table with ``ccd``, ``line`` and ``sample`` columns.
        image_sizes: CCD name -> ``(n_lines, n_samples)``.
        grids: Grid sizes.
    """
    ccd = _column(table, "ccd").astype(str)
    line = _column(table, "line").astype(np.float64)
    sample = _column(table, "sample").astype(np.float64)
    return {
        c: sdu_percent(line[ccd == c], sample[ccd == c], nl, ns, grids)
        for c, (nl, ns) in image_sizes.items()
    }
