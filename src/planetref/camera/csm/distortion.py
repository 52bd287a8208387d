"""usgscsm's lens distortion models (``radial``, ``transverse``, ``radtan``) on focal-plane mm.

All functions work on focal-plane coordinates in mm about the focal-plane origin (the
principal point), in the ISD's sensor frame. *Apply* maps undistorted -> distorted (used
by ground-to-image), *remove* distorted -> undistorted (image-to-ground), as usgscsm's
``applyDistortion`` / ``removeDistortion``:

* ``radial`` (3 coefficients, mm based): remove ``u = d (1 - (k0 + k1 r^2 + k2 r^4))``
  with ``r = |d|``; apply by usgscsm's fixed-point iteration.
* ``transverse`` (10 + 10 coefficients): apply is the cubic polynomial of each axis
  (terms ``1, x, y, x^2, xy, y^2, x^3, x^2 y, x y^2, y^3``); remove by Newton.
* ``radtan`` (5 coefficients ``k1, k2, p1, p2, k3``, OpenCV's order and formula) on
  coordinates normalised by the focal length, ``(x, y) = (u_x, u_y) / f``: apply is::

      x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
      y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y

  times ``f``; remove by Newton. (usgscsm's ``RadTanInversionTest``: ``f = 1000``,
  ``(5, 6)`` mm with its coefficients -> ``(5.0000006007539586, 6.0000016383447505)``.)

Newton inversions run to 1e-13 mm (usgscsm stops at its tolerance).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from planetref.arrays import F64

__all__ = ["radtan_basis", "radtan_displacement"]

#: ``(x, y) -> (fx, fy, dfx/dx, dfx/dy, dfy/dx, dfy/dy)``: a forward map and its Jacobian.
_Forward = Callable[[F64, F64], tuple[F64, F64, F64, F64, F64, F64]]


def _transverse_poly(coeffs: F64, x: F64, y: F64) -> tuple[F64, F64]:
    terms = np.stack(
        [np.ones_like(x), x, y, x * x, x * y, y * y, x**3, x * x * y, x * y * y, y**3], axis=-1
    )
    return terms @ coeffs[:10], terms @ coeffs[10:]


def _transverse_jacobian(coeffs: F64, x: F64, y: F64) -> tuple[F64, F64, F64, F64]:
    zero, one = np.zeros_like(x), np.ones_like(x)
    d_dx = np.stack([zero, one, zero, 2 * x, y, zero, 3 * x * x, 2 * x * y, y * y, zero], -1)
    d_dy = np.stack([zero, zero, one, zero, x, 2 * y, zero, x * x, 2 * x * y, 3 * y * y], -1)
    return (d_dx @ coeffs[:10], d_dy @ coeffs[:10], d_dx @ coeffs[10:], d_dy @ coeffs[10:])


def radtan_displacement(coeffs: F64, x: F64, y: F64) -> tuple[F64, F64]:
    """``radtan``'s displacement ``(x_d - x, y_d - y)`` at normalised coordinates."""
    k1, k2, p1, p2, k3 = (float(c) for c in coeffs)
    r2 = x * x + y * y
    radial = r2 * (k1 + r2 * (k2 + r2 * k3))
    return (
        x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
        y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
    )


def radtan_basis(x: F64, y: F64) -> tuple[F64, F64]:
    """The displacement's partials w.r.t. ``(k1, k2, p1, p2, k3)``: two ``(m, 5)`` arrays.

    ``radtan_displacement(c, x, y) == (bx @ c, by @ c)``: the model is linear in its
    coefficients (used to fit them).
    """
    r2 = x * x + y * y
    bx = np.stack([x * r2, x * r2 * r2, 2.0 * x * y, r2 + 2.0 * x * x, x * r2**3], axis=-1)
    by = np.stack([y * r2, y * r2 * r2, r2 + 2.0 * y * y, 2.0 * x * y, y * r2**3], axis=-1)
    return bx, by


