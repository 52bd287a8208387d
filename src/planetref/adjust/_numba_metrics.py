"""numba implementation of grouped reprojection sums (lazy import).

The twin of :func:`planetref.adjust.metrics.reprojection_metrics` called once per group (the
numpy reference; a test binds both bit for bit): one pass sorts the kept residuals of
every group into a contiguous buffer (stable, so each group keeps the observations'
order), then each group's sums follow numpy's own pairwise summation (``np.add.reduce``
over a contiguous float64 array: blocks of up to 128 elements in 8 interleaved partial
sums, halves split at multiples of 8), so ``sum / n`` equals ``np.mean`` of the gathered
array exactly. Importing this module imports numba; the functions compile on first use
or load from numba's on-disk cache.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

from planetref.arrays import F64

#: The sums of :func:`group_sums`, in column order (x = sample, y = line residual).
SUMS = ("x2+y2", "x2", "y2", "x", "y", "hypot")


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _term(x: F64, y: F64, i: int, kind: int) -> float:
    if kind == 0:
        return x[i] * x[i] + y[i] * y[i]
    if kind == 1:
        return x[i] * x[i]
    if kind == 2:
        return y[i] * y[i]
    if kind == 3:
        return x[i]
    if kind == 4:
        return y[i]
    return math.hypot(x[i], y[i])


@numba.njit(cache=True, nogil=True, error_model="numpy")
def pairwise_sum(x: F64, y: F64, a: int, n: int, kind: int) -> float:
    """The pairwise sum (numpy's) of ``term(i)`` over ``i`` in ``[a, a + n)``.

    ``kind``: the term, ``0..5`` for :data:`SUMS`; ``6``: ``x[i]`` (a sum of ``x``
    itself, e.g. of lengths computed before).
    """
    k = kind if kind < 6 else 3
    if n < 8:
        res = 0.0
        for i in range(a, a + n):
            res += _term(x, y, i, k)
        return res
    if n <= 128:
        r0 = _term(x, y, a, k)
        r1 = _term(x, y, a + 1, k)
        r2 = _term(x, y, a + 2, k)
        r3 = _term(x, y, a + 3, k)
        r4 = _term(x, y, a + 4, k)
        r5 = _term(x, y, a + 5, k)
        r6 = _term(x, y, a + 6, k)
        r7 = _term(x, y, a + 7, k)
        end = a + n - n % 8
        i = a + 8
        while i < end:
            r0 += _term(x, y, i, k)
            r1 += _term(x, y, i + 1, k)
            r2 += _term(x, y, i + 2, k)
            r3 += _term(x, y, i + 3, k)
            r4 += _term(x, y, i + 4, k)
            r5 += _term(x, y, i + 5, k)
            r6 += _term(x, y, i + 6, k)
            r7 += _term(x, y, i + 7, k)
            i += 8
        res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
        while i < a + n:
            res += _term(x, y, i, k)
            i += 1
        return res
    n2 = n // 2
    n2 -= n2 % 8
    return pairwise_sum(x, y, a, n2, kind) + pairwise_sum(x, y, a + n2, n - n2, kind)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _sums5(bx: F64, by: F64, a: int, n: int, out: F64) -> None:
    """The first five :data:`SUMS` of ``[a, a + n)`` at once, into ``out[:5]``.

    Each is summed as :func:`pairwise_sum` sums it (the same tree, the same order).
    """
    if n < 8:
        s0 = s1 = s2 = s3 = s4 = 0.0
        for i in range(a, a + n):
            x, y = bx[i], by[i]
            s0 += x * x + y * y
            s1 += x * x
            s2 += y * y
            s3 += x
            s4 += y
        out[0], out[1], out[2], out[3], out[4] = s0, s1, s2, s3, s4
        return
    if n <= 128:
        r = np.empty((5, 8))
        for j in range(8):
            x, y = bx[a + j], by[a + j]
            r[0, j] = x * x + y * y
            r[1, j] = x * x
            r[2, j] = y * y
            r[3, j] = x
            r[4, j] = y
        end = a + n - n % 8
        i = a + 8
        while i < end:
            for j in range(8):
                x, y = bx[i + j], by[i + j]
                r[0, j] += x * x + y * y
                r[1, j] += x * x
                r[2, j] += y * y
                r[3, j] += x
                r[4, j] += y
            i += 8
        for k in range(5):
            out[k] = ((r[k, 0] + r[k, 1]) + (r[k, 2] + r[k, 3])) + (
                (r[k, 4] + r[k, 5]) + (r[k, 6] + r[k, 7])
            )
        while i < a + n:
            x, y = bx[i], by[i]
            out[0] += x * x + y * y
            out[1] += x * x
            out[2] += y * y
            out[3] += x
            out[4] += y
            i += 1
        return
    n2 = n // 2
    n2 -= n2 % 8
    left = np.empty(5)
    _sums5(bx, by, a, n2, left)
    _sums5(bx, by, a + n2, n - n2, out)
    for k in range(5):
        out[k] = left[k] + out[k]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def group_sums(x: F64, y: F64, keep: Any, group: Any, n_groups: int) -> tuple[Any, Any, F64, F64]:
    """Counts, sums and extremes of the kept finite residuals of every group.

    Args:
        x: Sample residuals, ``(M,)``.
        y: Line residuals, ``(M,)``.
        keep: Rows that count as inliers, ``(M,)`` bool (non-finite rows never do).
        group: Group codes, ``(L, M)``: each row of codes is one partition level (a row
            may belong to one group per level; ``-1``: none), codes ``< n_groups``.
        n_groups: Number of group codes over all levels.

    Returns:
        ``(n_total, n_in, sums, extremes)``: rows per group, kept finite rows, the
        :data:`SUMS` ``(n_groups, 6)`` and ``(max x, min x, max y, min y)``
        ``(n_groups, 4)`` (NaN for a group without kept rows).
    """
    m = x.shape[0]
    n_total = np.zeros(n_groups, np.int64)
    n_in = np.zeros(n_groups, np.int64)
    # The length of every kept row, computed once for all levels (hypot is the costly
    # term).
    kept = np.zeros(m, np.bool_)
    length = np.empty(m)
    for i in range(m):
        if keep[i] and math.isfinite(x[i]) and math.isfinite(y[i]):
            kept[i] = True
            length[i] = math.hypot(x[i], y[i])
    # One level at a time below: the gathered residuals of a level's groups (contiguous
    # per group, in row order, for numpy's pairwise sums) fit in buffers of the level
    # with the most kept rows, reused for every level.
    per_level = np.zeros(group.shape[0], np.int64)
    for lv in range(group.shape[0]):
        for i in range(m):
            g = group[lv, i]
            if g >= 0:
                n_total[g] += 1
                if kept[i]:
                    n_in[g] += 1
                    per_level[lv] += 1
    size = 0
    for lv in range(group.shape[0]):
        size = max(size, per_level[lv])
    bx = np.empty(size)
    by = np.empty(size)
    bl = np.empty(size)
    sums = np.zeros((n_groups, 6))
    ext = np.full((n_groups, 4), np.nan)
    on_level = np.zeros(n_groups, np.bool_)
    start = np.zeros(n_groups + 1, np.int64)
    pos = np.zeros(n_groups, np.int64)
    for lv in range(group.shape[0]):
        on_level[:] = False
        for i in range(m):
            g = group[lv, i]
            if g >= 0:
                on_level[g] = True
        for g in range(n_groups):
            start[g + 1] = start[g] + (n_in[g] if on_level[g] else 0)
        for g in range(n_groups):
            pos[g] = start[g]
        for i in range(m):
            g = group[lv, i]
            if g >= 0 and kept[i]:
                p = pos[g]
                bx[p] = x[i]
                by[p] = y[i]
                bl[p] = length[i]
                pos[g] = p + 1
        for g in range(n_groups):
            a, n = start[g], start[g + 1] - start[g]
            if n == 0:
                continue
            _sums5(bx, by, a, n, sums[g])
            sums[g, 5] = pairwise_sum(bl, bl, a, n, 6)
            mx, mnx, my, mny = bx[a], bx[a], by[a], by[a]
            for i in range(a + 1, a + n):
                mx = max(mx, bx[i])
                mnx = min(mnx, bx[i])
                my = max(my, by[i])
                mny = min(mny, by[i])
            ext[g, 0], ext[g, 1], ext[g, 2], ext[g, 3] = mx, mnx, my, mny
    return n_total, n_in, sums, ext
