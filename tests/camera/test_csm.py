"""Tests of the USGS CSM line-scan ISD reader and camera (planetref.camera.csm).

Expected numbers marked "usgscsm" come from usgscsm's own test suite
(tests/LineScanCameraTests.cpp and tests/DistortionTests.cpp of DOI-USGS/usgscsm, the
version whose OrbitalLineScanSensorModel.Center expects -812.35021438796923, i.e. after
the ephemeris resampling to 25 nodes was introduced); the test names are cited.
"""

from __future__ import annotations

import copy
import csv
import json
import math
import tomllib
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from planetref.camera.base import Camera, ConstantHeight, isis_to_csm
from planetref.camera.csm import (
    CsmCorrection,
    CsmIsd,
    CsmLineScanCamera,
    read_isd,
    write_isd,
)
from planetref.camera.csm.distortion import apply_distortion, remove_distortion
from planetref.errors import GeometryError, InputError, MissingFileError, UnsupportedFormatError
from planetref.geometry.geodesy import Ellipsoid, xyz_to_lonlat

SHARED = Path(__file__).resolve().parents[2].parent / "shared"
ISD_DIRS = ("data/csm", "data/ale", "data/ctx_syrtis")
ALL_ISDS = (
    sorted(str(p.relative_to(SHARED)) for d in ISD_DIRS for p in (SHARED / d).glob("*.json"))
    if SHARED.is_dir()
    else []
)
REAL_ISDS = [p for p in ALL_ISDS if "LineScan" not in p or "ctxLineScan" in p]


def _camera(path: Path) -> CsmLineScanCamera:
    # The ALE HRSC ISD times half its lines outside its ephemeris (see its own test).
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return CsmLineScanCamera.from_file(path)


@pytest.fixture
def csm_dir(shared: Path) -> Path:
    return shared / "data" / "csm"


# ---------------------------------------------------------------------------------------
# A small synthetic ISD (no ../shared needed): a 1000 km sphere, a circular polar orbit at
# 1050 km, a nadir-looking 16 x 16 line scanner.
# ---------------------------------------------------------------------------------------


def make_isd(tilt_deg: float = 0.0) -> dict:
    times = 999.2 + 0.1 * np.arange(16)
    w = 1e-3  # rad/s
    th = w * (times - 1000.0)
    pos = 1050.0 * np.stack([np.cos(th), np.zeros_like(th), -np.sin(th)], axis=1)
    vel = 1050.0 * w * np.stack([-np.sin(th), np.zeros_like(th), -np.cos(th)], axis=1)
    quats = []
    for p, v in zip(pos, vel, strict=True):
        z = -p / np.linalg.norm(p)
        x = v / np.linalg.norm(v)
        y = np.cross(z, x)
        m = np.stack([x, y, z])  # J2000 -> sensor
        tilt = Rotation.from_euler("x", tilt_deg, degrees=True).as_matrix()
        quats.append(Rotation.from_matrix(tilt @ m).as_quat(scalar_first=True))
    ident = [[1.0, 0.0, 0.0, 0.0]] * 16
    return {
        "name_model": "USGS_ASTRO_LINE_SCANNER_SENSOR_MODEL",
        "name_platform": "SYNTHETIC",
        "name_sensor": "SYNTH",
        "center_ephemeris_time": 1000.0,
        "starting_ephemeris_time": 999.15,
        "line_scan_rate": [[0.5, -0.85, 0.1]],
        "detector_sample_summing": 1,
        "detector_line_summing": 1,
        "focal2pixel_lines": [0.0, -10.0, 0.0],
        "focal2pixel_samples": [0.0, 0.0, 10.0],
        "focal_length_model": {"focal_length": 50.0},
        "image_lines": 16,
        "image_samples": 16,
        "detector_center": {"line": 0.5, "sample": 8.0},
        "starting_detector_line": 1,
        "starting_detector_sample": 0,
        "optical_distortion": {"radial": {"coefficients": [0.0, 0.0, 0.0]}},
        "radii": {"semimajor": 1000.0, "semiminor": 1000.0, "unit": "km"},
        "reference_height": {"maxheight": 1000, "minheight": -1000, "unit": "m"},
        "instrument_position": {
            "unit": "km",
            "positions": pos.tolist(),
            "velocities": vel.tolist(),
            "ephemeris_times": times.tolist(),
            "reference_frame": 1,
        },
        "instrument_pointing": {
            "quaternions": np.array(quats).tolist(),
            "ephemeris_times": times.tolist(),
            "angular_velocities": [[0.0, 0.0, 0.0]] * 16,
            "reference_frame": 1,
        },
        "body_rotation": {
            "quaternions": ident,
            "ephemeris_times": times.tolist(),
            "angular_velocities": [[0.0, 0.0, 0.0]] * 16,
            "reference_frame": 1,
            "time_dependent_frames": [10, 1],
        },
        "t0_ephemeris": -0.8,
        "dt_ephemeris": 0.1,
    }


