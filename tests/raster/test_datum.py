"""DEM datums: areoid heights converted to body heights, plausibility warnings, bad files."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from rasterio.transform import from_origin

from planetref.errors import InputError, MissingFileError, UnsupportedFormatError
from planetref.raster.datum import (
    apply_areoid,
    areoid_above_body_estimate_m,
    datum_warning,
    open_reference_dem,
)
from planetref.raster.dem import GridTerrain

EQC = "IAU_2015:49910"  # Mars sphere, equirectangular (m)
GEO = "IAU_2015:49900"  # Mars sphere, lon/lat (degrees)
R = 3396190.0
M_PER_DEG = R * np.pi / 180.0


def _write(write_geotiff, path: Path, data: np.ndarray, transform, crs: str, nodata=None) -> Path:
    return write_geotiff(path, data, transform=transform, crs=crs, nodata=nodata)


def _dem(
    write_geotiff, tmp_path: Path, lat0: float = 20.0, heights=None
) -> tuple[Path, GridTerrain]:
    """A 40 x 50 DEM of 463 m pixels near (lon 70, lat ``lat0``) on the Mars sphere."""
    rng = np.random.default_rng(0)
    h = rng.normal(-1500.0, 400.0, (40, 50)) if heights is None else heights
    t = from_origin(70.0 * M_PER_DEG, (lat0 + 0.2) * M_PER_DEG, 463.0, 463.0)
    p = _write(write_geotiff, tmp_path / "dem.tif", h.astype(np.float32), t, EQC, nodata=np.nan)
    return p, GridTerrain.from_geotiff(p)


def _linear_areoid(write_geotiff, tmp_path: Path, a: float, b: float, c: float) -> Path:
    """Areoid raster in lon/lat degrees (another CRS and grid than the DEM's):
    ``N = a + b (lon - 70) + c (lat - 20)`` metres, sampled at its pixel centres."""
    res = 0.05
    lon = 69.5 + res * (np.arange(40) + 0.5)
    lat = 21.0 - res * (np.arange(40) + 0.5)
    n = a + b * (lon[None, :] - 70.0) + c * (lat[:, None] - 20.0)
    return _write(write_geotiff, tmp_path / "areoid.tif", n, from_origin(69.5, 21.0, res, res), GEO)


@pytest.mark.parametrize("abc", [(-1234.5, 0.0, 0.0), (250.0, 180.0, -95.0)])
def test_constant_and_linear_areoid_recovered_exactly(tmp_path, abc, write_geotiff):
    dem_path, dem = _dem(write_geotiff, tmp_path)
    areoid = _linear_areoid(write_geotiff, tmp_path, *abc)
    body = apply_areoid(dem, areoid)
    rows, cols = np.indices(dem.shape)
    x, y = dem.transform @ (cols + 0.5, rows + 0.5)
    lon, lat = dem.map_to_lonlat(x, y)
    expected = (
        dem.heights.astype(np.float64) + abc[0] + abc[1] * (lon - 70.0) + abc[2] * (lat - 20.0)
    )
    # Bilinear interpolation reproduces a linear function: exact up to rounding.
    assert np.max(np.abs(body.heights - expected)) < 1e-6
    assert body.transform == dem.transform and body.crs == dem.crs
    via = open_reference_dem(dem_path, datum="areoid", areoid=areoid)
    assert np.array_equal(via.heights, body.heights)
    assert np.array_equal(open_reference_dem(dem_path).heights, dem.heights)  # "body"


def test_bad_areoid_files_are_one_line_errors_naming_the_file(tmp_path, write_geotiff):
    dem_path, dem = _dem(write_geotiff, tmp_path)
    with pytest.raises(MissingFileError, match=r"nope\.tif"):
        apply_areoid(dem, tmp_path / "nope.tif")
    junk = tmp_path / "junk.tif"
    junk.write_bytes(b"not a raster at all")
    with pytest.raises(UnsupportedFormatError, match=r"junk\.tif") as err:
        apply_areoid(dem, junk)
    assert "\n" not in str(err.value)
    # An areoid raster that does not cover the DEM.
    small = _write(
        write_geotiff,
        tmp_path / "small.tif",
        np.zeros((4, 4)),
        from_origin(69.5, 21.0, 0.01, 0.01),
        GEO,
    )
    with pytest.raises(InputError, match=r"small.tif.*does not cover the DEM"):
        apply_areoid(dem, small)
    # Another body (an Earth CRS).
    earth = _write(
        write_geotiff,
        tmp_path / "earth.tif",
        np.zeros((40, 40)),
        from_origin(69.5, 21.0, 0.05, 0.05),
        "EPSG:4326",
    )
    with pytest.raises(InputError, match=r"earth.tif.*another body"):
        apply_areoid(dem, earth)
    with pytest.raises(InputError, match="needs an areoid"):
        open_reference_dem(dem_path, datum="areoid")


def test_implausible_heights_for_the_declared_datum_warn(tmp_path, caplog, write_geotiff):
    # Plausible: no warning either way near the equator.
    _, dem = _dem(write_geotiff, tmp_path)
    assert datum_warning(dem, "body", "dem.tif") is None
    assert datum_warning(dem, "areoid", "dem.tif") is None
    # Radii given instead of heights.
    radii = GridTerrain(dem.heights + R, dem.transform, dem.crs)
    msg = datum_warning(radii, "body", "dem.tif")
    assert msg and "dem.tif" in msg and "radii" in msg and "\n" not in msg
    # Heights above the sphere at 75 N (about -18 km there) declared as above the areoid.
    est = float(areoid_above_body_estimate_m(np.array([75.0]), dem.ellipsoid)[0])
    assert -20000.0 < est < -17000.0  # the areoid's flattening on the IAU sphere
    sub = tmp_path / "north"
    sub.mkdir()
    _, north = _dem(write_geotiff, sub, lat0=75.0, heights=np.full((40, 50), est - 1500.0))
    assert datum_warning(north, "body", "n.tif") is None
    warn = datum_warning(north, "areoid", "n.tif")
    assert warn and "dem_datum = 'areoid'" in warn
    with caplog.at_level(logging.WARNING, logger="planetref.raster.datum"):
        open_reference_dem(sub / "dem.tif", datum="body")
        assert not caplog.records
        areoid = _linear_areoid(write_geotiff, tmp_path, 0.0, 0.0, 0.0)
        with pytest.raises(InputError):  # the areoid raster is near 20 N, not 75 N
            open_reference_dem(sub / "dem.tif", datum="areoid", areoid=areoid, implausible="warn")
        with pytest.raises(InputError, match="implausible"):  # an error unless accepted
            open_reference_dem(sub / "dem.tif", datum="areoid", areoid=areoid)
    assert len(caplog.records) == 1 and "implausible" in caplog.records[0].getMessage()


def test_parallel_workers_read_the_converted_dem(tmp_path, write_geotiff):
    """A DEM above the areoid reaches tile workers as one body-height file in the run folder."""
    from types import SimpleNamespace

    from planetref.pipeline.rundir import RunDir
    from planetref.scene.inputs import worker_dem

    dem_path, _ = _dem(write_geotiff, tmp_path)
    areoid = _linear_areoid(write_geotiff, tmp_path, 321.0, 10.0, -5.0)
    body = open_reference_dem(dem_path, datum="areoid", areoid=areoid)
    ref = SimpleNamespace(dem=dem_path.name, dem_datum="areoid")
    man = SimpleNamespace(reference=ref, resolve=lambda root, rel: Path(root) / rel)
    run = RunDir(tmp_path / "run", "georef", {"test": 1})
    try:
        target = run.file("reference", "dem_body.tif")
        path = worker_dem(man, tmp_path, body, target)
        assert path.parent.parent == run.path and path.is_file()
        back = GridTerrain.from_geotiff(path)
        assert np.array_equal(back.heights, body.heights) and back.transform == body.transform
        assert worker_dem(man, tmp_path, body, target) == path  # written once
        ref.dem_datum = "body"
        assert worker_dem(man, tmp_path, body, target) == dem_path  # the scene's own file
    finally:
        run.close()
