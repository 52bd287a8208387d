from __future__ import annotations

import math

import numpy as np
import pytest

from planetref.geometry.rotations import rotation_matrix
from planetref.raster.dem import GridTerrain
from planetref.simulate.config import SimulationConfig
from planetref.simulate.grid import MapGrid, local_crs_wkt
from planetref.simulate.measure import measure_initial_errors
from planetref.simulate.orbit import (
    MARS_ROTATION_RAD_S,
    CircularOrbit,
    angles_from_rotation,
    build_strip_cameras,
)
from planetref.simulate.render import corner_rays

NO_ERRORS = {
    "position_bias_m": [0.0, 0.0, 0.0],
    "position_drift_m_per_s": [0.0, 0.0, 0.0],
    "attitude_bias_urad": [0.0, 0.0, 0.0],
    "attitude_drift_urad_per_s": [0.0, 0.0, 0.0],
    "focal_length_error_ppm": 0.0,
}


def _flat_dem(cfg: SimulationConfig) -> GridTerrain:
    grid = MapGrid(-3000.0, 3000.0, 10.0, 600, 600)
    return GridTerrain(
        np.zeros(grid.shape, np.float32),
        grid.transform,
        local_crs_wkt(cfg.site.lat_deg, cfg.site.lon_deg),
    )


def test_angles_from_rotation_inverts_rotation_matrix() -> None:
    rng = np.random.default_rng(0)
    ang = rng.uniform(-1.2, 1.2, (20, 3))
    back = angles_from_rotation(rotation_matrix(ang[:, 0], ang[:, 1], ang[:, 2]))
    np.testing.assert_allclose(back, ang, atol=1e-12)


def test_orbit_is_circular_and_tracks_the_heading() -> None:
    orb = CircularOrbit(25.0, 110.0, -8.0, 265e3, body_rotation=True)
    t = np.linspace(-2.0, 2.0, 9)
    r = np.linalg.norm(orb.position(t), axis=1)
    np.testing.assert_allclose(r, orb.radius_m, rtol=1e-12)
    # Body-fixed velocity at t = 0 is horizontal, along the heading.
    frame = orb.frame(np.zeros(1))[0]
    lat, lon = math.radians(25.0), math.radians(110.0)
    north = np.array(
        [-math.sin(lat) * math.cos(lon), -math.sin(lat) * math.sin(lon), math.cos(lat)]
    )
    assert math.degrees(math.acos(frame[:, 0] @ north)) == pytest.approx(8.0, abs=1e-6)
    # Numerical derivative of the position is the velocity.
    dt = 1e-3
    v_num = (orb.position(np.array([dt])) - orb.position(np.array([-dt]))) / (2 * dt)
    np.testing.assert_allclose(v_num[0], orb.velocity(np.zeros(1))[0], rtol=1e-7)
    assert 3000 < orb.ground_speed() < 3400
    assert MARS_ROTATION_RAD_S == pytest.approx(7.088218e-5, rel=1e-6)


NO_MISMATCH = {
    "ccd_offset_px": 0.0,
    "ccd_rotation_urad": 0.0,
    "ccd_scale_ppm": 0.0,
    "line_rate_error_ppm": 0.0,
    "position_oscillation_m": [0.0, 0.0, 0.0],
    "attitude_oscillation_urad": [0.0, 0.0, 0.0],
    "radial_k1_px": 0.0,
    "radial_k2_px": 0.0,
    "decentering_px": 0.0,
}


