"""Robust fits of a tile's matches: translation consensus, USAC_MAGSAC verification, thinning.

Over one tile the initial camera's error is close to a translation on the reference grid,
so true matches share (nearly) one displacement; :func:`robust_translation` finds it,
:func:`verify_points` checks the geometry with OpenCV's USAC_MAGSAC, and
:func:`spread_select` thins a set of points evenly over its extent (an option for speed;
never what a metric counts).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from planetref.arrays import F64

__all__ = ["robust_translation", "spread_select", "verify_points"]


def robust_translation(
    displacement: F64, radius: float, weights: F64 | None = None
) -> tuple[F64 | None, NDArray[np.bool_]]:
    """The dominant translation among displacement vectors (a translation consensus).

    Each displacement is a candidate; the one with the most displacements within
    ``radius`` wins (ties: the larger summed weight), and the offset is the median of its
    consensus set, refined once.

    Args:
        displacement: ``(N, 2)`` vectors (e.g. reference pixels).
        radius: Consensus radius, same unit.
        weights: Optional ``(N,)`` tie-breaking weights (e.g. confidences).

    Returns:
        ``(offset, inliers)``: the ``(2,)`` offset (None when there is no displacement)
        and the ``(N,)`` mask of displacements within ``radius`` of it.
    """
    d = np.asarray(displacement, np.float64).reshape(-1, 2)
    n = len(d)
    if n == 0:
        return None, np.zeros(0, bool)
    w = np.ones(n) if weights is None else np.asarray(weights, np.float64)
    # Candidates: every displacement up to 2000 (evenly strided beyond); chunked so the
    # pairwise distance matrix stays small.
    cand = np.arange(n) if n <= 2000 else np.linspace(0, n - 1, 2000).astype(np.intp)
    best, best_score = -1, (-1, -np.inf)
    r2 = radius * radius
    x, y = d[:, 0], d[:, 1]
    for a in range(0, len(cand), 256):
        c = cand[a : a + 256]
        # dx^2 + dy^2 per coordinate (the same sums as over a last axis of length 2,
        # without its (256, N, 2) temporaries)
        dx = x[c][:, None] - x[None, :]
        dy = y[c][:, None] - y[None, :]
        close = dx * dx + dy * dy <= r2
        counts = np.count_nonzero(close, axis=1)
        wsum = close @ w
        # The chunk's best: most neighbours, then the largest weight, then the first.
        top = np.flatnonzero(counts == counts.max())
        i = int(top[np.argmax(wsum[top])])
        score = (int(counts[i]), float(wsum[i]))
        if score > best_score:
            best, best_score = int(c[i]), score
    inl = np.sum((d - d[best]) ** 2, axis=1) <= r2
    offset = np.median(d[inl], axis=0)
    inl = np.sum((d - offset) ** 2, axis=1) <= r2
    if inl.any():
        offset = np.median(d[inl], axis=0)
    return offset, inl


def verify_points(
    points0: F64,
    points1: F64,
    model: str = "homography",
    threshold: float = 1.0,
    confidence: float = 0.999,
    max_iters: int = 10000,
) -> NDArray[np.bool_]:
    """Geometric verification of point pairs with OpenCV's USAC_MAGSAC.

    A thin layer over :func:`planetref.matching.ransac.verify_matches` that centres the
    coordinates first (reference pixels of a large mosaic are big numbers) and keeps only
    the inliers whose residual under the fitted model is within ``threshold``.

    Args:
        points0: ``(N, 2)`` points in image 0.
        points1: ``(N, 2)`` points in image 1.
        model: ``"homography"`` (needs 4 matches) or ``"affine"`` (3).
        threshold: Inlier threshold in image-1 pixels.
        confidence: RANSAC confidence.
        max_iters: Iteration cap.

    Returns:
        ``(N,)`` inlier mask; all False when there are too few matches or no model.
    """
    from planetref.matching.base import Matches
    from planetref.matching.ransac import verify_matches

    p0 = np.asarray(points0, np.float64).reshape(-1, 2)
    p1 = np.asarray(points1, np.float64).reshape(-1, 2)
    n = len(p0)
    if n == 0:
        return np.zeros(0, bool)
    c0, c1 = p0.mean(axis=0), p1.mean(axis=0)
    ver = verify_matches(
        Matches(p0 - c0, p1 - c1, np.ones(n)),
        model,  # type: ignore[arg-type]
        threshold=float(threshold),
        confidence=float(confidence),
        max_iters=int(max_iters),
    )
    if ver.matrix is None:
        return np.zeros(n, bool)
    m = np.asarray(ver.matrix, np.float64)
    if m.shape == (2, 3):
        m = np.vstack([m, [0.0, 0.0, 1.0]])
    q = np.column_stack([p0 - c0, np.ones(n)]) @ m.T
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = q[:, :2] / q[:, 2:3]
    resid = np.linalg.norm(proj - (p1 - c1), axis=1)
    return ver.inliers & (resid <= threshold)


def spread_select(line: F64, sample: F64, conf: F64, n_max: int) -> NDArray[np.intp]:
    """Up to ``n_max`` indices spread over the points' extent, best confidence first."""
    n = len(line)
    if n_max <= 0 or n <= n_max:
        return np.arange(n)
    g = max(1, int(np.ceil(np.sqrt(n_max))))

    def cell(v: F64) -> NDArray[np.intp]:
        lo, hi = float(v.min()), float(v.max())
        return np.minimum(((v - lo) / max(hi - lo, 1e-9) * g).astype(np.intp), g - 1)

    cid = cell(line) * g + cell(sample)
    order = np.lexsort((-conf, cid))
    rank = np.empty(n, np.intp)
    # Rank within the cell: round-robin over cells keeps the spread.
    sorted_cid = cid[order]
    starts = np.r_[0, np.flatnonzero(np.diff(sorted_cid)) + 1]
    run = np.arange(n) - np.repeat(starts, np.diff(np.r_[starts, n]))
    rank[order] = run
    pick = np.lexsort((-conf, rank))[:n_max]
    return np.sort(pick)
