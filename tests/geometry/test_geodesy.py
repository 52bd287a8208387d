import numpy as np
import pyproj
import pytest

from planetref.errors import CrsError, InputError
from planetref.geometry.geodesy import (
    EARTH_WGS84,
    MARS_IAU2015_ELLIPSOID,
    MARS_IAU2015_SPHERE,
    CrsGround,
    Ellipsoid,
    lonlat_to_xyz,
    ray_ellipsoid_intersection,
    wrap_longitude,
    xyz_to_lonlat,
)


@pytest.fixture
def points():
    rng = np.random.default_rng(42)
    n = 2000
    return rng.uniform(-180, 180, n), rng.uniform(-89.9, 89.9, n), rng.uniform(-9000, 400e3, n)


@pytest.mark.parametrize("ell", [MARS_IAU2015_SPHERE, MARS_IAU2015_ELLIPSOID, EARTH_WGS84])
def test_geodetic_xyz_matches_proj(ell, points):
    """Independent check against PROJ's geodetic -> geocentric conversion."""
    lon, lat, h = points
    t = pyproj.Transformer.from_crs(
        pyproj.CRS.from_proj4(f"+proj=longlat +a={ell.semi_major_m} +b={ell.semi_minor_m}"),
        pyproj.CRS.from_proj4(ell.to_proj4()),
        always_xy=True,
    )
    ref = np.stack(t.transform(lon, lat, h), axis=-1)
    xyz = lonlat_to_xyz(lon, lat, h, ell, "planetographic")
    assert np.abs(xyz - ref).max() < 1e-6


@pytest.mark.parametrize("ell", [MARS_IAU2015_ELLIPSOID, EARTH_WGS84])
def test_planetocentric_latitude_matches_proj_geoc(ell, points):
    lon, lat_g, _ = points
    t = pyproj.Transformer.from_pipeline(
        "+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad "
        f"+step +proj=geoc +a={ell.semi_major_m} +b={ell.semi_minor_m} "
        "+step +proj=unitconvert +xy_in=rad +xy_out=deg"
    )
    _, lat_c_ref = t.transform(lon, lat_g)
    xyz = lonlat_to_xyz(lon, lat_g, 0.0, ell, "planetographic")
    _, lat_c, h = xyz_to_lonlat(xyz, ell, "planetocentric")
    assert np.abs(lat_c - lat_c_ref).max() < 1e-10
    assert np.abs(h).max() < 1e-6
    # and the other way round
    back = lonlat_to_xyz(lon, lat_c, 0.0, ell, "planetocentric")
    assert np.abs(back - xyz).max() < 1e-6


@pytest.mark.parametrize("ell", [MARS_IAU2015_SPHERE, MARS_IAU2015_ELLIPSOID])
@pytest.mark.parametrize("kind", ["planetocentric", "planetographic"])
def test_round_trip(ell, kind, points):
    lon, lat, h = points
    xyz = lonlat_to_xyz(lon, lat, h, ell, kind)
    lon2, lat2, h2 = xyz_to_lonlat(xyz, ell, kind)
    assert np.abs(wrap_longitude(lon2 - lon)).max() < 1e-10
    assert np.abs(lat2 - lat).max() < 1e-10
    assert np.abs(h2 - h).max() < 1e-6


def test_sphere_height_is_radius_difference():
    xyz = np.array([[3396190.0 + 1234.5, 0, 0], [0, 0, -(3396190.0 - 10.0)]])
    _lon, lat, h = xyz_to_lonlat(xyz, MARS_IAU2015_SPHERE)
    assert h == pytest.approx([1234.5, -10.0])
    assert lat == pytest.approx([0.0, -90.0])


def test_poles_on_ellipsoid():
    xyz = np.array([[0.0, 0.0, 3376200.0 + 5.0], [0.0, 0.0, -3376200.0]])
    _, lat, h = xyz_to_lonlat(xyz, MARS_IAU2015_ELLIPSOID)
    assert lat == pytest.approx([90.0, -90.0])
    assert h == pytest.approx([5.0, 0.0], abs=1e-6)


