"""Vertical datums of reference DEMs: heights above the body or above the areoid.

planetref's ground is body-fixed XYZ, and a DEM's heights are read as metres above the
scene's reference body (the sphere or ellipsoid of ``[body]``). Real products differ:
MOLA MEGDR heights are above the *areoid* (the equipotential surface GMM-2B whose mean
equatorial radius is 3,396.2 km), while CTX/HRSC/HiRISE DEMs are usually above the IAU
sphere. On Mars the two surfaces differ by kilometres away from the equator (the
areoid's flattening alone puts it ~20 km below a 3,396.19 km sphere at the poles), so
mixing them shifts every MCP by hundreds of metres to kilometres.

* ``dem_datum = "body"`` (default): heights are used as they are.
* ``dem_datum = "areoid"`` with ``areoid = "file.tif"``: ``file.tif`` is a raster of the
  areoid's height above the body (metres, any map CRS of the same body); it is sampled
  bilinearly at the DEM's pixel centres and added, so the DEM is converted to
  body-relative heights once, when it is read.

Plausibility check (:func:`datum_warning`). Mars' relief above the areoid spans
-7,825 m (Hellas) to +21,183 m (Olympus Mons) (MOLA; Smith et al. 1999, Science 284).
A DEM declared ``areoid`` must lie within that range, widened by
:data:`RELIEF_MARGIN_M`; a DEM declared ``body`` must lie within it after removing an
estimate of the areoid's height above the body at the DEM's latitudes, from an
ellipsoidal areoid (equatorial radius 3,396.2 km, flattening 1/169.8, MOLA) with
:data:`AREOID_MARGIN_M` for the undulations that model leaves out. The check only runs
for Mars-sized bodies and catches heights given as radii, in km, or above the other
datum where the two differ by more than the relief allows (a sphere-relative DEM
declared ``areoid`` at high latitudes, say); it cannot catch a mix-up near the equator.
"""

from __future__ import annotations

import logging
from os import PathLike
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from planetref.errors import InputError, MissingFileError
from planetref.geometry.geodesy import Ellipsoid, lonlat_to_xyz

__all__ = [
    "AREOID_MARGIN_M",
    "MARS_RELIEF_M",
    "RELIEF_MARGIN_M",
    "DemDatum",
    "apply_areoid",
    "areoid_above_body_estimate_m",
    "datum_warning",
    "open_reference_dem",
]

log = logging.getLogger(__name__)

DemDatum = Literal["body", "areoid"]

#: Lowest and highest heights above the areoid on Mars (m): Hellas and Olympus Mons (MOLA).
MARS_RELIEF_M = (-7825.0, 21183.0)
#: Slack on the relief range (m): local DEM noise, spikes at crater rims, other areoids.
RELIEF_MARGIN_M = 1000.0
#: Slack for the areoid's undulations about its ellipsoidal approximation (m).
AREOID_MARGIN_M = 3000.0
#: MOLA's mean equatorial radius (m) and inverse flattening: the areoid's approximation.
_AREOID_A_M = 3396200.0
_AREOID_INV_F = 169.8
_MARS_A_M = 3396190.0


def _radius(lat_deg: NDArray[np.float64], ellipsoid: Ellipsoid) -> NDArray[np.float64]:
    """Geocentric radius (m) of an ellipsoid at planetocentric latitudes (degrees)."""
    lat = np.asarray(lat_deg, float)
    return np.linalg.norm(lonlat_to_xyz(0.0, lat, 0.0, ellipsoid, "planetocentric"), axis=-1)


def areoid_above_body_estimate_m(lat_deg: NDArray[np.float64], body: object) -> NDArray[np.float64]:
    """Estimated areoid height above the body (m) at planetocentric latitudes (degrees).

    The areoid is approximated by the ellipsoid of MOLA's mean equatorial radius and
    shape flattening; ``body`` is an :class:`~planetref.geometry.geodesy.Ellipsoid`.
    """
    areoid = Ellipsoid(_AREOID_A_M, _AREOID_A_M * (1.0 - 1.0 / _AREOID_INV_F))
    return _radius(lat_deg, areoid) - _radius(lat_deg, body)  # type: ignore[arg-type]


