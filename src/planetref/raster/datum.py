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
    "Implausible",
    "apply_areoid",
    "areoid_above_body_estimate_m",
    "areoid_warning",
    "check_physical_heights",
    "datum_warning",
    "open_reference_dem",
]

log = logging.getLogger(__name__)

DemDatum = Literal["body", "areoid"]
#: What implausible (but physically possible) heights are: an error (the default) or a
#: warning the user accepted (``[reference] implausible_heights = "warn"``).
Implausible = Literal["error", "warn"]
#: Heights beyond this fraction of the body's radius are not terrain (as the camera CLI's
#: ``--height`` limit): a 1e30 fill value, radii, kilometres read as metres...
PHYSICAL_FRACTION = 0.01

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


def check_physical_heights(grid: object, path: str | PathLike[str], what: str) -> None:
    """Refuse a raster of heights with a finite value beyond +-1 % of the body's radius.

    Such a value is never terrain (a fill value such as 1e30, radii instead of heights):
    added unchecked, it fails almost every tile and moves the adjustment by hundreds of
    metres while the run "succeeds".

    Args:
        grid: A :class:`~planetref.raster.dem.GridTerrain`.
        path: Its file (named in the message).
        what: What it is ("reference DEM", "areoid raster", ...).

    Raises:
        InputError: One line naming the file, the range and the worst cell.
    """
    limit = PHYSICAL_FRACTION * float(grid.ellipsoid.semi_major_m)  # type: ignore[attr-defined]
    h = np.asarray(grid.heights, np.float64)  # type: ignore[attr-defined]
    with np.errstate(invalid="ignore"):
        bad = np.isfinite(h) & (np.abs(h) > limit)
        inf = np.isinf(h)
    if not (bad.any() or inf.any()):
        return
    worst = np.where(bad | inf, np.abs(np.nan_to_num(h, nan=0.0, posinf=np.inf)), -1.0)
    r, c = np.unravel_index(int(np.argmax(worst)), h.shape)
    n = int(bad.sum() + inf.sum())
    raise InputError(
        f"the {what} holds {n} value(s) outside the physically meaningful range "
        f"[{-limit:.0f}, {limit:.0f}] m (+-1 % of the body's radius), e.g. {h[r, c]:.6g} at "
        f"row {r}, column {c}: a fill value without nodata, radii or the wrong units?",
        path=path,
    )


def areoid_warning(
    areoid: object, body: object, path: str | PathLike[str], lat_deg: NDArray[np.float64]
) -> str | None:
    """One line when an areoid raster departs from Mars' areoid by more than it can.

    The areoid's height above the body is known to within :data:`AREOID_MARGIN_M` from
    its ellipsoidal approximation (:func:`areoid_above_body_estimate_m`); a raster
    beyond that (a tilt of +-20 km, a constant offset of kilometres) is not the areoid.

    Args:
        areoid: The sampled areoid heights (m) at ``lat_deg``.
        body: The body (an :class:`~planetref.geometry.geodesy.Ellipsoid`).
        path: The areoid raster (named in the message).
        lat_deg: Planetocentric latitudes of the samples.
    """
    if abs(float(body.semi_major_m) - _MARS_A_M) > 0.01 * _MARS_A_M:  # type: ignore[attr-defined]
        return None
    n = np.asarray(areoid, np.float64)
    ok = np.isfinite(n)
    if not ok.any():
        return None
    dev = n[ok] - areoid_above_body_estimate_m(np.asarray(lat_deg)[ok], body)
    lo, hi = float(dev.min()), float(dev.max())
    if -AREOID_MARGIN_M <= lo and hi <= AREOID_MARGIN_M:
        return None
    return (
        f"{path}: the areoid raster is implausible: it departs from Mars' areoid "
        f"(MOLA's ellipsoidal approximation) by {lo:.0f} to {hi:.0f} m over the DEM, more "
        f"than the +-{AREOID_MARGIN_M:.0f} m its undulations allow; check that it holds "
        "the areoid's height above [body] in metres"
    )


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


