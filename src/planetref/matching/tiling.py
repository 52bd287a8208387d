"""Matching large images tile by tile, and merging the results.

Tiles are taken at the same pixel window in both images, which assumes the two images are
roughly aligned (e.g. map-projected on the same grid, or an image against an orthoimage
resampled to its footprint); the overlap between tiles must exceed the largest expected
displacement for matches near tile borders to survive.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.errors import InputError
from planetref.matching.base import MIN_SIDE, Matcher, Matches

__all__ = ["deduplicate", "match_tiled", "tile_windows"]


def tile_windows(
    shape: tuple[int, int], tile_size: int, overlap: int
) -> Iterator[tuple[int, int, int, int]]:
    """Yield ``(row0, col0, rows, cols)`` windows covering ``shape`` with overlap.

    Args:
        shape: ``(H, W)`` pixels.
        tile_size: Tile side, pixels.
        overlap: Overlap between neighbouring tiles, pixels (``< tile_size``).
    """
    if tile_size <= 0 or not 0 <= overlap < tile_size:
        raise InputError(f"need tile_size > overlap >= 0, got {tile_size}, {overlap}")
    step = tile_size - overlap

    def starts(n: int) -> list[int]:
        if n <= tile_size:
            return [0]
        out = list(range(0, n - tile_size, step))
        out.append(n - tile_size)  # last tile flush with the edge
        return out

    h, w = shape
    for r in starts(h):
        for c in starts(w):
            yield r, c, min(tile_size, h - r), min(tile_size, w - c)


def deduplicate(matches: Matches, radius: float = 0.5) -> Matches:
    """Drop near-duplicate matches, keeping the most confident one of each group.

    Two matches are duplicates when their ``(x0, y0, x1, y1)`` lie within ``radius``.

    Args:
        matches: Matches, pixels.
        radius: Distance in the 4-D ``(x0, y0, x1, y1)`` space, pixels.

    Returns:
        The surviving matches, ordered by decreasing confidence.
    """
    if len(matches) < 2:
        return matches
    from scipy.spatial import cKDTree

    order = np.argsort(-matches.confidence, kind="stable")
    pts = np.column_stack([matches.keypoints0, matches.keypoints1])[order]
    # Greedy in confidence order: a match survives unless a more confident survivor lies
    # within the radius. Only the close pairs need visiting (in order of their first one).
    pairs = cKDTree(pts).query_pairs(radius, output_type="ndarray")
    removed = np.zeros(len(pts), bool)
    if len(pairs):
        pairs = np.sort(pairs, axis=1)
        for i, j in pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))].tolist():
            if not removed[i]:
                removed[j] = True
    return matches.select(order[~removed])


def match_tiled(
    matcher: Matcher,
    image0: ArrayLike,
    image1: ArrayLike,
    mask0: ArrayLike | None = None,
    mask1: ArrayLike | None = None,
    *,
    tile_size: int = 1024,
    overlap: int = 128,
    dedup_radius: float = 0.5,
) -> Matches:
    """Match two images whole, or tile by tile when either exceeds ``tile_size``.

    Args:
        matcher: Any :class:`~planetref.matching.base.Matcher`.
        image0: 2-D array.
        image1: 2-D array on (roughly) the same pixel grid.
        mask0: Valid-pixel mask of ``image0`` or ``None``.
        mask1: Valid-pixel mask of ``image1`` or ``None``.
        tile_size: Tile side, pixels.
        overlap: Overlap between tiles, pixels.
        dedup_radius: Matches found twice in overlaps closer than this (pixels) are merged.

    Returns:
        Matches in full-image pixel coordinates (first pixel centre at ``(0.5, 0.5)``).
    """
    a0: NDArray = np.asanyarray(image0)
    a1: NDArray = np.asanyarray(image1)
    if a0.ndim != 2 or a1.ndim != 2:
        raise InputError(f"images must be 2-D, got shapes {a0.shape} and {a1.shape}")
    m0 = None if mask0 is None else np.asarray(mask0)
    m1 = None if mask1 is None else np.asarray(mask1)
    if max(a0.shape + a1.shape) <= tile_size:
        return matcher.match(a0, a1, m0, m1)
    parts = []
    for r, c, nr, nc in tile_windows(a0.shape, tile_size, overlap):
        r1, c1 = min(r + nr, a1.shape[0]), min(c + nc, a1.shape[1])
        if r1 - r < MIN_SIDE or c1 - c < MIN_SIDE:
            continue
        win0 = (slice(r, r + nr), slice(c, c + nc))
        win1 = (slice(r, r1), slice(c, c1))
        found = matcher.match(
            a0[win0],
            a1[win1],
            None if m0 is None else m0[win0],
            None if m1 is None else m1[win1],
        )
        if len(found):
            parts.append(found.shifted((c, r), (c, r)))
    return deduplicate(Matches.concatenate(parts), dedup_radius)