def datum_warning(dem: object, datum: DemDatum, path: str | PathLike[str] | None) -> str | None:
    """One line saying why a DEM's heights are implausible for its datum, or None.

    Args:
        dem: The DEM as read (a :class:`~planetref.raster.dem.GridTerrain`, heights above
            its declared datum).
        datum: The declared datum.
        path: The DEM file (named in the message).
    """
    body = dem.ellipsoid  # type: ignore[attr-defined]
    if abs(float(body.semi_major_m) - _MARS_A_M) > 0.01 * _MARS_A_M:
        return None  # the relief figures are Mars'
    h = np.asarray(dem.heights, np.float64)  # type: ignore[attr-defined]
    finite = np.isfinite(h)
    lo_r, hi_r = MARS_RELIEF_M[0] - RELIEF_MARGIN_M, MARS_RELIEF_M[1] + RELIEF_MARGIN_M
    if datum == "areoid":
        rel = h[finite]
        lo, hi = lo_r, hi_r
    else:
        rows, cols = np.nonzero(finite)
        x, y = dem.transform @ (cols + 0.5, rows + 0.5)  # type: ignore[attr-defined]
        _, lat = dem.map_to_lonlat(np.asarray(x), np.asarray(y))  # type: ignore[attr-defined]
        rel = h[finite] - areoid_above_body_estimate_m(lat, body)
        lo, hi = lo_r - AREOID_MARGIN_M, hi_r + AREOID_MARGIN_M
    h_min, h_max = float(rel.min()), float(rel.max())
    if lo <= h_min and h_max <= hi:
        return None
    what = "above the areoid" if datum == "areoid" else "above the areoid (estimated)"
    return (
        f"{path}: DEM heights are implausible for dem_datum = {datum!r}: they span "
        f"{h_min:.0f} to {h_max:.0f} m {what}, but Mars' relief is "
        f"{MARS_RELIEF_M[0]:.0f} to {MARS_RELIEF_M[1]:.0f} m; check [reference] dem_datum "
        "(MOLA MEGDR heights are above the areoid, most CTX/HRSC DEMs above the sphere), "
        "the units (metres) and that the band holds heights, not radii"
    )


def apply_areoid(dem: object, areoid_path: str | PathLike[str]) -> object:
    """The DEM with the areoid's height above the body added (areoid -> body heights).

    Args:
        dem: A :class:`~planetref.raster.dem.GridTerrain` of heights above the areoid.
        areoid_path: Raster of the areoid's height above the body (m), any map CRS of the
            same body, covering the DEM; sampled bilinearly at the DEM's pixel centres.

    Returns:
        A new :class:`~planetref.raster.dem.GridTerrain` of heights above the body
        (float64), same grid and CRS.

    Raises:
        InputError: One line naming the areoid file: unreadable, on another body, or not
            covering every DEM pixel that holds a height.
    """
    from planetref.raster.dem import GridTerrain

    p = Path(areoid_path)
    if not p.is_file():
        raise MissingFileError("areoid raster not found", path=p)
    areoid = GridTerrain.from_geotiff(p)  # errors name the file
    a_dem = float(dem.ellipsoid.semi_major_m)  # type: ignore[attr-defined]
    a_ar = float(areoid.ellipsoid.semi_major_m)
    if abs(a_dem - a_ar) > 0.01 * a_dem:
        raise InputError(
            f"the areoid raster is on another body (a = {a_ar:.0f} m) than the DEM "
            f"(a = {a_dem:.0f} m)",
            path=p,
        )
    h = np.asarray(dem.heights, np.float64)  # type: ignore[attr-defined]
    rows, cols = np.indices(h.shape)
    x, y = dem.transform @ (cols.ravel() + 0.5, rows.ravel() + 0.5)  # type: ignore[attr-defined]
    lon, lat = dem.map_to_lonlat(np.asarray(x), np.asarray(y))  # type: ignore[attr-defined]
    n = areoid.height(lon, lat).reshape(h.shape)
    missing = np.isfinite(h) & ~np.isfinite(n)
    if missing.any():
        raise InputError(
            f"the areoid raster does not cover the DEM ({int(missing.sum())} of "
            f"{int(np.isfinite(h).sum())} DEM pixels fall outside it or on its nodata)",
            path=p,
        )
    return GridTerrain(h + np.where(np.isfinite(n), n, 0.0), dem.transform, dem.crs)  # type: ignore[attr-defined]


def open_reference_dem(
    path: str | PathLike[str],
    *,
    band: int = 1,
    datum: DemDatum = "body",
    areoid: str | PathLike[str] | None = None,
) -> object:
    """Read a reference DEM and return heights above the body (see the module doc).

    Logs one warning when the heights are implausible for ``datum``.

    Raises:
        InputError: ``datum = "areoid"`` without an areoid raster, or a bad areoid file.
    """
    from planetref.raster.dem import GridTerrain

    dem = GridTerrain.from_geotiff(path, band=band)
    warning = datum_warning(dem, datum, path)
    if warning:
        log.warning("%s", warning)
    if datum == "body":
        return dem
    if areoid is None:
        raise InputError("dem_datum = 'areoid' needs an areoid raster (areoid = ...)", path=path)
    return apply_areoid(dem, areoid)
