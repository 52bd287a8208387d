"""Geodesy of Mars (and any biaxial body): body-fixed XYZ <-> latitude, longitude, height.

Conventions used throughout planetref:

* Body-fixed Cartesian coordinates ``XYZ`` are in metres, origin at the body's centre
  of mass, Z along the spin axis, X through the prime meridian (the frame of ISIS,
  ALE and usgscsm, e.g. IAU_MARS).
* Longitudes are east-positive degrees wrapped to ``[-180, 180)``.
* Latitudes are **planetocentric** degrees by default. ``latitude="planetographic"``
  selects geodetic (planetographic) latitude; on a sphere both are equal.
* Heights are metres above the reference ellipsoid measured along the ellipsoid
  normal, as PROJ measures ellipsoidal heights. With planetocentric latitude the
  latitude is that of the foot point on the ellipsoid, which is what PROJ returns for
  the IAU_2015 "Ocentric" CRSs (e.g. IAU_2015:49902). On a sphere the height is simply
  ``|XYZ| - R``.

Raster CRSs are handled by :class:`CrsGround`, which goes through pyproj for the map
projection and through this module for the ellipsoid, so the two can be tested
against each other.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.errors import CrsError, InputError

LatitudeKind = Literal["planetocentric", "planetographic"]

__all__ = [
    "EARTH_WGS84",
    "MARS_IAU2015_ELLIPSOID",
    "MARS_IAU2015_SPHERE",
    "CrsGround",
    "Ellipsoid",
    "lonlat_to_xyz",
    "lonlat_xyz_jacobian",
    "ray_ellipsoid_intersection",
    "wrap_longitude",
    "xyz_to_lonlat",
]


@dataclass(frozen=True)
class Ellipsoid:
    """A biaxial (oblate) reference body.

    Attributes:
        semi_major_m: Equatorial radius in metres.
        semi_minor_m: Polar radius in metres (equal to ``semi_major_m`` for a sphere).
        name: A human-readable name, informative only.
    """

    semi_major_m: float
    semi_minor_m: float
    name: str = ""

    def __post_init__(self) -> None:
        a, b = self.semi_major_m, self.semi_minor_m
        if not (np.isfinite(a) and np.isfinite(b) and a > 0 and b > 0):
            raise InputError(f"ellipsoid radii must be finite and positive, got a={a}, b={b}")
        if b > a:
            raise InputError(f"only oblate bodies are supported (b={b} > a={a})")

    @property
    def is_sphere(self) -> bool:
        """True when the two radii are equal."""
        return self.semi_major_m == self.semi_minor_m

    @property
    def e2(self) -> float:
        """First eccentricity squared, ``1 - b^2/a^2``."""
        return 1.0 - (self.semi_minor_m / self.semi_major_m) ** 2

    @classmethod
    def from_crs(cls, crs: object) -> Ellipsoid:
        """The ellipsoid of a CRS (anything ``pyproj.CRS.from_user_input`` accepts).

        Raises:
            CrsError: If the CRS cannot be parsed or has no ellipsoid.
        """
        from pyproj import CRS
        from pyproj.exceptions import CRSError

        try:
            c = CRS.from_user_input(crs)
        except CRSError as exc:
            raise CrsError(f"not a valid CRS: {crs!r} ({exc})") from None
        ell = c.ellipsoid
        if ell is None:
            raise CrsError(f"CRS has no ellipsoid: {c.name}")
        return cls(float(ell.semi_major_metre), float(ell.semi_minor_metre), ell.name or c.name)

    def to_proj4(self) -> str:
        """A PROJ string for the geocentric Cartesian CRS on this ellipsoid."""
        return f"+proj=geocent +a={self.semi_major_m!r} +b={self.semi_minor_m!r} +units=m +no_defs"


MARS_IAU2015_SPHERE = Ellipsoid(3396190.0, 3396190.0, "Mars (2015) - Sphere")
MARS_IAU2015_ELLIPSOID = Ellipsoid(3396190.0, 3376200.0, "Mars (2015)")
EARTH_WGS84 = Ellipsoid(6378137.0, 6356752.314245179, "WGS 84")


def wrap_longitude(lon_deg: ArrayLike) -> NDArray[np.float64]:
    """Wrap longitudes in degrees to ``[-180, 180)``."""
    lon = np.asarray(lon_deg, dtype=np.float64)
    return (lon + 180.0) % 360.0 - 180.0


def _ocentric_to_ographic(lat_c: NDArray[np.float64], ell: Ellipsoid) -> NDArray[np.float64]:
    # Valid for points on the ellipsoid surface: tan(lat_g) = (a/b)^2 tan(lat_c).
    if ell.is_sphere:
        return lat_c
    ratio = (ell.semi_major_m / ell.semi_minor_m) ** 2
    return np.arctan2(ratio * np.sin(lat_c), np.cos(lat_c))


def _ographic_to_ocentric(lat_g: NDArray[np.float64], ell: Ellipsoid) -> NDArray[np.float64]:
    if ell.is_sphere:
        return lat_g
    ratio = (ell.semi_minor_m / ell.semi_major_m) ** 2
    return np.arctan2(ratio * np.sin(lat_g), np.cos(lat_g))


def _latitude_as(
    lat_deg: ArrayLike, source: str, target: str, ell: Ellipsoid
) -> NDArray[np.float64]:
    """A latitude in degrees of kind ``source`` as one of kind ``target``, in degrees.

    Only planetocentric <-> planetographic converts (for points on the ellipsoid surface);
    any other pair returns the latitude unchanged (via radians and back).
    """
    lat = np.radians(np.asarray(lat_deg, float))
    if (source, target) == ("planetocentric", "planetographic"):
        lat = _ocentric_to_ographic(lat, ell)
    elif (source, target) == ("planetographic", "planetocentric"):
        lat = _ographic_to_ocentric(lat, ell)
    return np.degrees(lat)


def lonlat_to_xyz(
    lon_deg: ArrayLike,
    lat_deg: ArrayLike,
    height_m: ArrayLike,
    ellipsoid: Ellipsoid,
    latitude: LatitudeKind = "planetocentric",
) -> NDArray[np.float64]:
    """Longitude, latitude and height to body-fixed XYZ.

    Args:
        lon_deg: East-positive longitude in degrees (any range).
        lat_deg: Latitude in degrees, of the kind given by ``latitude``.
        height_m: Height in metres above the ellipsoid, along its normal.
        ellipsoid: The reference body.
        latitude: ``"planetocentric"`` (default) or ``"planetographic"``.

    Returns:
        Array of shape ``broadcast(lon, lat, h).shape + (3,)``, metres.
    """
    lon = np.radians(np.asarray(lon_deg, dtype=np.float64))
    lat = np.radians(np.asarray(lat_deg, dtype=np.float64))
    h = np.asarray(height_m, dtype=np.float64)
    lon, lat, h = np.broadcast_arrays(lon, lat, h)
    if latitude == "planetocentric":
        lat_g = _ocentric_to_ographic(lat, ellipsoid)
    elif latitude == "planetographic":
        lat_g = lat
    else:
        raise InputError(f"unknown latitude kind {latitude!r}")
    a, e2 = ellipsoid.semi_major_m, ellipsoid.e2
    sin_lat, cos_lat = np.sin(lat_g), np.cos(lat_g)
    n = a / np.sqrt(1.0 - e2 * sin_lat**2)
    x = (n + h) * cos_lat * np.cos(lon)
    y = (n + h) * cos_lat * np.sin(lon)
    z = (n * (1.0 - e2) + h) * sin_lat
    return np.stack([x, y, z], axis=-1)


def xyz_to_lonlat(
    xyz: ArrayLike, ellipsoid: Ellipsoid, latitude: LatitudeKind = "planetocentric"
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Body-fixed XYZ to longitude, latitude and height.

    Uses Vermeille's closed form (J. Geodesy 2002), exact to machine precision for points
    outside the ellipsoid's evolute, which includes every point within thousands of
    kilometres of a planet's surface.

    Args:
        xyz: Array of shape ``(..., 3)`` in metres.
        ellipsoid: The reference body.
        latitude: ``"planetocentric"`` (default) or ``"planetographic"``.

    Returns:
        ``(lon_deg, lat_deg, height_m)``, each of shape ``xyz.shape[:-1]``; longitude in
        ``[-180, 180)``.
    """
    p = np.asarray(xyz, dtype=np.float64)
    if p.shape[-1:] != (3,):
        raise InputError(f"xyz must have a last axis of length 3, got shape {p.shape}")
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    lon = np.degrees(np.arctan2(y, x))
    a, b = ellipsoid.semi_major_m, ellipsoid.semi_minor_m
    rxy = np.hypot(x, y)
    if ellipsoid.is_sphere:
        lat_g = np.arctan2(z, rxy)
        h = np.sqrt(rxy**2 + z**2) - a
    else:
        e2 = ellipsoid.e2
        e4 = e2 * e2
        pp = (x * x + y * y) / (a * a)
        q = (1.0 - e2) * z * z / (a * a)
        r = (pp + q - e4) / 6.0
        s = e4 * pp * q / (4.0 * r**3)
        t = np.cbrt(1.0 + s + np.sqrt(s * (2.0 + s)))
        u = r * (1.0 + t + 1.0 / t)
        v = np.sqrt(u * u + e4 * q)
        w = e2 * (u + v - q) / (2.0 * v)
        k = np.sqrt(u + v + w * w) - w
        d = k * rxy / (k + e2)
        hyp = np.hypot(d, z)
        lat_g = 2.0 * np.arctan2(z, d + hyp)
        h = (k + e2 - 1.0) / k * hyp
        # Near the axis Vermeille's d -> 0 is fine, but exactly on it use the pole formula.
        on_axis = rxy < 1e-9 * a
        if np.any(on_axis):
            lat_g = np.where(on_axis, np.sign(z) * np.pi / 2, lat_g)
            h = np.where(on_axis, np.abs(z) - b, h)
    if latitude == "planetocentric":
        lat = _ographic_to_ocentric(lat_g, ellipsoid)
    elif latitude == "planetographic":
        lat = lat_g
    else:
        raise InputError(f"unknown latitude kind {latitude!r}")
    return wrap_longitude(lon), np.degrees(lat), h