def test_longitude_range():
    assert wrap_longitude([180.0, -180.0, 359.0, 540.0]).tolist() == [-180.0, -180.0, -1.0, -180.0]


@pytest.mark.parametrize("ell", [MARS_IAU2015_SPHERE, MARS_IAU2015_ELLIPSOID])
def test_ray_intersection_hits_requested_height(ell):
    rng = np.random.default_rng(1)
    n = 500
    lon, lat = rng.uniform(-180, 180, n), rng.uniform(-80, 80, n)
    origin = lonlat_to_xyz(lon, lat, 265e3, ell)
    target = lonlat_to_xyz(lon + rng.normal(0, 0.5, n), lat + rng.normal(0, 0.5, n), 0.0, ell)
    d = target - origin
    heights = rng.uniform(-8000, 20000, n)
    s = ray_ellipsoid_intersection(origin, d, ell, heights)
    _, _, h = xyz_to_lonlat(origin + s[:, None] * d, ell)
    assert np.abs(h - heights).max() < 1e-4
    # A ray pointing away misses, and so does one passing beside the body.
    miss = ray_ellipsoid_intersection(origin[:2], -d[:2], ell, 0.0)
    assert np.all(np.isnan(miss))
    side = ray_ellipsoid_intersection(np.array([[4e6, 0, 0]]), np.array([[0, 1.0, 0]]), ell, 0)
    assert np.isnan(side[0])


def test_ellipsoid_validation():
    with pytest.raises(InputError):
        Ellipsoid(3396190.0, float("nan"))
    with pytest.raises(InputError):
        Ellipsoid(1.0, 2.0)


def test_ellipsoid_from_iau_crs():
    ell = Ellipsoid.from_crs("IAU_2015:49900")
    assert ell.semi_major_m == ell.semi_minor_m == 3396190.0
    assert Ellipsoid.from_crs("IAU_2015:49901").semi_minor_m == 3376200.0
    with pytest.raises(CrsError):
        Ellipsoid.from_crs("not a crs")


def test_crs_ground_equirectangular_sphere():
    g = CrsGround("IAU_2015:49910")
    r = 3396190.0
    lon, lat = 74.25, 19.5
    x, y = np.radians(lon) * r, np.radians(lat) * r
    assert g.map_to_lonlat(x, y) == pytest.approx((lon, lat), abs=1e-9)
    xyz = g.map_to_xyz(x, y, 250.0)
    assert xyz == pytest.approx(lonlat_to_xyz(lon, lat, 250.0, MARS_IAU2015_SPHERE), abs=1e-6)
    x2, y2, h2 = g.xyz_to_map(xyz)
    assert (x2, y2, h2) == pytest.approx((x, y, 250.0), abs=1e-6)


def test_crs_ground_west_positive_and_ocentric_geographic():
    # IAU_2015:49901 is planetographic with west-positive longitude.
    west = CrsGround("IAU_2015:49901")
    lon, lat_c = west.map_to_lonlat(10.0, 20.0)
    assert lon == pytest.approx(-10.0)
    xyz = lonlat_to_xyz(-10.0, 20.0, 0.0, MARS_IAU2015_ELLIPSOID, "planetographic")
    assert west.map_to_xyz(10.0, 20.0, 0.0) == pytest.approx(xyz, abs=1e-6)
    # IAU_2015:49902 is planetocentric, east-positive.
    east = CrsGround("IAU_2015:49902")
    xyz_c = lonlat_to_xyz(10.0, 20.0, 0.0, MARS_IAU2015_ELLIPSOID, "planetocentric")
    assert east.map_to_xyz(10.0, 20.0, 0.0) == pytest.approx(xyz_c, abs=1e-6)
    # Same place described by two CRSs: planetocentric 20 N is not planetographic 20 N.
    assert lat_c < 20.0


def test_crs_ground_rejects_geocentric():
    with pytest.raises(CrsError):
        CrsGround(MARS_IAU2015_SPHERE.to_proj4())
