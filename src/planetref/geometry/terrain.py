"""Terrains and the one intersection of camera lines of sight with a terrain.

Every planetref camera (native line scan, CSM, RPC), the front end's
``rays_to_ground`` and the simulator's renderer find ground points here:
:func:`intersect_terrain` for straight rays, :func:`first_crossing` for any line of
sight given as a path (an RPC's is a curve of heights). A grid may offer a fast
certified guess (:class:`GuessingTerrain`, e.g. the fixed-point solver of
:class:`~planetref.raster.dem.GridTerrain`); everything else is decided here.

Method
------
A line of sight can only meet the terrain between the surfaces of constant height
``terrain.max_height_m`` and ``terrain.min_height_m`` above ``terrain.ellipsoid``. It is
followed from where it enters the upper surface (1 m above it; or from its origin, when
that lies below it) to where it reaches the lower surface (or leaves the upper one again,
for a grazing ray), in steps of half ``terrain.sampling_m`` metres along the ray. The
first step at which the line passes from above to on or below the terrain brackets the
first crossing seen from the camera, which bisection refines to ``tol_m`` (1 µm by
default) along the ray.

Rule at terrain holes
---------------------
A NaN height (a nodata cell of a DEM, or a point outside the DEM's extent) is *unknown
terrain*: the real surface is there, at an unknown height that is assumed to lie within
``[min_height_m, max_height_m]``. Hence:

* **A line of sight that reaches unknown terrain at a height where the surface could be
  (at or below ``max_height_m``) before it has crossed known terrain has no
  intersection** (NaN, or a :class:`~planetref.errors.GeometryError`): the hidden surface
  could have stopped it there, so any point found beyond the hole could be wrong.
* Whichever comes first along the line decides: the march brackets the first sample
  that is on/below known terrain *or* in unknown terrain, and bisection finds which of
  the two happens first (to ``tol_m``).
* Unknown terrain that the line passes *above* ``max_height_m`` does not matter, and
  neither does anything after the first crossing (it is hidden from the camera).

So a hole never moves a ground point: it only removes the points that it could hide.
The rule is the same for every camera and for the front end, which therefore agree at
holes (``tests/raster/test_terrain_holes.py``). Holes narrower than half a sample along
the ray are seen only if a sample falls into them; a DEM hole is always wider (a NaN
cell poisons the bilinear surface over two cells), so no DEM hole is ever stepped over.

A surface of constant height (``min_height_m == max_height_m``) needs no marching: the
intersection is computed in closed form.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.errors import GeometryError, InputError
from planetref.geometry.geodesy import Ellipsoid, ray_ellipsoid_intersection, xyz_to_lonlat

__all__ = [
    "TOP_MARGIN_M",
    "ConstantHeight",
    "GuessingTerrain",
    "OnMiss",
    "Terrain",
    "first_crossing",
    "intersect_terrain",
]

OnMiss = Literal["nan", "raise"]

#: Default bisection tolerance along the line of sight (metres).
DEFAULT_TOL_M = 1e-6
#: The search starts this far (metres) above ``max_height_m``, where no terrain can be.
TOP_MARGIN_M = 1.0
#: Upper bound of marching steps per call; longer paths take proportionally longer steps.
_MAX_STEPS = 20000

#: ``profile(idx, s) -> (h_path, h_terrain)``: for the lines of sight ``idx`` at path
#: parameters ``s`` (metres), the height of the path point and of the terrain below it
#: (NaN: unknown terrain), both above the terrain's ellipsoid in metres.
Profile = Callable[
    [NDArray[np.intp], NDArray[np.float64]], tuple[NDArray[np.float64], NDArray[np.float64]]
]


@runtime_checkable
class Terrain(Protocol):
    """A height surface above a reference ellipsoid.

    Attributes:
        ellipsoid: The body the heights refer to.
        min_height_m: A lower bound of every height the surface takes (metres).
        max_height_m: An upper bound (metres).
    """

    # Read-only members: terrains are immutable (frozen dataclasses, properties).
    @property
    def ellipsoid(self) -> Ellipsoid:
        """The body the heights refer to."""
        ...

    @property
    def min_height_m(self) -> float:
        """A lower bound of every height the surface takes (metres)."""
        ...

    @property
    def max_height_m(self) -> float:
        """An upper bound (metres)."""
        ...

    def height(
        self, lon_deg: NDArray[np.float64], lat_deg: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """Height (m) at planetocentric lon/lat (degrees); NaN outside or in holes."""
        ...

    @property
    def sampling_m(self) -> float:
        """The surface's ground sampling distance in metres (twice the marching step)."""
        ...


