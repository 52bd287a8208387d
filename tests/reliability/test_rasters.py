"""Poisoned rasters: every input raster is checked where it enters (issue 35, group 2).

An areoid raster with +-1e30 cells was added unchecked (rc 0, 1,600 of 1,602 tiles
failed, 209.7 m true error against 1.80 m); an areoid tilting +-20 km was accepted; a
DEM with a 1e30 spike degraded the run silently (its warning was logged before the
run's log opened). Values beyond +-1 % of the body's radius are always an error;
implausible ones are an error unless the scene says ``implausible_heights = "warn"``,
and then the warning reaches stderr and the run's log.
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin
from reliability_helpers import one_line_error, run_cli

from planetref.errors import InputError
from planetref.raster.datum import open_reference_dem
from planetref.raster.dem import GridTerrain

EQC = "IAU_2015:49910"  # Mars sphere, equirectangular (m)
GEO = "IAU_2015:49900"  # Mars sphere, lon/lat (degrees)
R = 3396190.0
M_PER_DEG = R * np.pi / 180.0


def _write(write_geotiff, path: Path, data: np.ndarray, transform, crs: str) -> Path:
    return write_geotiff(path, data, transform=transform, crs=crs)


def _dem(write_geotiff, folder: Path, heights: np.ndarray | None = None) -> Path:
    """A 40 x 50 DEM of 463 m pixels near (lon 70, lat 0) on the Mars sphere."""
    h = np.random.default_rng(0).normal(-1500.0, 400.0, (40, 50)) if heights is None else heights
    t = from_origin(70.0 * M_PER_DEG, 0.2 * M_PER_DEG, 463.0, 463.0)
    return _write(write_geotiff, folder / "dem.tif", h.astype(np.float32), t, EQC)


def _areoid(write_geotiff, folder: Path, n: np.ndarray) -> Path:
    """An areoid raster in lon/lat degrees around the DEM (40 x 40 cells of 0.05 deg)."""
    return _write(write_geotiff, folder / "areoid.tif", n, from_origin(69.5, 1.0, 0.05, 0.05), GEO)


def _areoid_plane(tilt_m: float) -> np.ndarray:
    """An areoid near the equator (a few metres above the sphere) tilted +-``tilt_m``."""
    return np.full((40, 40), 10.0) + np.linspace(-tilt_m, tilt_m, 40)[None, :]


def test_an_areoid_with_fill_values_is_refused(tmp_path: Path, write_geotiff) -> None:
    # scene.toml: dem_datum = "areoid", areoid = "areoid.tif" holding +-1e30 cells
    dem = _dem(write_geotiff, tmp_path)
    n = _areoid_plane(0.0)
    n[5, 7], n[30, 20] = 1e30, -1e30
    areoid = _areoid(write_geotiff, tmp_path, n)
    with pytest.raises(InputError, match="physically meaningful range") as err:
        open_reference_dem(dem, datum="areoid", areoid=areoid, implausible="warn")
    msg = str(err.value)
    assert str(areoid) in msg and "2 value(s)" in msg and "[-33962, 33962] m" in msg
    assert "\n" not in msg
    # The same areoid without the fill values is accepted and added.
    good = _areoid(write_geotiff, tmp_path, _areoid_plane(0.0))
    out = open_reference_dem(dem, datum="areoid", areoid=good)
    assert np.allclose(out.heights, GridTerrain.from_geotiff(dem).heights + 10.0, atol=1e-3)


def test_a_tilted_areoid_is_implausible(tmp_path: Path, write_geotiff) -> None:
    # an areoid raster tilting +-20 km across the DEM (within +-1 % of the radius)
    dem = _dem(write_geotiff, tmp_path)
    areoid = _areoid(write_geotiff, tmp_path, _areoid_plane(20000.0))
    with pytest.raises(InputError, match="areoid raster is implausible") as err:
        open_reference_dem(dem, datum="areoid", areoid=areoid)
    assert str(areoid) in str(err.value) and 'implausible_heights = "warn"' in str(err.value)
    warnings: list[str] = []
    open_reference_dem(dem, datum="areoid", areoid=areoid, implausible="warn", warnings=warnings)
    assert len(warnings) == 1 and "areoid raster is implausible" in warnings[0]
    # +-2 km (the areoid's undulations) is plausible.
    ok = _areoid(write_geotiff, tmp_path, _areoid_plane(2000.0))
    warnings.clear()
    open_reference_dem(dem, datum="areoid", areoid=ok, warnings=warnings)
    assert warnings == []


def test_a_dem_with_a_spike_is_refused(tmp_path: Path, write_geotiff) -> None:
    # the reference DEM holds one 1e30 cell (a fill value without nodata)
    h = np.random.default_rng(1).normal(-1500.0, 400.0, (40, 50))
    h[12, 34] = 1e30
    dem = _dem(write_geotiff, tmp_path, h)
    with pytest.raises(InputError, match=r"1e\+30 at row 12, column 34") as err:
        open_reference_dem(dem, implausible="warn")
    assert str(dem) in str(err.value) and "reference DEM" in str(err.value)


def test_the_dem_is_checked_after_the_areoid_is_added(tmp_path: Path, write_geotiff) -> None:
    # heights of 30 km above an areoid 10 km above the body: 40 km, beyond 1 % of R
    dem = _dem(write_geotiff, tmp_path, np.full((40, 50), 30000.0))
    areoid = _areoid(write_geotiff, tmp_path, np.full((40, 40), 10000.0))
    with pytest.raises(InputError, match="after the areoid was added"):
        open_reference_dem(dem, datum="areoid", areoid=areoid, implausible="warn")


def _poisoned_scene(mini_scene: Path, tmp_path: Path, *, warn: bool) -> Path:
    """The mini scene with its DEM raised by 26 km: implausible, not beyond 1 % of R."""
    scene = tmp_path / "scene"
    shutil.copytree(mini_scene, scene, ignore=shutil.ignore_patterns("run.json", ".planetref*"))
    text = (scene / "scene.toml").read_text()
    dem_rel = re.search(r'^dem = "([^"]+)"', text, re.M)
    assert dem_rel is not None
    with rasterio.open(scene / dem_rel.group(1), "r+") as ds:
        ds.write(ds.read(1) + np.float32(26000.0), 1)
    if warn:
        text = text.replace("[reference]\n", '[reference]\nimplausible_heights = "warn"\n', 1)
        (scene / "scene.toml").write_text(text)
    return scene


def test_implausible_dem_is_an_error_before_the_run(mini_scene: Path, tmp_path: Path) -> None:
    # planetref georef scene --matcher sift --out run, the DEM 26 km too high
    scene = _poisoned_scene(mini_scene, tmp_path, warn=False)
    r = run_cli("-q", "georef", scene, "--matcher", "sift", "--out", tmp_path / "run")
    one_line_error(r, "DEM heights are implausible", 'implausible_heights = "warn"')
    assert not (tmp_path / "run").exists()


def test_accepted_implausible_dem_reaches_the_run_log(mini_scene: Path, tmp_path: Path) -> None:
    # the same with implausible_heights = "warn": the warning goes to stderr and to
    # planetref.log (it was logged before the run's log opened)
    scene = _poisoned_scene(mini_scene, tmp_path, warn=True)
    out = tmp_path / "run"
    r = run_cli("georef", scene, "--matcher", "sift", "--out", out)
    assert "DEM heights are implausible" in r.stderr
    log = (out / "planetref.log").read_text()
    assert re.search(r"WARNING planetref\.\S+: .*DEM heights are implausible", log), log[-2000:]
