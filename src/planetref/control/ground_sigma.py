"""A-priori sigmas of the ground point of a matched control point (MCP).

An MCP's ground coordinates come from the reference orthoimage (planimetry) and DEM
(height), so they are observations with errors of their own, not fixed points: the
planimetric sigma follows the reference's pixel size, the height sigma the DEM's post
spacing, local slope and curvature. Units: metres; map coordinates in the reference CRS
(metres).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "GROUND_SIGMA_H_FLOOR_M",
    "GROUND_SIGMA_XY_REF_PX",
    "ground_sigmas",
    "reference_gsd_m",
]

#: Planimetric a-priori sigma of an MCP, in reference pixels (GSD units): the match is
#: located on the reference grid to a fraction of its pixel.
GROUND_SIGMA_XY_REF_PX = 0.5
#: Floor of the height sigma (metres): the DEM's own vertical error where it is flat.
GROUND_SIGMA_H_FLOOR_M = 1.0


def reference_gsd_m(ref: Any) -> float:
    """Pixel size of the reference orthoimage (metres; its CRS is in metres)."""
    t = ref.transform
    return float(min(math.hypot(t.a, t.d), math.hypot(t.b, t.e)))


def ground_sigmas(
    ref: Any, dem: Any, ref_x: ArrayLike, ref_y: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A-priori sigmas of MCP ground points from the reference's resolution and terrain.

    * planimetric (per horizontal axis): ``s_xy = GROUND_SIGMA_XY_REF_PX x GSD`` of the
      reference orthoimage (its map units taken as metres): a match is located on its
      grid to a fraction of a pixel;
    * height: ``s_h = sqrt((res/2 * slope)^2 + (s_xy * slope)^2 + rough^2 + floor^2)``
      with ``res`` the DEM's post spacing, ``slope`` the local gradient (m/m, central
      differences one post either side), ``rough`` the local curvature term
      ``(|h(+x) + h(-x) - 2h| + |h(+y) + h(-y) - 2h|) / 4`` (what bilinear interpolation
      between posts misses) and ``floor = GROUND_SIGMA_H_FLOOR_M``. A terrain without
      posts (a constant height) gives the floor.

    Args:
        ref: The reference orthoimage (``transform`` in metres).
        dem: The reference DEM (a :class:`~planetref.raster.dem.GridTerrain`; a terrain
            without ``sampling_m`` gives the floor).
        ref_x: Map x of the points.
        ref_y: Map y.

    Returns:
        ``(sigma_xy_m, sigma_h_m)`` per point.
    """
    x = np.asarray(ref_x, np.float64).ravel()
    y = np.asarray(ref_y, np.float64).ravel()
    s_xy = np.full(x.shape, GROUND_SIGMA_XY_REF_PX * reference_gsd_m(ref))
    s_h = np.full(x.shape, GROUND_SIGMA_H_FLOOR_M)
    res = getattr(dem, "sampling_m", None)
    if not x.size or res is None:
        return s_xy, s_h
    from planetref.camera.mapping import map_to_ground

    res = float(res)

    def h(xx: NDArray[np.float64], yy: NDArray[np.float64]) -> NDArray[np.float64]:
        return map_to_ground(ref, dem, xx, yy)[3]

    h0, hxp, hxm = h(x, y), h(x + res, y), h(x - res, y)
    hyp, hym = h(x, y + res), h(x, y - res)
    with np.errstate(invalid="ignore"):
        slope = np.hypot((hxp - hxm) / (2 * res), (hyp - hym) / (2 * res))
        rough = 0.25 * (np.abs(hxp + hxm - 2 * h0) + np.abs(hyp + hym - 2 * h0))
        var = (0.5 * res * slope) ** 2 + (s_xy * slope) ** 2 + rough**2
    var = np.where(np.isfinite(var), var, 0.0)
    return s_xy, np.sqrt(var + GROUND_SIGMA_H_FLOOR_M**2)
