"""Tests of planetref.camera.rpc: files, GDAL agreement, inversion, terrain, fitting."""

from __future__ import annotations

import math
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine
from rasterio.transform import RPCTransformer

from planetref.camera.base import Camera, ConstantHeight
from planetref.camera.rpc import (
    EARTH_BODY,
    MARS_BODY,
    Rpc,
    RpcBody,
    RpcCamera,
    fit_rpc,
    read_rpc,
    read_rpc_body,
    rpc_sidecar_path,
    write_rpc,
    write_rpc_geotiff,
    write_rpc_rpb,
    write_rpc_txt,
)
from planetref.errors import GeometryError, InputError, MissingFileError, UnsupportedFormatError
from planetref.geometry.geodesy import (
    EARTH_WGS84,
    MARS_IAU2015_ELLIPSOID,
    MARS_IAU2015_SPHERE,
    lonlat_to_xyz,
    ray_ellipsoid_intersection,
    xyz_to_lonlat,
)

# Rasters written here without georeferencing are expected; the warning is noise.
pytestmark = pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")

PLEIADES = ("img_01.tif", "img_02.tif")
# GDAL's RPC inverse is a fixed-Jacobian iteration with a 0.1 px default threshold; ask
# it for round-off accuracy so that the comparison measures planetref, not GDAL.
GDAL_OPTS = {"RPC_PIXEL_ERROR_THRESHOLD": 1e-9, "RPC_MAX_ITERATIONS": 100}


def _pleiades(shared: Path, name: str) -> Path:
    path = shared / "data" / "pleiades_rpc" / name
    if not path.is_file():
        pytest.skip(f"{path} not found (Pléiades RPC test data absent)")
    return path


def _identity(x: float) -> float:
    return x


def _synthetic_rpc() -> Rpc:
    # Full 17-digit coefficients, so that any formatting with fewer digits shows.
    rng = np.random.default_rng(42)
    line_den = (1.0, *rng.normal(0, 1e-3, 19))
    samp_den = (1.0, *rng.normal(0, 1e-3, 19))
    line_num = (0.01, -0.02, -1.0, 0.3, *rng.normal(0, 1e-3, 16))
    samp_num = (-0.03, 1.0, 0.01, -0.2, *rng.normal(0, 1e-3, 16))
    return Rpc(
        line_off=512.5 + 1 / 3,
        samp_off=511.5 - 1 / 7,
        lat_off=18.123456789012345,
        long_off=77.98765432109876,
        height_off=-2345.6789,
        line_scale=530.1 + 1 / 3,
        samp_scale=515.9 - 1 / 9,
        lat_scale=0.0911805852907 / 3,
        long_scale=0.0985353286675 / 7,
        height_scale=1315.0 + 1 / 11,
        line_num_coeff=line_num,
        line_den_coeff=line_den,
        samp_num_coeff=samp_num,
        samp_den_coeff=samp_den,
    )


def _tiny_tif(write_geotiff, path: Path) -> Path:
    return write_geotiff(path, np.zeros((6, 8), np.uint8))


# ----------------------------------------------------------------- agreement with GDAL


