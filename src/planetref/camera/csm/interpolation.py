"""Interpolation of ephemerides as usgscsm does it.

Cubic Hermite (with velocities) or natural cubic spline resampling to evenly spaced
epochs, and Lagrange interpolation whose order drops near the ends of the table.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = []


def interp_index(
    times: NDArray[np.float64], t: NDArray[np.float64]
) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """ALE's ``interpolationIndex`` and the fraction within the interval."""
    idx = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    frac = (t - times[idx]) / (times[idx + 1] - times[idx])
    return idx, frac


# ---------------------------------------------------------------------------------------
# Interpolation as usgscsm does it
# ---------------------------------------------------------------------------------------


def hermite(
    times: NDArray[np.float64],
    pos: NDArray[np.float64],
    vel: NDArray[np.float64],
    t: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """ALE's cubic Hermite position and derivative (times centred on their midpoint)."""
    base = (times[0] + times[-1]) / 2.0
    x = times - base
    s = t - base
    idx, _ = interp_index(x, s)
    x0, x1 = x[idx], x[idx + 1]
    h = (x1 - x0)[:, None]
    u = ((s - x0) / (x1 - x0))[:, None]
    y0, y1, m0, m1 = pos[idx], pos[idx + 1], vel[idx], vel[idx + 1]
    p = (
        (2 * u**3 - 3 * u**2 + 1) * y0
        + (u**3 - 2 * u**2 + u) * h * m0
        + (-2 * u**3 + 3 * u**2) * y1
        + (u**3 - u**2) * h * m1
    )
    v = (
        (6 * u**2 - 6 * u) * y0
        + (3 * u**2 - 4 * u + 1) * h * m0
        + (-6 * u**2 + 6 * u) * y1
        + (3 * u**2 - 2 * u) * h * m1
    ) / h
    return p, v


def natural_spline(
    times: NDArray[np.float64], values: NDArray[np.float64], t: NDArray[np.float64]
) -> NDArray[np.float64]:
    """GSL's ``cspline`` (natural cubic spline), linear for two points."""
    if len(times) < 3:
        idx, frac = interp_index(times, t)
        return values[idx] + frac[:, None] * (values[idx + 1] - values[idx])
    from scipy.interpolate import CubicSpline

    return CubicSpline(times, values, axis=0, bc_type="natural")(t)


def lagrange(
    values: NDArray[np.float64], t0: float, dt: float, t: NDArray[np.float64], max_order: int
) -> NDArray[np.float64]:
    """Port of usgscsm's ``lagrangeInterp`` on evenly spaced nodes, vectorised.

    The order is 8 (or ``max_order``) in the middle and drops to 6, 4 and 2 (linear) in
    the three intervals nearest each end; times outside the nodes extrapolate with the
    first/last interval's polynomial.
    """
    n = values.shape[0]
    t = np.asarray(t, dtype=np.float64)
    finite = np.isfinite(t)
    fndex = np.where(finite, (np.where(finite, t, t0) - t0) / dt, 0.0)
    # C++ static_cast<int> truncates towards zero before the clamping.
    index = np.clip(np.trunc(np.clip(fndex, -1e9, 1e9)).astype(np.int64), 0, n - 2)
    order = np.full(index.shape, 2)
    order = np.where((index >= 1) & (index < n - 2), 4, order)
    order = np.where((index >= 2) & (index < n - 3), 6, order)
    order = np.where((index >= 3) & (index < n - 4), 8, order)
    order = np.minimum(order, max_order)
    tau = fndex - index
    out = np.zeros(t.shape + values.shape[1:])
    for o in np.unique(order):
        sel = order == o
        half = int(o) // 2
        offs = np.arange(-(half - 1), half + 1)
        ts = tau[sel][:, None]
        w = np.ones((ts.shape[0], len(offs)))
        for k, ok in enumerate(offs):
            for oj in offs:
                if oj != ok:
                    w[:, k] *= (ts[:, 0] - oj) / (ok - oj)
        nodes = index[sel][:, None] + offs[None, :]
        out[sel] = np.einsum("mk,mk...->m...", w, values[nodes])
    out[~finite] = np.nan
    return out
