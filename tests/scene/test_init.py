"""``planetref scene init``: a checked scene.toml from images, cameras and a reference."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import rasterio
from click.testing import CliRunner
from rasterio.transform import from_origin

from planetref.camera.io import load_camera
from planetref.cli import main
from planetref.errors import CrsError, InputError
from planetref.geometry.geodesy import xyz_to_lonlat
from planetref.scene.init import CcdInput, init_scene, resolve_dem_datum
from planetref.scene.manifest import load_manifest

SHARED = Path(__file__).resolve().parents[3] / "shared"
CTX_ISD = SHARED / "data" / "ale" / "ctx_isd.json"
R = 3396190.0  # the IAU 2015 Mars sphere of IAU_2015:49910 (equirectangular, metres)


def _raster(
    write_geotiff, path: Path, data: np.ndarray, lon0: float, lat1: float, res_m: float, crs: str
):
    """A one-band GeoTIFF whose top-left corner is at (lon0, lat1) degrees."""
    if crs == "EPSG:4326":  # an Earth CRS in degrees
        x0, y0, res = lon0, lat1, res_m / 111_000.0
    else:
        x0, y0, res = math.radians(lon0) * R, math.radians(lat1) * R, res_m
    return write_geotiff(path, data, crs=crs, transform=from_origin(x0, y0, res, res))


def _ctx_inputs(write_geotiff, tmp_path: Path, *, lon0=-174.0, crs="IAU_2015:49912", dem_m=0.0):
    """The real CTX ISD with a blank image of its size, and a reference around 80 S."""
    image = np.zeros((400, 5056), np.uint8)  # the ISD's image_lines x image_samples
    write_geotiff(tmp_path / "ctx.tif", image)
    span_lon, span_lat = 6.0, 3.0
    res_o, res_d = 500.0, 2000.0
    h = int(math.radians(span_lat) * R / res_o)
    w = int(math.radians(span_lon) * R / res_o)
    ortho = _raster(
        write_geotiff,
        tmp_path / "ortho.tif",
        np.full((h, w), 100, np.uint8),
        lon0,
        -78.5,
        res_o,
        crs,
    )
    hd, wd = int(h * res_o / res_d), int(w * res_o / res_d)
    dem = _raster(
        write_geotiff,
        tmp_path / "dem.tif",
        np.full((hd, wd), dem_m, np.float32),
        lon0,
        -78.5,
        res_d,
        crs,
    )
    return tmp_path / "ctx.tif", ortho, dem


@pytest.mark.shared
@pytest.mark.skipif(not CTX_ISD.exists(), reason="../shared/data/ale/ctx_isd.json not found")
def test_a_real_csm_isd_gets_its_footprint_and_its_datum_refused(tmp_path, write_geotiff):
    image, ortho, dem = _ctx_inputs(write_geotiff, tmp_path)
    ccd = [CcdInput(image, CTX_ISD)]
    # The ISD's body is the MOLA-shaped ellipsoid (3396.19 / 3376.2 km), nearly the areoid:
    # flat heights fit both datums, so the datum is not guessed.
    with pytest.raises(InputError, match=r"cannot tell the DEM's datum.*--dem-datum body"):
        init_scene(tmp_path / "scene", ccd, ortho, dem)
    assert not (tmp_path / "scene" / "scene.toml").exists()
    result = init_scene(tmp_path / "scene", ccd, ortho, dem, dem_datum="body", crop=True)
    # The footprint on the flat DEM against the camera's own corners at height 0 (the
    # camera API, not the DEM intersection init uses): -172.18 to -169.73 E near 80 S.
    camera = load_camera(CTX_ISD)
    corners = camera.image_to_ground([0.5, 0.5, 399.5, 399.5], [0.5, 5055.5, 0.5, 5055.5], 0.0)
    lon, lat, _ = xyz_to_lonlat(corners, camera.ellipsoid)
    expected = [lon.min(), lat.min(), lon.max(), lat.max()]
    assert result.footprints["ctx"] == pytest.approx(expected, abs=1e-4)
    assert expected[0] == pytest.approx(-172.18, abs=0.01)
    assert expected[2] == pytest.approx(-169.73, abs=0.01)
    assert result.outside_share == {"ctx": 0.0}
    assert result.warnings == []  # the reference is on the ISD's ellipsoid
    assert result.body == (3396190.0, 3376200.0)
    manifest, root = load_manifest(result.path)
    assert manifest.body.semi_minor_m == 3376200.0
    assert manifest.reference.dem_datum == "body"
    assert manifest.reference.ortho == "reference/ortho.tif"
    with rasterio.open(root / "reference" / "ortho.tif") as cut, rasterio.open(ortho) as full:
        assert cut.width < full.width / 2 and cut.height < full.height / 2
        # The crop holds the footprint plus the margin: 2.4 deg of longitude at 80 S.
        assert cut.width * 500.0 > math.radians(2.39) * R


@pytest.mark.shared
@pytest.mark.skipif(not CTX_ISD.exists(), reason="../shared/data/ale/ctx_isd.json not found")
def test_one_line_errors_for_no_overlap_wrong_body_and_existing_scene(tmp_path, write_geotiff):
    image, ortho, dem = (
        _ctx_inputs(write_geotiff, tmp_path / "far", lon0=10.0)
        if (tmp_path / "far").mkdir() is None
        else None
    )
    with pytest.raises(InputError, match="no image point of its CCDs falls on the reference") as e:
        init_scene(tmp_path / "s1", [CcdInput(image, CTX_ISD)], ortho, dem, dem_datum="body")
    assert str(ortho) in str(e.value) and "\n" not in str(e.value)
    (tmp_path / "earth").mkdir()
    image, ortho, dem = _ctx_inputs(write_geotiff, tmp_path / "earth", crs="EPSG:4326")
    with pytest.raises(CrsError, match="not a Mars CRS") as e:
        init_scene(tmp_path / "s2", [CcdInput(image, CTX_ISD)], ortho, dem, dem_datum="body")
    assert str(ortho) in str(e.value)
    (tmp_path / "ok").mkdir()
    image, ortho, dem = _ctx_inputs(write_geotiff, tmp_path / "ok")
    init_scene(tmp_path / "s3", [CcdInput(image, CTX_ISD)], ortho, dem, dem_datum="body")
    with pytest.raises(InputError, match="--overwrite"):
        init_scene(tmp_path / "s3", [CcdInput(image, CTX_ISD)], ortho, dem, dem_datum="body")


def test_the_demo_scene_is_rebuilt_from_its_files(tiny_scene, tmp_path):
    """Without its scene.toml, the simulated scene's files give the same inputs back."""
    scene = tmp_path / "tiny"
    shutil.copytree(tiny_scene / "reference", scene / "reference")
    shutil.copytree(tiny_scene / "strips", scene / "strips")
    original, _ = load_manifest(tiny_scene)
    strip = scene / "strips" / "strip1"
    args = ["scene", "init", str(scene), "--ortho", str(scene / "reference" / "ortho.tif")]
    args += ["--dem", str(scene / "reference" / "dem.tif")]
    for c in ("ccd1", "ccd2", "ccd3"):
        args += ["--ccd", str(strip / f"{c}.tif"), str(strip / "camera.json")]
    # Near 25 N flat-ish simulated heights fit both datums: refused, and told what to declare.
    refused = CliRunner().invoke(main, args)
    assert refused.exit_code == 1
    assert "--dem-datum body" in refused.output and "dem.tif" in refused.output
    assert len(refused.output.strip().splitlines()) == 1
    done = CliRunner().invoke(main, [*args, "--dem-datum", "body"])
    assert done.exit_code == 0, done.output
    made, _ = load_manifest(scene)
    # The same reference, except the declared accuracies: the simulator writes the
    # spread its errors were drawn from, scene init never invents one (a user declares it).
    declared = {"accuracy_m": None, "accuracy_length_m": None}
    assert made.reference == original.reference.model_copy(update=declared)
    assert made.body.semi_major_m == original.body.semi_major_m
    assert made.body.semi_minor_m == original.body.semi_minor_m
    # The same CCDs, images and cameras (the original also names the fitted RPCs, which a
    # georef run does not read).
    assert made.strips[0].ccds == tuple(
        c.model_copy(update={"rpc": None}) for c in original.strips[0].ccds
    )
    assert made.truth is None