@pytest.mark.shared
@pytest.mark.parametrize("name", PLEIADES)
def test_pleiades_agrees_with_gdal_rpc_transformer(shared: Path, name: str) -> None:
    path = _pleiades(shared, name)
    with rasterio.open(path) as src:
        gdal_rpc = src.rpcs
        size = (src.height, src.width)
    cam = RpcCamera.from_file(path)
    assert cam.image_size() == size
    assert cam.ellipsoid == EARTH_WGS84 and cam.latitude_kind == "planetographic"
    lines, samples = np.meshgrid(
        np.linspace(0, size[0], 13), np.linspace(0, size[1], 11), indexing="ij"
    )
    lines, samples = lines.ravel(), samples.ravel()
    for h in (-50.0, 0.0, 1295.0, 2610.0):
        zs = np.full(lines.size, h)
        with RPCTransformer(gdal_rpc, **GDAL_OPTS) as tr:
            # offset="ul" passes the pixel coordinates through unchanged, so they are in
            # GDAL's own convention (top-left corner of the first pixel at 0,0).
            glon, glat = (np.asarray(v) for v in tr.xy(lines, samples, zs=zs, offset="ul"))
        assert np.all(np.isfinite(glon)) and np.all(np.isfinite(glat))
        lon, lat = cam.localize(lines, samples, h)
        # Localisation: 1e-9 deg is 0.1 mm; the Pléiades pixel is 0.5 m.
        assert np.max(np.abs(lon - glon)) < 1e-9
        assert np.max(np.abs(lat - glat)) < 1e-9
        pl, ps = cam.project(glon, glat, h)
        assert np.max(np.hypot(pl - lines, ps - samples)) < 1e-3
        # Projection: GDAL's rowcol (no rounding) equals planetref's project.
        with RPCTransformer(gdal_rpc) as tr:
            grow, gcol = tr.rowcol(lon, lat, zs=zs, op=_identity)
        ml, ms = cam.project(lon, lat, h)
        assert np.max(np.abs(np.asarray(grow) - ml)) < 1e-6
        assert np.max(np.abs(np.asarray(gcol) - ms)) < 1e-6


@pytest.mark.shared
def test_gdal_half_pixel_and_rpc_height_conventions(shared: Path) -> None:
    path = _pleiades(shared, "img_01.tif")
    rpc = read_rpc(path)
    with rasterio.open(path) as src:
        gdal_rpc = src.rpcs
    lon, lat, h = rpc.long_off + 0.001, rpc.lat_off - 0.002, 300.0
    # Raw RPC coordinates (first pixel centre at 0) vs GDAL/planetref (centre at 0.5).
    rn, cn = rpc.evaluate_normalized(*rpc.normalize_ground(lon, lat, h))
    raw_line = rn * rpc.line_scale + rpc.line_off
    raw_sample = cn * rpc.samp_scale + rpc.samp_off
    with RPCTransformer(gdal_rpc) as tr:
        grow, gcol = tr.rowcol(lon, lat, zs=h, op=_identity)
    assert grow - raw_line == pytest.approx(0.5, abs=1e-6)
    assert gcol - raw_sample == pytest.approx(0.5, abs=1e-6)
    # RPC_HEIGHT is an offset added to the z passed in (z is "height above ground").
    with RPCTransformer(gdal_rpc, RPC_HEIGHT=h) as tr:
        grow0, gcol0 = tr.rowcol(lon, lat, zs=0.0, op=_identity)
    pl, ps = rpc.project(lon, lat, h)
    assert abs(grow0 - pl) < 1e-6 and abs(gcol0 - ps) < 1e-6


