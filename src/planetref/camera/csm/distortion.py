"""usgscsm's lens distortion models (``radial`` and ``transverse``) on focal-plane mm."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = []


# ---------------------------------------------------------------------------------------
# Lens distortion (focal-plane millimetres), vectorised usgscsm models
# ---------------------------------------------------------------------------------------


def _transverse_poly(
    coeffs: NDArray[np.float64], x: NDArray[np.float64], y: NDArray[np.float64]
) -> tuple[NDArray[np.float64], ...]:
    terms = np.stack(
        [np.ones_like(x), x, y, x * x, x * y, y * y, x**3, x * x * y, x * y * y, y**3], axis=-1
    )
    return terms @ coeffs[:10], terms @ coeffs[10:]


def _transverse_jacobian(
    coeffs: NDArray[np.float64], x: NDArray[np.float64], y: NDArray[np.float64]
) -> tuple[NDArray[np.float64], ...]:
    zero, one = np.zeros_like(x), np.ones_like(x)
    d_dx = np.stack([zero, one, zero, 2 * x, y, zero, 3 * x * x, 2 * x * y, y * y, zero], -1)
    d_dy = np.stack([zero, zero, one, zero, x, 2 * y, zero, x * x, 2 * x * y, 3 * y * y], -1)
    return (d_dx @ coeffs[:10], d_dy @ coeffs[:10], d_dx @ coeffs[10:], d_dy @ coeffs[10:])


def _remove_distortion(
    model: str, coeffs: NDArray[np.float64], dx: NDArray[np.float64], dy: NDArray[np.float64]
) -> tuple[NDArray[np.float64], ...]:
    """Distorted -> undistorted focal-plane coordinates (mm)."""
    if model == "radial":
        rr = dx * dx + dy * dy
        dr = coeffs[0] + rr * (coeffs[1] + rr * coeffs[2])
        return dx * (1.0 - dr), dy * (1.0 - dr)
    # transverse: the polynomial maps undistorted -> distorted; invert by Newton.
    ux, uy = dx.copy(), dy.copy()
    for _ in range(50):
        fx, fy = _transverse_poly(coeffs, ux, uy)
        rx, ry = dx - fx, dy - fy
        jxx, jxy, jyx, jyy = _transverse_jacobian(coeffs, ux, uy)
        det = jxx * jyy - jxy * jyx
        ok = np.abs(det) > 1e-12
        with np.errstate(invalid="ignore", divide="ignore"):
            ux = np.where(ok, ux + (jyy * rx - jxy * ry) / det, ux)
            uy = np.where(ok, uy + (jxx * ry - jyx * rx) / det, uy)
        if np.all(~ok | (np.abs(rx) + np.abs(ry) < 1e-13)):
            break
    return ux, uy


def _apply_distortion(
    model: str, coeffs: NDArray[np.float64], ux: NDArray[np.float64], uy: NDArray[np.float64]
) -> tuple[NDArray[np.float64], ...]:
    """Undistorted -> distorted focal-plane coordinates (mm)."""
    if model == "transverse":
        return _transverse_poly(coeffs, ux, uy)
    # usgscsm's fixed-point iteration r = rp + dr(r) * r, here run to convergence; where it
    # does not converge (far outside the focal plane) no distortion is applied, as usgscsm.
    rp2 = ux * ux + uy * uy
    rp = np.sqrt(rp2)
    k0, k1, k2 = coeffs
    dr = k0 + rp2 * (k1 + rp2 * k2)
    r = rp + dr * rp
    converged = np.zeros(r.shape, dtype=bool)
    for _ in range(50):
        r_prev = r
        dr = np.where(converged, dr, k0 + r * r * (k1 + r * r * k2))
        r = np.where(converged, r, rp + dr * r_prev)
        with np.errstate(invalid="ignore"):
            converged |= np.abs(r - r_prev) <= 1e-14 * np.maximum(1.0, rp)
        if np.all(converged | ~np.isfinite(r)):
            break
    dr = np.where(converged & (np.abs(r) < 1e9), dr, 0.0)
    return ux / (1.0 - dr), uy / (1.0 - dr)