def lonlat_xyz_jacobian(
    xyz: ArrayLike, ellipsoid: Ellipsoid, latitude: LatitudeKind = "planetocentric"
) -> NDArray[np.float64]:
    """Partial derivatives of ``(lon_deg, lat_deg, height_m)`` with respect to ``XYZ``.

    The derivative of :func:`xyz_to_lonlat`. The forward map
    (:func:`lonlat_to_xyz`) has orthogonal columns ``dXYZ/dlon = (N + h) cos(lat_g)
    e_east``, ``dXYZ/dlat_g = (M + h) e_north`` and ``dXYZ/dh = e_up`` (``N``, ``M``: the
    prime-vertical and meridian radii of curvature), so its inverse is each column over
    its squared length. Planetocentric latitude is that of the foot point, a function of
    the geodetic latitude alone (``tan lat_c = (b/a)^2 tan lat_g``), so
    ``dlat_c/dlat_g = (b/a)^2 / (cos^2 lat_g + (b/a)^4 sin^2 lat_g)``.

    Args:
        xyz: Body-fixed points, metres, shape ``(..., 3)``.
        ellipsoid: The reference body.
        latitude: ``"planetocentric"`` (default) or ``"planetographic"``.

    Returns:
        ``(..., 3, 3)``: rows ``(lon, lat, h)`` in degrees, degrees and metres per metre
        of ``(X, Y, Z)``.
    """
    if latitude not in ("planetocentric", "planetographic"):
        raise InputError(f"unknown latitude kind {latitude!r}")
    lon_d, lat_gd, h = xyz_to_lonlat(xyz, ellipsoid, "planetographic")
    lon, lat_g = np.radians(lon_d), np.radians(lat_gd)
    a, e2 = ellipsoid.semi_major_m, ellipsoid.e2
    sl, cl = np.sin(lat_g), np.cos(lat_g)
    so, co = np.sin(lon), np.cos(lon)
    w2 = 1.0 - e2 * sl**2
    n = a / np.sqrt(w2)
    m = a * (1.0 - e2) / w2**1.5
    east = np.stack([-so, co, np.zeros_like(so)], axis=-1)
    north = np.stack([-sl * co, -sl * so, cl], axis=-1)
    up = np.stack([cl * co, cl * so, sl], axis=-1)
    deg = 180.0 / np.pi
    with np.errstate(divide="ignore", invalid="ignore"):
        d_lon = east / ((n + h) * cl)[..., None] * deg
    d_lat = north / (m + h)[..., None] * deg
    if latitude == "planetocentric" and not ellipsoid.is_sphere:
        k = 1.0 - e2  # (b/a)^2: tan(lat_c) = k tan(lat_g)
        d_lat = d_lat * (k / (cl**2 + k * k * sl**2))[..., None]
    return np.stack([d_lon, d_lat, up], axis=-2)


