from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from planetref.camera.base import Terrain
from planetref.errors import InputError, MissingFileError
from planetref.geometry.geodesy import MARS_IAU2015_SPHERE, CrsGround, lonlat_to_xyz
from planetref.geometry.terrain import intersect_terrain
from planetref.raster.dem import GridTerrain, MapProjection
from planetref.raster.dem_holes import DemHoles
from planetref.simulate.grid import MapGrid, local_crs_wkt

LAT, LON = 25.1, 109.9


def _plane_dem(res: float = 2.0, n: int = 200, nan_hole: bool = False) -> GridTerrain:
    grid = MapGrid(-n * res / 2, n * res / 2, res, n, n)
    x = grid.x_centres()[None, :]
    y = grid.y_centres()[:, None]
    h = (10.0 + 0.05 * x - 0.02 * y + 0 * x * y).astype(np.float64)
    if nan_hole:
        h[50, 60] = np.nan
    return GridTerrain(h, grid.transform, local_crs_wkt(LAT, LON))


def test_protocol_and_bilinear_is_exact_on_planes() -> None:
    dem = _plane_dem()
    assert isinstance(dem, Terrain)
    rng = np.random.default_rng(0)
    x = rng.uniform(-150, 150, 500)
    y = rng.uniform(-150, 150, 500)
    np.testing.assert_allclose(dem.height_at_map(x, y), 10.0 + 0.05 * x - 0.02 * y, atol=1e-9)
    lon, lat = dem.map_to_lonlat(x, y)
    np.testing.assert_allclose(dem.height(lon, lat), 10.0 + 0.05 * x - 0.02 * y, atol=1e-6)
    assert dem.sampling_m == pytest.approx(2.0, rel=1e-3)
    assert np.isnan(dem.height_at_map(np.array([500.0]), np.array([0.0])))[0]


def test_nodata_propagates_as_nan() -> None:
    dem = _plane_dem(nan_hole=True)
    x, y = dem.transform @ (60.5, 50.5)
    assert np.isnan(dem.height_at_map(np.array([x + 0.3]), np.array([y])))[0]
    assert np.isfinite(dem.height_at_map(np.array([x + 5.0]), np.array([y])))[0]
    with pytest.raises(InputError):
        GridTerrain(np.full((4, 4), np.nan), (0, 1, 0, 0, 0, -1), "IAU_2015:49910")
    with pytest.raises(InputError):
        GridTerrain(np.zeros(4), (0, 1, 0, 0, 0, -1), "IAU_2015:49910")


def test_fast_eqc_path_matches_proj() -> None:
    for crs in ("IAU_2015:49910", local_crs_wkt(LAT, LON)):
        proj = MapProjection(crs)
        assert proj.is_closed_form
        ref = CrsGround(crs)
        lon = LON + np.linspace(-0.2, 0.2, 7)
        lat = LAT + np.linspace(-0.2, 0.2, 7)
        x, y = proj.lonlat_to_map(lon, lat)
        xr, yr = ref.lonlat_to_map(lon, lat)
        np.testing.assert_allclose(x, xr, atol=1e-6)
        np.testing.assert_allclose(y, yr, atol=1e-6)
        xyz = lonlat_to_xyz(lon, lat, 100.0, MARS_IAU2015_SPHERE)
        x2, y2, h2 = proj.xyz_to_map(xyz)
        np.testing.assert_allclose([x2, y2], [xr, yr], atol=1e-6)
        np.testing.assert_allclose(h2, 100.0, atol=1e-6)


def test_geotiff_round_trip_with_nodata(tmp_path: Path, write_geotiff) -> None:
    dem = _plane_dem(nan_hole=True)
    p = tmp_path / "dem.tif"
    dem.to_geotiff(p)
    # Holes kept as read (the default fills small holes, see test_dem_holes.py).
    back = GridTerrain.from_geotiff(p, holes=DemHoles(fill=False))
    np.testing.assert_array_equal(np.isnan(back.heights), np.isnan(dem.heights))
    assert back.transform == dem.transform
    # An integer DEM with a numeric nodata value (as MOLA products are).
    q = tmp_path / "int.tif"
    h = np.arange(100, dtype=np.int16).reshape(10, 10)
    h[3, 3] = -32768
    write_geotiff(q, h, crs="IAU_2015:49910", transform=dem.transform, nodata=-32768)
    back = GridTerrain.from_geotiff(q, holes=DemHoles(fill=False))
    assert np.isnan(back.heights[3, 3]) and back.heights[2, 2] == 22
    # By default the one-cell hole is filled: harmonic filling is exact on a plane.
    with pytest.warns(UserWarning, match=r"int\.tif: filled 1 nodata cells in 1 holes"):
        back = GridTerrain.from_geotiff(q)
    assert back.heights[3, 3] == pytest.approx(33.0, abs=1e-4) and back.heights[2, 2] == 22
    with pytest.raises(MissingFileError):
        GridTerrain.from_geotiff(tmp_path / "none.tif")
    with pytest.raises(InputError, match="band"):
        GridTerrain.from_geotiff(p, band=2)