@pytest.mark.shared
def test_terrain_intersection_agrees_with_gdal_rpc_dem(
    shared: Path, tmp_path: Path, write_geotiff
) -> None:
    path = _pleiades(shared, "img_02.tif")
    cam = RpcCamera.from_file(path)
    with rasterio.open(path) as src:
        gdal_rpc = src.rpcs
    n_l, n_s = cam.image_size()
    lon_c, lat_c = (float(v) for v in cam.localize(n_l / 2, n_s / 2, 1000.0))
    # A tilted plane: GDAL's bilinear interpolation of a plane is exact, so both
    # implementations see the same surface.
    gx, gy = 8000.0, -5000.0  # metres per degree: slopes of ~7 % and ~4.5 %
    res, half = 0.0005, 0.02
    x0, y0 = lon_c - half, lat_c + half
    n = round(2 * half / res)
    cols = x0 + (np.arange(n) + 0.5) * res
    rows = y0 - (np.arange(n) + 0.5) * res
    dem = 1000.0 + gx * (cols[None, :] - lon_c) + gy * (rows[:, None] - lat_c)
    dem_path = tmp_path / "plane_dem.tif"
    write_geotiff(
        dem_path,
        dem,
        dtype="float64",
        crs="EPSG:4326",
        transform=Affine(res, 0.0, x0, 0.0, -res, y0),
    )

    class PlaneTerrain:
        ellipsoid = EARTH_WGS84
        min_height_m = float(dem.min())
        max_height_m = float(dem.max())
        sampling_m = 50.0

        def height(self, lon_deg: np.ndarray, lat_deg: np.ndarray) -> np.ndarray:
            # Terrain.height takes planetocentric latitude; the DEM is geodetic.
            xyz = lonlat_to_xyz(lon_deg, lat_deg, 0.0, EARTH_WGS84, "planetocentric")
            lon_g, lat_g, _ = xyz_to_lonlat(xyz, EARTH_WGS84, "planetographic")
            return 1000.0 + gx * (lon_g - lon_c) + gy * (lat_g - lat_c)

    lines, samples = np.meshgrid(np.linspace(0, n_l, 7), np.linspace(0, n_s, 7), indexing="ij")
    lines, samples = lines.ravel(), samples.ravel()
    with RPCTransformer(gdal_rpc, RPC_DEM=str(dem_path), **GDAL_OPTS) as tr:
        glon, glat = (
            np.asarray(v) for v in tr.xy(lines, samples, zs=np.zeros(lines.size), offset="ul")
        )
    xyz = cam.image_to_ground(lines, samples, PlaneTerrain())
    lon, lat, h = xyz_to_lonlat(xyz, EARTH_WGS84, "planetographic")
    assert np.max(np.abs(lon - glon)) < 1e-9
    assert np.max(np.abs(lat - glat)) < 1e-9
    expected_h = 1000.0 + gx * (lon - lon_c) + gy * (lat - lat_c)
    assert np.max(np.abs(h - expected_h)) < 1e-3


# ----------------------------------------------------------------- inversion


@pytest.mark.shared
@pytest.mark.parametrize("name", PLEIADES)
def test_localize_project_round_trip_over_the_whole_rpc_domain(shared: Path, name: str) -> None:
    rpc = read_rpc(_pleiades(shared, name))
    rng = np.random.default_rng(1)
    n = 5000
    lon = rpc.long_off + rpc.long_scale * rng.uniform(-1, 1, n)
    lat = rpc.lat_off + rpc.lat_scale * rng.uniform(-1, 1, n)
    h = rpc.height_off + rpc.height_scale * rng.uniform(-1, 1, n)
    line, sample = rpc.project(lon, lat, h)
    # The crops' RPCs cover the whole ~40000-line scene.
    assert np.ptp(line) > 30000
    lon2, lat2 = rpc.localize(line, sample, h)
    line2, sample2 = rpc.project(lon2, lat2, h)
    assert np.max(np.hypot(line2 - line, sample2 - sample)) < 1e-6
    assert np.max(np.abs(lon2 - lon)) < 1e-10
    assert np.max(np.abs(lat2 - lat)) < 1e-10


def test_camera_protocol_and_ground_round_trip() -> None:
    rpc = _synthetic_rpc()
    cam = RpcCamera(rpc, MARS_IAU2015_SPHERE, "planetocentric", (1060, 1031), name="syn")
    assert isinstance(cam, Camera)
    assert cam.ccd_names == ("syn",)
    rng = np.random.default_rng(3)
    lines = rng.uniform(0, 1060, 2000)
    samples = rng.uniform(0, 1031, 2000)
    xyz = cam.image_to_ground(lines, samples, -2000.0)
    assert xyz.shape == (2000, 3)
    _, _, h = xyz_to_lonlat(xyz, MARS_IAU2015_SPHERE)
    assert np.max(np.abs(h + 2000.0)) < 1e-6
    pts = cam.ground_to_image(xyz)
    assert pts.valid.all() and pts.in_image.all()
    assert np.max(np.hypot(pts.line - lines, pts.sample - samples)) < 1e-6
    # A ConstantHeight on the same body takes the same path as a float.
    same = cam.image_to_ground(
        lines[:10], samples[:10], ConstantHeight(MARS_IAU2015_SPHERE, -2000.0)
    )
    np.testing.assert_array_equal(same, xyz[:10])
    # A surface given on another ellipsoid (~2 km below the sphere here) is found too.
    oblate = cam.image_to_ground(
        lines[:50], samples[:50], ConstantHeight(MARS_IAU2015_ELLIPSOID, 100.0)
    )
    _, _, h_oblate = xyz_to_lonlat(oblate, MARS_IAU2015_ELLIPSOID)
    assert np.max(np.abs(h_oblate - 100.0)) < 1e-3
    assert np.max(np.abs(cam.ground_to_image(oblate).line - lines[:50])) < 1e-6
    with pytest.raises(InputError, match="unknown CCD"):
        cam.image_size("other")


