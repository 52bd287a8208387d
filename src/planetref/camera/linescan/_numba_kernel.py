"""numba implementation of :mod:`planetref.camera.linescan.compiled` (imported lazily).

Importing this module imports numba; the functions compile on first use or load from
numba's on-disk cache.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
_CHORD_ITERATIONS = 40

njit = numba.njit(cache=True, nogil=True, error_model="numpy")


@njit
def row_of(x: float, starts: F64) -> int:
    # np.searchsorted(starts, x, side="right") - 1, clipped to [0, n - 1].
    j = len(starts) - 1
    while j > 0 and starts[j] > x:
        j -= 1
    return j


@njit
def window_of(t: float, times: F64, k: int) -> int:
    n = len(times)
    i = n - 1
    while i >= 0 and times[i] > t:
        i -= 1
    s = i - k // 2 + 1
    if s < 0:
        s = 0
    if s > n - k:
        s = n - k
    return s


@njit
def evaluate(
    line: float,
    rs: F64,
    rt0: F64,
    rp: F64,
    times: F64,
    centre: F64,
    k: int,
    poly: F64,
    r0: F64,
    io: F64,
    ccd: F64,
    p: F64,
    full: bool,
    eo: F64,
    deo: F64,
    res: F64,
) -> int:
    """Offset, sample, depth (res[0:3]); with ``full`` also EO and its derivative."""
    j = row_of(line, rs)
    t = rt0[j] + (line - rs[j]) * rp[j]
    s = window_of(t, times, k)
    tau = t - centre[s]
    for c in range(6):
        v = poly[s, k - 1, c]
        for q in range(k - 2, -1, -1):
            v = v * tau + poly[s, q, c]
        eo[c] = v
        if full:
            d = (k - 1) * poly[s, k - 1, c]
            for q in range(k - 2, 0, -1):
                d = d * tau + q * poly[s, q, c]
            deo[c] = d
    e0 = p[0] - eo[0]
    e1 = p[1] - eo[1]
    e2 = p[2] - eo[2]
    d0 = e0 * r0[0, 0] + e1 * r0[1, 0] + e2 * r0[2, 0]
    d1 = e0 * r0[0, 1] + e1 * r0[1, 1] + e2 * r0[2, 1]
    d2 = e0 * r0[0, 2] + e1 * r0[1, 2] + e2 * r0[2, 2]
    cp, sp = math.cos(eo[3]), math.sin(eo[3])
    co, so = math.cos(eo[4]), math.sin(eo[4])
    ck, sk = math.cos(eo[5]), math.sin(eo[5])
    a0 = cp * d0 + sp * d2
    a2 = -sp * d0 + cp * d2
    b1 = co * d1 + so * a2
    b2 = -so * d1 + co * a2
    u = ck * a0 + sk * b1
    v_ = -sk * a0 + ck * b1
    w = b2
    inv_w = 1.0 / w
    xn = u * inv_w
    yn = v_ * inv_w
    x0, y0, f = io[0], io[1], io[2]
    sa, ca, pitch = ccd[4], ccd[5], ccd[3]
    dx = x0 - f * xn - ccd[0]
    dy = y0 - f * yn - ccd[1]
    res[0] = (dx * ca - dy * sa) / pitch  # offset
    res[1] = (dx * sa + dy * ca) / pitch  # sample
    res[2] = w
    if not full:
        return s
    # Partials (see kernel.state): jac rows 0-2 = d(u,v,w)/dP, 3-5 angles.
    res[3] = u
    res[4] = v_
    res[5] = a0
    res[6] = a2
    res[7] = b1
    res[8] = rp[j]
    res[9] = tau
    return s


@njit
def project(
    rs: F64,
    rt0: F64,
    rp: F64,
    times: F64,
    centre: F64,
    coef: F64,
    r0: F64,
    k: int,
    lo: float,
    hi: float,
    poly: F64,
    io: F64,
    ccd: F64,
    pts: F64,
    guess: F64,
    rate_in: F64,
    full: bool,
    chord_tol: float,
    step_valid: float,
    out_line: F64,
    out_samp: F64,
    out_valid: Any,
    out_rate: F64,
    out_start: Any,
    out_w: F64,
    out_imp: F64,
) -> None:
    eo = np.empty(6)
    deo = np.empty(6)
    res = np.empty(10)
    jac = np.empty((6, 3))
    raw = np.empty((2, 15))
    f = io[2]
    sa, ca, pitch = ccd[4], ccd[5], ccd[3]
    for i in range(len(pts)):
        p = pts[i]
        line = guess[i]
        if not math.isfinite(line):
            line = 0.5 * (lo + hi)
        line = min(max(line, lo), hi)
        evaluate(line, rs, rt0, rp, times, centre, k, poly, r0, io, ccd, p, False, eo, deo, res)
        off = res[0]
        rate = rate_in[i]
        if not (math.isfinite(rate) and rate != 0.0):
            evaluate(
                line + 1.0, rs, rt0, rp, times, centre, k, poly, r0, io, ccd, p, False, eo,
                deo, res,
            )  # fmt: skip
            rate = res[0] - off
        step = -off / rate
        active = math.isfinite(step) and abs(step) > chord_tol
        for _ in range(_CHORD_ITERATIONS):
            if not active:
                break
            line = min(max(line + step, lo), hi)
            evaluate(line, rs, rt0, rp, times, centre, k, poly, r0, io, ccd, p, False, eo, deo, res)
            step = -res[0] / rate
            active = math.isfinite(step) and abs(step) > chord_tol
        if not full:
            evaluate(line, rs, rt0, rp, times, centre, k, poly, r0, io, ccd, p, False, eo, deo, res)
            step = -res[0] / rate
            lo_ = line + step
            out_line[i] = lo_
            out_samp[i] = res[1]
            out_rate[i] = rate
            out_valid[i] = (
                math.isfinite(lo_)
                and math.isfinite(res[1])
                and res[2] < 0
                and abs(step) < step_valid
                and lo_ >= lo
                and lo_ <= hi
            )
            continue
        s = evaluate(line, rs, rt0, rp, times, centre, k, poly, r0, io, ccd, p, True, eo, deo, res)
        off, samp, w = res[0], res[1], res[2]
        u, v_, a0, a2, b1, period, tau = res[3], res[4], res[5], res[6], res[7], res[8], res[9]
        b2 = w
        cp, sp = math.cos(eo[3]), math.sin(eo[3])
        co, so = math.cos(eo[4]), math.sin(eo[4])
        ck, sk = math.cos(eo[5]), math.sin(eo[5])
        bp1 = so * (-a0)
        jac[3, 0] = ck * a2 + sk * bp1
        jac[3, 1] = -sk * a2 + ck * bp1
        jac[3, 2] = co * (-a0)
        jac[4, 0] = sk * b2
        jac[4, 1] = ck * b2
        jac[4, 2] = -b1
        jac[5, 0] = v_
        jac[5, 1] = -u
        jac[5, 2] = 0.0
        for r in range(3):
            e0, e1, e2 = r0[r, 0], r0[r, 1], r0[r, 2]
            ga0 = cp * e0 + sp * e2
            ga2 = -sp * e0 + cp * e2
            gb1 = co * e1 + so * ga2
            jac[r, 0] = ck * ga0 + sk * gb1
            jac[r, 1] = -sk * ga0 + ck * gb1
            jac[r, 2] = -so * e1 + co * ga2
        inv_w = 1.0 / w
        xn = u * inv_w
        yn = v_ * inv_w
        fw = -f * inv_w / pitch
        c_ca = fw * ca
        c_sa = fw * sa
        rate_f = 0.0
        srate = 0.0
        for q in range(6):
            dxq = jac[q, 0] - xn * jac[q, 2]
            dyq = jac[q, 1] - yn * jac[q, 2]
            doff = dxq * c_ca - dyq * c_sa
            dsmp = dxq * c_sa + dyq * c_ca
            if q < 3:
                raw[0, 9 + q] = doff
                raw[1, 9 + q] = dsmp
                raw[0, q] = -doff
                raw[1, q] = -dsmp
            else:
                raw[0, q] = doff
                raw[1, q] = dsmp
        raw[0, 6], raw[1, 6] = ca / pitch, sa / pitch
        raw[0, 7], raw[1, 7] = -sa / pitch, ca / pitch
        raw[0, 8] = (-xn * ca + yn * sa) / pitch
        raw[1, 8] = (-xn * sa - yn * ca) / pitch
        raw[0, 12], raw[1, 12] = -ca / pitch, -sa / pitch
        raw[0, 13], raw[1, 13] = sa / pitch, -ca / pitch
        raw[0, 14] = -samp
        raw[1, 14] = off
        for q in range(6):
            rate_f += raw[0, q] * deo[q]
            srate += raw[1, q] * deo[q]
        rate_f *= period
        srate *= period
        step = -off / rate_f
        nir = -1.0 / rate_f
        lo_ = line + step
        so_ = samp + srate * step
        out_line[i] = lo_
        out_samp[i] = so_
        out_rate[i] = rate_f
        out_valid[i] = (
            math.isfinite(lo_)
            and math.isfinite(so_)
            and w < 0
            and abs(step) < step_valid
            and lo_ >= lo
            and lo_ <= hi
        )
        out_start[i] = s
        for jb in range(k):
            wv = coef[s, jb, k - 1]
            for q in range(k - 2, -1, -1):
                wv = wv * tau + coef[s, jb, q]
            out_w[i, jb] = wv
        for q in range(15):
            a = raw[0, q] * nir
            out_imp[i, 0, q] = a
            out_imp[i, 1, q] = a * srate + raw[1, q]