def _radtan_forward(coeffs: F64, f: float) -> _Forward:
    """``radtan``'s apply (in mm) with its Jacobian, for the Newton inversion."""
    k1, k2, p1, p2, k3 = (float(c) for c in coeffs)

    def forward(ux: F64, uy: F64) -> tuple[F64, F64, F64, F64, F64, F64]:
        x, y = ux / f, uy / f
        r2 = x * x + y * y
        g = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dg = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3))  # d g / d(r^2), times 2
        ddx, ddy = radtan_displacement(coeffs, x, y)
        jxx = g + x * x * dg + 2.0 * p1 * y + 6.0 * p2 * x
        jxy = x * y * dg + 2.0 * p1 * x + 2.0 * p2 * y
        jyx = x * y * dg + 2.0 * p1 * x + 2.0 * p2 * y
        jyy = g + y * y * dg + 6.0 * p1 * y + 2.0 * p2 * x
        return ux + f * ddx, uy + f * ddy, jxx, jxy, jyx, jyy

    return forward


def _transverse_forward(coeffs: F64) -> _Forward:
    def forward(ux: F64, uy: F64) -> tuple[F64, F64, F64, F64, F64, F64]:
        return (*_transverse_poly(coeffs, ux, uy), *_transverse_jacobian(coeffs, ux, uy))

    return forward


def _newton_inverse(forward: _Forward, dx: F64, dy: F64) -> tuple[F64, F64]:
    """Undistorted ``(x, y)`` with ``forward(x, y) = (dx, dy)`` (2-D Newton from ``(dx, dy)``)."""
    ux, uy = dx.copy(), dy.copy()
    for _ in range(50):
        fx, fy, jxx, jxy, jyx, jyy = forward(ux, uy)
        rx, ry = dx - fx, dy - fy
        det = jxx * jyy - jxy * jyx
        ok = np.abs(det) > 1e-12
        with np.errstate(invalid="ignore", divide="ignore"):
            ux = np.where(ok, ux + (jyy * rx - jxy * ry) / det, ux)
            uy = np.where(ok, uy + (jxx * ry - jyx * rx) / det, uy)
        if np.all(~ok | (np.abs(rx) + np.abs(ry) < 1e-13)):
            break
    return ux, uy


def remove_distortion(
    model: str, coeffs: F64, dx: F64, dy: F64, *, focal_length_mm: float | None = None
) -> tuple[F64, ...]:
    """Distorted -> undistorted focal-plane coordinates (mm).

    ``focal_length_mm`` (the ISD's) is needed by ``radtan`` only.
    """
    if model == "radial":
        rr = dx * dx + dy * dy
        dr = coeffs[0] + rr * (coeffs[1] + rr * coeffs[2])
        return dx * (1.0 - dr), dy * (1.0 - dr)
    if model == "radtan":
        return _newton_inverse(_radtan_forward(coeffs, _focal(focal_length_mm)), dx, dy)
    # transverse: the polynomial maps undistorted -> distorted; invert by Newton.
    return _newton_inverse(_transverse_forward(coeffs), dx, dy)


def apply_distortion(
    model: str, coeffs: F64, ux: F64, uy: F64, *, focal_length_mm: float | None = None
) -> tuple[F64, ...]:
    """Undistorted -> distorted focal-plane coordinates (mm).

    ``focal_length_mm`` (the ISD's) is needed by ``radtan`` only.
    """
    if model == "transverse":
        return _transverse_poly(coeffs, ux, uy)
    if model == "radtan":
        f = _focal(focal_length_mm)
        ddx, ddy = radtan_displacement(coeffs, ux / f, uy / f)
        return ux + f * ddx, uy + f * ddy
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


def _focal(focal_length_mm: float | None) -> float:
    if focal_length_mm is None or not focal_length_mm > 0:
        raise ValueError(f"radtan distortion needs the focal length, got {focal_length_mm}")
    return float(focal_length_mm)
