"""numba implementation of the dense NCC matcher's correlation and peak tests (lazy import).

The twin of :func:`planetref.matching.ncc.correlate_batch` for whole templates that share
one predicted displacement (the dense fine stage): the numpy reference correlates every
template with its own search window by OpenCV's ``matchTemplate`` (an FFT per template);
here the templates' overlap is shared instead. For one candidate displacement
``(di, dj)``, the raw cross product of template ``n`` with its window is the box sum of
the product image ``a(x) b(x + d)`` over the template's footprint: the column sums of the
products are carried down the rows of a band of templates (one new row added, one old
row taken off per row), and each template row reads its box sums from one prefix sum
across the columns. With templates every few pixels, a product is computed twice per
(pixel, displacement) instead of ``(2t + 1)^2 / spacing^2`` times per template, and the
inner loop runs over the displacements' columns, contiguous in memory, where LLVM
vectorises it. Window sums and sums of squares come from box sums of image 1 computed
once per call (the numpy side), template means and norms once per template, and the
normalisation is OpenCV's ``TM_CCOEFF_NORMED`` rule, so the surfaces agree with the
reference to its float32 rounding; a test binds both.

The peak rules (strict interior maximum, no invalid value in the 3x3 patch, the
ambiguity test against other local maxima more than 2 pixels away) are the reference's,
one template at a time, without the ``(N, span, span)`` temporaries of the vectorised
numpy form. One module, so that no compiled function calls into another file (numba's
cache would not see a change there). Importing this module imports numba; the functions
compile on first use or load from numba's on-disk cache.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import NDArray

#: Value given to surface positions without a defined correlation (as the reference's).
INVALID = -2.0


@numba.njit(cache=True, nogil=True)
def band_surfaces(
    a: NDArray[np.float64],
    b: NDArray[np.float64],
    rows: NDArray[np.int64],
    cols: NDArray[np.int64],
    start: int,
    stop: int,
    t: int,
    span: int,
    off_r: int,
    off_c: int,
    tmean: NDArray[np.float64],
    tnorm: NDArray[np.float64],
    s1: NDArray[np.float64],
    s2: NDArray[np.float64],
    blocked: NDArray[np.bool_],
    out: NDArray[np.float32],
) -> None:
    """ZNCC surfaces of templates ``start .. stop - 1`` (sorted by centre row).

    Template ``n`` is the ``(2t + 1)^2`` block of ``a`` centred on ``(rows[n], cols[n])``;
    its surface value ``(i, j)`` correlates it with the block of ``b`` centred on
    ``(rows[n] + off_r + i, cols[n] + off_c + j)`` (``b``'s own indices).

    Args:
        a: Image 0, float64, any constant subtracted (ZNCC ignores it).
        b: Image 1 region, float64, any constant subtracted; every block read lies inside.
        rows: Template centre rows in ``a``, ascending over ``start .. stop - 1``.
        cols: Template centre columns in ``a``.
        start: First template of the band.
        stop: One past the last template of the band.
        t: Template half size, pixels.
        span: Surface side (``2 * search_radius + 1``).
        off_r: Row of ``b``'s block for surface row 0, minus the template's centre row.
        off_c: The same for columns.
        tmean: Mean of each template, ``(N,)``.
        tnorm: ``sqrt(sum((template - mean)^2))`` of each template, ``(N,)``; a value
            ``<= 0`` marks a flat template (its surface is all :data:`INVALID`).
        s1: Box sum of ``b`` over the ``(2t + 1)^2`` block centred on each pixel of ``b``.
        s2: The same for ``b^2``.
        blocked: Per pixel of ``b``: a candidate centre there is excluded.
        out: ``(stop - start, span, span)`` surfaces (written).
    """
    n_px = float((2 * t + 1) * (2 * t + 1))
    ra = rows[start]
    rb = rows[stop - 1]
    cmin = cols[start]
    cmax = cols[start]
    for k in range(start, stop):
        cmin = min(cmin, cols[k])
        cmax = max(cmax, cols[k])
    c_lo = cmin - t
    nc = cmax + t - c_lo + 1
    colsum = np.zeros((nc, span))
    pre = np.zeros((nc + 1, span))
    for i in range(span):
        # the column sums of the band's first template row, then slid down the rows
        colsum[:, :] = 0.0
        # (row views: without them LLVM does not vectorise the loops over j, 5x slower)
        for u in range(ra - t, ra + t + 1):
            br = u + off_r + i
            for c in range(nc):
                av = a[u, c_lo + c]
                bc = c_lo + c + off_c
                cs = colsum[c]
                bv = b[br, bc : bc + span]
                for j in range(span):
                    cs[j] += av * bv[j]
        k = start
        for r in range(ra, rb + 1):
            if r > ra:
                un = r + t
                uo = r - t - 1
                brn = un + off_r + i
                bro = uo + off_r + i
                for c in range(nc):
                    an = a[un, c_lo + c]
                    ao = a[uo, c_lo + c]
                    bc = c_lo + c + off_c
                    cs = colsum[c]
                    bn = b[brn, bc : bc + span]
                    bo = b[bro, bc : bc + span]
                    for j in range(span):
                        cs[j] += an * bn[j] - ao * bo[j]
            if k >= stop or rows[k] != r:
                continue
            for c in range(nc):
                p0 = pre[c]
                p1 = pre[c + 1]
                cs = colsum[c]
                for j in range(span):
                    p1[j] = p0[j] + cs[j]
            while k < stop and rows[k] == r:
                lo = cols[k] - t - c_lo
                hi = cols[k] + t + 1 - c_lo
                cr = r + off_r + i
                cb = cols[k] + off_c
                m = tmean[k]
                tn = tnorm[k]
                for j in range(span):
                    if tn <= 0.0 or blocked[cr, cb + j]:
                        out[k - start, i, j] = INVALID
                        continue
                    w1 = s1[cr, cb + j]
                    num = (pre[hi, j] - pre[lo, j]) - m * w1
                    # OpenCV's TM_CCOEFF_NORMED normalisation, its guard included
                    den = math.sqrt(max(s2[cr, cb + j] - w1 * w1 / n_px, 0.0)) * tn
                    if abs(num) < den:
                        v = num / den
                    elif abs(num) < den * 1.125:
                        v = 1.0 if num > 0 else -1.0
                    else:
                        v = 0.0
                    out[k - start, i, j] = v
                k += 1


@numba.njit(cache=True, nogil=True)
def surface_peaks(
    res: NDArray[np.float32],
    min_ncc: float,
    ambiguity_ratio: float,
    peak_i: NDArray[np.int64],
    peak_j: NDArray[np.int64],
    peak: NDArray[np.float64],
    patch: NDArray[np.float64],
    good: NDArray[np.bool_],
) -> None:
    """Integer peak, its 3x3 patch and the peak tests of each surface.

    The rules of :func:`planetref.matching.ncc.correlate_batch`: the first maximum in
    row-major order; good when at least ``min_ncc``, not on the border, no
    :data:`INVALID` value in its 3x3 patch, and (``ambiguity_ratio < 1``) no local
    maximum (a value at least each of its in-bounds 3x3 neighbours) more than 2 pixels
    away in rows or columns reaching ``ambiguity_ratio`` times the peak.

    Args:
        res: ``(N, span, span)`` surfaces.
        min_ncc: Smallest peak value.
        ambiguity_ratio: Rival share; ``1.0`` disables the test.
        peak_i: ``(N,)`` peak rows (written).
        peak_j: ``(N,)`` peak columns (written).
        peak: ``(N,)`` peak values (written).
        patch: ``(N, 3, 3)`` patches around the peak, clipped inside (written).
        good: ``(N,)`` whether the peak passed (written).
    """
    n, span, _ = res.shape
    for k in range(n):
        bi = 0
        bj = 0
        best = np.float64(res[k, 0, 0])
        for i in range(span):
            for j in range(span):
                v = np.float64(res[k, i, j])
                if v > best:
                    best = v
                    bi = i
                    bj = j
        peak_i[k] = bi
        peak_j[k] = bj
        peak[k] = best
        ok = best >= min_ncc and bi > 0 and bj > 0 and bi < span - 1 and bj < span - 1
        ci = min(max(bi, 1), span - 2)
        cj = min(max(bj, 1), span - 2)
        for di in range(3):
            for dj in range(3):
                v = np.float64(res[k, ci - 1 + di, cj - 1 + dj])
                patch[k, di, dj] = v
                if v <= INVALID:
                    ok = False
        if ok and ambiguity_ratio < 1.0 and span * span > 9:
            bar = ambiguity_ratio * best
            for i in range(span):
                for j in range(span):
                    v = np.float64(res[k, i, j])
                    if v < bar or v <= INVALID:
                        continue
                    if abs(i - bi) <= 2 and abs(j - bj) <= 2:
                        continue
                    local = True
                    for p in range(max(i - 1, 0), min(i + 2, span)):
                        for q in range(max(j - 1, 0), min(j + 2, span)):
                            if np.float64(res[k, p, q]) > v:
                                local = False
                    if local:
                        ok = False
                        break
                if not ok:
                    break
        good[k] = ok


@numba.njit(cache=True, nogil=True)
def finish_surfaces(
    res: NDArray[np.float32],
    blocked: NDArray[np.bool_],
    top: NDArray[np.int64],
    left: NDArray[np.int64],
    flat: NDArray[np.bool_],
) -> None:
    """The reference's clean-up of OpenCV's surfaces, in place.

    Non-finite values (a masked template over a flat window) and the surfaces of flat
    templates become :data:`INVALID`, values above 1 become 1, and so do excluded
    candidate centres: surface ``(i, j)`` of template ``k`` is ``blocked[top[k] + i,
    left[k] + j]``.
    """
    n, sh, sw = res.shape
    for k in range(n):
        for i in range(sh):
            for j in range(sw):
                v = res[k, i, j]
                if flat[k] or blocked[top[k] + i, left[k] + j] or not math.isfinite(v):
                    res[k, i, j] = INVALID
                elif v > 1.0:
                    res[k, i, j] = 1.0