def ray_ellipsoid_intersection(
    origin: ArrayLike, direction: ArrayLike, ellipsoid: Ellipsoid, height_m: ArrayLike = 0.0
) -> NDArray[np.float64]:
    """Distance along rays to their first intersection with an ellipsoid of constant height.

    The surface of constant height above an oblate ellipsoid is not itself an
    ellipsoid; it is approximated by the ellipsoid with radii ``a + h`` and ``b + h``
    and then refined by Newton iterations on the exact height, so the returned point
    lies at ``height_m`` to well under a millimetre.

    Args:
        origin: Ray origins, shape ``(..., 3)``, metres, body-fixed.
        direction: Ray directions, shape ``(..., 3)`` (need not be unit length).
        ellipsoid: The reference body.
        height_m: Height of the surface above the ellipsoid, metres (broadcast).

    Returns:
        Ray parameter ``s`` (so the point is ``origin + s * direction``), shape ``(...)``;
        NaN where the ray misses the surface or the intersection lies behind the origin.
    """
    o = np.asarray(origin, dtype=np.float64)
    d = np.asarray(direction, dtype=np.float64)
    h = np.asarray(height_m, dtype=np.float64)
    o, d = np.broadcast_arrays(o, d)
    h = np.broadcast_to(h, o.shape[:-1])
    a = ellipsoid.semi_major_m + h
    b = ellipsoid.semi_minor_m + h
    scale = np.stack([1.0 / a, 1.0 / a, 1.0 / b], axis=-1)
    os_, ds = o * scale, d * scale
    qa = np.sum(ds * ds, axis=-1)
    qb = 2.0 * np.sum(os_ * ds, axis=-1)
    qc = np.sum(os_ * os_, axis=-1) - 1.0
    disc = qb * qb - 4.0 * qa * qc
    with np.errstate(invalid="ignore", divide="ignore"):
        sq = np.sqrt(disc)
        # From outside, the nearer root in the cancellation-free form; from inside (qc < 0)
        # the only positive root, where the ray leaves the surface.
        s = np.where(qc >= 0, (2.0 * qc) / (-qb + sq), (-qb + sq) / (2.0 * qa))
    s = np.where((disc >= 0) & (s >= 0) & ((qc < 0) | (qb < 0)), s, np.nan)
    if not ellipsoid.is_sphere:
        dnorm = np.linalg.norm(d, axis=-1)
        for _ in range(3):
            pt = o + s[..., None] * d
            _, _, hh = xyz_to_lonlat(pt, ellipsoid)
            # d(height)/ds along the ray is the cosine between the ray and the normal.
            lon_g, lat_g, _ = xyz_to_lonlat(pt, ellipsoid, "planetographic")
            la, lo = np.radians(lat_g), np.radians(lon_g)
            nrm = np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], -1)
            dh_ds = np.sum(nrm * d, axis=-1)
            with np.errstate(invalid="ignore", divide="ignore"):
                s = s - (hh - h) / dh_ds
            if np.all(~np.isfinite(s) | (np.abs(hh - h) < 1e-5 * np.maximum(dnorm, 1.0))):
                break
    return s