def apply_areoid(
    dem: object,
    areoid_path: str | PathLike[str],
    *,
    implausible: Implausible = "error",
    warnings: list[str] | None = None,
) -> object:
    """The DEM with the areoid's height above the body added (areoid -> body heights).

    Args:
        dem: A :class:`~planetref.raster.dem.GridTerrain` of heights above the areoid.
        areoid_path: Raster of the areoid's height above the body (m), any map CRS of the
            same body, covering the DEM; sampled bilinearly at the DEM's pixel centres.
        implausible: An areoid far from Mars' (:func:`areoid_warning`) is an error, or
            a warning (``"warn"``).
        warnings: Where the warning goes (else it is logged).

    Returns:
        A new :class:`~planetref.raster.dem.GridTerrain` of heights above the body
        (float64), same grid and CRS.

    Raises:
        InputError: One line naming the areoid file: unreadable, on another body, not
            covering every DEM pixel that holds a height, values beyond +-1 % of the
            radius, or implausible (unless ``implausible = "warn"``).
    """
    from planetref.raster.dem import GridTerrain

    p = Path(areoid_path)
    if not p.is_file():
        raise MissingFileError("areoid raster not found", path=p)
    areoid = GridTerrain.from_geotiff(p)  # errors name the file
    check_physical_heights(areoid, p, "areoid raster")
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
    on_dem = np.where(np.isfinite(h), n, np.nan)  # judged where the DEM has heights
    warning = areoid_warning(on_dem, dem.ellipsoid, p, lat.reshape(h.shape))  # type: ignore[attr-defined]
    if warning:
        _implausible(warning, implausible, warnings)
    return GridTerrain(h + np.where(np.isfinite(n), n, 0.0), dem.transform, dem.crs)  # type: ignore[attr-defined]


def _implausible(message: str, implausible: Implausible, warnings: list[str] | None) -> None:
    """Raise ``message`` (one line) or pass it on as a warning the user accepted."""
    if implausible == "error":
        raise InputError(
            message + ' (set [reference] implausible_heights = "warn" in scene.toml to '
            "accept the heights as they are)"
        )
    if warnings is None:
        log.warning("%s", message)
    else:
        warnings.append(message)


def open_reference_dem(
    path: str | PathLike[str],
    *,
    band: int = 1,
    datum: DemDatum = "body",
    areoid: str | PathLike[str] | None = None,
    implausible: Implausible = "error",
    warnings: list[str] | None = None,
) -> object:
    """Read a reference DEM and return heights above the body (see the module doc).

    Every raster is checked where it enters: the DEM as read and after the areoid is
    added, and the areoid raster, hold no value beyond +-1 % of the body's radius (an
    error, always); heights implausible for ``datum`` (:func:`datum_warning`) or an
    areoid far from Mars' (:func:`areoid_warning`) are an error unless ``implausible``
    is ``"warn"``.

    Args:
        path: The DEM.
        band: Its band.
        datum: What its heights are above.
        areoid: The areoid raster (``datum = "areoid"``).
        implausible: ``"error"`` or ``"warn"``.
        warnings: Where the accepted warnings go (the run logs them into its own log and
            report); without it they are logged here.

    Raises:
        InputError: ``datum = "areoid"`` without an areoid raster, a bad areoid file,
            heights beyond the physical range, or implausible ones (unless ``"warn"``).
    """
    from planetref.raster.dem import GridTerrain

    dem = GridTerrain.from_geotiff(path, band=band)
    check_physical_heights(dem, path, "reference DEM")
    warning = datum_warning(dem, datum, path)
    if warning:
        _implausible(warning, implausible, warnings)
    if datum == "body":
        return dem
    if areoid is None:
        raise InputError("dem_datum = 'areoid' needs an areoid raster (areoid = ...)", path=path)
    body = apply_areoid(dem, areoid, implausible=implausible, warnings=warnings)
    check_physical_heights(body, path, "reference DEM after the areoid was added")
    return body
