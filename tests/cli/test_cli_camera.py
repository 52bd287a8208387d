import json
import subprocess
import sys

import numpy as np
import pytest
from click.testing import CliRunner

from planetref.camera.io import load_camera
from planetref.camera.orbit import OrbitGeometry, ccd_row, orbit_camera
from planetref.cli import main
from planetref.geometry.geodesy import xyz_to_lonlat


@pytest.fixture
def camera_file(tmp_path):
    ccds = ccd_row(3, 256, 512, 0.010, overlap_px=16, stagger_mm=1.0)
    cam, _ = orbit_camera(OrbitGeometry(20.0, 74.0, 10.0), focal_length_mm=4640.0, ccds=ccds)
    return cam, cam.to_json(tmp_path / "cam.json")


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


def test_version_and_help():
    from planetref import __version__

    r = run("--version")
    assert r.exit_code == 0 and __version__ in r.output
    r = run("--help")
    assert "camera" in r.output and "info" in r.output


def test_info_json():
    r = run("info", "--json")
    info = json.loads(r.output)
    for key in ("planetref", "torch", "kornia", "rasterio", "gdal", "proj", "weights_dir"):
        assert key in info
    assert info["gdal"].count(".") >= 1


def test_image_to_ground_and_back(camera_file):
    cam, path = camera_file
    r = run(
        "camera",
        "image-to-ground",
        path,
        "--line",
        100.25,
        "--sample",
        40.5,
        "--height",
        -1500,
        "--ccd",
        "ccd2",
    )
    assert r.exit_code == 0, r.output
    out = json.loads(r.output)
    assert set(out) == {"x_m", "y_m", "z_m", "lat_deg", "lon_deg", "height_m"}
    xyz = cam.image_to_ground([100.25], [40.5], -1500.0, ccd="ccd2")[0]
    assert [out["x_m"], out["y_m"], out["z_m"]] == pytest.approx(xyz.tolist(), abs=1e-6)
    assert out["height_m"] == pytest.approx(-1500.0, abs=1e-4)
    r = run(
        "camera",
        "ground-to-image",
        path,
        "--lat",
        out["lat_deg"],
        "--lon",
        out["lon_deg"],
        "--height",
        out["height_m"],
        "--ccd",
        "ccd2",
    )
    back = json.loads(r.output)
    assert back["line"] == pytest.approx(100.25, abs=1e-6)
    assert back["sample"] == pytest.approx(40.5, abs=1e-6)
    r = run("camera", "ground-to-image", path, "--xyz", *xyz, "--ccd", "ccd2")
    assert json.loads(r.output)["line"] == pytest.approx(100.25, abs=1e-6)
    lon, lat, _ = xyz_to_lonlat(xyz, cam.ellipsoid)
    assert out["lat_deg"] == pytest.approx(float(lat)) and out["lon_deg"] == pytest.approx(
        float(lon)
    )


@pytest.mark.parametrize(
    "content, needle",
    [
        ('{"format": "planetref-linescan", "version": 1', "not valid JSON"),
        ('{"a": 1}', "neither a planetref line-scan camera nor a CSM"),
        ("hello", "unrecognised camera file"),
    ],
)
def test_bad_camera_file_is_one_line_error(tmp_path, content, needle):
    p = tmp_path / "bad.json"
    p.write_text(content)
    r = CliRunner().invoke(
        main, ["camera", "image-to-ground", str(p), "--line", "1", "--sample", "1"]
    )
    assert r.exit_code == 1
    assert needle in r.output and str(p) in r.output
    assert "Traceback" not in r.output and r.output.count("\n") == 1


def test_missing_file_and_bad_ccd(camera_file, tmp_path):
    _, path = camera_file
    r = CliRunner().invoke(
        main, ["camera", "ground-to-image", str(tmp_path / "x.json"), "--xyz", "1", "2", "3"]
    )
    assert r.exit_code == 1 and "no such camera file" in r.output
    r = CliRunner().invoke(
        main,
        ["camera", "image-to-ground", str(path), "--line", "1", "--sample", "1", "--ccd", "ccd9"],
    )
    assert r.exit_code == 1 and "unknown CCD 'ccd9'" in r.output