@runtime_checkable
class GuessingTerrain(Terrain, Protocol):
    """A terrain that can solve some rays faster than marching (e.g. a DEM grid)."""

    def first_hit_guess(
        self, origin: NDArray[np.float64], direction: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """Ray parameters (metres along unit ``direction``) of certified first hits.

        A guess must be the first crossing of known terrain with no unknown terrain on
        the ray before it (the module's hole rule); rays the terrain cannot certify are
        NaN and are marched by :func:`intersect_terrain`.

        Args:
            origin: Ray origins, body-fixed metres, ``(M, 3)``, above ``max_height_m``.
            direction: Unit ray directions, ``(M, 3)``.
        """
        ...


@dataclass(frozen=True)
class ConstantHeight:
    """The surface at a constant height above an ellipsoid.

    Attributes:
        ellipsoid: The reference body.
        height_m: Height above the ellipsoid in metres.
    """

    ellipsoid: Ellipsoid
    height_m: float = 0.0

    @property
    def min_height_m(self) -> float:
        """Equal to ``height_m``."""
        return self.height_m

    @property
    def max_height_m(self) -> float:
        """Equal to ``height_m``."""
        return self.height_m

    @property
    def sampling_m(self) -> float:
        """Infinite: a constant surface needs no marching."""
        return float("inf")

    def height(
        self, lon_deg: NDArray[np.float64], lat_deg: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """``height_m`` everywhere."""
        return np.full(np.broadcast(np.asarray(lon_deg), np.asarray(lat_deg)).shape, self.height_m)


def first_crossing(
    profile: Profile,
    s_start: NDArray[np.float64],
    s_end: NDArray[np.float64],
    step: float,
    *,
    max_height_m: float,
    tol_m: float = DEFAULT_TOL_M,
) -> NDArray[np.float64]:
    """Path parameter of the first terrain crossing of each line of sight (the hole rule).

    Args:
        profile: Heights of the path and of the terrain at path parameters (see
            :data:`Profile`); the path's height must start above the terrain.
        s_start: Where each search starts (metres; NaN: no search), shape ``(M,)``.
        s_end: Where it ends, shape ``(M,)``.
        step: Marching step in metres of path parameter.
        max_height_m: Highest height unknown terrain can take (the terrain's bound).
        tol_m: Bisection tolerance in metres of path parameter.

    Returns:
        The parameter of the first point on or below the terrain (to ``tol_m``), shape
        ``(M,)``; NaN where the line never crosses known terrain, starts under it, or
        meets unknown terrain first (see the module's rule at holes).
    """
    m = len(s_start)
    result = np.full(m, np.nan)
    active = np.flatnonzero(np.isfinite(s_start) & np.isfinite(s_end))
    if active.size == 0:
        return result

    def above(idx: NDArray[np.intp], s: NDArray[np.float64]) -> NDArray[np.float64]:
        # +1 above known terrain, -1 on/below it, NaN in unknown terrain it could hit.
        h_path, h_terrain = profile(idx, s)
        out = np.where(h_path > h_terrain, 1.0, -1.0)
        unknown = ~np.isfinite(h_terrain) & ~(h_path > max_height_m)
        out[unknown] = np.nan
        out[~np.isfinite(h_terrain) & (h_path > max_height_m)] = 1.0
        return out

    s_prev = s_start[active]
    f_prev = above(active, s_prev)
    # Starting on or below the terrain (an origin under it) or in a hole: nothing seen.
    ok = f_prev > 0
    idx, s_prev = active[ok], s_prev[ok]
    # March to the first "event": the path on/below known terrain, or in unknown terrain
    # where the surface could be. The event that comes first decides (hit or miss).
    s_lo = np.full(m, np.nan)
    s_hi = np.full(m, np.nan)
    f_hi = np.full(m, np.nan)
    while idx.size:
        s_cur = np.minimum(s_prev + step, s_end[idx])
        f_cur = above(idx, s_cur)
        event = ~(f_cur > 0)
        s_lo[idx[event]] = s_prev[event]
        s_hi[idx[event]] = s_cur[event]
        f_hi[idx[event]] = f_cur[event]
        keep = ~event & (s_cur < s_end[idx])
        idx, s_prev = idx[keep], s_cur[keep]
    found = np.flatnonzero(np.isfinite(s_hi))
    if found.size == 0:
        return result
    lo, hi, fh = s_lo[found], s_hi[found], f_hi[found]
    # No event at the lower end of the bracket, one at the upper end: halving keeps the
    # first event inside; whether it is a crossing or unknown terrain decides.
    width = max(float(np.max(hi - lo)), tol_m)
    for _ in range(int(np.ceil(np.log2(width / tol_m))) + 1):
        mid = 0.5 * (lo + hi)
        f_mid = above(found, mid)
        event = ~(f_mid > 0)
        hi = np.where(event, mid, hi)
        fh = np.where(event, f_mid, fh)
        lo = np.where(event, lo, mid)
    good = fh < 0
    result[found[good]] = hi[good]
    return result


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
    origin: NDArray[np.float64],
    direction: NDArray[np.float64],
    terrain: Terrain,
    h0: NDArray[np.float64],
    step: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Ray parameters where the search for a crossing starts and ends (NaN: no search)."""
    ell = terrain.ellipsoid
    top = float(terrain.max_height_m) + TOP_MARGIN_M
    bottom = float(terrain.min_height_m)
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


def _check_bounds(terrain: Terrain) -> tuple[float, float]:
    lo, hi = float(terrain.min_height_m), float(terrain.max_height_m)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise InputError(f"terrain height bounds must be finite with min <= max, got [{lo}, {hi}]")
    return lo, hi


def intersect_terrain(
    origin: ArrayLike,
    direction: ArrayLike,
    terrain: Terrain,
    on_miss: OnMiss = "raise",
    *,
    tol_m: float = DEFAULT_TOL_M,
) -> NDArray[np.float64]:
    """First intersection of straight rays with a terrain, seen from the ray origins.

    Args:
        origin: Ray origins, body-fixed XYZ in metres, shape ``(M, 3)`` (or ``(3,)``).
        direction: Ray directions, shape ``(M, 3)``; need not be unit length; the
            intersection is searched for only in front of the origin.
        terrain: Any :class:`Terrain` (NaN heights are unknown terrain, see the module's
            rule at holes). A :class:`GuessingTerrain` solves the rays it can certify
            itself; the others are marched. A surface whose bounds are equal (e.g.
            :class:`ConstantHeight`) is intersected in closed form.
        on_miss: ``"raise"`` a :class:`~planetref.errors.GeometryError` when any ray
            has no intersection, or return NaN rows for those rays (``"nan"``).
        tol_m: Tolerance of the intersection along the ray (metres).

    Returns:
        Body-fixed XYZ of the intersections in metres, shape ``(M, 3)``.

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
    n = np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2 + d[:, 2] ** 2)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = d / n[:, None]
    lo, hi = _check_bounds(terrain)
    if lo == hi:
        s = ray_ellipsoid_intersection(o, d, terrain.ellipsoid, hi)
    else:
        s = _solve_rays(o, d, terrain, tol_m)
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


def _solve_rays(
    o: NDArray[np.float64], d: NDArray[np.float64], terrain: Terrain, tol_m: float
) -> NDArray[np.float64]:
    """Ray parameter of the first crossing: the terrain's guesses, then marching."""
    step = 0.5 * float(terrain.sampling_m)
    if not (math.isfinite(step) and step > 0):
        raise InputError(f"terrain.sampling_m must be finite and positive, got {2 * step}")
    ell = terrain.ellipsoid
    s = np.full(len(o), np.nan)
    todo = np.arange(len(o))
    if isinstance(terrain, GuessingTerrain):
        # Origins outside the ellipsoid of radii (a, a, b) + top + 1 km are above the
        # search's start (that ellipsoid is within metres of the surface of constant
        # height top + 1 km).
        top = float(terrain.max_height_m) + TOP_MARGIN_M + 1000.0
        a, b = ell.semi_major_m + top, ell.semi_minor_m + top
        q = (o[:, 0] ** 2 + o[:, 1] ** 2) / (a * a) + o[:, 2] ** 2 / (b * b)
        high = np.flatnonzero(q > 1.0)
        if high.size:
            s[high] = terrain.first_hit_guess(o[high], d[high])
        todo = np.flatnonzero(~np.isfinite(s))
    if todo.size == 0:
        return s
    ot, dt = o[todo], d[todo]
    _, _, h0 = xyz_to_lonlat(ot, ell)
    s_start, s_end = _shell_interval(ot, dt, terrain, h0, step)
    live = np.isfinite(s_start)
    if not live.any():
        return s
    # Bound the work for grazing rays (very long paths through the shell).
    step = max(step, float(np.max(s_end[live] - s_start[live])) / _MAX_STEPS)

    def profile(
        idx: NDArray[np.intp], t: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        lon, lat, h = xyz_to_lonlat(ot[idx] + t[:, None] * dt[idx], ell)
        return h, np.asarray(terrain.height(lon, lat), dtype=np.float64)

    s[todo] = first_crossing(
        profile, s_start, s_end, step, max_height_m=float(terrain.max_height_m), tol_m=tol_m
    )
    return s
