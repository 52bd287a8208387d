"""Standard products: strip orthoimages (type, round grid, overviews, mosaic), ASP/ISIS
exports of control points, and DEM datums in the scene manifest."""

from __future__ import annotations

import csv
import dataclasses
import shutil

import numpy as np
import pytest
import rasterio
from rasterio.enums import Resampling

from planetref.camera.io import load_camera
from planetref.camera.mapping import image_gsd_m
from planetref.control.exports import (
    CNET_COLUMNS,
    FREE_SIGMA_M,
    ControlPoints,
    write_asp_gcp,
    write_isis_cnet_csv,
)
from planetref.errors import InputError
from planetref.geometry.geodesy import Ellipsoid, lonlat_to_xyz
from planetref.products.ortho_strip import PixelType, orthorectify_strip, round_gsd
from planetref.products.orthoimage import compression
from planetref.raster.image import CcdImage
from planetref.scene.inputs import open_reference
from planetref.scene.manifest import load_manifest


def test_round_gsd_and_pixel_types():
    assert round_gsd(0.4873) == 0.5
    assert round_gsd(2.7) == 2.5
    assert round_gsd(5.1) == 5.0
    assert round_gsd(0.36) == 0.4
    assert round_gsd(1.13) == 1.2
    assert round_gsd(93.0) == 100.0
    with pytest.raises(InputError):
        round_gsd(0.0)
    u8 = PixelType.of(np.uint8)
    assert (u8.dtype, u8.nodata) == (np.dtype(np.uint8), 255.0)
    v = u8.cast(np.array([[0.4, 254.6, 255.0, np.nan]], np.float32))
    # Rounded; a saturated 255 is written as 254 so that it never reads as nodata.
    assert v.tolist() == [[0, 254, 254, 255]] and v.dtype == np.uint8
    i16 = PixelType.of(np.int16)
    assert i16.nodata == -32768.0
    assert i16.cast(np.array([-32768.0, np.nan], np.float32)).tolist() == [-32767, -32768]
    f = PixelType.of(np.float32)
    assert f.dtype == np.float32 and np.isnan(f.nodata)
    assert PixelType.of(np.float64).dtype == np.float64


@pytest.fixture(scope="module")
def strip(tiny_scene):
    m, root = load_manifest(tiny_scene)
    ref, dem = open_reference(m, root)
    s = m.strips[0]
    cam = load_camera(m.resolve(root, s.ccds[0].camera))
    images = {c.camera_ccd or c.name: CcdImage(m.resolve(root, c.image)) for c in s.ccds}
    return cam, images, dem, ref.crs


def test_strip_orthoimages_and_mosaic(strip, tmp_path):
    cam, images, dem, crs = strip
    native = float(np.median([image_gsd_m(cam, c, dem) for c in images]))
    gsd = round_gsd(native)
    paths = {c: tmp_path / f"{c}.tif" for c in images}
    res = orthorectify_strip(
        images, cam, dem, crs, paths, gsd_m=gsd, mosaic=tmp_path / "mosaic.tif", threads=3
    )
    assert set(res.ccds) == set(images) and not res.resumed
    in_dtype = next(iter(images.values())).dtype
    values, masks = {}, {}
    m_ds = rasterio.open(res.mosaic)
    mt = m_ds.transform
    for c, p in res.ccds.items():
        with rasterio.open(p) as ds:
            assert ds.dtypes[0] == in_dtype.name  # the input's type is kept
            assert ds.nodata == PixelType.of(in_dtype).nodata
            assert ds.crs == crs
            t = ds.transform
            assert (t.a, -t.e) == (gsd, gsd)
            # One lattice: the origin is a multiple of the pixel size.
            assert t.c / gsd == pytest.approx(round(t.c / gsd), abs=1e-6)
            assert t.f / gsd == pytest.approx(round(t.f / gsd), abs=1e-6)
            a = ds.read(1, masked=True)
            assert 0.3 < (~a.mask).mean() < 1.0
            # Place the CCD's pixels into the mosaic grid (integer offsets).
            col = round((t.c - mt.c) / gsd)
            row = round((mt.f - t.f) / gsd)
            assert col >= 0 and row >= 0
            full = np.ma.masked_all((m_ds.height, m_ds.width), a.dtype)
            full[row : row + ds.height, col : col + ds.width] = a
            values[c], masks[c] = full.filled(0), ~np.ma.getmaskarray(full)
    mos = m_ds.read(1, masked=True)
    assert m_ds.dtypes[0] == in_dtype.name
    m_ds.close()
    valid = ~np.ma.getmaskarray(mos)
    any_ccd = np.any(list(masks.values()), axis=0)
    assert np.array_equal(valid, any_ccd)
    mv = mos.filled(0)
    n_valid = np.sum(list(masks.values()), axis=0)
    for c in images:
        only = masks[c] & (n_valid == 1)
        assert np.array_equal(mv[only], values[c][only])  # single coverage: that CCD
    overlap = n_valid >= 2
    assert overlap.sum() > 100
    equal_one = np.zeros_like(overlap)
    for c in images:
        equal_one |= masks[c] & (mv == values[c])
    assert equal_one[overlap].all()  # overlaps: one of the CCDs' values
    # Threads (CCDs resampled at once) do not change a pixel.
    one = orthorectify_strip(
        images,
        cam,
        dem,
        crs,
        {c: tmp_path / f"t1_{c}.tif" for c in images},
        gsd_m=gsd,
        mosaic=tmp_path / "t1_mosaic.tif",
        threads=1,
        overviews=False,
    )
    with rasterio.open(one.mosaic) as a, rasterio.open(res.mosaic) as b:
        assert np.array_equal(a.read(1), b.read(1))
    # Resume: same inputs -> kept.
    again = orthorectify_strip(
        images, cam, dem, crs, paths, gsd_m=gsd, mosaic=tmp_path / "mosaic.tif"
    )
    assert again.resumed