def test_usage_errors(camera_file):
    _, path = camera_file
    r = CliRunner().invoke(main, ["camera", "ground-to-image", str(path)])
    assert r.exit_code == 2 and "--xyz" in r.output
    r = CliRunner().invoke(
        main,
        ["camera", "ground-to-image", str(path), "--lat", "100", "--lon", "0", "--height", "0"],
    )
    assert r.exit_code == 1 and "--lat" in r.output


def test_console_script_runs():
    r = subprocess.run(
        [sys.executable, "-m", "planetref", "--version"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert r.returncode == 0 and "planetref" in r.stdout


def test_behind_camera_point_is_reported(camera_file):
    cam, path = camera_file
    s, _ = cam.exterior([256.0])
    # A point 20 % beyond the satellite is refused for its height (checked before any
    # projection, as --lat/--lon/--height are)...
    r = CliRunner().invoke(
        main, ["camera", "ground-to-image", str(path), "--xyz", *map(str, (1.2 * s[0]).tolist())]
    )
    assert r.exit_code == 1 and "--xyz: the point's height" in r.output
    assert np.isfinite(s).all()
    # ...and a ground point on the far side, behind the camera, cannot be projected.
    r = CliRunner().invoke(
        main,
        ["camera", "ground-to-image", str(path), "--lat", "20", "--lon", "-106", "--height", "0"],
    )
    assert r.exit_code == 1 and "cannot be projected" in r.output


def test_fit_rpc_command_round_trip(camera_file, tmp_path):
    cam, path = camera_file
    out = tmp_path / "ccd2.RPB"
    r = run(
        "camera",
        "fit-rpc",
        path,
        "--ccd",
        "ccd2",
        "--out",
        out,
        "--height-range",
        -3000,
        3000,
        "--grid",
        11,
        11,
        5,
    )
    assert r.exit_code == 0, r.output
    rep = json.loads(r.output)
    assert rep["check_max_px"] < 1e-3
    # The written RPC is itself a camera the CLI can use, and agrees with the rigorous one.
    xyz = cam.image_to_ground([200.5], [100.5], 500.0, ccd="ccd2")[0]
    r = run("camera", "ground-to-image", out, "--xyz", *xyz)
    got = json.loads(r.stdout)
    assert got["line"] == pytest.approx(200.5, abs=1e-3)
    assert got["sample"] == pytest.approx(100.5, abs=1e-3)


def _raster(write_geotiff, path, lines, samples):
    return write_geotiff(path, np.arange(lines * samples, dtype=np.uint16).reshape(lines, samples))


def test_fit_rpc_into_a_geotiff_of_other_pixels_or_read_only(camera_file, tmp_path, write_geotiff):
    # Embedding RPCs in a GeoTIFF whose size is not the camera's image would give that
    # image a wrong geolocation (a CTX fit went into a 1024 x 1024 Pleiades crop); a file
    # marked read-only is not replaced even with --overwrite (root ignores os.access).
    cam, path = camera_file
    n_lines, n_samples = cam.image_size("ccd2")
    fit = ["camera", "fit-rpc", path, "--ccd", "ccd2", "--height-range", -3000, 3000, "--overwrite"]
    other = _raster(write_geotiff, tmp_path / "other.tif", 64, 64)
    before = other.read_bytes()
    r = run(*fit, "--out", other)
    assert (
        r.exit_code == 1 and "64 x 64 raster" in r.output and f"{n_lines} x {n_samples}" in r.output
    )
    assert other.read_bytes() == before
    mine = _raster(write_geotiff, tmp_path / "ccd2.tif", n_lines, n_samples)
    mine.chmod(0o444)
    before = mine.read_bytes()
    r = run(*fit, "--out", mine)
    assert r.exit_code == 1 and "read-only file (mode 444)" in r.output
    assert mine.read_bytes() == before
    mine.chmod(0o644)  # the same file, writable: its RPCs are written, and read back
    r = run(*fit, "--out", mine)
    assert r.exit_code == 0, r.output
    xyz = cam.image_to_ground([200.5], [100.5], 500.0, ccd="ccd2")[0]
    got = json.loads(run("camera", "ground-to-image", mine, "--xyz", *xyz).stdout)
    assert got["line"] == pytest.approx(200.5, abs=1e-2)
    assert got["sample"] == pytest.approx(100.5, abs=1e-2)


def test_warnings_are_one_log_line(shared):
    # A Python warning (here: HRSC's line-scan-rate table outruns its ephemeris) is one
    # "WARNING" line naming the file, not Python's "path:line: UserWarning" plus a code line;
    # -q silences it like every other warning.
    isd = shared / "data" / "ale" / "mexhrsc_isd.json"
    args = ["camera", "image-to-ground", str(isd), "--line", "10", "--sample", "10"]
    for flags, expect_lines in (([], 1), (["-q"], 0)):
        r = subprocess.run(
            [sys.executable, "-m", "planetref", *flags, *args],
            capture_output=True,
            text=True,
            check=False,
        )
        assert r.returncode == 0, r.stderr
        lines = r.stderr.splitlines()
        assert len(lines) == expect_lines, r.stderr
        if lines:
            assert lines[0].startswith("WARNING planetref.warnings: ")
            assert str(isd) in lines[0] and "usgscsm extrapolates" in lines[0]
            assert "UserWarning" not in lines[0] and ".py:" not in lines[0]
        out = json.loads(r.stdout)
        # The point itself: 25.97 N 78.21 E on the ellipsoid (HRSC over Nili Fossae).
        assert abs(out["lat_deg"] - 25.9722448) < 1e-6 and abs(out["lon_deg"] - 78.2110398) < 1e-6


def test_far_points_give_the_error_alone(shared):
    # A point far outside the CTX image (and the body's centre) used to print numpy's
    # "overflow encountered in multiply" / "divide by zero" before the error line.
    ctx = shared / "data" / "csm" / "ctxLineScan.json"
    r = run("camera", "ground-to-image", ctx, "--lat", 0, "--lon", 0, "--height", 0)
    assert r.exit_code == 1 and "outside the image (0 to 11264)" in r.output
    r2 = run("camera", "ground-to-image", ctx, "--xyz", 0, 0, 0)
    assert r2.exit_code == 1 and "--xyz: the point's height -3.3762e+06 m" in r2.output
    for res in (r, r2):
        lines = [ln for ln in res.output.splitlines() if ln.strip()]
        assert len(lines) == 1 and "Warning" not in res.output, res.output


def test_simulate_help_names_every_preset():
    from planetref.simulate.config import available_presets

    r = run("simulate", "--help")
    text = " ".join(r.output.split())
    for name in available_presets():
        assert f"{name} (" in text, name


def test_fit_rpc_avoids_a_pole_on_a_real_ctx_image(shared, tmp_path):
    # G21 (19,456 CTX lines): fit_rpc's default regularisation put a denominator zero near
    # the image (check max 1452.7 px, min |D| 5e-5); the regularisation ladder keeps
    # 1.23 px, and what remains above 1 px is said on stderr.
    isd = shared / "data" / "ctx_syrtis" / "G21_026491_2001_XN_20N286W.lev1.json"
    out = tmp_path / "g21.RPB"
    r = run("camera", "fit-rpc", isd, "--out", out, "--height-range", -4000, 0)
    assert r.exit_code == 0, r.output
    rep = json.loads(r.stdout)
    assert rep["check_max_px"] < 1.5 and rep["check_rms_px"] < 0.7, rep
    assert "WARNING planetref.camera" in r.stderr and "max 1.23 px" in r.stderr
    # The RPC written agrees with the ISD at a ground point inside the image.
    cam = load_camera(isd)
    xyz = cam.image_to_ground([9000.5], [2500.5], -2000.0)[0]
    got = json.loads(run("camera", "ground-to-image", out, "--xyz", *xyz).stdout)
    assert np.hypot(got["line"] - 9000.5, got["sample"] - 2500.5) < 1.5