def test_terrain_march_finds_first_crossing_and_reports_misses() -> None:
    rpc = _synthetic_rpc()
    cam = RpcCamera(rpc, MARS_IAU2015_SPHERE, "planetocentric", (1060, 1031))
    lon0, lat0 = rpc.long_off, rpc.lat_off

    class Ridge:
        ellipsoid = MARS_IAU2015_SPHERE
        min_height_m = -3000.0
        max_height_m = 500.0
        sampling_m = 20.0

        def height(self, lon_deg: np.ndarray, lat_deg: np.ndarray) -> np.ndarray:
            # A sinusoidal ridge (slopes up to 1.5), and a hole (NaN) east of lon0 + 0.01.
            h = -1500.0 + 600.0 * np.sin((np.asarray(lat_deg) - lat0) * 150.0)
            return np.where(np.asarray(lon_deg) > lon0 + 0.01, np.nan, h)

    lines = np.linspace(10, 1050, 40)
    samples = np.linspace(10, 300, 40)
    xyz = cam.image_to_ground(lines, samples, Ridge(), on_miss="nan")
    ok = np.all(np.isfinite(xyz), axis=1)
    assert ok.sum() > 20
    lon, lat, h = xyz_to_lonlat(xyz[ok], MARS_IAU2015_SPHERE)
    assert np.max(np.abs(h - Ridge().height(lon, lat))) < 1e-3
    pts = cam.ground_to_image(xyz[ok])
    assert np.max(np.hypot(pts.line - lines[ok], pts.sample - samples[ok])) < 1e-6
    # The first crossing from above: nothing on the line of sight above it is under
    # the surface.
    for j, i in enumerate(np.flatnonzero(ok)[:8]):
        hs = np.linspace(h[j] + 0.5, 600.0, 400)
        lo, la = cam.localize(np.full(hs.size, lines[i]), np.full(hs.size, samples[i]), hs)
        assert np.all(hs > Ridge().height(lo, la))
    # Points over the hole miss.
    hole_sample = 1000.0
    lon_h, _ = cam.localize(500.0, hole_sample, 0.0)
    assert lon_h > lon0 + 0.01
    with pytest.raises(GeometryError, match="1 of 1 image points"):
        cam.image_to_ground([500.0], [hole_sample], Ridge())
    assert np.isnan(cam.image_to_ground([500.0], [hole_sample], Ridge(), on_miss="nan")).all()


# ----------------------------------------------------------------- readers and writers


@pytest.mark.parametrize("writer", [write_rpc_rpb, write_rpc_txt], ids=["rpb", "txt"])
@pytest.mark.parametrize("body", [None, MARS_BODY])
def test_text_round_trip_is_exact(tmp_path: Path, writer: object, body: RpcBody | None) -> None:
    rpc = _synthetic_rpc()
    for x in (rpc, replace(rpc, err_bias=-1.0, err_rand=0.25)):
        out = writer(x, tmp_path / ("a.RPB" if writer is write_rpc_rpb else "a_RPC.TXT"), body=body)
        assert read_rpc(out) == x
        assert read_rpc_body(out) == body
        assert sorted(os.listdir(tmp_path)) == [out.name]  # no temporary files left


