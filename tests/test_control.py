"""Matched control points: conversion from matches, counts, and file round trips."""

from __future__ import annotations

import numpy as np
import pytest
from affine import Affine

from planetref.control.mcp import (
    MCP_COLUMNS,
    McpTable,
    mcps_from_matches,
    mcps_from_tiles,
    read_mcps,
    write_mcps,
)
from planetref.errors import InputError, MissingFileError, UnsupportedFormatError
from planetref.frontend.result import TileResult
from planetref.frontend.tiles import Tile
from planetref.geometry.geodesy import MARS_IAU2015_SPHERE, lonlat_to_xyz
from planetref.raster.dem import GridTerrain
from planetref.raster.ortho import ReferenceOrtho

CRS = "IAU_2015:49910"
X0, Y0 = 4_387_000.0, 1_185_000.0  # about 74 E, 20 N on the Mars sphere


@pytest.fixture(scope="module")
def ref_and_dem():
    ref = ReferenceOrtho(
        np.ones((200, 200), np.float32), transform=Affine(5, 0, X0, 0, -5, Y0), crs=CRS
    )
    h = np.fromfunction(lambda r, c: 10.0 * r + c - 2000.0, (30, 30))
    h[4:6, 4:6] = np.nan  # a hole
    dem = GridTerrain(h, Affine(50, 0, X0 - 200, 0, -50, Y0 + 200), CRS)
    return ref, dem


def _points(ref):
    # Map coordinates of reference pixel centres, away from the DEM hole.
    cols = np.array([40.5, 60.5, 80.5, 100.5, 120.5])
    rows = np.array([50.5, 70.5, 90.5, 110.5, 130.5])
    x, y = ref.pixel_to_map(cols, rows)
    return x, y


def test_mcps_heights_xyz_and_counts(ref_and_dem):
    ref, dem = ref_and_dem
    x, y = _points(ref)
    # Add: one point in the DEM hole, one outside the ortho, one duplicate (less confident)
    # and a CCD-2 point at the same raw position (not a duplicate: another CCD).
    hole_x, hole_y = dem.transform @ (5.0, 5.0)
    xs = np.r_[x, hole_x, X0 - 50.0, x[0], x[1]]
    ys = np.r_[y, hole_y, Y0 - 100.0, y[0], y[1]]
    line = np.r_[100.5, 200.5, 300.5, 400.5, 500.5, 600.5, 700.5, 100.7, 200.5]
    sample = np.r_[10.5, 20.5, 30.5, 40.5, 50.5, 60.5, 70.5, 10.4, 20.5]
    conf = np.r_[0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3, 0.2, 0.9]
    ccd = ["ccd1"] * 8 + ["ccd2"]
    t = mcps_from_matches(
        ccd=ccd,
        tile_id="ccd1:r000c000",
        line=line,
        sample=sample,
        ref_x=xs,
        ref_y=ys,
        confidence=conf,
        matcher="sift",
        ref=ref,
        dem=dem,
    )
    c = t.counts
    assert (c.candidates, c.nan_dem, c.outside_reference, c.duplicates, c.kept) == (9, 1, 1, 1, 6)
    assert len(t) == 6 and list(t["mcp_id"]) == list(range(6))
    assert list(t["ccd"]) == ["ccd1"] * 5 + ["ccd2"]
    np.testing.assert_allclose(t["confidence"][:5], conf[:5])  # the duplicate lost
    np.testing.assert_allclose(t["height_m"], dem.height_at_map(t["ref_x"], t["ref_y"]))
    lon, lat = ref.ground.map_to_lonlat(t["ref_x"], t["ref_y"])
    np.testing.assert_allclose(t["lon_deg"], lon)
    np.testing.assert_allclose(t["lat_deg"], lat)
    xyz = lonlat_to_xyz(lon, lat, t["height_m"], MARS_IAU2015_SPHERE)
    np.testing.assert_allclose(t.xyz(), xyz, atol=1e-6)
    assert 73 < t["lon_deg"].mean() < 75 and 19 < t["lat_deg"].mean() < 21
    # Bilinear: midway between DEM cells the height is the mean of its neighbours.
    mx, my = dem.transform @ (15.0, 15.0)
    t2 = mcps_from_matches(
        ccd="a",
        tile_id="t",
        line=[1.0],
        sample=[1.0],
        ref_x=[mx],
        ref_y=[my],
        confidence=[1.0],
        matcher="m",
        ref=ref,
        dem=dem,
    )
    assert t2["height_m"][0] == pytest.approx(
        np.mean([10.0 * r + c - 2000 for r in (14, 15) for c in (14, 15)])
    )