def _write(tmp_path: Path, data: dict | str, name: str = "isd.json") -> Path:
    p = tmp_path / name
    p.write_text(data if isinstance(data, str) else json.dumps(data))
    return p


def test_synthetic_camera_protocol_and_round_trip(tmp_path):
    cam = CsmLineScanCamera.from_file(_write(tmp_path, make_isd()))
    assert isinstance(cam, Camera)
    assert cam.ccd_names == ("SYNTH",)
    assert cam.image_size() == (16, 16)
    # Nadir-looking: the image centre is under the spacecraft, 50 km below it.
    xyz = cam.image_to_ground(8.0, 8.0)
    np.testing.assert_allclose(np.linalg.norm(xyz), 1e6, rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(cam.sensor_position(8.0) - xyz), 50e3, rtol=1e-3)
    lines, samples = np.meshgrid(np.linspace(0.5, 15.5, 7), np.linspace(0.5, 15.5, 7))
    g = cam.image_to_ground(lines.ravel(), samples.ravel(), 250.0)
    ip = cam.ground_to_image(g)
    assert ip.valid.all() and ip.in_image.all()
    assert np.max(np.hypot(ip.line - lines.ravel(), ip.sample - samples.ravel())) < 1e-6
    # image_time: usgscsm's getImageTime, t0 + rate * (line - line0 + 0.5).
    np.testing.assert_allclose(cam.image_time([0.0, 0.5, 8.0]), [-0.85, -0.8, -0.05])
    with pytest.raises(InputError, match="unknown CCD"):
        cam.image_size("other")
    with pytest.raises(InputError, match="on_miss"):
        cam.image_to_ground(1.0, 1.0, on_miss="ignore")


def test_points_behind_or_outside(tmp_path):
    cam = CsmLineScanCamera.from_file(_write(tmp_path, make_isd()))
    centre = cam.image_to_ground(8.0, 8.0)[0]
    sensor = cam.sensor_position(8.0)[0]
    beyond = cam.image_to_ground(8.0, 8.0)[0] + np.array([0.0, 3000.0, 0.0])
    ip = cam.ground_to_image(np.stack([centre, 2 * sensor - centre, beyond, [np.nan, 0.0, 0.0]]))
    # Behind the sensor (above it) and non-finite: not projectable.
    assert ip.valid.tolist() == [True, False, True, False]
    assert np.isnan(ip.line[[1, 3]]).all()
    # Off the side of the image: projected (extrapolated), flagged outside.
    assert ip.in_image.tolist() == [True, False, False, False]
    assert ip.sample[2] > 16 or ip.sample[2] < 0


def test_rays_into_space_raise_geometry_error(tmp_path):
    # Tilted 72 degrees across track, so part of each line looks past the limb.
    cam = CsmLineScanCamera.from_file(_write(tmp_path, make_isd(tilt_deg=72.0)))
    samples = np.arange(0.5, 16.0)
    with pytest.raises(GeometryError) as info:
        cam.image_to_ground(np.full(16, 8.0), samples)
    msg = str(info.value)
    assert "\n" not in msg and "isd.json" in msg and "see no ground" in msg
    g = cam.image_to_ground(np.full(16, 8.0), samples, on_miss="nan")
    hit = np.isfinite(g[:, 0])
    assert 0 < hit.sum() < 16


# ---------------------------------------------------------------------------------------
# Bad input: one-line errors naming the file and the field
# ---------------------------------------------------------------------------------------


def _error_of(tmp_path, data, exc_type=InputError):
    p = _write(tmp_path, data)
    with pytest.raises(exc_type) as info:
        read_isd(p)
    msg = str(info.value)
    assert "\n" not in msg and str(p) in msg
    return msg


def _set(d: dict, key: str, value) -> dict:
    d = copy.deepcopy(d)
    node = d
    parts = key.split(".")
    for part in parts[:-1]:
        node = node[part]
    if value is _DELETE:
        del node[parts[-1]]
    else:
        node[parts[-1]] = value
    return d


_DELETE = object()


