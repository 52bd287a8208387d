"""numba implementation of the dense NCC matcher's correlation and peak tests (lazy import).

The twin of :func:`planetref.matching.ncc.correlate_batch` for templates that share one
predicted displacement (the dense fine stage): the numpy reference correlates every
template with its own search window by OpenCV's ``matchTemplate`` (an FFT per template,
float32); here the templates' overlap is shared instead. For one candidate displacement
``d``, the raw cross product of template ``n`` with its window is the box sum of the
product image ``a(x) b(x + d)`` over the template's footprint: the column sums of the
products are carried down the rows of a block of templates (one new row added, one old
row taken off per row), and each template row reads its box sums from one prefix sum
across the columns. With templates every few pixels, a product is computed about twice
per (pixel, displacement) instead of ``(2t + 1)^2 / spacing^2`` times per template, and
the inner loop runs over the displacements' columns, contiguous in memory, where LLVM
vectorises it (given row views). Sums in float64: the surfaces are the exact ZNCC to
float32 rounding (OpenCV's FFT differs from it by up to ~2e-4 on real texture), with
OpenCV's ``TM_CCOEFF_NORMED`` rules: for whole templates the window sums come from box
sums of image 1 computed once per call and OpenCV's guard of the division is kept; for
partial templates (masked) the window's sums over the template's valid pixels are
carried as two more running sums. Tests bind both to an exact float64 reference and to
the OpenCV one.

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
def band_surfaces_masked(
    a: NDArray[np.float64],
    v: NDArray[np.float64],
    b: NDArray[np.float64],
    bb: NDArray[np.float64],
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
    count: NDArray[np.float64],
    blocked: NDArray[np.bool_],
    out: NDArray[np.float32],
) -> None:
    """:func:`band_surfaces` for partial templates: ZNCC over each template's valid pixels.

    OpenCV's masked ``TM_CCOEFF_NORMED`` with a 0/1 mask: the window's mean and variance
    are taken over the same pixels as the template's, so besides the products ``a b``
    the running sums carry ``v b`` and ``v b^2`` (``v`` image 0's validity); a window
    without variance there is undefined (:data:`INVALID`, OpenCV's NaN), and values
    above 1 (rounding) are 1.

    Args:
        a: Image 0, float64, a constant subtracted, 0 where invalid.
        v: Validity of image 0 as 0.0 / 1.0.
        b: Image 1 region as for :func:`band_surfaces`.
        bb: ``b ** 2``.
        rows: Template centre rows, ascending over ``start .. stop - 1``.
        cols: Template centre columns.
        start: First template of the band.
        stop: One past the last template of the band.
        t: Template half size, pixels.
        span: Surface side.
        off_r: As for :func:`band_surfaces`.
        off_c: As for :func:`band_surfaces`.
        tmean: Mean of each template over its valid pixels.
        tnorm: ``sqrt(sum((template - mean)^2))`` over its valid pixels; ``<= 0``: flat.
        count: Valid pixels of each template.
        blocked: Per pixel of ``b``: a candidate centre there is excluded.
        out: ``(stop - start, span, span)`` surfaces (written).
    """
    ra = rows[start]
    rb = rows[stop - 1]
    cmin = cols[start]
    cmax = cols[start]
    for k in range(start, stop):
        cmin = min(cmin, cols[k])
        cmax = max(cmax, cols[k])
    c_lo = cmin - t
    nc = cmax + t - c_lo + 1
    colsum = np.zeros((3, nc, span))
    pre = np.zeros((3, nc + 1, span))
    for i in range(span):
        colsum[:, :, :] = 0.0
        for u in range(ra - t, ra + t + 1):
            br = u + off_r + i
            for c in range(nc):
                av = a[u, c_lo + c]
                vv = v[u, c_lo + c]
                if vv == 0.0:
                    continue  # nothing to add (a is 0 there too)
                bc = c_lo + c + off_c
                cs0 = colsum[0, c]
                cs1 = colsum[1, c]
                cs2 = colsum[2, c]
                bv = b[br, bc : bc + span]
                bq = bb[br, bc : bc + span]
                for j in range(span):
                    cs0[j] += av * bv[j]
                    cs1[j] += vv * bv[j]
                    cs2[j] += vv * bq[j]
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
                    vn = v[un, c_lo + c]
                    vo = v[uo, c_lo + c]
                    if vn == 0.0 and vo == 0.0:
                        continue
                    bc = c_lo + c + off_c
                    cs0 = colsum[0, c]
                    cs1 = colsum[1, c]
                    cs2 = colsum[2, c]
                    bn = b[brn, bc : bc + span]
                    bo = b[bro, bc : bc + span]
                    qn = bb[brn, bc : bc + span]
                    qo = bb[bro, bc : bc + span]
                    for j in range(span):
                        cs0[j] += an * bn[j] - ao * bo[j]
                        cs1[j] += vn * bn[j] - vo * bo[j]
                        cs2[j] += vn * qn[j] - vo * qo[j]
            if k >= stop or rows[k] != r:
                continue
            for q in range(3):
                for c in range(nc):
                    p0 = pre[q, c]
                    p1 = pre[q, c + 1]
                    cs = colsum[q, c]
                    for j in range(span):
                        p1[j] = p0[j] + cs[j]
            while k < stop and rows[k] == r:
                lo = cols[k] - t - c_lo
                hi = cols[k] + t + 1 - c_lo
                cr = r + off_r + i
                cb = cols[k] + off_c
                m = tmean[k]
                tn = tnorm[k]
                cnt = count[k]
                for j in range(span):
                    if tn <= 0.0 or blocked[cr, cb + j]:
                        out[k - start, i, j] = INVALID
                        continue
                    w1 = pre[1, hi, j] - pre[1, lo, j]
                    w2 = pre[2, hi, j] - pre[2, lo, j]
                    num = (pre[0, hi, j] - pre[0, lo, j]) - m * w1
                    den = math.sqrt(max(w2 - w1 * w1 / cnt, 0.0)) * tn
                    if den > 0.0:
                        out[k - start, i, j] = min(num / den, 1.0)
                    else:
                        out[k - start, i, j] = INVALID
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
