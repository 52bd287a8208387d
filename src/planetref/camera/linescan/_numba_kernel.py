"""numba implementation of :mod:`planetref.camera.linescan.compiled` (imported lazily).

Importing this module imports numba; the functions compile on first use or load from
numba's on-disk cache.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

from planetref.arrays import F64

_CHORD_ITERATIONS = 40

njit = numba.njit(cache=True, nogil=True, error_model="numpy", fastmath={"contract"})


_inline = numba.njit(
    cache=True, nogil=True, error_model="numpy", inline="always", fastmath={"contract"}
)


@_inline
def row_of(x: float, starts: F64) -> int:
    # np.searchsorted(starts, x, side="right") - 1, clipped to [0, n - 1].
    j = len(starts) - 1
    while j > 0 and starts[j] > x:
        j -= 1
    return j


@_inline
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


@_inline
def horner(poly: F64, s: int, k: int, c: int, tau: float) -> float:
    v = poly[s, k - 1, c]
    for q in range(k - 2, -1, -1):
        v = v * tau + poly[s, q, c]
    return v


@_inline
def horner_dt(poly: F64, s: int, k: int, c: int, tau: float) -> float:
    d = (k - 1) * poly[s, k - 1, c]
    for q in range(k - 2, 0, -1):
        d = d * tau + q * poly[s, q, c]
    return d


@_inline
def locate(line: float, rs: F64, rt0: F64, rp: F64, times: F64, centre: F64, k: int) -> Any:
    """Window start, time within the window and line period at a line."""
    j = row_of(line, rs)
    t = rt0[j] + (line - rs[j]) * rp[j]
    s = window_of(t, times, k)
    return s, t - centre[s], rp[j]


#: Angle changes below which cos/sin are updated from the previous evaluation's
#: (rad): the series below are then exact to double precision.
_NEAR_RAD = 1e-4


@_inline
def cos_sin(a: float, a0: float, c0: float, s0: float, near: bool) -> Any:
    """``(cos a, sin a)``, from those of a nearby angle ``a0`` when ``near``.

    Chord iterations move the line by pixels: the attitude changes by ~1e-9 rad, and
    the angle-addition formulas with 5th-order series of the change replace two
    library calls (a few ulp from ``math.cos``/``math.sin``).
    """
    d = a - a0
    if near and abs(d) < _NEAR_RAD:
        d2 = d * d
        cd = 1.0 - d2 * (0.5 - d2 * (1.0 / 24.0))
        sd = d * (1.0 - d2 * (1.0 / 6.0 - d2 * (1.0 / 120.0)))
        return c0 * cd - s0 * sd, s0 * cd + c0 * sd
    return math.cos(a), math.sin(a)


@_inline
def collinear(
    poly: F64,
    s: int,
    k: int,
    tau: float,
    r0: F64,
    io: F64,
    ccd: F64,
    p: F64,
    i: int,
    prev: Any,
    near: bool,
) -> Any:
    """Offset, sample, depth and the intermediate terms of point ``p[i]`` at ``(s, tau)``.

    Scalars only (no temporaries): ``(offset, sample, w, u, v, a0, a2, b1, cos phi,
    sin phi, cos omega, sin omega, cos kappa, sin kappa, phi, omega, kappa)``. With
    ``near``, the cosines and sines come from ``prev`` (an earlier result for the same
    point) where the angles moved little (:func:`cos_sin`).
    """
    e0 = p[i, 0] - horner(poly, s, k, 0, tau)
    e1 = p[i, 1] - horner(poly, s, k, 1, tau)
    e2 = p[i, 2] - horner(poly, s, k, 2, tau)
    phi = horner(poly, s, k, 3, tau)
    omega = horner(poly, s, k, 4, tau)
    kappa = horner(poly, s, k, 5, tau)
    d0 = e0 * r0[0, 0] + e1 * r0[1, 0] + e2 * r0[2, 0]
    d1 = e0 * r0[0, 1] + e1 * r0[1, 1] + e2 * r0[2, 1]
    d2 = e0 * r0[0, 2] + e1 * r0[1, 2] + e2 * r0[2, 2]
    cp, sp = cos_sin(phi, prev[14], prev[8], prev[9], near)
    co, so = cos_sin(omega, prev[15], prev[10], prev[11], near)
    ck, sk = cos_sin(kappa, prev[16], prev[12], prev[13], near)
    a0 = cp * d0 + sp * d2
    a2 = -sp * d0 + cp * d2
    b1 = co * d1 + so * a2
    b2 = -so * d1 + co * a2
    u = ck * a0 + sk * b1
    v_ = -sk * a0 + ck * b1
    inv_w = 1.0 / b2
    xn = u * inv_w
    yn = v_ * inv_w
    sa, ca, pitch = ccd[4], ccd[5], ccd[3]
    dx = io[0] - io[2] * xn - ccd[0]
    dy = io[1] - io[2] * yn - ccd[1]
    off = (dx * ca - dy * sa) / pitch
    samp = (dx * sa + dy * ca) / pitch
    return off, samp, b2, u, v_, a0, a2, b1, cp, sp, co, so, ck, sk, phi, omega, kappa


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
    out_tau: F64,
) -> None:
    jac = np.empty((6, 3))
    raw = np.empty((2, 15))
    deo = np.empty(6)
    f = io[2]
    sa, ca, pitch = ccd[4], ccd[5], ccd[3]
    none = (0.0,) * 17  # no earlier evaluation
    for i in range(len(pts)):
        line = guess[i]
        if not math.isfinite(line):
            line = 0.5 * (lo + hi)
        line = min(max(line, lo), hi)
        # ``ev`` always holds the evaluation at ``line``: the last one of the chord
        # iterations is the final one (its terms give the partials).
        s, tau, period = locate(line, rs, rt0, rp, times, centre, k)
        ev = collinear(poly, s, k, tau, r0, io, ccd, pts, i, none, False)
        off = ev[0]
        rate = rate_in[i]
        if not (math.isfinite(rate) and rate != 0.0):
            s1, tau1, _ = locate(line + 1.0, rs, rt0, rp, times, centre, k)
            rate = collinear(poly, s1, k, tau1, r0, io, ccd, pts, i, ev, True)[0] - off
        step = -off / rate
        active = math.isfinite(step) and abs(step) > chord_tol
        for _ in range(_CHORD_ITERATIONS):
            if not active:
                break
            line = min(max(line + step, lo), hi)
            s, tau, period = locate(line, rs, rt0, rp, times, centre, k)
            ev = collinear(poly, s, k, tau, r0, io, ccd, pts, i, ev, True)
            step = -ev[0] / rate
            active = math.isfinite(step) and abs(step) > chord_tol
        if not full:
            step = -ev[0] / rate
            lo_ = line + step
            out_line[i] = lo_
            out_samp[i] = ev[1]
            out_rate[i] = rate
            out_valid[i] = (
                math.isfinite(lo_)
                and math.isfinite(ev[1])
                and ev[2] < 0
                and abs(step) < step_valid
                and lo_ >= lo
                and lo_ <= hi
            )
            continue
        off, samp, w, u, v_, a0, a2, b1, cp, sp, co, so, ck, sk, _, _, _ = ev
        for c in range(6):
            deo[c] = horner_dt(poly, s, k, c, tau)
        b2 = w
        # Partials (see kernel.state): jac rows 0-2 = d(u,v,w)/dP, 3-5 angles.
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
        out_tau[i] = tau
        for jb in range(k):
            wv = coef[s, jb, k - 1]
            for q in range(k - 2, -1, -1):
                wv = wv * tau + coef[s, jb, q]
            out_w[i, jb] = wv
        for q in range(15):
            a = raw[0, q] * nir
            out_imp[i, 0, q] = a
            out_imp[i, 1, q] = a * srate + raw[1, q]


@njit
def fill_partials(imp: F64, weights: F64, placement: bool, dp: F64, dg: F64) -> None:
    """Adjustment partials from a projection's (see ``LineScanParameterization.evaluate``).

    ``dp[:, :, 6 j + c] = imp[:, :, c] * weights[:, j]`` (node ``j`` of the window, EO
    column ``c``), then the interior (and placement) columns; ``dg`` the ground columns.
    """
    m = imp.shape[0]
    k = weights.shape[1]
    k6 = 6 * k
    for i in range(m):
        for r in range(2):
            for j in range(k):
                wj = weights[i, j]
                for c in range(6):
                    dp[i, r, 6 * j + c] = imp[i, r, c] * wj
            for c in range(3):
                dp[i, r, k6 + c] = imp[i, r, 6 + c]
                dg[i, r, c] = imp[i, r, 9 + c]
            if placement:
                for c in range(3):
                    dp[i, r, k6 + 3 + c] = imp[i, r, 12 + c]
