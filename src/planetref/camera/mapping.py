"""Camera, DEM and reference-grid plumbing shared by the front-end modules.

Every function works with any :class:`~planetref.camera.base.Camera` (rigorous line
scan, CSM, RPC) and any :class:`~planetref.camera.base.Terrain`; fast paths are taken
when the camera exposes ``look_rays`` and the terrain ``intersect_rays`` (the native
line-scan camera over a :class:`~planetref.raster.dem.GridTerrain`), and when the
line-scan ``ground_to_image`` accepts ``line_guess``.

Coordinates: image ``(line, sample)`` with the first pixel centre at ``(0.5, 0.5)``;
reference pixels ``(col, row)`` with the first pixel centre at ``(0.5, 0.5)``; map
coordinates in the reference CRS; body-fixed XYZ in metres.
"""

from __future__ import annotations

import inspect
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from planetref.arrays import F64
from planetref.camera.base import Camera, Terrain
from planetref.geometry.geodesy import lonlat_to_xyz
from planetref.raster.ortho import ReferenceOrtho

__all__ = [
    "image_gsd_m",
    "image_to_ref_pixel",
    "map_to_ground",
    "project_to_image",
    "rays_to_ground",
]


def rays_to_ground(
    camera: Camera, ccd: str, line: ArrayLike, sample: ArrayLike, terrain: Terrain
) -> F64:
    """Intersect image rays with the terrain.

    Args:
        camera: The (initial) camera.
        ccd: CCD name.
        line: Lines, ``(M,)``.
        sample: Samples, ``(M,)``.
        terrain: The DEM (or any terrain).

    Returns:
        Body-fixed XYZ (m), ``(M, 3)``; NaN rows where a ray misses the terrain.
    """
    line = np.atleast_1d(np.asarray(line, np.float64))
    sample = np.atleast_1d(np.asarray(sample, np.float64))
    if hasattr(camera, "look_rays") and hasattr(terrain, "intersect_rays"):
        origin, direction = camera.look_rays(line, sample, ccd=ccd)
        return np.asarray(terrain.intersect_rays(origin, direction).xyz, np.float64)
    return np.asarray(
        camera.image_to_ground(line, sample, terrain, ccd=ccd, on_miss="nan"), np.float64
    )


def _same_crs(a: Any, b: Any) -> bool:
    try:
        return bool(a.equals(b))
    except Exception:  # pragma: no cover - exotic CRS objects
        return False


def map_to_ground(
    ref: ReferenceOrtho, terrain: Terrain, x: ArrayLike, y: ArrayLike
) -> tuple[F64, F64, F64, F64]:
    """Ground points of reference map coordinates, with heights from the terrain.

    Args:
        ref: The reference orthoimage (its CRS gives the map coordinates).
        terrain: The DEM; a grid in the same CRS is sampled directly in map
            coordinates, any other terrain through planetocentric lon/lat.
        x: Map x (CRS units).
        y: Map y.

    Returns:
        ``(xyz, lon_deg, lat_deg, height_m)``: body-fixed XYZ (m, ``(M, 3)``), planetocentric
        east longitude and latitude (degrees) and the height (m); NaN where the terrain has
        no height.
    """
    x = np.atleast_1d(np.asarray(x, np.float64))
    y = np.atleast_1d(np.asarray(y, np.float64))
    lon, lat = ref.ground.map_to_lonlat(x, y)
    if hasattr(terrain, "height_at_map") and _same_crs(getattr(terrain, "crs", None), ref.crs):
        h = np.asarray(terrain.height_at_map(x, y), np.float64)
    else:
        h = np.asarray(terrain.height(lon, lat), np.float64)
    xyz = lonlat_to_xyz(lon, lat, h, terrain.ellipsoid)
    return xyz, lon, lat, h


@lru_cache(maxsize=64)
def _accepts_line_guess(func: Any) -> bool:
    try:
        return "line_guess" in inspect.signature(func).parameters
    except (TypeError, ValueError):  # pragma: no cover
        return False