@pytest.mark.parametrize("fmt", ["rpb", "txt"])
def test_gdal_reads_the_sidecars_planetref_writes(tmp_path: Path, fmt: str, write_geotiff) -> None:
    rpc = replace(_synthetic_rpc(), err_bias=3.5, err_rand=0.125)
    image = _tiny_tif(write_geotiff, tmp_path / "scene.tif")
    sidecar = write_rpc(rpc, rpc_sidecar_path(image, fmt), body=MARS_BODY)
    assert sidecar.name == {"rpb": "scene.RPB", "txt": "scene_RPC.TXT"}[fmt]
    with rasterio.open(image) as src:
        assert sidecar.name in {Path(f).name for f in src.files}
        gdal_md = src.tags(ns="RPC")
        gdal_rpc = src.rpcs
    # GDAL keeps sidecar numbers as text: the values are exactly ours.
    assert Rpc.from_gdal(gdal_md) == rpc
    assert Rpc.from_rasterio(gdal_rpc) == rpc
    lon = rpc.long_off + rpc.long_scale * np.linspace(-0.9, 0.9, 7)
    lat = rpc.lat_off + rpc.lat_scale * np.linspace(0.8, -0.8, 7)
    with RPCTransformer(gdal_rpc) as tr:
        grow, gcol = tr.rowcol(lon, lat, zs=np.full(7, rpc.height_off), op=_identity)
    pl, ps = rpc.project(lon, lat, rpc.height_off)
    assert np.max(np.abs(grow - pl)) < 1e-6 and np.max(np.abs(gcol - ps)) < 1e-6
    # The image size comes from the raster next to the sidecar; the body from the file.
    cam = RpcCamera.from_file(sidecar)
    assert cam.image_size() == (6, 8)
    assert (cam.ellipsoid, cam.latitude_kind) == (MARS_IAU2015_SPHERE, "planetocentric")
    earth = RpcCamera.from_file(sidecar, body="earth")
    assert (earth.ellipsoid, earth.latitude_kind) == (EARTH_WGS84, "planetographic")


def test_geotiff_round_trip_exact_and_gdal_compatible(tmp_path: Path) -> None:
    rpc = _synthetic_rpc()
    path = write_rpc_geotiff(
        rpc, tmp_path / "img.tif", data=np.ones((6, 8), np.uint16), body=MARS_BODY
    )
    assert sorted(os.listdir(tmp_path)) == ["img.tif"]
    assert read_rpc(path) == rpc
    assert read_rpc_body(path) == MARS_BODY
    with rasterio.open(path) as src:
        assert src.count == 1 and src.read(1).sum() == 48
        gdal_rpc = Rpc.from_rasterio(src.rpcs)
    # GDAL reports the RPC tag with 15 significant digits.
    for name in ("line_off", "lat_off", "long_scale", "height_scale"):
        assert getattr(gdal_rpc, name) == pytest.approx(getattr(rpc, name), rel=1e-14)
    np.testing.assert_allclose(gdal_rpc.line_num_coeff, rpc.line_num_coeff, rtol=1e-14)
    # Updating the RPC of the existing file keeps its pixels.
    moved = replace(rpc, line_off=rpc.line_off + 100.25, err_bias=2.0)
    write_rpc(moved, path, body=EARTH_BODY)
    assert read_rpc(path) == moved
    assert read_rpc_body(path) == EARTH_BODY
    with rasterio.open(path) as src:
        assert src.read(1).sum() == 48
    # If other software rewrites the RPC tag, the stale exact copy is not used.
    other = replace(rpc, lat_off=rpc.lat_off + 0.5)
    with rasterio.open(path, "r+") as dst:
        dst.rpcs = other.to_rasterio()
    got = read_rpc(path)
    assert got.lat_off == pytest.approx(other.lat_off, rel=1e-14)
    assert got.line_off == pytest.approx(rpc.line_off, rel=1e-14)


@pytest.mark.shared
def test_pleiades_rpc_survives_all_three_formats(shared: Path, tmp_path: Path) -> None:
    path = _pleiades(shared, "img_01.tif")
    rpc = read_rpc(path)
    with rasterio.open(path) as src:
        assert rpc == Rpc.from_rasterio(src.rpcs)
    assert rpc.err_bias == -1.0 and read_rpc_body(path) is None
    for name in ("x.RPB", "x_RPC.TXT"):
        assert read_rpc(write_rpc(rpc, tmp_path / name)) == rpc
    tif = write_rpc_geotiff(rpc, tmp_path / "x.tif", data=np.zeros((4, 4), np.uint8))
    assert read_rpc(tif) == rpc


