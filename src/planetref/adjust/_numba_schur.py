"""numba implementation of the point elimination of :mod:`~planetref.adjust.schur` (lazy).

Importing this module imports numba; the function compiles on first use or loads from
numba's on-disk cache.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


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
) -> int:
    """Subtract the points' Schur terms from ``s_mat`` and ``rhs`` (see ``SchurMixin``).

    Point ``u`` owns the tie rows ``starts[u]:starts[u + 1]``. Returns -1, or the first
    point whose (damped) normal block is not positive definite.
    """
    q = a_t.shape[2]
    n_u = len(starts) - 1
    y = np.empty((1, q, 3))
    z = np.empty((1, q, 3))
    for u in range(n_u):
        o0, o1 = starts[u], starts[u + 1]
        v = np.empty((3, 3))
        g = np.empty(3)
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
        # C C^T = V^-1 (lower): S -= (y C)(y C)^T keeps each point's term symmetric PSD.
        c00 = math.sqrt(vi[0, 0])
        c10 = vi[1, 0] / c00
        c20 = vi[2, 0] / c00
        c11 = math.sqrt(vi[1, 1] - c10 * c10)
        c21 = (vi[2, 1] - c20 * c10) / c11
        c22 = math.sqrt(vi[2, 2] - c20 * c20 - c21 * c21)
        vb = np.empty(3)
        for i in range(3):
            vb[i] = vi[i, 0] * bx_out[u, 0] + vi[i, 1] * bx_out[u, 1] + vi[i, 2] * bx_out[u, 2]
        n_o = o1 - o0
        if y.shape[0] < n_o:
            y = np.empty((n_o, q, 3))
            z = np.empty((n_o, q, 3))
        # y_o = A_o^T W_o B_o (q x 3); z_o = y_o C.
        for k in range(n_o):
            o = o0 + k
            gp = gpat_t[o]
            for c in range(q):
                col = cols[gp, c]
                if col == sink:
                    continue
                for i in range(3):
                    y[k, c, i] = (
                        a_t[o, 0, c] * w_t[o, 0] * b_t[o, 0, i]
                        + a_t[o, 1, c] * w_t[o, 1] * b_t[o, 1, i]
                    )
                rhs[col] -= y[k, c, 0] * vb[0] + y[k, c, 1] * vb[1] + y[k, c, 2] * vb[2]
                z[k, c, 0] = y[k, c, 0] * c00 + y[k, c, 1] * c10 + y[k, c, 2] * c20
                z[k, c, 1] = y[k, c, 1] * c11 + y[k, c, 2] * c21
                z[k, c, 2] = y[k, c, 2] * c22
        for k1 in range(n_o):
            g1 = gpat_t[o0 + k1]
            for k2 in range(n_o):
                g2 = gpat_t[o0 + k2]
                for c1 in range(q):
                    col1 = cols[g1, c1]
                    if col1 == sink:
                        continue
                    for c2 in range(q):
                        col2 = cols[g2, c2]
                        if col2 == sink:
                            continue
                        s_mat[col1, col2] -= (
                            z[k1, c1, 0] * z[k2, c2, 0]
                            + z[k1, c1, 1] * z[k2, c2, 1]
                            + z[k1, c1, 2] * z[k2, c2, 2]
                        )
    return -1
