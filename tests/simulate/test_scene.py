from __future__ import annotations

import csv
import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.errors import NotGeoreferencedWarning

from planetref.camera.linescan import LineScanCamera
from planetref.errors import InputError
from planetref.raster.dem import GridTerrain
from planetref.scene.manifest import load_manifest
from planetref.simulate.scene import simulate_scene


def _read(path: Path) -> tuple[np.ndarray, object, object]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(path) as ds:
            return ds.read(1), ds.transform, ds.crs


def test_scene_layout_and_rasters(mini_scene: Path) -> None:
    manifest, root = load_manifest(mini_scene)
    assert manifest.name == "mini" and len(manifest.strips) == 1
    strip = manifest.strips[0]
    assert [c.name for c in strip.ccds] == ["ccd1", "ccd2", "ccd3"]
    ortho, t, crs = _read(root / manifest.reference.ortho)
    assert ortho.dtype == np.uint8 and t.a == 5.0 and t.e == -5.0
    assert "Equirectangular" in crs.to_wkt() and "3396190" in crs.to_wkt()
    dem, t, _ = _read(root / manifest.reference.dem)
    assert dem.dtype == np.float32 and t.a == pytest.approx(463.0836)
    assert np.isfinite(dem).all()
    for c in strip.ccds:
        img, t, crs = _read(root / c.image)
        assert img.shape == (96, 64) and img.dtype == np.uint16
        assert crs is None and t.is_identity
        assert 1000 < img.mean() < 60000 and img.std() > 50
        cam = LineScanCamera.from_json(root / c.camera)
        assert c.camera_ccd in cam.ccd_names
    assert manifest.truth is not None
    errors = json.loads((root / manifest.truth.errors).read_text())
    e = errors["strip1"]["initial_errors"]["ground_m"]
    assert 30.0 < e["horizontal"]["rms"] < 500.0  # tens to hundreds of metres


