"""numba implementation of the normal-equation accumulation (lazy import).

The twin of :meth:`~planetref.adjust.linearization.LinearizationMixin._accumulate` (the
numpy reference; a test binds both): ``N += A^T W A`` and ``g += A^T W r`` over the active
columns of each observation's pattern (a line scanner's runs of one Lagrange window as
moments of the time within it: :func:`linearize_rows`). Importing this module imports
numba; the function compiles on first use or loads from numba's on-disk cache.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

from planetref.arrays import F64

_jit = numba.njit(cache=True, nogil=True, error_model="numpy")

#: Loss codes of :func:`linearize_rows` (the names of :func:`planetref.adjust.robust.robust_rho`).
LOSS_CODES = {"linear": 0, "huber": 1, "cauchy": 2}


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _flush(
    blk: F64, gb: F64, na: int, cols: Any, normal: tuple[F64, F64], slot: int, slot_n: F64,
    col_off: int,
) -> None:  # fmt: skip
    """Add a run's block to ``N``/``g`` (and to its slot's matrix), and zero it."""
    n_cc, g_c = normal
    for a in range(na):
        ca = cols[a]
        g_c[ca] += gb[a]
        gb[a] = 0.0
        for b in range(na):
            cb = cols[b]
            n_cc[ca, cb] += blk[a, b]
            if slot >= 0:
                slot_n[slot, ca - col_off, cb - col_off] += blk[a, b]
            blk[a, b] = 0.0


#: Runs of equal patterns shorter than this are accumulated row by row even when
#: their partials are factored: the moment form's flush (``na^2 k^2 / 2``) would cost
#: more than it saves (``~2 na^2`` per row).
MIN_MOMENT_RUN = 16


@_jit
def linearize_rows(
    proj: tuple[F64, F64, Any],
    observed: tuple[F64, F64, F64],
    loss: int,
    thr: F64,
    partials: tuple[F64, F64, Any, Any, F64, Any, F64],
    gp: Any,
    tables: tuple[Any, Any, Any],
    slots: tuple[Any, F64, int],
    normal: tuple[F64, F64],
    out: tuple[F64, F64, F64],
) -> None:
    """Residuals, robust weights and the normal equations of a chunk, in one pass.

    The compiled twin of the per-chunk numpy code of
    :meth:`~planetref.adjust.linearization.LinearizationMixin._linearize` and its
    :meth:`~planetref.adjust.linearization.LinearizationMixin._accumulate` (the numpy
    reference): ``r = projected - observed``, ``s = r^T W0 r``, the IRLS weight
    ``W = W0 rho'(s)`` (:func:`~planetref.adjust.robust.robust_rho`), invalid rows weight
    0 and ``s = inf``; then ``N += A^T W A`` and ``g += A^T W r`` over each pattern's
    active columns. Runs of equal patterns (rows sorted by line) are summed in a small
    dense block, added to ``N`` (and to the slot's matrix) once per run; a run also ends
    where the slot changes.

    Within a run, two forms give the same sums:

    - Row by row: each row's two image rows (line, sample) in one rank-2 update of the
      ``na x na`` block of active columns (measured: the full square update is faster
      than the upper triangle, which does not vectorise, and than one BLAS product per
      run of gathered rows).
    - Moments, when the partials are factored with Lagrange weights (a line scanner's:
      column ``(c, j)`` is ``imp[:, c] * w_j(tau)``, ``w_j`` a polynomial of degree
      ``k - 1`` in the time ``tau`` within the run's window) and the run has at least
      :data:`MIN_MOMENT_RUN` rows. Each row adds ``M = sum_r e_r imp_r imp_r^T`` over
      the run's distinct sources of ``imp`` (3 for node attitudes) times
      ``tau^0 ... tau^(2k-2)``, and ``sum_r e_r imp_r res_r`` times ``tau^0 ... tau^(k-1)``;
      the block is expanded once per run:
      ``N[(c,j),(c',j')] = sum_{q,q'} a_jq a_j'q' H_{q+q'}[c,c']`` with ``a_jq`` the
      window's basis coefficients. With 4 nodes and 3 attitude sources that is ~70
      multiply-adds per row instead of ~310 (with 6 EO sources, ~220 instead of
      ~1200). The basis is centred on its window (``tau`` within ~1.5 node spacings),
      so the expansion loses only a few bits to cancellation (a test binds the two
      forms and the numpy reference).

    Args:
        proj: ``(line, sample, valid)`` projected, ``(m,)`` each.
        observed: ``(line, sample, w0)``: observed ``(m,)``, ``(m,)`` and the a-priori
            weights ``(m, 2)`` (1/sigma^2, line then sample).
        loss: :data:`LOSS_CODES` code.
        thr: Robust threshold (normalised units), ``(1,)`` or per row ``(m,)``.
        partials: ``(imp, weights, src, node, tau, start, coef)``: the partials in
            pattern column order are ``imp[i, r, src[c]] * weights[i, node[c]]`` (times 1
            where ``node[c] < 0``): a line scanner's node columns are multiplied out here
            (:class:`~planetref.adjust.models.protocol.Evaluation` ``factors``), where
            ``weights[i, j] = sum_q coef[start[i], j, q] tau[i]^q``; plain partials
            ``d (m, 2, q)`` are ``(d, any, arange(q), -1, (0,), (0,), (0, 0, 0))``;
            factored partials without ``tau`` (``(0,)``) are accumulated row by row.
        gp: Global pattern of each row ``(m,)``.
        tables: ``(act_n, act_loc, act_col)``: per pattern, the number of active
            columns, their local (pattern) indices and global columns (padded).
        slots: ``(slot of each row (-1: none), slot matrices (n_slot, P_m + 1, P_m + 1),
            the model's first global column)``; a run's block is also added to its
            slot's matrix over the model's own columns.
        normal: ``(n_cc (P + 1, P + 1), g_c (P + 1,))``, added to in place.
        out: ``(r (m, 2), s (m,), weight (m, 2))``, written.
    """
    p_line, p_samp, valid = proj
    o_line, o_samp, w0 = observed
    act_n, act_loc, act_col = tables
    slot, slot_n, col_off = slots
    r, s_out, weight = out
    imp, wn, src, node, tau, start, coef = partials
    m = gp.shape[0]
    q = act_loc.shape[1]
    per_row = thr.shape[0] == m and m != 1
    blk = np.zeros((q, q))
    gb = np.zeros(q)
    v0 = np.empty(q)
    v1 = np.empty(q)
    # Per run, each active column's source in ``imp`` and its factor's slot in ``wk``
    # (the row's weights, then 1 for columns without one).
    asrc = np.empty(q, np.intp)
    anode = np.empty(q, np.intp)
    k = wn.shape[1]
    wk = np.ones(k + 1)
    factored = wn.shape[0] == m and m > 0
    moments = factored and tau.shape[0] == m
    # The moment form's scratch: distinct sources, each column's source index and
    # basis coefficients, the pair index of two sources, the moments.
    kp = coef.shape[2] if moments else 1
    nmom = 2 * kp - 1
    usrc = np.empty(q, np.intp)
    ua = np.empty(q, np.intp)
    pa = np.zeros((q, kp))
    pair = np.empty((q, q), np.intp)
    hm = np.zeros((nmom, q * (q + 1) // 2))
    gm = np.zeros((kp, q))
    mv = np.empty(q * (q + 1) // 2)
    gv = np.empty(q)
    tp = np.empty(nmom)
    x0 = np.empty(q)
    x1 = np.empty(q)
    ns = 0
    npair = 0
    a0 = 0
    while a0 < m:
        g = gp[a0]
        sl = slot[a0]
        b0 = a0 + 1
        # With the moment form a run also keeps one window (equal patterns imply it
        # for valid rows; invalid ones carry pattern 0 whatever their window).
        while b0 < m and gp[b0] == g and slot[b0] == sl and (not moments or start[b0] == start[a0]):
            b0 += 1
        na = act_n[g]
        for a in range(na):
            col = act_loc[g, a]
            asrc[a] = src[col]
            anode[a] = node[col] if node[col] >= 0 else k
        use_mom = moments and b0 - a0 >= MIN_MOMENT_RUN
        if use_mom:
            ns = 0
            for a in range(na):
                u = -1
                for w in range(ns):
                    if usrc[w] == asrc[a]:
                        u = w
                if u < 0:
                    u = ns
                    usrc[ns] = asrc[a]
                    ns += 1
                ua[a] = u
                for qq in range(kp):
                    if anode[a] < k:
                        pa[a, qq] = coef[start[a0], anode[a], qq]
                    else:
                        pa[a, qq] = 1.0 if qq == 0 else 0.0
            npair = 0
            for u in range(ns):
                for w in range(u, ns):
                    pair[u, w] = npair
                    pair[w, u] = npair
                    npair += 1
        for i in range(a0, b0):
            r0 = p_line[i] - o_line[i]
            r1 = p_samp[i] - o_samp[i]
            r[i, 0] = r0
            r[i, 1] = r1
            s = r0 * r0 * w0[i, 0] + r1 * r1 * w0[i, 1]
            rw = 1.0
            if loss != 0:
                t = thr[i] if per_row else thr[0]
                t2 = t * t
                if loss == 1:
                    if s > t2:
                        rw = math.sqrt(t2) / math.sqrt(s)
                else:
                    rw = 1.0 / (1.0 + s / t2)
            if not valid[i]:
                weight[i, 0] = 0.0
                weight[i, 1] = 0.0
                s_out[i] = math.inf
                continue  # weight 0: adds nothing
            e0 = w0[i, 0] * rw
            e1 = w0[i, 1] * rw
            weight[i, 0] = e0
            weight[i, 1] = e1
            s_out[i] = s
            f0 = e0 * r0
            f1 = e1 * r1
            if use_mom:
                t = tau[i]
                tp[0] = 1.0
                for n in range(1, nmom):
                    tp[n] = tp[n - 1] * t
                for u in range(ns):
                    x0[u] = imp[i, 0, usrc[u]]
                    x1[u] = imp[i, 1, usrc[u]]
                hp = 0
                for u in range(ns):
                    gv[u] = x0[u] * f0 + x1[u] * f1
                    y0 = e0 * x0[u]
                    y1 = e1 * x1[u]
                    for w in range(u, ns):
                        mv[hp] = y0 * x0[w] + y1 * x1[w]
                        hp += 1
                # Contiguous inner loops over the pairs (they vectorise).
                for n in range(nmom):
                    tn = tp[n]
                    for hp in range(npair):
                        hm[n, hp] += mv[hp] * tn
                for n in range(kp):
                    tn = tp[n]
                    for u in range(ns):
                        gm[n, u] += gv[u] * tn
                continue
            if factored:
                for j in range(k):
                    wk[j] = wn[i, j]
            for a in range(na):
                f = wk[anode[a]]
                v0[a] = imp[i, 0, asrc[a]] * f
                v1[a] = imp[i, 1, asrc[a]] * f
            for a in range(na):
                y0, y1 = v0[a], v1[a]
                gb[a] += y0 * f0 + y1 * f1
                y0, y1 = e0 * y0, e1 * y1
                for b in range(na):
                    blk[a, b] += y0 * v0[b] + y1 * v1[b]
        if use_mom:  # expand the moments into the block
            for a in range(na):
                u = ua[a]
                acc = 0.0
                for qq in range(kp):
                    acc += pa[a, qq] * gm[qq, u]
                gb[a] = acc
                for b in range(a, na):
                    hp = pair[u, ua[b]]
                    acc = 0.0
                    for qq in range(kp):
                        if pa[a, qq] != 0.0:
                            acc2 = 0.0
                            for q2 in range(kp):
                                acc2 += pa[b, q2] * hm[qq + q2, hp]
                            acc += pa[a, qq] * acc2
                    blk[a, b] = acc
                    blk[b, a] = acc
            hm[:, :npair] = 0.0
            gm[:, :ns] = 0.0
        _flush(blk, gb, na, act_col[g], normal, sl, slot_n, col_off)
        a0 = b0


@_jit
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


@_jit
def tie_rows(
    partials: tuple[F64, F64, Any, Any],
    ground: tuple[F64, Any],
    tie_pos: Any,
    gp: Any,
    out: tuple[F64, F64, Any],
) -> None:
    """Write the partials of a chunk's rows on unknown points into the tie arrays.

    The twin of the numpy scatter in
    :meth:`~planetref.adjust.linearization.LinearizationMixin._linearize` (``_tie_rows``:
    the factors expanded for the tie rows, then fancy-indexed stores): row ``i`` with
    ``tie_pos[i] = t >= 0`` gets ``a_t[t, r, c] = imp[i, r, src[c]] * weights[i, node[c]]``
    (times 1 where ``node[c] < 0``) for its ``len(src)`` pattern columns and 0 in the
    columns after them, ``b_t[t, r, c] = gsrc[i, r, gcol[c]]`` and ``gpat_t[t] =
    gp[i]``: every element of the row is written (the arrays may be a retired
    linearisation's). The same products, so the same numbers bit for bit.

    Args:
        partials: ``(imp, weights, src, node)`` as in :func:`linearize_rows`.
        ground: ``(gsrc (m, 2, *), gcol (3,))``: the array holding the ground partials
            and their three columns in it.
        tie_pos: Row in the tie arrays of each chunk row, or -1, ``(m,)``.
        gp: Global pattern of each row ``(m,)``.
        out: ``(a_t (Mt, 2, q), b_t (Mt, 2, 3), gpat_t (Mt,))``, written at the tie rows.
    """
    imp, wn, src, node = partials
    gsrc, gcol = ground
    a_t, b_t, gpat_t = out
    qm = src.shape[0]
    factored = wn.shape[0] == tie_pos.shape[0] and tie_pos.shape[0] > 0
    for i in range(tie_pos.shape[0]):
        t = tie_pos[i]
        if t < 0:
            continue
        for r in range(2):
            for c in range(qm):
                v = imp[i, r, src[c]]
                if factored and node[c] >= 0:
                    v = v * wn[i, node[c]]
                a_t[t, r, c] = v
            for c in range(qm, a_t.shape[2]):
                a_t[t, r, c] = 0.0
            for c in range(3):
                b_t[t, r, c] = gsrc[i, r, gcol[c]]
        gpat_t[t] = gp[i]


@_jit
def point_redundancy(
    a_u: F64,
    b_u: F64,
    gpat_u: Any,
    w: F64,
    rows: Any,
    starts: Any,
    prior_w: F64,
    q_mat: F64,
    tables: tuple[Any, Any, Any],
    h_out: F64,
    qjj_out: F64,
) -> None:
    """Cofactor diagonals of the observations of unknown points, and the points' cofactors.

    The twin of the pair loop of :func:`planetref.adjust.redundancy._finish` (the numpy
    reference). Point ``u`` owns the kept rows ``rows[starts[u]:starts[u + 1]]`` of
    ``a_u``/``b_u``/``gpat_u`` (``w``: their weights, in the order of ``rows``). With
    ``V = P_u + sum_k B_k^T W_k B_k``, ``C_k = V^-1 B_k^T W_k`` and ``G_ik = A_i Q A_k^T``
    (over each pattern's active columns)::

        T_i = sum_k G_ik C_k^T,   Q_XX = V^-1 + sum_i C_i T_i,
        H_i = G_ii - T_i B_i^T - B_i T_i^T + B_i Q_XX B_i^T

    ``h_out[j]`` gets ``diag(H_i)`` of the ``j``-th row in ``rows``' order (``(n, 2)``),
    ``qjj_out[u]`` gets ``Q_XX`` (``(n_u, 3, 3)``).

    Args:
        a_u: Camera partials ``(Mt, 2, q)`` in pattern column order.
        b_u: Ground partials ``(Mt, 2, 3)``.
        gpat_u: Global pattern of each kept row.
        w: Plain weights ``(n, 2)`` of the rows in ``rows``' order.
        rows: Kept rows, point after point.
        starts: First position in ``rows`` of each point, then ``len(rows)``.
        prior_w: A-priori weight matrices of the points ``(n_u, 3, 3)``.
        q_mat: Cofactor matrix of the camera parameters ``(P, P)``.
        tables: ``(act_n, act_loc, act_col)`` (see :func:`linearize_rows`).
        h_out: Output ``(n, 2)``.
        qjj_out: Output ``(n_u, 3, 3)``.
    """
    act_n, act_loc, act_col = tables
    q = act_loc.shape[1]
    n_max = 0
    for u in range(len(starts) - 1):
        n_max = max(n_max, starts[u + 1] - starts[u])
    # Per observation of the point: Q A_k^T over the active columns of every
    # observation of the point (qa[k, i, a, s]: row i's column a), C_k, T_k.
    qa = np.empty((n_max, n_max, q, 2))
    cm = np.empty((n_max, 3, 2))
    tm = np.empty((n_max, 2, 3))
    gd = np.empty((n_max, 2, 2))
    v = np.empty((3, 3))
    vi = np.empty((3, 3))
    for u in range(len(starts) - 1):
        j0, j1 = starts[u], starts[u + 1]
        n = j1 - j0
        for i in range(3):
            for j in range(3):
                v[i, j] = prior_w[u, i, j]
        for jj in range(j0, j1):
            o = rows[jj]
            for r in range(2):
                wr = w[jj, r]
                for i in range(3):
                    wb = wr * b_u[o, r, i]
                    for j in range(3):
                        v[i, j] += wb * b_u[o, r, j]
        _inverse3(v, vi)
        for k in range(n):
            o = rows[j0 + k]
            for i in range(3):
                for r in range(2):
                    cm[k, i, r] = (
                        vi[i, 0] * b_u[o, r, 0] + vi[i, 1] * b_u[o, r, 1] + vi[i, 2] * b_u[o, r, 2]
                    ) * w[j0 + k, r]
        # qa[k, i, a, s] = sum_b Q[col_a(i), col_b(k)] A_k[s, b].
        for k in range(n):
            ok = rows[j0 + k]
            gk = gpat_u[ok]
            nk = act_n[gk]
            for i in range(n):
                gi = gpat_u[rows[j0 + i]]
                for a in range(act_n[gi]):
                    ca = act_col[gi, a]
                    s0 = 0.0
                    s1 = 0.0
                    for b in range(nk):
                        qv = q_mat[ca, act_col[gk, b]]
                        lb = act_loc[gk, b]
                        s0 += qv * a_u[ok, 0, lb]
                        s1 += qv * a_u[ok, 1, lb]
                    qa[k, i, a, 0] = s0
                    qa[k, i, a, 1] = s1
        for i in range(n):
            oi = rows[j0 + i]
            gi = gpat_u[oi]
            for r in range(2):
                for c in range(3):
                    tm[i, r, c] = 0.0
            for k in range(n):
                # G_ik = A_i (Q A_k^T)
                g00 = g01 = g10 = g11 = 0.0
                for a in range(act_n[gi]):
                    la = act_loc[gi, a]
                    x0, x1 = a_u[oi, 0, la], a_u[oi, 1, la]
                    g00 += x0 * qa[k, i, a, 0]
                    g01 += x0 * qa[k, i, a, 1]
                    g10 += x1 * qa[k, i, a, 0]
                    g11 += x1 * qa[k, i, a, 1]
                if k == i:
                    gd[i, 0, 0], gd[i, 0, 1], gd[i, 1, 0], gd[i, 1, 1] = g00, g01, g10, g11
                for c in range(3):
                    tm[i, 0, c] += g00 * cm[k, c, 0] + g01 * cm[k, c, 1]
                    tm[i, 1, c] += g10 * cm[k, c, 0] + g11 * cm[k, c, 1]
        qx = qjj_out[u]
        for i in range(3):
            for j in range(3):
                acc = vi[i, j]
                for k in range(n):
                    acc += cm[k, i, 0] * tm[k, 0, j] + cm[k, i, 1] * tm[k, 1, j]
                qx[i, j] = acc
        for i in range(n):
            oi = rows[j0 + i]
            for r in range(2):
                tb = 0.0
                bqb = 0.0
                for c in range(3):
                    tb += tm[i, r, c] * b_u[oi, r, c]
                    for d in range(3):
                        bqb += b_u[oi, r, c] * qx[c, d] * b_u[oi, r, d]
                h_out[j0 + i, r] = gd[i, r, r] - 2.0 * tb + bqb


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _inverse3(m: F64, out: F64) -> None:
    """``out = m^-1`` of a 3x3 matrix (cofactors over the determinant)."""
    c00 = m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1]
    c01 = m[1, 2] * m[2, 0] - m[1, 0] * m[2, 2]
    c02 = m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]
    det = m[0, 0] * c00 + m[0, 1] * c01 + m[0, 2] * c02
    inv = 1.0 / det
    out[0, 0] = c00 * inv
    out[1, 0] = c01 * inv
    out[2, 0] = c02 * inv
    out[0, 1] = (m[0, 2] * m[2, 1] - m[0, 1] * m[2, 2]) * inv
    out[1, 1] = (m[0, 0] * m[2, 2] - m[0, 2] * m[2, 0]) * inv
    out[2, 1] = (m[0, 1] * m[2, 0] - m[0, 0] * m[2, 1]) * inv
    out[0, 2] = (m[0, 1] * m[1, 2] - m[0, 2] * m[1, 1]) * inv
    out[1, 2] = (m[0, 2] * m[1, 0] - m[0, 0] * m[1, 2]) * inv
    out[2, 2] = (m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]) * inv