def test_round_trips(tmp_path, ref_and_dem):
    ref, dem = ref_and_dem
    x, y = _points(ref)
    t = mcps_from_matches(
        ccd=["ccd1", "ccd1", "ccd2", "ccd2", "ccd3"],
        tile_id="ccd1:r001c002",
        line=np.arange(5) * 10.5,
        sample=np.arange(5) * 3.25,
        ref_x=x,
        ref_y=y,
        confidence=np.linspace(0.1, 1, 5),
        matcher="disk-lightglue",
        ref=ref,
        dem=dem,
    )
    files = write_mcps(t, tmp_path / "out" / "mcps.parquet")
    assert [f.suffix for f in files] == [".parquet", ".gpkg"]
    csv_files = write_mcps(t, tmp_path / "mcps.csv", gpkg=tmp_path / "points.gpkg")
    assert csv_files[1].name == "points.gpkg"
    for f in (files[0], files[1], csv_files[0]):
        back = read_mcps(f)
        assert len(back) == len(t)
        for c in MCP_COLUMNS:
            if t[c].dtype == object:
                assert list(back[c]) == list(t[c]), (f, c)
            else:
                np.testing.assert_allclose(
                    np.asarray(back[c], float),
                    t[c],
                    rtol=0,
                    atol=1e-9 * max(1.0, np.abs(t[c]).max()),
                )
    from pyproj import CRS as PCRS

    assert PCRS.from_wkt(read_mcps(files[0]).crs_wkt).equals(PCRS(CRS))
    assert PCRS.from_wkt(read_mcps(files[1]).crs_wkt).equals(PCRS(CRS))
    assert read_mcps(csv_files[0]).crs_wkt is None
    assert read_mcps(csv_files[0], crs=CRS).crs_wkt is not None
    assert read_mcps(files[0]).counts.to_dict() == t.counts.to_dict()
    # The GeoPackage geometry is the reference map position.
    from pyogrio.raw import read

    meta, _, geom, _ = read(str(files[1]))
    assert meta["geometry_type"] == "Point"
    xy = np.array([np.frombuffer(g[5:21], "<f8") for g in geom])
    np.testing.assert_allclose(xy, np.column_stack([t["ref_x"], t["ref_y"]]))
    # Atomic writes leave no temporary file behind.
    assert not [p for p in tmp_path.rglob("*") if ".tmp" in p.name]
    # Empty tables round-trip too.
    e = McpTable.empty(t.crs_wkt)
    write_mcps(e, tmp_path / "empty.parquet")
    assert len(read_mcps(tmp_path / "empty.parquet")) == 0
    assert len(read_mcps(tmp_path / "empty.gpkg")) == 0