def test_overviews_are_internal(strip, tmp_path):
    cam, images, dem, crs = strip
    ccd = next(iter(images))
    # A fine pixel size makes the orthoimage large enough for two overview levels.
    gsd = round_gsd(image_gsd_m(cam, ccd, dem) / 3.0)
    res = orthorectify_strip(
        {ccd: images[ccd]}, cam, dem, crs, {ccd: tmp_path / "o.tif"}, gsd_m=gsd
    )
    with rasterio.open(res.ccds[ccd]) as ds:
        factors = ds.overviews(1)
        assert factors and factors[0] == 2
        assert min(ds.width, ds.height) // factors[-1] >= 256
        # Padded so that every overview pixel covers its exact block of pixels.
        assert ds.width % factors[-1] == 0 and ds.height % factors[-1] == 0
        assert ds.tags(ns="rio_overview") == {"resampling": "average"}
        # ZSTD wherever this GDAL writes it (DEFLATE was always chosen before: rasterio's
        # enum names are lower case); the same pixels, ~4x faster to write.
        written = str(getattr(ds.compression, "value", ds.compression)).lower()
    # The overviews made while writing are GDAL's AVERAGE of the written pixels.
    gdal = tmp_path.parent / f"{tmp_path.name}_gdal.tif"
    shutil.copy(res.ccds[ccd], gdal)
    with rasterio.open(gdal, "r+") as ds:
        ds.build_overviews(factors, Resampling.average)
    for k in range(len(factors)):
        with (
            rasterio.open(res.ccds[ccd], overview_level=k) as a,
            rasterio.open(gdal, overview_level=k) as b,
        ):
            assert np.array_equal(a.read(1), b.read(1), equal_nan=True)
    gdal.unlink()
    assert written == compression()["compress"]
    from rasterio.io import MemoryFile

    try:
        with MemoryFile() as mem:
            from affine import Affine

            one = {"driver": "GTiff", "width": 1, "height": 1, "count": 1, "dtype": "uint8"}
            one["transform"] = Affine(2.0, 0.0, 0.0, 0.0, -2.0, 2.0)
            with mem.open(**one, compress="zstd") as t:
                t.write(np.zeros((1, 1, 1), np.uint8))
            with mem.open() as t:
                zstd_here = str(getattr(t.compression, "value", t.compression)).upper() == "ZSTD"
    except Exception:
        zstd_here = False
    assert written == ("zstd" if zstd_here else "deflate")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o.tif", "o.tif.inputs.sha256"]