class CrsGround:
    """Map coordinates of a raster CRS <-> body-fixed XYZ, through pyproj.

    The CRS's map coordinates are converted to the longitude/latitude of its own
    geographic base CRS by pyproj (which knows about west-positive and planetographic
    IAU codes), then to XYZ with this module's ellipsoid formulas. Heights are taken to
    be ellipsoidal heights above the CRS's ellipsoid (the convention of MOLA/HRSC/CTX
    DTMs in the IAU Mars sphere CRSs, where they equal heights above the sphere).

    Args:
        crs: Anything ``pyproj.CRS.from_user_input`` accepts (WKT, "IAU_2015:49910", a
            rasterio CRS...).

    Raises:
        CrsError: If the CRS cannot be parsed, or is geocentric.
    """

    def __init__(self, crs: object) -> None:
        from pyproj import CRS, Transformer
        from pyproj.exceptions import CRSError

        try:
            self.crs = CRS.from_user_input(crs.to_wkt() if hasattr(crs, "to_wkt") else crs)
        except CRSError as exc:
            raise CrsError(f"not a valid CRS: {crs!r} ({exc})") from None
        if self.crs.is_geocentric:
            raise CrsError(f"a map or geographic CRS is needed, got geocentric {self.crs.name}")
        self.ellipsoid = Ellipsoid.from_crs(self.crs)
        geo = self.crs.geodetic_crs
        if geo is None:
            raise CrsError(f"CRS has no geographic base: {self.crs.name}")
        self._geographic: tuple[float, LatitudeKind] | None = None
        if not self.crs.is_projected:
            # pyproj's always_xy does not normalise the IAU geographic CRSs that have
            # west-positive or planetocentric axes, so read the axes directly. Rasters
            # store geographic coordinates as x = longitude, y = latitude (GDAL's
            # traditional GIS order).
            axes = self.crs.axis_info
            lon_axis = next((a for a in axes if "lon" in a.name.lower()), None)
            lat_axis = next((a for a in axes if "lat" in a.name.lower()), None)
            if lon_axis is None or lat_axis is None or lon_axis.unit_name != "degree":
                raise CrsError(f"unsupported geographic CRS axes in {self.crs.name}")
            sign = -1.0 if lon_axis.direction.lower() == "west" else 1.0
            kind: LatitudeKind = (
                "planetocentric"
                if "planetocentric" in lat_axis.name.lower() or self.ellipsoid.is_sphere
                else "planetographic"
            )
            self._geographic = (sign, kind)
        else:
            # A geographic CRS with the ellipsoid of ``crs`` whose latitude is geodetic, in
            # lon/lat order, is the common ground between pyproj and this module.
            lonlat = CRS.from_proj4(
                f"+proj=longlat +a={self.ellipsoid.semi_major_m!r} "
                f"+b={self.ellipsoid.semi_minor_m!r} +no_defs"
            )
            self._to_lonlat = Transformer.from_crs(self.crs, lonlat, always_xy=True)
            self._from_lonlat = Transformer.from_crs(lonlat, self.crs, always_xy=True)

    def _map_to_geodetic(
        self, x: ArrayLike, y: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        x, y = np.asarray(x, float), np.asarray(y, float)
        if self._geographic is None:
            lon, lat = self._to_lonlat.transform(x, y)
            return np.asarray(lon, float), np.asarray(lat, float)
        sign, kind = self._geographic
        return sign * x, _latitude_as(y, kind, "planetographic", self.ellipsoid)

    def _geodetic_to_map(
        self, lon: ArrayLike, lat: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        lon, lat = np.asarray(lon, float), np.asarray(lat, float)
        if self._geographic is None:
            x, y = self._from_lonlat.transform(lon, lat)
            return np.asarray(x, float), np.asarray(y, float)
        sign, kind = self._geographic
        return sign * wrap_longitude(lon), _latitude_as(lat, "planetographic", kind, self.ellipsoid)

    def map_to_xyz(self, x: ArrayLike, y: ArrayLike, height_m: ArrayLike) -> NDArray[np.float64]:
        """Map coordinates (CRS units, x/easting first) and heights (m) to XYZ (m)."""
        lon, lat = self._map_to_geodetic(x, y)
        return lonlat_to_xyz(lon, lat, height_m, self.ellipsoid, "planetographic")

    def xyz_to_map(
        self, xyz: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """XYZ (m) to map coordinates (CRS units) and ellipsoidal height (m)."""
        lon, lat, h = xyz_to_lonlat(xyz, self.ellipsoid, "planetographic")
        x, y = self._geodetic_to_map(lon, lat)
        return x, y, h

    def lonlat_to_map(
        self, lon_deg: ArrayLike, lat_deg: ArrayLike, latitude: LatitudeKind = "planetocentric"
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Longitude/latitude (degrees, east-positive) to map coordinates."""
        lat = _latitude_as(lat_deg, latitude, "planetographic", self.ellipsoid)
        return self._geodetic_to_map(np.asarray(lon_deg, float), lat)

    def map_to_lonlat(
        self, x: ArrayLike, y: ArrayLike, latitude: LatitudeKind = "planetocentric"
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Map coordinates to longitude/latitude in degrees (east-positive, [-180, 180))."""
        lon, lat = self._map_to_geodetic(x, y)
        return wrap_longitude(lon), _latitude_as(lat, "planetographic", latitude, self.ellipsoid)