def project_to_image(
    camera: Camera, ccd: str, xyz: ArrayLike, line_guess: ArrayLike | None = None
) -> tuple[F64, F64]:
    """Project ground points into a CCD image, with a starting line when the camera takes one.

    Args:
        camera: The (initial) camera.
        ccd: CCD name.
        xyz: Body-fixed points (m), ``(M, 3)``; NaN rows give NaN.
        line_guess: Starting lines (``(M,)``), which make the native line-scan projection
            several times cheaper; ignored by cameras that do not take it.

    Returns:
        ``(line, sample)``, NaN where the projection fails.
    """
    p = np.atleast_2d(np.asarray(xyz, np.float64))
    line = np.full(len(p), np.nan)
    sample = np.full(len(p), np.nan)
    ok = np.all(np.isfinite(p), axis=1)
    if not ok.any():
        return line, sample
    kwargs: dict[str, Any] = {"ccd": ccd}
    if line_guess is not None and _accepts_line_guess(type(camera).ground_to_image):
        guess = np.broadcast_to(np.asarray(line_guess, np.float64), (len(p),))[ok]
        if np.all(np.isfinite(guess)):
            kwargs["line_guess"] = guess
    pts = camera.ground_to_image(p[ok], **kwargs)
    valid = np.asarray(pts.valid, bool)
    idx = np.flatnonzero(ok)
    line[idx[valid]] = np.asarray(pts.line)[valid]
    sample[idx[valid]] = np.asarray(pts.sample)[valid]
    return line, sample


def image_to_ref_pixel(
    camera: Camera,
    ccd: str,
    line: ArrayLike,
    sample: ArrayLike,
    ref: ReferenceOrtho,
    terrain: Terrain,
) -> tuple[F64, F64]:
    """Where the camera and the DEM put image points on the reference grid.

    Returns:
        Reference ``(col, row)`` (first pixel centre at 0.5), NaN where a ray misses.
    """
    xyz = rays_to_ground(camera, ccd, line, sample, terrain)
    ok = np.all(np.isfinite(xyz), axis=1)
    col = np.full(len(xyz), np.nan)
    row = np.full(len(xyz), np.nan)
    if ok.any():
        x, y, _ = ref.ground.xyz_to_map(xyz[ok])
        col[ok], row[ok] = ref.map_to_pixel(x, y)
    return col, row


def image_gsd_m(
    camera: Camera,
    ccd: str,
    terrain: Terrain,
    line: float | None = None,
    sample: float | None = None,
) -> float:
    """Ground sampling distance (m) of a CCD image at a pixel (default: its centre).

    The geometric mean of the along-line and along-sample ground steps of one pixel.
    Without an explicit pixel, the centre is tried first and then a 5 x 5 grid over the
    image, so a hole in the DEM under the centre does not stop the measurement.

    Raises:
        GeometryError: If the rays of the pixel (every tried pixel) miss the terrain.
    """
    from planetref.errors import GeometryError

    n_lines, n_samples = camera.image_size(ccd)
    if line is not None or sample is not None:
        tries = [
            (
                n_lines / 2.0 if line is None else float(line),
                n_samples / 2.0 if sample is None else float(sample),
            )
        ]
    else:
        f = np.linspace(0.1, 0.9, 5)
        tries = [(n_lines / 2.0, n_samples / 2.0)] + [
            (a * n_lines, b * n_samples) for a in f for b in f
        ]
    for lc, sc in tries:
        xyz = rays_to_ground(camera, ccd, [lc, lc + 1.0, lc], [sc, sc, sc + 1.0], terrain)
        if np.all(np.isfinite(xyz)):
            d_line = float(np.linalg.norm(xyz[1] - xyz[0]))
            d_sample = float(np.linalg.norm(xyz[2] - xyz[0]))
            return float(np.sqrt(d_line * d_sample))
    lc, sc = tries[0]
    raise GeometryError(
        f"the rays of CCD {ccd!r} at (line {lc}, sample {sc})"
        f"{' and elsewhere' if len(tries) > 1 else ''} miss the terrain; "
        "cannot measure its ground sampling distance"
    )