def test_truth_is_consistent_with_the_camera(mini_scene: Path) -> None:
    manifest, root = load_manifest(mini_scene)
    assert manifest.truth is not None
    cam = LineScanCamera.from_json(root / manifest.truth.cameras["strip1"])
    dem = GridTerrain.from_geotiff(root / manifest.truth.dem)
    rng = np.random.default_rng(11)
    for ccd in cam.ccd_names:
        n_lines, n_samples = cam.image_size(ccd)
        lines = rng.uniform(0, n_lines, 30)
        samples = rng.uniform(0, n_samples, 30)
        xyz = cam.image_to_ground(lines, samples, dem, ccd=ccd)
        ip = cam.ground_to_image(xyz, ccd=ccd)
        assert np.max(np.hypot(ip.line - lines, ip.sample - samples)) < 0.01
    with open(root / manifest.truth.checkpoints, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 3 * 5
    for r in rows:
        xyz = np.array([[float(r["x_m"]), float(r["y_m"]), float(r["z_m"])]])
        ip = cam.ground_to_image(xyz, ccd=r["ccd"])
        assert abs(ip.line[0] - float(r["line"])) < 0.01
        assert abs(ip.sample[0] - float(r["sample"])) < 0.01
        lon, lat = dem.projection.map_to_lonlat(*dem.xyz_to_map(xyz)[:2])
        assert float(dem.height(lon, lat)[0]) == pytest.approx(float(r["height_m"]), abs=1e-3)


def _all_files(root: Path) -> dict[str, bytes]:
    return {
        p.relative_to(root).as_posix(): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def test_same_seed_gives_identical_files(
    mini_scene: Path,
    mini_config,
    tmp_path: Path,  # type: ignore[no-untyped-def]
) -> None:
    again = tmp_path / "again"
    simulate_scene(mini_config(seed=7), again)
    a, b = _all_files(mini_scene), _all_files(again)
    assert a.keys() == b.keys()
    for name in a:
        assert a[name] == b[name], name
    other = tmp_path / "other"
    simulate_scene(mini_config(seed=8), other)
    c = _all_files(other)
    for name in a:
        if name.endswith(".tif"):
            assert a[name] != c[name], name


def test_ortho_offset_shifts_the_geotransform_only(
    mini_scene: Path,
    mini_config,  # type: ignore[no-untyped-def]
    tmp_path: Path,
) -> None:
    out = tmp_path / "offset"
    simulate_scene(mini_config(seed=7, reference={"ortho_offset_m": [30.0, -20.0]}), out)
    m, root = load_manifest(out)
    assert m.truth is not None and m.truth.ortho_offset_m == (30.0, -20.0)
    a, ta, _ = _read(mini_scene / "reference" / "ortho.tif")
    b, tb, _ = _read(root / "reference" / "ortho.tif")
    np.testing.assert_array_equal(a, b)
    assert tb.c - ta.c == pytest.approx(30.0) and tb.f - ta.f == pytest.approx(-20.0)


def test_refuses_non_empty_out_dir_and_cleans_up(
    mini_config,
    tmp_path: Path,  # type: ignore[no-untyped-def]
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    out = tmp_path / "busy"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    with pytest.raises(InputError, match="not empty"):
        simulate_scene(mini_config(), out)
    assert (out / "keep.txt").exists()

    import planetref.simulate.render as render

    def boom(*_a: object, **_k: object) -> None:
        raise RuntimeError("interrupted")

    monkeypatch.setattr(render, "render_ccd", boom)
    with pytest.raises(RuntimeError):
        simulate_scene(mini_config(), out, overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["busy"]
    assert (out / "keep.txt").exists()


def test_two_strips_share_one_truth(mini_config, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    cfg = mini_config(
        strips=[
            {"id": "a", "cross_offset_m": -40.0},
            {"id": "b", "cross_offset_m": 40.0, "pointing_deg": [0.02, 0, 0]},
        ]
    )
    out = tmp_path / "two"
    res = simulate_scene(cfg, out)
    m, root = load_manifest(out)
    assert [s.id for s in m.strips] == ["a", "b"]
    assert m.truth is not None and set(m.truth.cameras) == {"a", "b"}
    dem = GridTerrain.from_geotiff(root / m.truth.dem)
    for sid in ("a", "b"):
        cam = LineScanCamera.from_json(root / m.truth.cameras[sid])
        xyz = cam.image_to_ground([10.5, 80.5], [5.5, 60.5], dem, ccd="ccd2")
        ip = cam.ground_to_image(xyz, ccd="ccd2")
        np.testing.assert_allclose(ip.line, [10.5, 80.5], atol=0.01)
        assert res.errors[sid]["consistency"]["roundtrip_max_px"] < 0.01


def test_an_areoid_scene_declares_its_datum_and_reads_back_body_heights(
    mini_scene: Path,
    mini_config,  # type: ignore[no-untyped-def]
    tmp_path: Path,
) -> None:
    """With ``[reference.mola] areoid`` the DEM holds heights above the areoid-like
    surface; the scene carries that surface (``reference/areoid.tif``) and declares
    ``dem_datum = "areoid"``, so the DEM read by the pipeline equals the same scene's
    DEM without an areoid (heights above the sphere) to float32 rounding."""
    from planetref.raster.datum import open_reference_dem
    from planetref.scene.inputs import open_reference

    mola = {"areoid": True, "areoid_offset_m": 250.0, "areoid_tilt_m_per_km": 40.0}
    out = tmp_path / "areoid"
    simulate_scene(mini_config(seed=7, reference={"mola": mola}), out)
    m, root = load_manifest(out)
    assert m.reference.dem_datum == "areoid" and m.reference.areoid == "reference/areoid.tif"
    assert "reference/areoid.tif" in m.paths()
    _, dem = open_reference(m, root)
    m0, root0 = load_manifest(mini_scene)
    assert m0.reference.dem_datum == "body"
    _, dem0 = open_reference(m0, root0)
    assert dem.heights.shape == dem0.heights.shape
    assert np.nanmax(np.abs(dem.heights - dem0.heights)) < 1e-3
    # The file itself is above the areoid: read as body heights it is 250 m +- the tilt low.
    naive = open_reference_dem(root / m.reference.dem)
    low = dem0.heights - naive.heights
    assert 200.0 < np.nanmin(low) < 250.0 < np.nanmax(low) < 300.0
