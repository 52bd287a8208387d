"""Counting and distribution metrics of matched points: NCP, SDU and the funnel.

* **NCP** (number of correct points), as the paper defines it: every correspondence that
  passed the tile's verification (RANSAC, consensus, back-projection and, if it ran,
  refinement), counted *before* any thinning for speed (:func:`ncp_verified`). The
  count of MCPs written (after thinning, if on) is reported beside it.
* **Funnel**: per CCD and in total, the correspondences left after each stage of the
  front end (``raw``, ``coarse_gate``, ``ransac``, ``consensus``, ``backprojection``,
  ``refine``, ``mcp``; :data:`FUNNEL_STAGES`) and how many each stage rejected
  (:func:`funnel_table`); :func:`full_funnel` appends the adjustment's outlier rule, so
  a reader sees the way from raw matches to adjustment inliers. The adjustment's
  outlier ratio (OR) is ``rejected / all MCPs that entered the adjustment``.
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

__all__ = [
    "FUNNEL_STAGES",
    "SDU_GRIDS",
    "full_funnel",
    "funnel_of",
    "funnel_table",
    "ncp",
    "ncp_per_ccd",
    "ncp_per_tile",
    "ncp_verified",
    "sdu_per_ccd",
    "sdu_percent",
]

FUNNEL_STAGES: tuple[str, ...] = (
    "raw",
    "coarse_gate",
    "ransac",
    "consensus",
    "backprojection",
    "refine",
    "mcp",
)
"""Stages of a tile's funnel, in order (``TileResult.funnel`` keys)."""

#: Stages after which a correspondence counts as verified (the last one present wins).
_VERIFIED = ("raw", "coarse_gate", "ransac", "consensus", "backprojection", "refine")

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
        table: An :class:`~planetref.control.mcp.McpTable` or a mapping with a ``ccd`` column.
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


def funnel_of(tile: Any) -> dict[str, int]:
    """The funnel of a tile result, in stage order (missing stages were not run).

    Uses ``tile.funnel`` when the front end records it; otherwise what older tile
    results carry: ``n_matches`` (raw), ``n_inliers`` (after RANSAC) and the kept
    points (mcp).
    """
    f = getattr(tile, "funnel", None)
    if f:
        return {k: int(f[k]) for k in FUNNEL_STAGES if k in f}
    out = {"raw": int(getattr(tile, "n_matches", 0))}
    if getattr(tile, "n_inliers", None) is not None:
        out["ransac"] = int(tile.n_inliers)
    out["mcp"] = len(getattr(tile, "line", ()))
    return out


def ncp_verified(tile: Any) -> int:
    """NCP of one tile: correspondences that passed its verification, before thinning.

    ``funnel["refine"]`` if refinement ran, else the last verification stage present
    (``backprojection``, ``consensus``, ``ransac``...); 0 for a tile without a funnel.
    """
    f = funnel_of(tile)
    for k in reversed(_VERIFIED):
        if k in f:
            return f[k]
    return 0


def funnel_table(tiles: Iterable[Any]) -> dict[str, Any]:
    """Funnel counts per CCD and in total, with the rejections of each stage.

    Args:
        tiles: Tile results (anything with ``tile.ccd`` and a funnel, see
            :func:`funnel_of`), or a ``StripMatches`` (its ``tiles``).

    Returns:
        ``{"ccds": {ccd: block}, "total": block}`` where a block is ``{"stages":
        {stage: count}, "rejected": {stage: count}, "rejected_pct": {stage: percent of
        the stage's input}, "ncp_verified": n, "n_mcp": n, "thinned": n_dropped}``.
        A stage's count sums the tiles that ran it; a stage run on some tiles only
        compares with the previous stage of those tiles.
    """
    tiles = list(getattr(tiles, "tiles", tiles))
    per: dict[str, list[Any]] = {}
    for t in tiles:
        per.setdefault(str(t.tile.ccd), []).append(t)

    def block(ts: list[Any]) -> dict[str, Any]:
        stages: dict[str, int] = {}
        rejected: dict[str, int] = {}
        entered: dict[str, int] = {}
        for t in ts:
            f = funnel_of(t)
            prev = None
            for k in FUNNEL_STAGES:
                if k not in f:
                    continue
                stages[k] = stages.get(k, 0) + f[k]
                if prev is not None:
                    rejected[k] = rejected.get(k, 0) + max(prev - f[k], 0)
                    entered[k] = entered.get(k, 0) + prev
                prev = f[k]
        ncp_v = sum(ncp_verified(t) for t in ts)
        n_mcp = stages.get("mcp", 0)
        return {
            "stages": {k: stages[k] for k in FUNNEL_STAGES if k in stages},
            "rejected": {k: rejected[k] for k in FUNNEL_STAGES if k in rejected},
            "rejected_pct": {
                k: 100.0 * rejected[k] / entered[k]
                for k in FUNNEL_STAGES
                if k in rejected and entered[k] > 0
            },
            "ncp_verified": ncp_v,
            "n_mcp": n_mcp,
            "thinned": max(ncp_v - n_mcp, 0),
        }

    return {"ccds": {c: block(ts) for c, ts in sorted(per.items())}, "total": block(tiles)}


def full_funnel(funnel: dict[str, Any], n_entered: int, n_inliers: int) -> list[dict[str, Any]]:
    """The whole way from raw matches to adjustment inliers, one row per stage.

    Args:
        funnel: A block of :func:`funnel_table` (e.g. its ``"total"``).
        n_entered: MCPs that entered the adjustment (usable, not held out).
        n_inliers: Of those, inliers after the outlier rule.

    Returns:
        Rows ``{"stage", "count", "rejected", "rejected_pct"}``; the last row
        (``adjustment``) has the paper's outlier ratio
        ``(n_entered - n_inliers) / n_entered`` as ``rejected_pct``.
    """
    rows = []
    for k, n in funnel.get("stages", {}).items():
        rows.append(
            {
                "stage": k,
                "count": int(n),
                "rejected": int(funnel.get("rejected", {}).get(k, 0)),
                "rejected_pct": funnel.get("rejected_pct", {}).get(k),
            }
        )
    rej = int(n_entered) - int(n_inliers)
    rows.append(
        {
            "stage": "adjustment",
            "count": int(n_inliers),
            "rejected": rej,
            "rejected_pct": 100.0 * rej / n_entered if n_entered else float("nan"),
        }
    )
    return rows