def _points():
    body = Ellipsoid(3396190.0, 3376200.0, "Mars ellipsoid")
    xyz = lonlat_to_xyz(
        np.array([10.0, 10.01, 10.02]),
        np.array([-30.0, -30.01, -30.02]),
        np.array([-1200.0, -1190.5, -1180.25]),
        body,
    )
    return body, ControlPoints(
        point_id=np.array(["s1:mcp0", "s1:mcp1", "tie0"], dtype=object),
        kind=np.array(["mcp", "mcp", "tie"], dtype=object),
        xyz=xyz,
        sigma_m=np.array([[2.5, 2.5, 4.0], [2.5, 2.5, 3.0], [np.inf] * 3]),
        check=np.array([False, True, False]),
        obs_point=np.array([0, 1, 2, 2]),
        obs_image=np.array(["/d/a.tif", "/d/a.tif", "/d/a.tif", "/d/b.tif"], dtype=object),
        obs_ccd=np.array(["ccd1", "ccd1", "ccd1", "ccd2"], dtype=object),
        line=np.array([10.5, 20.25, 30.0, 40.0]),
        sample=np.array([100.5, 200.75, 300.0, 400.0]),
        sigma_px=np.array([1.0, 1.0, 0.5, 0.5]),
    )


def test_asp_gcp_and_isis_csv_round_trip(tmp_path):
    body, pts = _points()
    gcp = write_asp_gcp(pts, body, tmp_path / "x.gcp")
    lines = gcp.read_text().splitlines()
    assert len(lines) == 3  # one line per point; a tie point's two images on one line
    f = [ln.split() for ln in lines]
    assert [len(x) for x in f] == [12, 12, 17]
    lat, lon, h = (np.array([float(x[k]) for x in f]) for k in (1, 2, 3))
    # Geodetic lat/lon/height above the body give back the same body-fixed points.
    back = lonlat_to_xyz(lon, lat, h, body, latitude="planetographic")
    assert np.max(np.abs(back - pts.xyz)) < 1e-6
    assert [float(v) for v in f[0][4:7]] == [2.5, 2.5, 4.0]
    assert [float(v) for v in f[2][4:7]] == [FREE_SIGMA_M] * 3
    # ASP pixels: first pixel's centre at (0, 0) -> col = sample - 0.5, row = line - 0.5.
    assert f[0][7:12] == ["/d/a.tif", "100.0", "10.0", "1.0", "1.0"]
    assert f[2][12:] == ["/d/b.tif", "399.5", "39.5", "0.5", "0.5"]
    cnet = write_isis_cnet_csv(pts, body, tmp_path / "x.csv")
    rows = list(csv.DictReader(cnet.open()))
    assert tuple(rows[0]) == CNET_COLUMNS and len(rows) == 4
    assert [r["PointType"] for r in rows] == ["Constrained", "Constrained", "Free", "Free"]
    assert [r["check"] for r in rows] == ["False", "True", "False", "False"]
    # ISIS pixels: first pixel's centre at (1, 1).
    assert float(rows[1]["Sample"]) == 201.25 and float(rows[1]["Line"]) == 20.75
    xyz = np.array([[float(r[k]) for k in ("AprioriX", "AprioriY", "AprioriZ")] for r in rows])
    assert np.max(np.abs(xyz - pts.xyz[pts.obs_point])) < 1e-6
    r0 = rows[0]
    assert float(r0["AprioriLongitude"]) == pytest.approx(10.0)
    assert float(r0["AprioriLatitude"]) == pytest.approx(-30.0)  # planetocentric
    assert float(r0["AprioriRadius"]) == pytest.approx(np.linalg.norm(pts.xyz[0]))
    assert rows[2]["AprioriRadiusSigma"] == "" and rows[0]["AprioriRadiusSigma"] == "4.0"
    both = ControlPoints.concatenate([pts, pts])
    assert both.obs_point.tolist() == [0, 1, 2, 2, 3, 4, 5, 5]
    # The matching tile of each MCP measure goes with it (none for tie points).
    assert [r["planetref_tile"] for r in rows] == [""] * 4
    tiled = dataclasses.replace(
        pts, obs_tile=np.array(["ccd1:r0c1", "ccd1:r2c0", "", ""], dtype=object)
    )
    mixed = ControlPoints.concatenate([tiled, pts])
    assert mixed.tiles.tolist() == ["ccd1:r0c1", "ccd1:r2c0"] + [""] * 6
    rows = list(csv.DictReader(write_isis_cnet_csv(mixed, body, tmp_path / "y.csv").open()))
    assert [r["planetref_tile"] for r in rows[:3]] == ["ccd1:r0c1", "ccd1:r2c0", ""]