def _bumpy_dem() -> GridTerrain:
    grid = MapGrid(-300.0, 300.0, 2.0, 300, 300)
    x = grid.x_centres()[None, :]
    y = grid.y_centres()[:, None]
    h = 30.0 * np.exp(-((x - 20) ** 2 + y**2) / 40.0**2) + 0.1 * x
    return GridTerrain(h.astype(np.float32), grid.transform, local_crs_wkt(LAT, LON))


def _rays(dem: GridTerrain, off_nadir_deg: float, n: int = 60) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(1)
    x = rng.uniform(-150, 150, n)
    y = rng.uniform(-150, 150, n)
    ground = dem.map_to_xyz(x, y, dem.height_at_map(x, y))
    up = ground / np.linalg.norm(ground, axis=1, keepdims=True)
    east = np.cross([0, 0, 1.0], up)
    east /= np.linalg.norm(east, axis=1, keepdims=True)
    t = np.radians(off_nadir_deg)
    direction = -(np.cos(t) * up + np.sin(t) * east)
    origin = ground - 265e3 / np.cos(t) * direction
    return origin, direction


@pytest.mark.parametrize("off_nadir", [0.3, 35.0])
def test_intersect_rays_agrees_with_raycast(off_nadir: float) -> None:
    dem = _bumpy_dem()
    origin, direction = _rays(dem, off_nadir)
    hits = dem.intersect_rays(origin, direction)
    ref = intersect_terrain(origin, direction, dem)
    assert hits.hit.all()
    np.testing.assert_allclose(hits.xyz, ref, atol=2e-3)
    # The point lies on the DEM surface.
    np.testing.assert_allclose(hits.height, dem.height_at_map(hits.x, hits.y), atol=1e-4)


def test_intersect_rays_misses_are_nan() -> None:
    dem = _bumpy_dem()
    origin, direction = _rays(dem, 0.3, 3)
    origin = origin + 5000.0 * np.cross(direction, [0, 0, 1.0])  # far outside the grid
    hits = dem.intersect_rays(origin, direction)
    assert not hits.hit.any() and np.isnan(hits.xyz).all()


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("rows", [2, 257, 513, 600])
def test_grid_statistics_by_row_blocks_equal_whole_grid(dtype, rows: int) -> None:
    # Height range, steepest step and hole test are computed over row blocks of 256 (no
    # grid-sized temporaries): they must equal the whole-grid formulas bit for bit,
    # including steps across block borders and NaN cells.
    rng = np.random.default_rng(rows)
    h = rng.normal(0.0, 50.0, (rows, 7)).astype(dtype)
    if rows > 256:
        h[256, 3] += 5e4  # the steepest step crosses the first block border (rows 255/256)
    grid = MapGrid(0.0, 7 * 2.0, 2.0, 7, rows)
    dem = GridTerrain(h, grid.transform, local_crs_wkt(LAT, LON))
    d1, d0 = np.abs(np.diff(h, axis=1)), np.abs(np.diff(h, axis=0))
    res = float(np.hypot(dem.transform.a, dem.transform.d))
    scale = dem.sampling_m / res
    whole = np.nanmax([np.nanmax(d1) / (res * scale), np.nanmax(d0) / (res * scale), 0.0])
    assert dem.max_slope == float(whole * np.sqrt(2.0))
    assert (dem.min_height_m, dem.max_height_m) == (float(h.min()), float(h.max()))
    assert dem._hole_table is None
    h[rows - 1, 2] = np.nan
    holed = GridTerrain(h, grid.transform, local_crs_wkt(LAT, LON))
    assert holed._hole_table is not None and holed._hole_table[-1, -1] == 1
    finite = h[np.isfinite(h)]
    assert (holed.min_height_m, holed.max_height_m) == (float(finite.min()), float(finite.max()))
    d1, d0 = np.abs(np.diff(h, axis=1)), np.abs(np.diff(h, axis=0))
    assert holed.max_slope == float(
        np.nanmax([np.nanmax(d1) / (res * scale), np.nanmax(d0) / (res * scale), 0.0])
        * np.sqrt(2.0)
    )