def test_heights_that_fit_one_datum_only_tell_it(tmp_path):
    """A sphere-relative DEM at 80 S lies ~19 km below the areoid: that can only be 'body'."""
    from planetref.geometry.geodesy import MARS_IAU2015_SPHERE
    from planetref.raster.datum import areoid_above_body_estimate_m
    from planetref.raster.dem import GridTerrain

    offset = float(areoid_above_body_estimate_m(np.array([-80.0]), MARS_IAU2015_SPHERE)[0])
    assert offset < -15_000.0  # the areoid is far below the sphere there
    h = np.full((20, 20), offset + 2000.0, np.float32)  # 2 km above the areoid, in body heights
    y0 = math.radians(-79.0) * R
    dem = GridTerrain(h, (0.0, 2000.0, 0, y0, 0, -2000.0), "IAU_2015:49910")
    datum, why = resolve_dem_datum(dem, Path("dem.tif"), None, None)
    assert datum == "body" and "body only" in why
    # 10 km above the areoid (a volcano's flank) read as body heights would be 29 km above
    # the areoid there, beyond Mars' relief: only 'areoid' fits, which needs the areoid.
    high = np.full((20, 20), 10_000.0, np.float32)
    areoid_heights = GridTerrain(high, (0.0, 2000.0, 0, y0, 0, -2000.0), "IAU_2015:49910")
    with pytest.raises(InputError, match=r"above the areoid only.*--dem-datum areoid --areoid"):
        resolve_dem_datum(areoid_heights, Path("dem.tif"), None, None)


