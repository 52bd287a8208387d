"""numba implementation of the point elimination of :mod:`~planetref.adjust.schur` (lazy).

Importing this module imports numba; the function compiles on first use or loads from
numba's on-disk cache.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

from planetref.arrays import F64


@numba.njit(cache=True, nogil=True, error_model="numpy")
def eliminate_points(
    a_t: F64,
    b_t: F64,
    w_t: F64,
    r_t: F64,
    gpat_t: Any,
    cols: Any,
    starts: Any,
    prior_w: F64,
    prior_g: F64,
    lam: float,
    sink: int,
    s_mat: F64,
    rhs: F64,
    vinv_out: F64,
    bx_out: F64,
    dx_out: F64,
    pool_max: int,
) -> int:
    """Subtract the points' Schur terms from ``s_mat`` and ``rhs`` (see ``SchurMixin``).

    Point ``u`` owns the tie rows ``starts[u]:starts[u + 1]``. Returns -1, or the first
    point whose (damped) normal block is not positive definite.

    Only the upper triangle of ``s_mat`` is updated point by point (each term is
    symmetric); the lower one is copied from it at the end, so ``s_mat`` leaves exactly
    symmetric. Points seen by one observation (MCPs) take a rank-2 form
    (:func:`_one_observation`); a point seen by several (a tie point) sums its
    ``Y = sum_o A_o^T W_o B_o`` over the distinct active columns of its observations
    first and updates ``S`` once with ``z z^T`` (``z = Y C``, ``C C^T = V^-1``), over
    those columns only (the same sum as the pairs of observations' ``z_k1 z_k2^T``;
    when all its observations share one pattern it is summed per pattern like the
    one-observation terms).
    """
    q = a_t.shape[2]
    n_u = len(starts) - 1
    # A point's compact columns (the distinct active columns of its observations, at
    # most ``sink``), their rows of Y (then z), and each column's place among them.
    ucol = np.empty(sink + 1, np.intp)
    y0, y1, y2 = np.empty(sink + 1), np.empty(sink + 1), np.empty(sink + 1)
    mark = np.full(sink + 1, -1, np.intp)
    pos = np.zeros(sink + 1, np.intp)
    # Scratch, overwritten for every point (no allocation per point).
    v = np.empty((3, 3))
    g = np.empty(3)
    vb = np.empty(3)
    p0 = np.empty(q)
    p1 = np.empty(q)
    act_n, act_c = _active_by_column(cols, sink)
    # The one-observation terms are summed per pattern in a dense block of its active
    # columns (contiguous rows, L1-resident) and added to ``s_mat`` once at the end,
    # unless that takes more than ``pool_max`` elements (they then go into ``s_mat``).
    n_pat = cols.shape[0]
    pooled = n_pat * q * q <= pool_max
    pool = np.zeros((n_pat if pooled else 0, q, q))
    for u in range(n_u):
        o0, o1 = starts[u], starts[u + 1]
        for i in range(3):
            g[i] = prior_g[u, i]
            for j in range(3):
                v[i, j] = prior_w[u, i, j]
        for o in range(o0, o1):
            for r in range(2):
                w = w_t[o, r]
                for i in range(3):
                    wb = w * b_t[o, r, i]
                    g[i] += wb * r_t[o, r]
                    for j in range(3):
                        v[i, j] += wb * b_t[o, r, j]
        for i in range(3):
            dx_out[u, i] = v[i, i]
        if lam:
            for i in range(3):
                v[i, i] += lam * dx_out[u, i]
        # Cholesky of the 3x3 block, then its inverse.
        l00 = v[0, 0]
        if not l00 > 0.0:
            return u
        l00 = math.sqrt(l00)
        l10 = v[1, 0] / l00
        l20 = v[2, 0] / l00
        d11 = v[1, 1] - l10 * l10
        if not d11 > 0.0:
            return u
        l11 = math.sqrt(d11)
        l21 = (v[2, 1] - l20 * l10) / l11
        d22 = v[2, 2] - l20 * l20 - l21 * l21
        if not d22 > 0.0:
            return u
        l22 = math.sqrt(d22)
        # M = L^-1 (lower); V^-1 = M^T M.
        m00 = 1.0 / l00
        m11 = 1.0 / l11
        m22 = 1.0 / l22
        m10 = -l10 * m00 / l11
        m21 = -l21 * m11 / l22
        m20 = -(l20 * m00 + l21 * m10) / l22
        vi = vinv_out[u]
        vi[0, 0] = m00 * m00 + m10 * m10 + m20 * m20
        vi[1, 1] = m11 * m11 + m21 * m21
        vi[2, 2] = m22 * m22
        vi[0, 1] = vi[1, 0] = m10 * m11 + m20 * m21
        vi[0, 2] = vi[2, 0] = m20 * m22
        vi[1, 2] = vi[2, 1] = m21 * m22
        for i in range(3):
            bx_out[u, i] = -g[i]
        for i in range(3):
            vb[i] = vi[i, 0] * bx_out[u, 0] + vi[i, 1] * bx_out[u, 1] + vi[i, 2] * bx_out[u, 2]
        n_o = o1 - o0
        if n_o == 1:
            gp = gpat_t[o0]
            act = act_c[gp, : act_n[gp]]
            block = pool[gp] if pooled else s_mat
            _one_observation(a_t, b_t, w_t, o0, act, cols[gp], vi, vb, block, pooled, rhs, p0, p1)
            continue
        # Several observations: Y = sum_o A_o^T W_o B_o over the union of their active
        # columns (compact, in increasing parameter column), z = Y C with C C^T = V^-1
        # (lower), and S -= z z^T: each point's term stays symmetric PSD.
        nu = 0
        same = True
        gp0 = gpat_t[o0]
        for o in range(o0, o1):
            gp = gpat_t[o]
            same = same and gp == gp0
            for ii in range(act_n[gp]):
                col = cols[gp, act_c[gp, ii]]
                if mark[col] != u:
                    mark[col] = u
                    ucol[nu] = col
                    nu += 1
        if not same:  # a union of patterns: sort its columns (a few dozen at most)
            for i in range(1, nu):
                x = ucol[i]
                j = i
                while j > 0 and ucol[j - 1] > x:
                    ucol[j] = ucol[j - 1]
                    j -= 1
                ucol[j] = x
        for i in range(nu):
            pos[ucol[i]] = i
            y0[i] = 0.0
            y1[i] = 0.0
            y2[i] = 0.0
        for o in range(o0, o1):
            gp = gpat_t[o]
            w0, w1 = w_t[o, 0], w_t[o, 1]
            wb00, wb01, wb02 = w0 * b_t[o, 0, 0], w0 * b_t[o, 0, 1], w0 * b_t[o, 0, 2]
            wb10, wb11, wb12 = w1 * b_t[o, 1, 0], w1 * b_t[o, 1, 1], w1 * b_t[o, 1, 2]
            for ii in range(act_n[gp]):
                c = act_c[gp, ii]
                i = pos[cols[gp, c]]
                a0, a1 = a_t[o, 0, c], a_t[o, 1, c]
                y0[i] += a0 * wb00 + a1 * wb10
                y1[i] += a0 * wb01 + a1 * wb11
                y2[i] += a0 * wb02 + a1 * wb12
        c00, c10, c20, c11, c21, c22 = _cholesky3(vi)
        for i in range(nu):
            t0, t1, t2 = y0[i], y1[i], y2[i]
            rhs[ucol[i]] -= t0 * vb[0] + t1 * vb[1] + t2 * vb[2]
            y0[i] = t0 * c00 + t1 * c10 + t2 * c20
            y1[i] = t1 * c11 + t2 * c21
            y2[i] = t2 * c22
        if same and pooled:
            # One pattern: its compact columns are the pattern's active ones in the
            # same order; whole rows (both triangles) vectorise.
            block = pool[gp0]
            for i in range(nu):
                x0, x1, x2 = y0[i], y1[i], y2[i]
                row = block[i]
                for j in range(nu):
                    row[j] += x0 * y0[j] + x1 * y1[j] + x2 * y2[j]
            continue
        for i in range(nu):  # the upper triangle of S (mirrored below)
            col1 = ucol[i]
            x0, x1, x2 = y0[i], y1[i], y2[i]
            for j in range(i, nu):
                s_mat[col1, ucol[j]] -= x0 * y0[j] + x1 * y1[j] + x2 * y2[j]
    for gp in range(n_pat if pooled else 0):
        for i in range(act_n[gp]):
            col1 = cols[gp, act_c[gp, i]]
            for j in range(i, act_n[gp]):
                s_mat[col1, cols[gp, act_c[gp, j]]] -= pool[gp, i, j]
    for i in range(sink):
        for j in range(i):
            s_mat[i, j] = s_mat[j, i]
    return -1


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _one_observation(
    a_t: F64,
    b_t: F64,
    w_t: F64,
    o: int,
    act: Any,
    col_of: Any,
    vi: F64,
    vb: F64,
    block: F64,
    pooled: bool,
    rhs: F64,
    p0: F64,
    p1: F64,
) -> None:
    """The Schur terms of a point seen by one observation (an MCP), upper triangle.

    Into ``block``: the pattern's dense block over its active columns (added with the
    ``+`` sign; ``pooled``) or the reduced matrix itself (subtracted).

    With one observation ``Y = A^T W B`` has rank 2, so ``Y V^-1 Y^T = A^T M A`` with
    the 2 x 2 ``M = W B V^-1 B^T W``. ``M`` is formed as a Gram matrix (``U U^T``, the
    rows of ``U = W B C`` with ``C C^T = V^-1``) and factored, ``M = L L^T``, so the
    term is ``P^T P`` with ``P = L^T A`` (2 x q): positive semi-definite by
    construction, as the general path's ``z z^T``, at two products per element instead
    of three.
    """
    c00, c10, c20, c11, c21, c22 = _cholesky3(vi)  # C C^T = V^-1, lower
    # Rows r of W B (3-vectors): U = W B C and e = W B V^-1 b_x.
    w = w_t[o, 0]
    b0, b1, b2 = w * b_t[o, 0, 0], w * b_t[o, 0, 1], w * b_t[o, 0, 2]
    u00, u01, u02 = b0 * c00 + b1 * c10 + b2 * c20, b1 * c11 + b2 * c21, b2 * c22
    e0 = b0 * vb[0] + b1 * vb[1] + b2 * vb[2]
    w = w_t[o, 1]
    b0, b1, b2 = w * b_t[o, 1, 0], w * b_t[o, 1, 1], w * b_t[o, 1, 2]
    u10, u11, u12 = b0 * c00 + b1 * c10 + b2 * c20, b1 * c11 + b2 * c21, b2 * c22
    e1 = b0 * vb[0] + b1 * vb[1] + b2 * vb[2]
    m00 = u00 * u00 + u01 * u01 + u02 * u02
    m01 = u00 * u10 + u01 * u11 + u02 * u12
    m11 = u10 * u10 + u11 * u11 + u12 * u12
    l00 = math.sqrt(m00)
    l10 = m01 / l00 if l00 > 0.0 else 0.0
    l11 = math.sqrt(max(m11 - l10 * l10, 0.0))
    # Over the pattern's active columns in increasing parameter column: the upper
    # triangle is each column with itself and the ones after it.
    n = len(act)
    for i in range(n):
        c = act[i]
        a0, a1 = a_t[o, 0, c], a_t[o, 1, c]
        rhs[col_of[c]] -= a0 * e0 + a1 * e1
        p0[i] = l00 * a0 + l10 * a1
        p1[i] = l11 * a1
    if pooled:  # ``block`` is the pattern's: += P^T P over its active columns
        # Whole rows (both triangles): a loop from 0 vectorises, one from i did not
        # (the tiny demo's NCC network: the update ~270 against ~575 ns per point).
        for i in range(n):
            x0, x1 = p0[i], p1[i]
            row = block[i]
            for j in range(n):
                row[j] += x0 * p0[j] + x1 * p1[j]
        return
    for i in range(n):  # ``block`` is S itself
        col1 = col_of[act[i]]
        x0, x1 = p0[i], p1[i]
        for j in range(i, n):
            block[col1, col_of[act[j]]] -= x0 * p0[j] + x1 * p1[j]


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _cholesky3(m: F64) -> tuple[float, float, float, float, float, float]:
    """``(l00, l10, l20, l11, l21, l22)`` of the lower Cholesky factor of a 3x3 SPD ``m``."""
    l00 = math.sqrt(m[0, 0])
    l10 = m[1, 0] / l00
    l20 = m[2, 0] / l00
    l11 = math.sqrt(m[1, 1] - l10 * l10)
    l21 = (m[2, 1] - l20 * l10) / l11
    l22 = math.sqrt(m[2, 2] - l20 * l20 - l21 * l21)
    return l00, l10, l20, l11, l21, l22


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _active_by_column(cols: Any, sink: int) -> tuple[Any, Any]:
    """Per pattern, its active pattern columns ordered by parameter column, and how many."""
    n_pat, q = cols.shape
    act_n = np.zeros(n_pat, np.intp)
    act_c = np.empty((n_pat, q), np.intp)
    for g in range(n_pat):
        k = 0
        for c in range(q):
            if cols[g, c] != sink:
                # Insertion by parameter column (patterns hold a few dozen columns).
                j = k
                while j > 0 and cols[g, act_c[g, j - 1]] > cols[g, c]:
                    act_c[g, j] = act_c[g, j - 1]
                    j -= 1
                act_c[g, j] = c
                k += 1
        act_n[g] = k
    return act_n, act_c


@numba.njit(cache=True, nogil=True, error_model="numpy")
def back_substitute(
    a_t: F64,
    b_t: F64,
    w_t: F64,
    gpat_t: Any,
    cols: Any,
    starts: Any,
    vinv: F64,
    bx: F64,
    dc_pad: F64,
    dx_out: F64,
) -> None:
    """Point steps ``dX_u = V_u^-1 (b_x,u - B_u^T W_u A_u dc)`` (``SchurMixin``).

    Point ``u`` owns the tie rows ``starts[u]:starts[u + 1]``; ``dc_pad`` is the camera
    step with a trailing zero at the sink column of the fixed parameters.
    """
    q = a_t.shape[2]
    for u in range(len(starts) - 1):
        t0 = t1 = t2 = 0.0
        for o in range(starts[u], starts[u + 1]):
            gp = gpat_t[o]
            ad0 = ad1 = 0.0
            for c in range(q):
                d = dc_pad[cols[gp, c]]
                ad0 += a_t[o, 0, c] * d
                ad1 += a_t[o, 1, c] * d
            w0, w1 = w_t[o, 0], w_t[o, 1]
            t0 += w0 * b_t[o, 0, 0] * ad0 + w1 * b_t[o, 1, 0] * ad1
            t1 += w0 * b_t[o, 0, 1] * ad0 + w1 * b_t[o, 1, 1] * ad1
            t2 += w0 * b_t[o, 0, 2] * ad0 + w1 * b_t[o, 1, 2] * ad1
        r0, r1, r2 = bx[u, 0] - t0, bx[u, 1] - t1, bx[u, 2] - t2
        for i in range(3):
            dx_out[u, i] = vinv[u, i, 0] * r0 + vinv[u, i, 1] * r1 + vinv[u, i, 2] * r2
