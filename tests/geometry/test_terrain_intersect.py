"""Tests of planetref.geometry.terrain.intersect_terrain on synthetic terrains."""

from __future__ import annotations

import numpy as np
import pytest

from planetref.camera.base import ConstantHeight
from planetref.errors import GeometryError, InputError
from planetref.geometry.geodesy import (
    MARS_IAU2015_ELLIPSOID,
    MARS_IAU2015_SPHERE,
    Ellipsoid,
    lonlat_to_xyz,
    ray_ellipsoid_intersection,
    xyz_to_lonlat,
)
from planetref.geometry.terrain import intersect_terrain


class WavyTerrain:
    """A sloped, sinusoidal terrain: ``h = h0 + slope*y + amp*sin(2 pi x / wavelength)``.

    ``x`` and ``y`` are metres east and north of (lon 0, lat 0) along the ellipsoid's
    equator and meridian. A box of NaN heights (a hole) can be added.
    """

    def __init__(
        self,
        ellipsoid: Ellipsoid,
        h0: float = 500.0,
        slope: float = 0.05,
        amp: float = 300.0,
        wavelength: float = 2000.0,
        sampling: float = 20.0,
        hole_lon: tuple[float, float] | None = None,
    ) -> None:
        self.ellipsoid = ellipsoid
        self.h0, self.slope, self.amp, self.wavelength = h0, slope, amp, wavelength
        self._sampling = sampling
        self.hole_lon = hole_lon
        self.min_height_m = h0 - amp - 2000.0
        self.max_height_m = h0 + amp + 2000.0

    @property
    def sampling_m(self) -> float:
        return self._sampling

    def height(self, lon_deg, lat_deg):
        r = self.ellipsoid.semi_major_m
        x = np.radians(lon_deg) * r
        y = np.radians(lat_deg) * r
        h = (
            self.h0
            + np.clip(self.slope * y, -2000, 2000)
            + self.amp * np.sin(2 * np.pi * x / self.wavelength)
        )
        if self.hole_lon is not None:
            h = np.where((lon_deg > self.hole_lon[0]) & (lon_deg < self.hole_lon[1]), np.nan, h)
        return h


def _rays(ell: Ellipsoid, angles_deg, altitude=250e3, lon=0.02, lat=0.01):
    """Rays from above (lon, lat) tilted eastwards by ``angles_deg`` from nadir."""
    origin = lonlat_to_xyz(lon, lat, altitude, ell)
    up = origin / np.linalg.norm(origin)
    east = np.array([-np.sin(np.radians(lon)), np.cos(np.radians(lon)), 0.0])
    a = np.radians(np.asarray(angles_deg, dtype=float))[:, None]
    d = -np.cos(a) * up + np.sin(a) * east
    return np.repeat(origin[None, :], len(a), axis=0), d


@pytest.mark.parametrize(
    "ell", [MARS_IAU2015_SPHERE, MARS_IAU2015_ELLIPSOID], ids=["sphere", "ellipsoid"]
)
def test_intersection_lies_on_terrain_and_is_first_crossing(ell):
    terrain = WavyTerrain(ell)
    o, d = _rays(ell, [0.0, 10.0, 30.0, 55.0, -40.0])
    xyz = intersect_terrain(o, d, terrain)
    lon, lat, h = xyz_to_lonlat(xyz, ell)
    # On the terrain (bisection tolerance 0.1 mm along the ray).
    np.testing.assert_allclose(h, terrain.height(lon, lat), atol=2e-4)
    # On the ray, in front of the origin.
    v = xyz - o
    s = np.sum(v * d, axis=1)
    assert np.all(s > 0)
    np.testing.assert_allclose(np.linalg.norm(v - s[:, None] * d, axis=1), 0, atol=1e-6)
    # First crossing: nothing below the terrain between the origin and the point.
    for k in range(len(o)):
        ss = np.linspace(0, s[k] - 0.05, 20000)
        p = o[k] + ss[:, None] * d[k]
        lo, la, hh = xyz_to_lonlat(p, ell)
        assert np.all(hh - terrain.height(lo, la) > 0)


def test_grazing_ray_finds_first_crest_not_a_later_one():
    # A ray at 80 degrees crosses several crests; the march must stop at the first.
    ell = MARS_IAU2015_SPHERE
    terrain = WavyTerrain(ell, slope=0.0, amp=400.0, wavelength=3000.0, sampling=10.0)
    o, d = _rays(ell, [80.0], altitude=20e3)
    xyz = intersect_terrain(o, d, terrain)
    s_hit = float(np.dot(xyz[0] - o[0], d[0]))
    ss = np.linspace(0, s_hit, 200000)[:-50]
    lo, la, hh = xyz_to_lonlat(o[0] + ss[:, None] * d[0], ell)
    assert np.all(hh > terrain.height(lo, la))


def test_constant_height_matches_closed_form():
    ell = MARS_IAU2015_ELLIPSOID
    o, d = _rays(ell, [0.0, 20.0, 45.0])
    for h in (-2000.0, 0.0, 3000.0):
        xyz = intersect_terrain(o, d, ConstantHeight(ell, h))
        s = ray_ellipsoid_intersection(o, d, ell, h)
        np.testing.assert_allclose(xyz, o + s[:, None] * d, atol=1e-6)
        np.testing.assert_allclose(xyz_to_lonlat(xyz, ell)[2], h, atol=1e-4)


def test_misses_raise_or_give_nan_rows():
    ell = MARS_IAU2015_SPHERE
    terrain = WavyTerrain(ell)
    o, d = _rays(ell, [0.0, 30.0])
    up = o[0] / np.linalg.norm(o[0])
    o = np.vstack([o, o[:1], o[:1]])
    # Straight up (away from Mars) and horizontal (passes above the max height).
    east = np.array([-np.sin(np.radians(0.02)), np.cos(np.radians(0.02)), 0.0])
    d = np.vstack([d, up, east])
    with pytest.raises(GeometryError, match="2 of 4 rays miss"):
        intersect_terrain(o, d, terrain)
    xyz = intersect_terrain(o, d, terrain, on_miss="nan")
    assert np.all(np.isfinite(xyz[:2])) and np.all(np.isnan(xyz[2:]))


def test_ray_through_hole_misses_instead_of_giving_a_wrong_point():
    ell = MARS_IAU2015_SPHERE
    terrain = WavyTerrain(ell, hole_lon=(0.0, 0.05))
    o, d = _rays(ell, [0.0])
    xyz = intersect_terrain(o, d, terrain, on_miss="nan")
    assert np.all(np.isnan(xyz))


def test_origin_under_the_terrain_sees_nothing():
    ell = MARS_IAU2015_SPHERE
    terrain = WavyTerrain(ell)
    o, d = _rays(ell, [0.0], altitude=-1500.0)
    assert np.all(np.isnan(intersect_terrain(o, d, terrain, on_miss="nan")))


def test_bad_arguments():
    ell = MARS_IAU2015_SPHERE
    o, d = _rays(ell, [0.0])
    with pytest.raises(InputError, match="on_miss"):
        intersect_terrain(o, d, ConstantHeight(ell), on_miss="ignore")
    with pytest.raises(InputError, match="shape"):
        intersect_terrain(o[:, :2], d, ConstantHeight(ell))
    with pytest.raises(InputError, match="sampling_m"):
        intersect_terrain(o, d, WavyTerrain(ell, sampling=0.0))