@pytest.mark.shared
@pytest.mark.skipif(not CTX_ISD.exists(), reason="../shared/data/ale/ctx_isd.json not found")
def test_a_dem_on_the_sphere_under_an_ellipsoid_camera_is_reported(tmp_path, write_geotiff):
    image, ortho, dem = _ctx_inputs(write_geotiff, tmp_path, crs="IAU_2015:49910")
    result = init_scene(tmp_path / "s", [CcdInput(image, CTX_ISD)], ortho, dem, dem_datum="body")
    assert len(result.warnings) == 1
    assert "polar radius 3396190 m" in result.warnings[0] and "19990 m" in result.warnings[0]


def test_append_adds_a_strip_on_the_scenes_reference(tiny_scene, tmp_path):
    scene = tmp_path / "campaign"
    shutil.copytree(tiny_scene / "reference", scene / "reference")
    shutil.copytree(tiny_scene / "strips", scene / "strips")
    strip = scene / "strips" / "strip1"
    ccds = [CcdInput(strip / f"{c}.tif", strip / "camera.json") for c in ("ccd1", "ccd2")]
    with pytest.raises(InputError, match="no scene manifest to add the strip to"):
        init_scene(scene, ccds, None, None, strip_id="b", append=True)
    ortho, dem = scene / "reference" / "ortho.tif", scene / "reference" / "dem.tif"
    init_scene(scene, ccds, ortho, dem, strip_id="a", dem_datum="body")
    with pytest.raises(InputError, match="--append to add a strip"):
        init_scene(scene, ccds, ortho, dem, strip_id="b", dem_datum="body")
    # The same CCDs again as a second strip: on the scene's reference, datum and body.
    added = init_scene(scene, ccds[:1], None, None, strip_id="b", append=True)
    assert added.dem_datum == "body" and added.outside_share == {"ccd1": 0.0}
    manifest, _ = load_manifest(scene)
    assert [s.id for s in manifest.strips] == ["a", "b"]
    assert [c.name for c in manifest.strips[1].ccds] == ["ccd1"]
    assert manifest.reference.ortho == "reference/ortho.tif"
    with pytest.raises(InputError, match="already has a strip 'b'"):
        init_scene(scene, ccds, None, None, strip_id="b", append=True)
    with pytest.raises(InputError, match="a scene has one reference"):
        init_scene(
            scene, ccds, tiny_scene / "reference" / "ortho.tif", None, strip_id="c", append=True
        )
    with pytest.raises(InputError, match="declares dem_datum = 'body'"):
        init_scene(scene, ccds, None, None, strip_id="c", dem_datum="areoid", append=True)


PLEIADES = SHARED / "data" / "pleiades_rpc" / "img_01.tif"


@pytest.mark.shared
@pytest.mark.skipif(not PLEIADES.exists(), reason="../shared/data/pleiades_rpc not found")
def test_a_real_rpc_product_on_an_earth_reference(tmp_path, write_geotiff):
    """A Pléiades crop whose RPC is in its own tags: the body is the Earth's, as is the CRS."""
    with rasterio.open(PLEIADES) as ds:
        n_lines, n_samples = ds.height, ds.width
    camera = load_camera(PLEIADES)
    corners = camera.image_to_ground(
        [0.5, 0.5, n_lines - 0.5, n_lines - 0.5],
        [0.5, n_samples - 0.5, 0.5, n_samples - 0.5],
        100.0,
    )
    lon, lat, _ = xyz_to_lonlat(corners, camera.ellipsoid, "planetographic")
    # A geographic WGS 84 reference (geodetic latitudes) around the crop, and a flat DEM
    # 100 m above the ellipsoid.
    res = 1e-4  # degrees (~11 m)
    west, north = float(lon.min()) - 0.01, float(lat.max()) + 0.01
    w = int((lon.max() - lon.min() + 0.02) / res)
    h = int((lat.max() - lat.min() + 0.02) / res)
    for name, value, dtype in (("ortho", 100, np.uint8), ("dem", 100.0, np.float32)):
        write_geotiff(
            tmp_path / f"{name}.tif",
            np.full((h, w), value, dtype),
            crs="EPSG:4326",
            transform=from_origin(west, north, res, res),
        )
    ccd = [CcdInput(PLEIADES, PLEIADES, name="img_01")]
    with pytest.raises(InputError, match="cannot tell the DEM's datum"):
        init_scene(tmp_path / "s", ccd, tmp_path / "ortho.tif", tmp_path / "dem.tif")
    result = init_scene(
        tmp_path / "s", ccd, tmp_path / "ortho.tif", tmp_path / "dem.tif", dem_datum="body"
    )
    assert result.body[0] == pytest.approx(6378137.0)
    assert result.outside_share == {"img_01": 0.0}
    # The footprint is reported in planetocentric (geocentric) latitudes.
    lon, lat, _ = xyz_to_lonlat(corners, camera.ellipsoid)
    expected = [lon.min(), lat.min(), lon.max(), lat.max()]
    assert result.footprints["img_01"] == pytest.approx(expected, abs=1e-5)
    manifest, _ = load_manifest(result.path)
    assert Path(manifest.strips[0].ccds[0].camera).resolve() == PLEIADES.resolve()