def test_bad_json(tmp_path):
    text = json.dumps(make_isd())
    assert "not valid JSON" in _error_of(tmp_path, text[: len(text) // 2])
    assert "not valid JSON" in _error_of(tmp_path, "")
    assert "must be a JSON object" in _error_of(tmp_path, "[1, 2]")
    with pytest.raises(MissingFileError):
        read_isd(tmp_path / "nope.json")


@pytest.mark.parametrize(
    "key",
    [
        "focal2pixel_lines",
        "line_scan_rate",
        "image_lines",
        "instrument_position.positions",
        "radii.semiminor",
        "focal_length_model.focal_length",
        "body_rotation",
        "instrument_pointing.quaternions",
        "optical_distortion",
    ],
)
def test_missing_key(tmp_path, key):
    msg = _error_of(tmp_path, _set(make_isd(), key, _DELETE))
    assert f"field '{key}'" in msg and "missing" in msg


def test_wrong_model_name(tmp_path):
    msg = _error_of(
        tmp_path,
        _set(make_isd(), "name_model", "USGS_ASTRO_FRAME_SENSOR_MODEL"),
        UnsupportedFormatError,
    )
    assert "field 'name_model'" in msg


def test_nan_values(tmp_path):
    d = make_isd()
    d["instrument_position"]["positions"][3][1] = float("nan")
    assert "field 'instrument_position.positions[3]'" in _error_of(tmp_path, d)
    msg = _error_of(tmp_path, _set(make_isd(), "focal_length_model.focal_length", float("inf")))
    assert "field 'focal_length_model.focal_length'" in msg and "finite" in msg


def test_bad_quaternions(tmp_path):
    d = make_isd()
    d["instrument_pointing"]["quaternions"][2] = [0.0, 0.0, 0.0, 0.0]
    msg = _error_of(tmp_path, d)
    assert "field 'instrument_pointing.quaternions[2]'" in msg and "zero norm" in msg
    d = make_isd()
    d["body_rotation"]["quaternions"][5] = [2.0, 0.0, 0.0, 0.0]
    assert "not a unit quaternion" in _error_of(tmp_path, d)


def test_wrong_units(tmp_path):
    msg = _error_of(tmp_path, _set(make_isd(), "instrument_position.unit", "m"))
    assert "field 'instrument_position.unit'" in msg and "'km'" in msg
    assert "field 'radii.unit'" in _error_of(tmp_path, _set(make_isd(), "radii.unit", "m"))
    # Radii in metres without a unit field: caught by their size.
    d = _set(make_isd(), "radii", {"semimajor": 3396190.0, "semiminor": 3376200.0})
    assert "metres" in _error_of(tmp_path, d)


def test_other_bad_fields(tmp_path):
    assert "expected a number" in _error_of(tmp_path, _set(make_isd(), "image_lines", "16"))
    assert "must be positive" in _error_of(tmp_path, _set(make_isd(), "image_samples", 0))
    d = make_isd()
    d["instrument_position"]["ephemeris_times"][4] = 999.0
    assert "strictly increasing" in _error_of(tmp_path, d)
    d = make_isd()
    d["instrument_position"]["positions"].pop()
    assert "rows for 16" in _error_of(tmp_path, d)
    msg = _error_of(
        tmp_path,
        _set(make_isd(), "optical_distortion", {"cahvor": {"coefficients": [0, 0, 0, 0, 0]}}),
        UnsupportedFormatError,
    )
    assert "cahvor" in msg and "field 'optical_distortion'" in msg
    msg = _error_of(
        tmp_path,
        _set(make_isd(), "instrument_position.reference_frame", 42),
        UnsupportedFormatError,
    )
    assert "reference frame 42" in msg


# ---------------------------------------------------------------------------------------
# Agreement with usgscsm's own tests
# ---------------------------------------------------------------------------------------


def test_orbital_center(csm_dir):
    # usgscsm OrbitalLineScanSensorModel.Center (EXPECT_NEAR 1e-9).
    cam = CsmLineScanCamera.from_file(csm_dir / "orbitalLineScan.json")
    xyz = cam.image_to_ground(8.5, 8.0, 0.0)[0]
    np.testing.assert_allclose(
        xyz, [999999.67004351015, 0.0, -812.35021438796923], rtol=0, atol=1e-9
    )


def test_orbital_image_to_ground_height(csm_dir):
    # usgscsm OrbitalLineScanSensorModel.ImageToGroundHeight (EXPECT_DOUBLE_EQ, 4 ulp).
    cam = CsmLineScanCamera.from_file(csm_dir / "orbitalLineScan.json")
    r = np.linalg.norm(cam.image_to_ground(8.5, 8.0, 100.0)[0])
    assert abs(r - 1000100.0) <= 4 * np.spacing(1000100.0)


@pytest.mark.parametrize("height", [0.0, 100.0, 4900.0])
def test_orbital_inversion(csm_dir, height):
    # usgscsm OrbitalLineScanSensorModel.Inversion / InversionHeight / InversionReallyHigh
    # (they allow 0.1 / 0.1 / 0.002 pixel; we iterate to 1e-9 pixel).
    cam = CsmLineScanCamera.from_file(csm_dir / "orbitalLineScan.json")
    lines = np.arange(0.5, 16.0)
    g = cam.image_to_ground(lines, np.full(16, 8.0), height)
    ip = cam.ground_to_image(g)
    np.testing.assert_allclose(ip.line, lines, atol=1e-6)
    np.testing.assert_allclose(ip.sample, 8.0, atol=1e-6)


def test_flipped_orbital_opposite_flight_detector(csm_dir):
    # usgscsm FlippedOrbitalLineScanSensorModel.OppositeFlightDetector (0.001 pixel).
    cam = CsmLineScanCamera.from_file(csm_dir / "flippedOrbitalLineScan.json")
    ip = cam.ground_to_image(cam.image_to_ground(8.7, 8.0, 0.0))
    np.testing.assert_allclose([ip.line[0], ip.sample[0]], [8.7, 8.0], atol=1e-6)


def test_const_velocity_center_and_locus(csm_dir):
    cam = CsmLineScanCamera.from_file(csm_dir / "constVelocityLineScan.json")
    # usgscsm ConstVelocityLineScanSensorModel.Center (1e-10).
    np.testing.assert_allclose(
        cam.image_to_ground(8.0, 8.0, 0.0)[0],
        [9.99999500000, 0.0, 0.00999999500],
        rtol=0,
        atol=1e-10,
    )
    # usgscsm ConstVelocityLineScanSensorModel.RemoteImageLocus (1e-10).
    sensor = cam.sensor_position(8.5)[0]
    np.testing.assert_allclose(sensor, [1000.0, 0.0, 0.0], rtol=0, atol=1e-10)
    g = cam.image_to_ground(8.5, 8.0, 0.0)[0]
    np.testing.assert_allclose(
        cam.look_direction(8.5, 8.0)[0], (g - sensor) / np.linalg.norm(g - sensor), atol=1e-10
    )
    # usgscsm ConstVelocityLineScanSensorModel.Inversion (1e-3 pixel).
    ip = cam.ground_to_image(g)
    np.testing.assert_allclose([ip.line[0], ip.sample[0]], [8.5, 8.0], atol=1e-6)


def test_const_velocity_off_body(csm_dir):
    # usgscsm ConstVelocityLineScanSensorModel.OffBody: the ray of (0, 4) misses the 10 m
    # body and usgscsm returns the ray's point nearest the body (0.04799688020,
    # -7.99961602495, 16.00004799688). planetref refuses to return a wrong point...
    cam = CsmLineScanCamera.from_file(csm_dir / "constVelocityLineScan.json")
    with pytest.raises(GeometryError):
        cam.image_to_ground(0.0, 4.0, 0.0)
    assert np.isnan(cam.image_to_ground(0.0, 4.0, 0.0, on_miss="nan")).all()
    # ... but its ray is usgscsm's: same nearest point (1e-10).
    o, d = cam.sensor_position(0.0)[0], cam.look_direction(0.0, 4.0)[0]
    np.testing.assert_allclose(
        o - np.dot(o, d) * d, [0.04799688020, -7.99961602495, 16.00004799688], atol=1e-10
    )


def test_focal_length_adjustment(csm_dir):
    # usgscsm ConstVelocityLineScanSensorModel.FocalLengthAdjustment (1e-14).
    cam = CsmLineScanCamera.from_file(csm_dir / "constVelocityLineScan.json")
    cam = cam.with_correction(CsmCorrection(focal_m=0.9 * cam.half_swath_m))
    scale = math.sqrt(5 * 5 + 0.4 * 0.4 + 0.05 * 0.05)
    np.testing.assert_allclose(
        cam.look_direction(8.5, 4.0)[0], np.array([-5.0, -0.4, -0.05]) / scale, rtol=0, atol=1e-14
    )


def test_attitude_correction_matrix(csm_dir):
    # usgscsm ConstVelocityLineScanSensorModel.calculateAttitudeCorrection (1e-8).
    cam = CsmLineScanCamera.from_file(csm_dir / "constVelocityLineScan.json")
    cam = cam.with_correction(CsmCorrection(phi_m=math.pi / 2 * cam.flying_height_m))
    m = cam._attitude_correction(np.array([999.5]))[0]
    np.testing.assert_allclose(m, [[0, 0, 1], [0, 1, 0], [-1, 0, 0]], atol=1e-8)


def test_distortion_models():
    # usgscsm Transverse.distortMe_AlternatingOnes / transverse.removeDistortion_
    # AlternatingOnes and Radial.testUndistortDistort (1e-8).
    alt = np.array([1.0, 0.0] * 5 + [0.0, 1.0] * 5)
    dx, dy = apply_distortion("transverse", alt, np.array([7.5]), np.array([7.5]))
    np.testing.assert_allclose([dx[0], dy[0]], [908.5, 963.75], atol=1e-8)
    ux, uy = remove_distortion("transverse", alt, np.array([908.5]), np.array([963.75]))
    np.testing.assert_allclose([ux[0], uy[0]], [7.5, 7.5], atol=1e-8)
    radial = np.array([0.03, 0.00001, 0.000004])
    ux, uy = remove_distortion("radial", radial, np.array([0.1]), np.array([0.0]))
    dx, dy = apply_distortion("radial", radial, ux, uy)
    np.testing.assert_allclose([dx[0], dy[0]], [0.1, 0.0], atol=1e-12)
    # CTX coefficients over its focal plane (+-17.8 mm): inverse to 1e-12 mm.
    ctx = np.array([-0.0073433925920054505, 2.8375878636241697e-05, 1.2841989124027099e-08])
    x = np.linspace(-17.8, 17.8, 41)
    ux, uy = remove_distortion("radial", ctx, x, 0.3 * x)
    dx, dy = apply_distortion("radial", ctx, ux, uy)
    np.testing.assert_allclose(np.stack([dx, dy]), np.stack([x, 0.3 * x]), atol=1e-12)
    # usgscsm RadTanInversionTest (k1, k2, p1, p2, k3; f = 1000 mm): apply, then remove.
    rt = np.array([0.000031, -0.000056, 1.3e-5, -1.7e-6, 2.9e-8])
    dx, dy = apply_distortion("radtan", rt, np.array([5.0]), np.array([6.0]), focal_length_mm=1e3)
    np.testing.assert_allclose([dx[0], dy[0]], [5.0000006007539586, 6.0000016383447505], atol=1e-12)
    ux, uy = remove_distortion("radtan", rt, dx, dy, focal_length_mm=1e3)
    np.testing.assert_allclose([ux[0], uy[0]], [5.0, 6.0], atol=1e-12)
    # A strong radtan lens over a 40 mm focal plane (f = 100 mm): remove inverts apply.
    strong = np.array([-0.2, 0.05, 1e-3, -2e-3, 0.01])
    x = np.linspace(-20.0, 20.0, 41)
    dx, dy = apply_distortion("radtan", strong, x, -0.5 * x, focal_length_mm=100.0)
    assert np.max(np.hypot(dx - x, dy + 0.5 * x)) > 0.1  # mm: a real distortion
    ux, uy = remove_distortion("radtan", strong, dx, dy, focal_length_mm=100.0)
    np.testing.assert_allclose(np.stack([ux, uy]), np.stack([x, -0.5 * x]), atol=1e-12)


# ---------------------------------------------------------------------------------------
# Every ISD in ../shared
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ALL_ISDS or ["<no ISDs>"])
def test_round_trips(shared, name):
    cam = _camera(shared / name)
    nl, ns = cam.image_size()
    lines, samples = np.meshgrid(
        np.linspace(0.5, nl - 0.5, 9), np.linspace(0.5, ns - 0.5, 9), indexing="ij"
    )
    lines, samples = lines.ravel(), samples.ravel()
    for height in (0.0, 1500.0):
        g = cam.image_to_ground(lines, samples, height, on_miss="nan")
        hit = np.isfinite(g[:, 0])
        assert hit.sum() >= 5  # the 10 m body of constVelocityLineScan is seen by few pixels
        ip = cam.ground_to_image(g[hit])
        assert ip.valid.all() and ip.in_image.all()
        err_px = np.hypot(ip.line - lines[hit], ip.sample - samples[hit])
        assert err_px.max() < 1e-6
        g2 = cam.image_to_ground(ip.line, ip.sample, height)
        err_m = np.linalg.norm(g2 - g[hit], axis=1)
        assert err_m.max() < 1e-6 * cam.gsd_m + 1e-9
        np.testing.assert_allclose(xyz_to_lonlat(g[hit], cam.ellipsoid)[2], height, atol=1e-4)


@pytest.mark.parametrize("name", ALL_ISDS or ["<no ISDs>"])
def test_write_read_round_trip(shared, tmp_path, name):
    cam = _camera(shared / name)
    out = write_isd(cam, tmp_path / "copy.json")
    assert [p.name for p in tmp_path.iterdir()] == ["copy.json"]  # no temporary left
    again = _camera(out)
    nl, ns = cam.image_size()
    lines = np.linspace(0.5, nl - 0.5, 5)
    samples = np.linspace(0.5, ns - 0.5, 5)
    a = cam.image_to_ground(lines, samples, 0.0, on_miss="nan")
    b = again.image_to_ground(lines, samples, 0.0, on_miss="nan")
    np.testing.assert_array_equal(a, b)
    assert again.isd.extra.keys() == cam.isd.extra.keys()


def test_hrsc_isd_timing_warning(shared):
    # ALE's HRSC ISD: the second line_scan_rate row starts at +98.35 s (the end of the
    # image) instead of -13.04 s, so usgscsm times lines 6665..15088 after the ephemeris.
    with pytest.warns(UserWarning, match="usgscsm extrapolates"):
        cam = CsmLineScanCamera.from_file(shared / "data/ale/mexhrsc_isd.json")
    np.testing.assert_allclose(cam.image_time([0.0, 15088.0]), [-98.35948, 209.76089], atol=1e-4)


@pytest.mark.parametrize("name", REAL_ISDS or ["<no ISDs>"])
def test_look_direction_plausible(shared, name):
    cam = _camera(shared / name)
    nl, ns = cam.image_size()
    centre = cam.image_to_ground(nl / 2, ns / 2, 0.0)[0]
    sensor = cam.sensor_position(nl / 2)[0]
    lon, lat, _ = xyz_to_lonlat(centre, cam.ellipsoid)
    slon, slat, alt = xyz_to_lonlat(sensor, cam.ellipsoid)
    look = cam.look_direction(nl / 2, ns / 2)[0]
    emission = np.degrees(np.arccos(np.dot(-look, centre / np.linalg.norm(centre))))
    print(
        f"{name}: centre {float(lat):.3f}N {float(lon) % 360:.3f}E, sub-spacecraft "
        f"{float(slat):.3f}N {float(slon) % 360:.3f}E, altitude {float(alt) / 1e3:.1f} km, "
        f"emission {emission:.1f} deg"
    )
    assert 150e3 < alt < 500e3  # Mars orbiters
    assert emission < 35.0
    assert abs(float(lat) - float(slat)) < 3.0 and abs(float(lon) - float(slon)) < 3.0
    stem = Path(name).stem
    if "_XN_" in stem:  # CTX product names end in e.g. 20N286W (planetocentric, west lon)
        tag = stem.split("_")[4].split(".")[0]
        lat_ref = float(tag[:2]) * (1 if tag[2] == "N" else -1)
        lon_ref = (-float(tag[3:6]) if tag[6] == "W" else float(tag[3:6])) % 360
        assert abs(float(lat) - lat_ref) < 1.0
        assert abs((float(lon) - lon_ref + 180) % 360 - 180) < 1.0


def test_isis_measures_half_pixel(shared):
    # Real CTX tie points: a priori XYZ and ISIS measures (first pixel centre at 1.0).
    folder = shared / "data" / "ctx_syrtis"
    net = tomllib.loads((folder / "network.toml").read_text())
    with open(folder / net["measures"], newline="") as fh:
        rows = list(csv.DictReader(fh))
    for image_id, fname in net["images"].items():
        mine = [r for r in rows if r["image_id"] == image_id]
        cam = CsmLineScanCamera.from_file(folder / fname)
        xyz = np.array([[float(r[f"apriori_{c}_m"]) for c in "xyz"] for r in mine])
        isis_line = np.array([float(r["line"]) for r in mine])
        isis_sample = np.array([float(r["sample"]) for r in mine])
        line, sample = isis_to_csm(isis_line, isis_sample)
        ip = cam.ground_to_image(xyz)
        assert ip.valid.all() and ip.in_image.all()
        dl, ds = ip.line - line, ip.sample - sample
        print(
            f"{fname}: {len(mine)} measures, mean residual (CSM = ISIS - 0.5) line "
            f"{dl.mean():+.3f} sample {ds.mean():+.3f} px (rms {dl.std():.3f}, "
            f"{ds.std():.3f}); without the shift {dl.mean() - 0.5:+.3f}, "
            f"{ds.mean() - 0.5:+.3f}"
        )
        # Unadjusted cameras and a priori points: a few pixels of bias, ~1 px scatter.
        assert np.max(np.hypot(dl, ds)) < 10.0
        assert dl.std() < 1.5 and ds.std() < 1.5


def test_terrain_intersection_with_real_camera(shared):
    cam = CsmLineScanCamera.from_file(
        shared / "data/ctx_syrtis/P15_006844_2009_XN_20N286W.lev1.json"
    )

    class Wavy:
        ellipsoid = cam.ellipsoid
        min_height_m, max_height_m, sampling_m = -4000.0, -1000.0, 18.0

        def height(self, lon, lat):
            return -2500.0 + 800.0 * np.sin(np.radians(lon) * 900.0) * np.cos(
                np.radians(lat) * 700.0
            )

    t = Wavy()
    lines = np.linspace(100.0, 52000.0, 12)
    samples = np.linspace(10.0, 4990.0, 12)
    g = cam.image_to_ground(lines, samples, t)
    lon, lat, h = xyz_to_lonlat(g, cam.ellipsoid)
    np.testing.assert_allclose(h, t.height(lon, lat), atol=1e-3)
    ip = cam.ground_to_image(g)
    np.testing.assert_allclose(ip.line, lines, atol=1e-6)
    np.testing.assert_allclose(ip.sample, samples, atol=1e-6)
    # A constant terrain is the same as a height.
    np.testing.assert_allclose(
        cam.image_to_ground(lines, samples, ConstantHeight(cam.ellipsoid, -2500.0)),
        cam.image_to_ground(lines, samples, -2500.0),
        atol=1e-9,
    )


# ---------------------------------------------------------------------------------------
# The correction (usgscsm's 16 adjustable parameters)
# ---------------------------------------------------------------------------------------


def test_correction_parameters():
    c = CsmCorrection.from_array(np.arange(16.0))
    np.testing.assert_array_equal(c.as_array(), np.arange(16.0))
    assert c.omega_m == 6.0 and c.focal_m == 15.0 and not c.is_zero
    assert CsmCorrection().is_zero
    with pytest.raises(InputError, match="16 parameters"):
        CsmCorrection.from_array([1.0, 2.0])
    with pytest.raises(InputError, match="phi_m"):
        CsmCorrection(phi_m=float("nan"))


def test_correction_moves_ground_as_expected(shared, tmp_path):
    cam = CsmLineScanCamera.from_file(
        shared / "data/ctx_syrtis/P15_006844_2009_XN_20N286W.lev1.json"
    )
    lines = np.array([5000.0, 26000.0, 47000.0])
    samples = np.array([2500.0, 1000.0, 4000.0])
    g0 = cam.image_to_ground(lines, samples)
    pos, vel = cam.sensor_state(lines)
    radial = pos / np.linalg.norm(pos, axis=1, keepdims=True)
    cross = np.cross(pos, vel)
    cross /= np.linalg.norm(cross, axis=1, keepdims=True)
    in_track = np.cross(cross, radial)
    # A 100 m in-track position bias moves the ground point 100 m along track.
    moved = cam.with_correction(CsmCorrection(in_track_m=100.0))
    d = moved.image_to_ground(lines, samples) - g0
    np.testing.assert_allclose(np.sum(d * in_track, axis=1), 100.0, atol=0.5)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 100.0, atol=0.5)
    # A cross-track bias of 50 m in the pointing angle phi (rad = 50 / flying height)
    # moves near-nadir ground points by about 50 m.
    tilted = cam.with_correction(CsmCorrection(phi_m=50.0))
    shift = np.linalg.norm(tilted.image_to_ground(lines, samples) - g0, axis=1)
    np.testing.assert_allclose(shift, 50.0, rtol=0.05)
    # A full correction still round-trips, and survives write_isd/read_isd exactly.
    full = cam.with_correction(
        CsmCorrection(
            in_track_m=30.0,
            cross_track_m=-20.0,
            radial_m=5.0,
            in_track_rate_m=3.0,
            cross_track_rate_m=-2.0,
            radial_rate_m=1.0,
            omega_m=12.0,
            phi_m=-8.0,
            kappa_m=6.0,
            omega_rate_m=2.0,
            phi_rate_m=-1.0,
            kappa_rate_m=0.5,
            omega_accel_m=0.3,
            phi_accel_m=-0.2,
            kappa_accel_m=0.1,
            focal_m=0.05,
        )
    )
    g = full.image_to_ground(lines, samples, 200.0)
    assert np.all(np.linalg.norm(g - cam.image_to_ground(lines, samples, 200.0), axis=1) > 10)
    ip = full.ground_to_image(g)
    np.testing.assert_allclose(ip.line, lines, atol=1e-6)
    np.testing.assert_allclose(ip.sample, samples, atol=1e-6)
    again = CsmLineScanCamera.from_file(write_isd(full, tmp_path / "adjusted.json"))
    assert again.correction == full.correction
    np.testing.assert_array_equal(again.image_to_ground(lines, samples, 200.0), g)
    assert isinstance(read_isd(tmp_path / "adjusted.json"), CsmIsd)