def test_mcps_from_tiles(ref_and_dem):
    ref, dem = ref_and_dem
    x, y = _points(ref)
    tile = Tile("ccd1:r000c000", "ccd1", 0, 0, 1000, 1000)
    ok = TileResult(
        tile=tile,
        matcher="sift",
        status="ok",
        line=np.arange(5.0) * 100 + 0.5,
        sample=np.arange(5.0) * 50 + 0.5,
        ref_col=np.zeros(5),
        ref_row=np.zeros(5),
        ref_x=x,
        ref_y=y,
        confidence=np.ones(5),
    )
    bad = TileResult(
        tile=Tile("ccd1:r000c001", "ccd1", 0, 900, 1000, 1000),
        matcher="sift",
        status="too_few_inliers",
        line=np.array([1.0]),
        sample=np.array([1.0]),
        ref_col=np.zeros(1),
        ref_row=np.zeros(1),
        ref_x=x[:1],
        ref_y=y[:1],
        confidence=np.ones(1),
    )
    t = mcps_from_tiles([ok, bad], ref=ref, dem=dem)
    assert len(t) == 5 and t.counts.tiles_skipped == 1 and set(t["tile_id"]) == {tile.tile_id}
    assert set(t["matcher"]) == {"sift"}
    assert len(mcps_from_tiles([bad], ref=ref, dem=dem)) == 0
    other = TileResult(
        tile=tile,
        matcher="ncc",
        status="ok",
        line=np.ones(1),
        sample=np.ones(1),
        ref_col=np.zeros(1),
        ref_row=np.zeros(1),
        ref_x=x[:1],
        ref_y=y[:1],
        confidence=np.ones(1),
    )
    with pytest.raises(InputError, match="several matchers"):
        mcps_from_tiles([ok, other], ref=ref, dem=dem)
    both = McpTable.concatenate([t, t])
    assert len(both) == 10 and list(both["mcp_id"]) == list(range(10))
    assert both.counts.kept == 10


def test_errors(tmp_path, ref_and_dem):
    with pytest.raises(MissingFileError):
        read_mcps(tmp_path / "nope.parquet")
    (tmp_path / "x.txt").write_text("")
    with pytest.raises(UnsupportedFormatError):
        read_mcps(tmp_path / "x.txt")
    with pytest.raises(UnsupportedFormatError):
        write_mcps(McpTable.empty(), tmp_path / "m.txt")
    with pytest.raises(InputError, match="CRS"):
        write_mcps(McpTable.empty(), tmp_path / "m.csv")
    with pytest.raises(InputError, match="lacks columns"):
        McpTable({"mcp_id": [1]})
    (tmp_path / "bad.csv").write_text("a,b\n1,2\n")
    with pytest.raises((InputError, UnsupportedFormatError)):
        read_mcps(tmp_path / "bad.csv")


def test_ground_sigmas_from_gsd_slope_and_round_trip(ref_and_dem, tmp_path):
    """Planimetric: half the 5 m GSD; height: slope terms of a planar DEM, curvature 0."""
    from planetref.control.mcp import GROUND_SIGMA_H_FLOOR_M, ground_sigmas

    ref, dem = ref_and_dem
    x, y = _points(ref)
    s_xy, s_h = ground_sigmas(ref, dem, x, y)
    assert np.allclose(s_xy, 2.5)
    # h = 10 row + col - 2000 on 50-unit posts: gradient (0.02, -0.2) per map unit.
    slope = np.hypot(0.02, 0.2)
    res = dem.sampling_m
    expected = np.sqrt((0.5 * res * slope) ** 2 + (2.5 * slope) ** 2 + GROUND_SIGMA_H_FLOOR_M**2)
    assert np.allclose(s_h, expected, rtol=1e-6)
    # A flat DEM gives the floor; a constant terrain (no posts) too.
    flat = GridTerrain(np.zeros((30, 30)), dem.transform, CRS)
    assert np.allclose(ground_sigmas(ref, flat, x, y)[1], GROUND_SIGMA_H_FLOOR_M)
    # The MCP table carries them and they survive Parquet and CSV.
    t = mcps_from_matches(
        ccd="ccd1",
        tile_id="t0",
        line=np.arange(len(x)) * 10.0 + 0.5,
        sample=np.full(len(x), 5.5),
        ref_x=x,
        ref_y=y,
        confidence=np.ones(len(x)),
        matcher="sift",
        ref=ref,
        dem=dem,
    )
    assert np.allclose(t["sigma_ground_h_m"], expected)
    for name in ("m.parquet", "m.csv"):
        write_mcps(t, tmp_path / name, gpkg=False)
        back = read_mcps(tmp_path / name)
        assert np.allclose(back["sigma_ground_xy_m"], 2.5)
        assert np.allclose(back["sigma_ground_h_m"], expected)