def test_scene_manifest_datum_keys(tiny_scene, tmp_path, write_geotiff):
    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    manifest, root = load_manifest(scene)
    _, dem = open_reference(manifest, root)
    with rasterio.open(scene / manifest.reference.dem) as ds:
        crs, transform, shape = ds.crs, ds.transform, ds.shape
    _write_constant_areoid(write_geotiff, scene / "reference" / "areoid.tif", crs, transform, shape)
    text = "\n".join(
        ln for ln in (scene / "scene.toml").read_text().splitlines() if "dem_datum" not in ln
    )
    head, rest = text.split("[reference]\n", 1)
    (scene / "scene.toml").write_text(
        head
        + '[reference]\ndem_datum = "areoid"\nareoid = "reference/areoid.tif"\n'
        # A constant areoid is not Mars' at the scene's latitude (it is about -3.6 km
        # there): accepted with a warning, as the scene says.
        + 'implausible_heights = "warn"\n'
        + rest
    )
    manifest2, root2 = load_manifest(scene)
    assert "reference/areoid.tif" in manifest2.paths()
    _, dem2 = open_reference(manifest2, root2)
    assert np.nanmax(np.abs(dem2.heights - (dem.heights + 150.0))) < 1e-3
    # dem_datum = "areoid" without a raster, or an areoid with dem_datum = "body": refused.
    (scene / "scene.toml").write_text(head + '[reference]\ndem_datum = "areoid"\n' + rest)
    with pytest.raises(InputError, match="needs areoid"):
        load_manifest(scene)


@pytest.mark.slow
def test_georef_with_an_areoid_dem(tiny_scene, tmp_path, write_geotiff):
    """The same scene declared above a +150 m areoid: every MCP's ground point lies 150 m
    above the scene's DEM (to float precision), whatever the matches."""
    from planetref.control.mcp import read_mcps
    from planetref.geometry.geodesy import xyz_to_lonlat
    from planetref.pipeline.georef import run_georef
    from planetref.raster.dem import GridTerrain

    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    dem_file = scene / "reference" / "dem.tif"
    with rasterio.open(dem_file) as ds:
        crs, transform, shape = ds.crs, ds.transform, ds.shape
    _write_constant_areoid(write_geotiff, scene / "reference" / "areoid.tif", crs, transform, shape)
    lines = [ln for ln in (scene / "scene.toml").read_text().splitlines() if "dem_datum" not in ln]
    text = "\n".join(lines) + "\n"
    head, rest = text.split("[reference]\n", 1)
    (scene / "scene.toml").write_text(
        head
        + '[reference]\ndem_datum = "areoid"\nareoid = "reference/areoid.tif"\n'
        # A constant areoid is not Mars' at the scene's latitude (it is about -3.6 km
        # there): accepted with a warning, as the scene says.
        + 'implausible_heights = "warn"\n'
        + rest
    )
    out = run_georef(scene, "sift", tmp_path / "run", progress=False)
    # The accepted warning (a constant areoid is not Mars' there) is in the run's report
    # and log, not only on the terminal before the run's log opened.
    assert any("areoid raster is implausible" in w for w in out.report["input_warnings"])
    assert "areoid raster is implausible" in (tmp_path / "run" / "planetref.log").read_text()
    table = read_mcps(tmp_path / "run" / "strip1" / "mcps.parquet")
    dem = GridTerrain.from_geotiff(dem_file)
    lon, lat, h = xyz_to_lonlat(table.xyz(), dem.ellipsoid)
    assert len(h) >= 12
    assert np.max(np.abs(h - (dem.height(lon, lat) + 150.0))) < 1e-3
    assert out.report["adjustment"]["n_total"] > 0


def _write_constant_areoid(write_geotiff, path, crs, transform, shape, height_m=150.0):
    """A constant areoid of ``height_m`` on the DEM's own grid, with a 2-pixel margin."""
    n = np.full((shape[0] + 4, shape[1] + 4), height_m)
    write_geotiff(path, n, crs=crs, transform=transform @ rasterio.Affine.translation(-2, -2))
