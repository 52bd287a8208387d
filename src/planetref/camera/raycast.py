"""Intersection of camera rays with a terrain surface.

Shared by every planetref camera model: a camera computes its rays (body-fixed
origins and directions) and :func:`intersect_terrain` finds where they first meet
the terrain.

Method
------
A ray can only meet the terrain between the surfaces of constant height
``terrain.max_height_m`` and ``terrain.min_height_m`` above the terrain's
ellipsoid. The ray is marched from where it enters the upper surface (or from its
origin, when that lies below it) towards where it reaches the lower surface (or
leaves the upper one again, for a grazing ray), in steps of about
``terrain.sampling_m`` metres along the ray. The first step at which the ray passes
from above to below the terrain brackets the first crossing seen from the camera,
which bisection then refines. A ray that never gets below the terrain (it misses
the body, or only crosses holes of the terrain) has no intersection: it gives a
:class:`~planetref.errors.GeometryError` or a NaN row, never a wrong point.

A surface of constant height (``min_height_m == max_height_m``) needs no marching:
the intersection is computed in closed form.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.camera.base import OnMiss, Terrain
from planetref.camera.geodesy import ray_ellipsoid_intersection, xyz_to_lonlat
from planetref.errors import GeometryError, InputError

__all__ = ["intersect_terrain"]

#: Bisection stops once the bracket is shorter than this (metres along the ray).
_BISECTION_TOLERANCE_M = 1e-4
#: Upper bound of marching steps per call; longer paths take proportionally longer steps.
_MAX_STEPS = 20000


def _height_above_terrain(points: NDArray[np.float64], terrain: Terrain) -> NDArray[np.float64]:
    """Ellipsoidal height of ``points`` minus the terrain height below them (NaN in holes)."""
    lon, lat, h = xyz_to_lonlat(points, terrain.ellipsoid)
    return h - np.asarray(terrain.height(lon, lat), dtype=np.float64)


def _far_root(
    origin: NDArray[np.float64], direction: NDArray[np.float64], a: float, b: float
) -> NDArray[np.float64]:
    """Ray parameter where rays leave the ellipsoid of radii (a, a, b) (NaN: they miss it)."""
    scale = np.array([1.0 / a, 1.0 / a, 1.0 / b])
    os_, ds = origin * scale, direction * scale
    qa = np.sum(ds * ds, axis=1)
    qb = 2.0 * np.sum(os_ * ds, axis=1)
    qc = np.sum(os_ * os_, axis=1) - 1.0
    disc = qb * qb - 4.0 * qa * qc
    with np.errstate(invalid="ignore"):
        return np.where(disc >= 0, (-qb + np.sqrt(disc)) / (2.0 * qa), np.nan)


def _shell_interval(
    origin: NDArray[np.float64], direction: NDArray[np.float64], terrain: Terrain, step: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Ray parameters where the search for a crossing starts and ends (NaN: no search)."""
    ell = terrain.ellipsoid
    top, bottom = float(terrain.max_height_m), float(terrain.min_height_m)
    _, _, h0 = xyz_to_lonlat(origin, ell)
    s_enter = ray_ellipsoid_intersection(origin, direction, ell, top)
    # An origin already inside the shell starts the search where it is.
    s_start = np.where(h0 <= top, 0.0, s_enter)
    s_bottom = ray_ellipsoid_intersection(origin, direction, ell, bottom)
    # A ray that misses the lower surface may still cross the terrain inside the shell:
    # search until it leaves the upper surface again. The far root of the ellipsoid
    # (a + top, b + top) is within metres of the exact one, hence the margin.
    margin = 2.0 * abs(top) * ell.e2 + step
    s_exit = _far_root(origin, direction, ell.semi_major_m + top, ell.semi_minor_m + top) + margin
    s_end = np.where(np.isfinite(s_bottom), s_bottom, s_exit)
    ok = np.isfinite(s_start) & np.isfinite(s_end) & (s_end >= s_start) & (h0 >= bottom)
    return np.where(ok, s_start, np.nan), np.where(ok, s_end, np.nan)