def test_write_isd_errors(tmp_path):
    isd = read_isd(_write(tmp_path, make_isd()))
    with pytest.raises(InputError, match="cannot write"):
        write_isd(isd, tmp_path / "missing_dir" / "x.json")
    with pytest.raises(InputError, match="expected a CsmLineScanCamera"):
        write_isd({"name_model": "x"}, tmp_path / "x.json")  # type: ignore[arg-type]


def test_ellipsoid_from_isd(tmp_path):
    cam = CsmLineScanCamera.from_file(_write(tmp_path, make_isd()))
    assert cam.ellipsoid == Ellipsoid(1e6, 1e6, cam.ellipsoid.name)


def test_body_fixed_isd_equals_j2000_isd(tmp_path):
    # The same camera given in J2000 with a body rotation, and directly body-fixed.
    d = make_isd()
    body_q = Rotation.from_euler("z", 30.0, degrees=True)  # J2000 -> body
    d["body_rotation"]["quaternions"] = [body_q.as_quat(scalar_first=True).tolist()] * 16
    fixed = copy.deepcopy(d)
    rb = body_q.as_matrix()
    for key in ("positions", "velocities"):
        fixed["instrument_position"][key] = (
            np.array(d["instrument_position"][key]) @ rb.T
        ).tolist()
    sensor = Rotation.from_quat(
        np.array(d["instrument_pointing"]["quaternions"]), scalar_first=True
    )
    fixed["instrument_pointing"]["quaternions"] = (
        (sensor * body_q.inv()).as_quat(scalar_first=True).tolist()
    )
    fixed["instrument_position"]["reference_frame"] = 10  # body_rotation's frame
    fixed["instrument_pointing"]["reference_frame"] = 10
    a = CsmLineScanCamera.from_file(_write(tmp_path, d, "j2000.json"))
    b = CsmLineScanCamera.from_file(_write(tmp_path, fixed, "fixed.json"))
    lines, samples = np.linspace(0.5, 15.5, 6), np.linspace(15.5, 0.5, 6)
    np.testing.assert_allclose(
        a.image_to_ground(lines, samples), b.image_to_ground(lines, samples), atol=1e-6
    )


def test_platform_flag_selects_lagrange_order(tmp_path):
    d = make_isd()
    d["platform_flag"] = 0
    cam = CsmLineScanCamera.from_file(_write(tmp_path, d))
    assert cam._ephemeris.order == 4 and cam.isd.platform_flag == 0
    ip = cam.ground_to_image(cam.image_to_ground([3.5, 12.5], [2.0, 14.0]))
    np.testing.assert_allclose(ip.line, [3.5, 12.5], atol=1e-6)


def test_velocity_includes_body_rotation(shared):
    # Body-fixed velocity = derivative of the body-fixed position: right only with the
    # -omega x r term of the J2000 -> Mars rotation (without it the error is ~250 m/s).
    cam = CsmLineScanCamera.from_file(
        shared / "data/ctx_syrtis/P15_006844_2009_XN_20N286W.lev1.json"
    )
    lines = np.array([15000.0, 26000.0, 37000.0])
    half = 0.5 / cam.isd.line_scan_rate[0, 2]  # half a second, in lines
    numeric = cam.sensor_position(lines + half) - cam.sensor_position(lines - half)
    _, vel = cam.sensor_state(lines)
    assert np.max(np.linalg.norm(vel - numeric, axis=1)) < 0.01
