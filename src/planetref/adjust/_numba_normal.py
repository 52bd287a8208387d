"""numba implementation of the normal-equation accumulation (lazy import).

The twin of :meth:`~planetref.adjust.linearization.LinearizationMixin._accumulate` (the
numpy reference; a test binds both): ``N += A^T W A`` and ``g += A^T W r`` over the active
columns of each observation's pattern. Importing this module imports numba; the function
compiles on first use or loads from numba's on-disk cache.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def accumulate(
    n_cc: F64,
    g_c: F64,
    d: F64,
    we: F64,
    wr: F64,
    gp: Any,
    act_n: Any,
    act_loc: Any,
    act_col: Any,
    slot: Any,
    slot_n: F64,
    col_off: int,
) -> None:
    """Add the observations' normal equations to ``n_cc`` and ``g_c`` (in place).

    Args:
        n_cc: ``(P + 1, P + 1)`` normal matrix.
        g_c: ``(P + 1,)`` right-hand side ``A^T W r``.
        d: Partials ``(m, 2, q)`` in pattern column order.
        we: Weights ``(m, 2)``.
        wr: Weighted residuals ``(m, 2)`` (0 where invalid).
        gp: Global pattern of each observation ``(m,)``.
        act_n: Active columns per pattern ``(n_pat,)``.
        act_loc: Their local (pattern) indices ``(n_pat, q)``.
        act_col: Their global columns ``(n_pat, q)``.
        slot: Per observation, its slot (``-1``: none) ``(m,)``.
        slot_n: Per slot, ``A^T W A`` of its observations over the model's own columns
            (global column - ``col_off``) ``(n_slot, P_m + 1, P_m + 1)``; added to in
            place.
        col_off: The model's first global column.

    Runs of equal patterns (observations sorted by line) are summed in a small dense
    block over the pattern's active columns, added to ``n_cc`` (and to the slot's
    matrix) once per run; each observation adds its two rows (line, sample) in one
    rank-2 update. A run also ends where the slot changes.
    """
    m = d.shape[0]
    q = act_loc.shape[1]
    blk = np.zeros((q, q))
    gb = np.zeros(q)
    v0 = np.empty(q)
    v1 = np.empty(q)
    cur = -1
    cur_s = -1
    na = 0
    for i in range(m + 1):
        g = gp[i] if i < m else -1
        sl = slot[i] if i < m else -1
        if g != cur or sl != cur_s:
            if cur >= 0:
                for a in range(na):
                    ca = act_col[cur, a]
                    g_c[ca] += gb[a]
                    gb[a] = 0.0
                    for b in range(na):
                        cb = act_col[cur, b]
                        n_cc[ca, cb] += blk[a, b]
                        if cur_s >= 0:
                            slot_n[cur_s, ca - col_off, cb - col_off] += blk[a, b]
                        blk[a, b] = 0.0
            if i == m:
                break
            cur = g
            cur_s = sl
            na = act_n[g]
        w0, w1 = we[i, 0], we[i, 1]
        r0, r1 = wr[i, 0], wr[i, 1]
        for a in range(na):
            col = act_loc[cur, a]
            v0[a] = d[i, 0, col]
            v1[a] = d[i, 1, col]
        for a in range(na):
            x0, x1 = v0[a], v1[a]
            gb[a] += x0 * r0 + x1 * r1
            y0, y1 = w0 * x0, w1 * x1
            for b in range(na):
                blk[a, b] += y0 * v0[b] + y1 * v1[b]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def diag_cofactor(
    d: F64, gp: Any, q_mat: F64, act_n: Any, act_loc: Any, act_col: Any, out: F64
) -> None:
    """``out[i] = A_i Q A_i^T`` (2 x 2) over the active columns of each observation.

    The twin of ``variance._PairG(i, i)`` (the numpy reference). ``d``: partials
    ``(m, 2, q)``; ``gp``: patterns; ``q_mat``: the cofactor matrix of the camera
    parameters (``(P, P)``); ``out``: ``(m, 2, 2)``. The pattern's block of ``Q`` is
    gathered once per run of equal patterns.
    """
    m = d.shape[0]
    q = act_loc.shape[1]
    qs = np.empty((q, q))
    a0 = np.empty(q)
    a1 = np.empty(q)
    cur = -1
    na = 0
    for i in range(m):
        g = gp[i]
        if g != cur:
            cur = g
            na = act_n[g]
            for a in range(na):
                for b in range(na):
                    qs[a, b] = q_mat[act_col[g, a], act_col[g, b]]
        for a in range(na):
            col = act_loc[cur, a]
            a0[a] = d[i, 0, col]
            a1[a] = d[i, 1, col]
        h00 = 0.0
        h01 = 0.0
        h11 = 0.0
        for a in range(na):
            t0 = 0.0
            t1 = 0.0
            for b in range(na):
                t0 += qs[a, b] * a0[b]
                t1 += qs[a, b] * a1[b]
            h00 += a0[a] * t0
            h01 += a0[a] * t1
            h11 += a1[a] * t1
        out[i, 0, 0] = h00
        out[i, 0, 1] = h01
        out[i, 1, 0] = h01
        out[i, 1, 1] = h11
