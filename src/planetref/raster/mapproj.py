"""Map coordinates of a CRS <-> lon/lat/XYZ, in closed form where possible.

:class:`MapProjection` converts between a map CRS's coordinates and planetocentric
lon/lat (degrees) or body-fixed XYZ (metres). Equirectangular CRSs on a sphere (such as
``IAU_2015:49910`` and the simulator's local maps) use closed formulas, checked against
PROJ when the object is built; any other CRS goes through
:class:`~planetref.geometry.geodesy.CrsGround`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.geometry.geodesy import (
    CrsGround,
    Ellipsoid,
    lonlat_to_xyz,
    wrap_longitude,
    xyz_to_lonlat,
)

__all__ = ["MapProjection"]


class _EqcSphere:
    """Closed-form equidistant cylindrical on a sphere (PROJ ``eqc``), for speed."""

    def __init__(
        self, radius: float, lat_ts: float, lat_0: float, lon_0: float, x_0: float, y_0: float
    ) -> None:
        self.r = radius
        self.kx = radius * np.cos(np.radians(lat_ts)) * np.pi / 180.0
        self.ky = radius * np.pi / 180.0
        self.lat_0, self.lon_0, self.x_0, self.y_0 = lat_0, lon_0, x_0, y_0

    def lonlat_to_map(
        self, lon: NDArray[np.float64], lat: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        dlon = wrap_longitude(lon - self.lon_0)
        return self.x_0 + self.kx * dlon, self.y_0 + self.ky * (lat - self.lat_0)

    def map_to_lonlat(
        self, x: NDArray[np.float64], y: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        lon = self.lon_0 + (x - self.x_0) / self.kx
        return wrap_longitude(lon), self.lat_0 + (y - self.y_0) / self.ky


def _eqc_fast_path(ground: CrsGround) -> _EqcSphere | None:
    """The closed form of an equirectangular CRS on a sphere, or None if not applicable."""
    crs = ground.crs
    if not crs.is_projected or not ground.ellipsoid.is_sphere:
        return None
    op = crs.coordinate_operation
    if op is None or "equidistant cylindrical" not in op.method_name.lower():
        return None
    axes = crs.axis_info
    if (
        len(axes) != 2
        or axes[0].direction.lower() != "east"
        or axes[1].direction.lower() != "north"
        or any(a.unit_name not in ("metre", "meter") for a in axes)
    ):
        return None
    values = {"lat_ts": 0.0, "lat_0": 0.0, "lon_0": 0.0, "x_0": 0.0, "y_0": 0.0}
    names = {
        "latitude of 1st standard parallel": "lat_ts",
        "latitude of natural origin": "lat_0",
        "longitude of natural origin": "lon_0",
        "false easting": "x_0",
        "false northing": "y_0",
    }
    for p in op.params:
        key = names.get(p.name.lower())
        if key is None:
            return None
        values[key] = float(p.value)
    fast = _EqcSphere(ground.ellipsoid.semi_major_m, **values)
    # Check the closed form against PROJ on a few points near the origin before trusting it.
    lon = fast.lon_0 + np.array([-0.3, 0.0, 0.2, 0.7])
    lat = np.array([-0.5, 0.1, 0.4, 0.8]) + np.clip(values["lat_ts"], -80.0, 80.0)
    x_ref, y_ref = ground.lonlat_to_map(lon, lat)
    x, y = fast.lonlat_to_map(lon, lat)
    if not (np.allclose(x, x_ref, atol=1e-6, rtol=0) and np.allclose(y, y_ref, atol=1e-6, rtol=0)):
        return None
    return fast


class MapProjection:
    """Map coordinates of a CRS <-> lon/lat/XYZ, in closed form where possible.

    Equirectangular CRSs on a sphere (such as ``IAU_2015:49910`` and the simulator's
    local maps) are converted with closed formulas (checked against PROJ when the object
    is built); any other CRS goes through :class:`~planetref.geometry.geodesy.CrsGround`.

    Args:
        crs: Anything ``pyproj.CRS.from_user_input`` accepts (not geocentric).

    Raises:
        CrsError: If the CRS is invalid or geocentric.
    """

    def __init__(self, crs: object) -> None:
        self.ground = CrsGround(crs)
        self.crs = self.ground.crs
        self.ellipsoid: Ellipsoid = self.ground.ellipsoid
        self._fast = _eqc_fast_path(self.ground)

    @property
    def is_closed_form(self) -> bool:
        """True when the closed-form equirectangular path is used."""
        return self._fast is not None

    def lonlat_to_map(
        self, lon_deg: ArrayLike, lat_deg: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Planetocentric lon/lat (degrees) to map coordinates."""
        lon, lat = np.asarray(lon_deg, float), np.asarray(lat_deg, float)
        if self._fast is not None:
            return self._fast.lonlat_to_map(lon, lat)
        return self.ground.lonlat_to_map(lon, lat)

    def map_to_lonlat(
        self, x: ArrayLike, y: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Map coordinates to planetocentric lon/lat in degrees."""
        x, y = np.asarray(x, float), np.asarray(y, float)
        if self._fast is not None:
            return self._fast.map_to_lonlat(x, y)
        return self.ground.map_to_lonlat(x, y)

    def xyz_to_map(
        self, xyz: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Body-fixed XYZ (m, shape ``(..., 3)``) to map ``x, y`` and height above the body."""
        if self._fast is not None:
            lon, lat, h = xyz_to_lonlat(xyz, self.ellipsoid)
            x, y = self._fast.lonlat_to_map(lon, lat)
            return x, y, h
        return self.ground.xyz_to_map(xyz)

    def map_to_xyz(self, x: ArrayLike, y: ArrayLike, height_m: ArrayLike) -> NDArray[np.float64]:
        """Map ``x, y`` and height (m) to body-fixed XYZ (m), shape ``(..., 3)``."""
        if self._fast is not None:
            lon, lat = self._fast.map_to_lonlat(np.asarray(x, float), np.asarray(y, float))
            return lonlat_to_xyz(lon, lat, height_m, self.ellipsoid)
        return self.ground.map_to_xyz(x, y, height_m)