def intersect_terrain(
    origin: ArrayLike, direction: ArrayLike, terrain: Terrain, on_miss: OnMiss = "raise"
) -> NDArray[np.float64]:
    """First intersection of rays with a terrain, seen from the ray origins.

    Args:
        origin: Ray origins, body-fixed XYZ in metres, shape ``(M, 3)`` (or ``(3,)``).
        direction: Ray directions, shape ``(M, 3)``; need not be unit length; the
            intersection is searched for only in front of the origin.
        terrain: Any :class:`~planetref.camera.base.Terrain`: heights in metres above
            ``terrain.ellipsoid`` at planetocentric longitude/latitude, bounded by
            ``min_height_m``/``max_height_m``; NaN heights are holes. A surface whose
            bounds are equal (e.g. :class:`~planetref.camera.base.ConstantHeight`) is
            intersected in closed form.
        on_miss: ``"raise"`` a :class:`~planetref.errors.GeometryError` when any ray
            has no intersection, or return NaN rows for those rays (``"nan"``).

    Returns:
        Body-fixed XYZ of the intersections in metres, shape ``(M, 3)``. The point lies
        on the terrain to about 0.1 mm along the ray (the marching step is about
        ``terrain.sampling_m``, so features narrower than that along a ray may be
        stepped over).

    Raises:
        InputError: If the shapes do not match or ``on_miss`` is unknown.
        GeometryError: If ``on_miss == "raise"`` and a ray misses the terrain.
    """
    if on_miss not in ("raise", "nan"):
        raise InputError(f"on_miss must be 'raise' or 'nan', got {on_miss!r}")
    o = np.atleast_2d(np.asarray(origin, dtype=np.float64))
    d = np.atleast_2d(np.asarray(direction, dtype=np.float64))
    if o.shape[-1] != 3 or d.shape[-1] != 3 or o.ndim != 2 or d.ndim != 2:
        raise InputError(
            f"origin and direction must have shape (M, 3), got {o.shape} and {d.shape}"
        )
    o, d = np.broadcast_arrays(o, d)
    n = np.linalg.norm(d, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = d / n[:, None]
    lo, hi = float(terrain.min_height_m), float(terrain.max_height_m)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise InputError(f"terrain height bounds must be finite with min <= max, got [{lo}, {hi}]")
    if lo == hi:
        s = ray_ellipsoid_intersection(o, d, terrain.ellipsoid, hi)
    else:
        s = _march(o, d, terrain)
    out = o + s[:, None] * d
    miss = ~np.all(np.isfinite(out), axis=1)
    if np.any(miss):
        if on_miss == "raise":
            first = int(np.flatnonzero(miss)[0])
            raise GeometryError(
                f"{int(miss.sum())} of {len(miss)} rays miss the terrain (first: ray {first} "
                f"from {o[first].round(3).tolist()} along {d[first].round(6).tolist()})"
            )
        out[miss] = np.nan
    return out


def _march(o: NDArray[np.float64], d: NDArray[np.float64], terrain: Terrain) -> NDArray[np.float64]:
    """Ray parameter of the first terrain crossing by marching + bisection (NaN: none)."""
    m = len(o)
    result = np.full(m, np.nan)
    step = float(terrain.sampling_m)
    if not (math.isfinite(step) and step > 0):
        raise InputError(f"terrain.sampling_m must be finite and positive, got {step}")
    s_start, s_end = _shell_interval(o, d, terrain, step)
    active = np.flatnonzero(np.isfinite(s_start))
    if active.size == 0:
        return result
    # Bound the work for grazing rays (very long paths through the shell).
    step = max(step, float(np.max(s_end[active] - s_start[active])) / _MAX_STEPS)
    s_prev = s_start[active]
    f_prev = _height_above_terrain(o[active] + s_prev[:, None] * d[active], terrain)
    # Already on or below the terrain where the search starts: if the ray came from
    # above the shell, it meets the terrain right there; if its origin is inside the
    # shell and under the terrain, nothing is visible from it.
    at_start = f_prev <= 0
    result[active[at_start & (s_prev > 0)]] = s_prev[at_start & (s_prev > 0)]
    idx, s_prev = active[~at_start], s_prev[~at_start]
    s_lo = np.full(m, np.nan)
    s_hi = np.full(m, np.nan)
    while idx.size:
        s_cur = np.minimum(s_prev + step, s_end[idx])
        f_cur = _height_above_terrain(o[idx] + s_cur[:, None] * d[idx], terrain)
        crossed = f_cur <= 0
        s_lo[idx[crossed]] = s_prev[crossed]
        s_hi[idx[crossed]] = s_cur[crossed]
        keep = ~crossed & (s_cur < s_end[idx])
        idx, s_prev = idx[keep], s_cur[keep]
    found = np.flatnonzero(np.isfinite(s_hi))
    if found.size == 0:
        return result
    lo, hi = s_lo[found], s_hi[found]
    ob, db = o[found], d[found]
    # The upper end of the bracket is on or below the terrain and the lower end above
    # it, so halving keeps the first crossing inside.
    width = max(float(np.max(hi - lo)), _BISECTION_TOLERANCE_M)
    for _ in range(int(np.ceil(np.log2(width / _BISECTION_TOLERANCE_M))) + 1):
        mid = 0.5 * (lo + hi)
        below = _height_above_terrain(ob + mid[:, None] * db, terrain) <= 0
        hi = np.where(below, mid, hi)
        lo = np.where(below, lo, mid)
    result[found] = hi
    return result