def test_truth_camera_geometry_and_jitter(mini_config) -> None:  # type: ignore[no-untyped-def]
    cfg = mini_config(
        jitter=[{"axis": "roll", "amplitude_urad": 20.0, "frequency_hz": 40.0}],
        initial_errors=NO_ERRORS,
        truth_mismatch=NO_MISMATCH,  # the jitter alone
    )
    sc = build_strip_cameras(cfg, cfg.strips[0], np.random.default_rng(0))
    cam = sc.truth
    f = cfg.camera.pixel_pitch_mm * cfg.orbit.altitude_m / cfg.camera.gsd_m
    assert cam.interior.focal_length_mm == pytest.approx(f)
    dem = _flat_dem(cfg)
    # Pixel size on the ground is the configured GSD (at nadir, on the datum), seen with
    # the jitter-free camera (the initial one, here without errors).
    _, n_samples = cam.image_size("ccd2")
    p = sc.initial.image_to_ground([48.5, 48.5, 49.5], [32.5, 33.5, 32.5], 0.0, ccd="ccd2")
    assert np.linalg.norm(p[1] - p[0]) == pytest.approx(cfg.camera.gsd_m, rel=1e-3)
    assert np.linalg.norm(p[2] - p[0]) == pytest.approx(cfg.camera.gsd_m, rel=2e-3)
    # CCDs overlap by the configured number of samples: the last 8 samples of ccd1 see
    # the same ground as the first 8 of ccd2 (at a different time: the CCDs are staggered,
    # so with jitter the overlap shifts; check it without).
    g = sc.initial.image_to_ground([48.5], [n_samples - 4.0], 0.0, ccd="ccd1")
    ip = sc.initial.ground_to_image(g, ccd="ccd2")
    assert ip.sample[0] == pytest.approx(cfg.camera.overlap_samples - 4.0, abs=0.05)
    # The jitter-free initial camera and the truth differ by the jitter (20 urad x 265 km).
    e = measure_initial_errors(cam, sc.initial, dem, sc.orbit.frame(np.zeros(1))[0], 12)
    assert e["ground_m"]["cross"]["max"] == pytest.approx(20e-6 * 265e3, rel=0.25)
    assert e["ground_m"]["along"]["max"] < 0.2


def test_renderer_rays_equal_look_rays(mini_config) -> None:  # type: ignore[no-untyped-def]
    cfg = mini_config()
    cam = build_strip_cameras(cfg, cfg.strips[0], np.random.default_rng(0)).truth
    lines = np.array([0.0, 13.25, 95.0])
    samples = np.array([0.0, 31.5, 64.0])
    o, d = corner_rays(cam, "ccd3", lines, samples)
    ll, ss = np.meshgrid(lines, samples, indexing="ij")
    o2, d2 = cam.look_rays(ll.ravel(), ss.ravel(), ccd="ccd3")
    np.testing.assert_allclose(d.reshape(-1, 3), d2, atol=1e-12)
    np.testing.assert_allclose(np.repeat(o, 3, axis=0), o2, atol=1e-6)


@pytest.mark.parametrize(
    ("errors", "check"),
    [
        ({"position_bias_m": [40.0, 0.0, 0.0]}, {"along": 40.0, "cross": 0.0}),
        ({"position_bias_m": [0.0, -25.0, 0.0]}, {"along": 0.0, "cross": -25.0}),
        ({"attitude_bias_urad": [150.0, 0.0, 0.0]}, {"along": 0.0, "cross": 150e-6 * 265e3}),
        ({"attitude_bias_urad": [0.0, -250.0, 0.0]}, {"along": 250e-6 * 265e3, "cross": 0.0}),
    ],
)
def test_initial_camera_is_off_by_the_configured_amounts(  # type: ignore[no-untyped-def]
    mini_config, errors, check
) -> None:
    cfg = mini_config(initial_errors={**NO_ERRORS, **errors}, jitter=[], truth_mismatch=NO_MISMATCH)
    sc = build_strip_cameras(cfg, cfg.strips[0], np.random.default_rng(0))
    e = measure_initial_errors(
        sc.truth, sc.initial, _flat_dem(cfg), sc.orbit.frame(np.zeros(1))[0], 5
    )
    g = e["ground_m"]
    assert g["along"]["mean"] == pytest.approx(check["along"], abs=0.5)
    assert g["cross"]["mean"] == pytest.approx(check["cross"], abs=0.5)


def test_focal_length_error_scales_the_swath(mini_config) -> None:  # type: ignore[no-untyped-def]
    cfg = mini_config(
        initial_errors={**NO_ERRORS, "focal_length_error_ppm": 1000.0},
        jitter=[],
        truth_mismatch=NO_MISMATCH,
    )
    sc = build_strip_cameras(cfg, cfg.strips[0], np.random.default_rng(0))
    e = measure_initial_errors(
        sc.truth, sc.initial, _flat_dem(cfg), sc.orbit.frame(np.zeros(1))[0], 5
    )
    # A longer focal length shrinks the ground swath by 1e-3: the outermost sample of
    # the outer CCDs (about 88 m from the centre) moves by about 0.09 m.
    half = 0.5 * (3 * 64 - 2 * 8) * cfg.camera.gsd_m
    assert e["ground_m"]["cross"]["max"] == pytest.approx(1e-3 * half, rel=0.1)