def test_failed_write_leaves_the_previous_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    rpc = _synthetic_rpc()
    target = write_rpc_rpb(rpc, tmp_path / "a.RPB")
    before = target.read_bytes()

    def broken_replace(src: object, dst: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(OSError, match="disk full"):
        write_rpc_rpb(replace(rpc, line_off=0.0), target)
    assert target.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["a.RPB"]


# ----------------------------------------------------------------- bad input


@pytest.fixture
def good_files(tmp_path: Path) -> tuple[Path, Path]:
    rpc = _synthetic_rpc()
    return write_rpc_rpb(rpc, tmp_path / "good.RPB"), write_rpc_txt(rpc, tmp_path / "good_RPC.TXT")


def _edit(src: Path, dst: Path, old: str, new: str, count: int = 1) -> Path:
    text = src.read_text()
    assert old in text
    dst.write_text(text.replace(old, new, count))
    return dst


@pytest.mark.parametrize(
    ("kind", "edit", "field", "message"),
    [
        ("rpb", "truncate", "sampNumCoef", "unterminated coefficient list"),
        ("rpb", ("lineOffset = ", "lineOffset = 12x"), "lineOffset", "expected a number"),
        (
            "rpb",
            ("latScale = ", "latScale = 0.0;\n\tjunk = "),
            "latScale",
            "scale must be non-zero",
        ),
        ("rpb", "drop_coeff", "lineDenCoef", "expected 20 coefficients, got 19"),
        ("rpb", "nan_coeff", "sampDenCoef[4]", "must be finite"),
        ("rpb", ("heightOffset", "heightOfset"), "heightOffset", "missing"),
        ("txt", "truncate", "SAMP_NUM_COEFF_8", "missing"),
        ("txt", ("LONG_SCALE: ", "LONG_SCALE: x"), "LONG_SCALE", "expected a number"),
        ("txt", ("HEIGHT_SCALE: ", "HEIGHT_SCALE: -0.0 #"), "HEIGHT_SCALE", "expected a number"),
        (
            "txt",
            ("LINE_DEN_COEFF_5: ", "LINE_DEN_COEFF_5: NaN\nCOMMENT: "),
            "LINE_DEN_COEFF_5",
            "must be finite",
        ),
        (
            "txt",
            ("LAT_SCALE: ", "LAT_SCALE: 0.0\nCOMMENT: "),
            "LAT_SCALE",
            "scale must be non-zero",
        ),
        ("txt", ("LINE_OFF: ", "garbage line\nLINE_OFF: "), None, "line 1: expected"),
    ],
)
def test_bad_files_give_one_line_errors_naming_file_and_field(
    good_files: tuple[Path, Path],
    tmp_path: Path,
    kind: str,
    edit: object,
    field: str | None,
    message: str,
) -> None:
    src = good_files[0] if kind == "rpb" else good_files[1]
    bad = tmp_path / ("bad.RPB" if kind == "rpb" else "bad_RPC.TXT")
    text = src.read_text()
    if edit == "truncate":
        cut = text.index("sampNumCoef" if kind == "rpb" else "SAMP_NUM_COEFF_8")
        bad.write_text(text[: cut + (60 if kind == "rpb" else 0)])
    elif edit == "drop_coeff":
        start = text.index("lineDenCoef")
        first = text.index("\n", text.index("(", start)) + 1
        second = text.index("\n", first) + 1
        bad.write_text(text[:first] + text[second:])
    elif edit == "nan_coeff":
        start = text.index("sampDenCoef")
        lines = text[start:].split("\n")
        lines[4] = "\t\t\tnan,"
        bad.write_text(text[:start] + "\n".join(lines))
    else:
        old, new = edit  # type: ignore[misc]
        _edit(src, bad, old, new)
    with pytest.raises(InputError) as info:
        read_rpc(bad)
    msg = str(info.value)
    assert "\n" not in msg
    assert msg.startswith(str(bad))
    assert message in msg
    if field is not None:
        assert f"field '{field}'" in msg
        assert info.value.field == field


def test_other_bad_inputs(tmp_path: Path, write_geotiff) -> None:
    with pytest.raises(MissingFileError, match="not found"):
        read_rpc(tmp_path / "nope.RPB")
    junk = tmp_path / "junk.bin"
    junk.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(UnsupportedFormatError, match="not an RPC file"):
        read_rpc(junk)
    text = tmp_path / "notes.txt"
    text.write_text("hello\n")
    with pytest.raises(UnsupportedFormatError, match="not an RPC file"):
        read_rpc(text)
    plain = _tiny_tif(write_geotiff, tmp_path / "plain.tif")
    with pytest.raises(InputError, match="field 'RPC': the raster has no RPC metadata"):
        read_rpc(plain)
    rpc = _synthetic_rpc()
    with pytest.raises(InputError, match="field 'line_num_coeff': expected 20 coefficients"):
        replace(rpc, line_num_coeff=rpc.line_num_coeff[:19])
    with pytest.raises(InputError, match="field 'samp_scale': scale must be non-zero"):
        replace(rpc, samp_scale=0.0)
    with pytest.raises(InputError, match="field 'lat_off': must be finite"):
        replace(rpc, lat_off=float("nan"))
    with pytest.raises(InputError, match="all denominator coefficients are zero"):
        replace(rpc, samp_den_coeff=(0.0,) * 20)
    with pytest.raises(InputError, match="field 'LINE_NUM_COEFF': expected 20"):
        Rpc.from_gdal({**rpc.to_gdal(), "LINE_NUM_COEFF": "1 2 3"}, path="meta")
    # Without a raster beside it, the image size comes from the RPC's domain.
    alone = RpcCamera.from_file(write_rpc_rpb(rpc, tmp_path / "alone.RPB"))
    assert alone.image_size() == (
        math.ceil(rpc.line_off + abs(rpc.line_scale) + 0.5),
        math.ceil(rpc.samp_off + abs(rpc.samp_scale) + 0.5),
    )
    with pytest.raises(InputError, match="unknown body"):
        RpcCamera.from_file(tmp_path / "alone.RPB", body="venus", image_size=(10, 10))
    with pytest.raises(UnsupportedFormatError, match="suffix"):
        write_rpc(rpc, tmp_path / "x.json")


# ----------------------------------------------------------------- fitting


class LinearPushbroom:
    """A pinhole line camera in straight, uniform motion 300 km above spherical Mars.

    The detector line is offset along track from the principal point, the lens has
    cubic radial distortion across track and the camera rolls slowly, so the geometry
    is not itself a rational polynomial. Only what ``fit_rpc`` uses is implemented.
    """

    ellipsoid = MARS_IAU2015_SPHERE
    latitude_kind = "planetocentric"

    def __init__(self, n_lines: int = 3000, n_samples: int = 2500) -> None:
        self._size = (n_lines, n_samples)
        lon0, lat0 = np.radians(74.0), np.radians(20.0)
        up = np.array([np.cos(lat0) * np.cos(lon0), np.cos(lat0) * np.sin(lon0), np.sin(lat0)])
        east = np.array([-np.sin(lon0), np.cos(lon0), 0.0])
        north = np.cross(up, east)
        self.c0 = (MARS_IAU2015_SPHERE.semi_major_m + 300e3) * up
        self.velocity = 3400.0 * north  # m/s
        self.line_time = 1.8e-3  # s; ~6 m along track per line
        self.focal_px = 50_000.0  # 20 microradian pixels, ~6 m across track
        self.k1 = 2.0  # cubic distortion: ~1.3 px at the swath edges
        self.axes = (east, north, -up)
        self.roll0, self.roll_rate = np.radians(8.0), np.radians(0.05)  # rad, rad/s

    @property
    def ccd_names(self) -> tuple[str, ...]:
        return ("ccd",)

    def image_size(self, ccd: str | None = None) -> tuple[int, int]:
        return self._size

    def image_to_ground(
        self,
        line: np.ndarray,
        sample: np.ndarray,
        terrain: float = 0.0,
        *,
        ccd: str | None = None,
        on_miss: str = "raise",
    ) -> np.ndarray:
        t = np.asarray(line, float) * self.line_time
        x = (np.asarray(sample, float) - self._size[1] / 2) / self.focal_px
        x = x * (1 + self.k1 * x * x)
        y = np.full_like(x, 0.002)  # detector 100 px ahead of the principal point
        roll = self.roll0 + self.roll_rate * t
        # Roll about the flight direction (north).
        xc = np.cos(roll) * x + np.sin(roll)
        zc = -np.sin(roll) * x + np.cos(roll)
        east, north, down = self.axes
        d = xc[:, None] * east + y[:, None] * north + zc[:, None] * down
        c = self.c0 + t[:, None] * self.velocity
        s = ray_ellipsoid_intersection(c, d, self.ellipsoid, float(terrain))
        return c + s[:, None] * d

    def ground_to_image(self, xyz: np.ndarray, *, ccd: str | None = None) -> object:
        raise NotImplementedError("fit_rpc needs only image_to_ground")


def test_fit_rpc_to_an_analytic_pushbroom_camera(tmp_path: Path) -> None:
    cam = LinearPushbroom()
    rpc, report = fit_rpc(cam, height_range_m=(-4000.0, 2000.0), grid=(15, 15, 5))
    print(report.summary())
    assert report.n_dropped == 0 and report.n_fit == 15 * 15 * 5
    assert report.n_check == 14 * 14 * 11
    assert report.check_max_px < 0.05
    assert report.check_rms_px < 0.01
    assert report.fit_rms_px <= report.check_max_px
    assert report.check_max_ground_m < 0.3  # 0.05 px of ~6 m
    assert report.min_abs_denominator > 0.5
    # The fitted RPC written as a Mars .RPB reads back as a Mars camera that localises
    # like the analytic one.
    out = write_rpc(rpc, tmp_path / "ctx_like.RPB", body=MARS_BODY)
    rcam = RpcCamera.from_file(out, image_size=cam.image_size())
    assert rcam.ellipsoid == MARS_IAU2015_SPHERE and rcam.latitude_kind == "planetocentric"
    rng = np.random.default_rng(5)
    lines, samples = rng.uniform(0, 3000, 500), rng.uniform(0, 2500, 500)
    for h in (-3500.0, 1500.0):
        d = np.linalg.norm(
            rcam.image_to_ground(lines, samples, h) - cam.image_to_ground(lines, samples, h), axis=1
        )
        assert np.max(d) < 0.3


@pytest.mark.shared
@pytest.mark.parametrize("name", PLEIADES)
def test_fit_rpc_recovers_a_pleiades_rpc(shared: Path, name: str) -> None:
    cam = RpcCamera.from_file(_pleiades(shared, name))
    r = cam.rpc
    fitted, report = fit_rpc(
        cam,
        height_range_m=(r.height_off - r.height_scale, r.height_off + r.height_scale),
        grid=(15, 15, 5),
    )
    print(report.summary())
    assert report.check_max_px < 1e-3
    assert report.check_max_ground_m < 1e-3
    # Independently of the report: compare the two RPCs on random ground points.
    rng = np.random.default_rng(7)
    lines = rng.uniform(0, cam.image_size()[0], 1000)
    samples = rng.uniform(0, cam.image_size()[1], 1000)
    h = rng.uniform(r.height_off - r.height_scale, r.height_off + r.height_scale, 1000)
    lon, lat = cam.localize(lines, samples, h)
    fl, fs = fitted.project(lon, lat, h)
    assert np.max(np.hypot(fl - lines, fs - samples)) < 1e-3


def test_fit_rpc_rejects_bad_arguments() -> None:
    cam = LinearPushbroom()
    with pytest.raises(InputError, match="height_range_m"):
        fit_rpc(cam, height_range_m=(100.0, 100.0))
    with pytest.raises(InputError, match="grid"):
        fit_rpc(cam, height_range_m=(0.0, 1.0), grid=(3, 10, 5))
    with pytest.raises(InputError, match="regularization"):
        fit_rpc(cam, height_range_m=(0.0, 1.0), regularization=-1.0)
