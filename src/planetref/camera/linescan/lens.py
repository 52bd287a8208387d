"""Lens distortion of a line-scan camera's focal plane (Brown-Conrady, detector -> ideal).

A CCD pixel's physical (detector) position ``(x, y)`` in the focal plane (mm, about the
focal-plane origin, the optical axis) is seen along the ray of the *ideal* position
``(x, y) + D(x, y)`` with ``r^2 = x^2 + y^2`` and::

    Dx = x (k1 r^2 + k2 r^4) + p1 (r^2 + 2 x^2) + 2 p2 x y
    Dy = y (k1 r^2 + k2 r^4) + p2 (r^2 + 2 y^2) + 2 p1 x y

(``k1`` in mm^-2, ``k2`` in mm^-4, ``p1``, ``p2`` in mm^-1). Along a line array this
bends the CCD's image in object space: the radial terms stretch it non-linearly along
the array, the decentering terms bow it along track. planetref's simulator puts it in the
*true* camera only (the estimated model has no distortion term). The inverse (ideal ->
detector, used when projecting ground points) is a fixed-point iteration, exact to
1e-12 mm for displacements of a few pixels.
"""

from __future__ import annotations

import math

import numpy as np

from planetref.arrays import F64

__all__ = ["NO_DISTORTION", "clip_radius_mm", "detector_position", "ideal_position"]


NO_DISTORTION = (0.0, 0.0, 0.0, 0.0)
"""``(k1, k2, p1, p2)`` of a distortion-free lens."""


def displacement(x: F64, y: F64, coeffs: tuple[float, float, float, float]) -> tuple[F64, F64]:
    """``D(x, y)`` in mm (see the module docstring) at detector positions in mm."""
    k1, k2, p1, p2 = coeffs
    r2 = x * x + y * y
    radial = k1 * r2 + k2 * r2 * r2
    dx = x * radial + p1 * (r2 + 2.0 * x * x) + 2.0 * p2 * x * y
    dy = y * radial + p2 * (r2 + 2.0 * y * y) + 2.0 * p1 * x * y
    return dx, dy


def ideal_position(x: F64, y: F64, coeffs: tuple[float, float, float, float]) -> tuple[F64, F64]:
    """Ideal (ray) position of detector positions ``(x, y)`` (mm)."""
    if not any(coeffs):
        return x, y
    dx, dy = displacement(x, y, coeffs)
    return x + dx, y + dy


def clip_radius_mm(x_mm: float, y_mm: float, angle_rad: float, length_mm: float) -> float:
    """1.5 x the distance from the axis of a CCD row's farthest end (mm).

    Args:
        x_mm: Along-track position of the row's sample-0 edge (mm).
        y_mm: Across-track position of that edge (mm).
        angle_rad: Rotation of the row from the y axis (rad).
        length_mm: Length of the row (mm).
    """
    x1 = x_mm + length_mm * math.sin(angle_rad)
    y1 = y_mm + length_mm * math.cos(angle_rad)
    return 1.5 * max(math.hypot(x_mm, y_mm), math.hypot(x1, y1))


def detector_position(
    xi: F64,
    yi: F64,
    coeffs: tuple[float, float, float, float],
    r_clip: float,
    iterations: int = 8,
) -> tuple[F64, F64]:
    """Detector position whose ideal position is ``(xi, yi)`` (mm): the inverse.

    Fixed-point iteration ``x <- xi - D(c(x))``, where ``c`` pulls points beyond
    ``r_clip`` from the axis radially back onto that circle: inside it (where the CCDs
    are) this is the exact inverse of :func:`ideal_position`; far outside, where the
    polynomial means nothing and would grow without bound, the displacement stays that of
    the circle, so a line search over the whole strip sees a smooth, monotonic offset.
    The iteration contracts by ``|dD/dx|`` (about 1e-3 for pixel-sized displacements
    across the field): 8 iterations reach 1e-20 mm.

    Args:
        xi: Ideal x (mm).
        yi: Ideal y (mm).
        coeffs: ``(k1, k2, p1, p2)``.
        r_clip: Radius (mm) beyond which the displacement is held constant radially.
        iterations: Fixed-point iterations.
    """
    if not any(coeffs):
        return xi, yi
    x, y = xi, yi
    for _ in range(iterations):
        r = np.hypot(x, y)
        with np.errstate(divide="ignore", invalid="ignore"):
            shrink = np.where(r > r_clip, r_clip / r, 1.0)
        dx, dy = displacement(x * shrink, y * shrink, coeffs)
        x, y = xi - dx, yi - dy
    return x, y
