"""One rule at DEM holes: cameras and the front end give the same ground points.

``camera.image_to_ground(.., dem)`` (the camera's rays through
:func:`planetref.geometry.terrain.intersect_terrain`) and the front end's
``rays_to_ground`` (``GridTerrain.intersect_rays``) must agree ray by ray on a DEM with
NaN cells, including the rays whose path meets a hole; and a hole may only remove points
(those it could hide), never move one.
"""

from __future__ import annotations

import numpy as np
import pytest

from planetref.camera.mapping import rays_to_ground
from planetref.camera.orbit import OrbitGeometry, ccd_row, orbit_camera
from planetref.camera.rpc import RpcCamera, fit_rpc
from planetref.geometry.geodesy import (
    MARS_IAU2015_SPHERE,
    ray_ellipsoid_intersection,
    xyz_to_lonlat,
)
from planetref.geometry.terrain import first_crossing, intersect_terrain
from planetref.raster.dem import GridTerrain

LAT, LON = 20.0, 74.0
R = MARS_IAU2015_SPHERE.semi_major_m
RES = 50.0
N = 120


def _dem(holes: list[tuple[int, int]]) -> GridTerrain:
    yy, xx = np.mgrid[0:N, 0:N].astype(float)
    h = 800.0 * np.sin(xx / 9.0) * np.cos(yy / 13.0) + 3.0 * xx
    for r, c in holes:
        h[r, c] = np.nan
    x0 = np.radians(LON) * R - N / 2 * RES
    y0 = np.radians(LAT) * R + N / 2 * RES
    return GridTerrain(h, (x0, RES, 0.0, y0, 0.0, -RES), "IAU_2015:49910")


@pytest.fixture(scope="module")
def camera():
    ccds = ccd_row(1, 400, 800, 0.010)
    cam, _ = orbit_camera(OrbitGeometry(LAT, LON, 30.0), focal_length_mm=5300.0, ccds=ccds)
    return cam


def _image_points(camera, dem_with_holes):
    """A lattice over the image plus, for every hole, the pixels that see its cell."""
    n_lines, n_samples = camera.image_size()
    gl, gs = np.meshgrid(np.linspace(1, n_lines - 1, 60), np.linspace(1, n_samples - 1, 30))
    return gl.ravel(), gs.ravel()


def test_camera_and_front_end_agree_at_holes(camera) -> None:
    clean = _dem([])
    # Holes inside the camera's footprint (pixels (row, col) of the 120 x 120 grid).
    holes = [(60, 60), (61, 60), (55, 52), (66, 67), (58, 70)]
    dem = _dem(holes)
    line, sample = _image_points(camera, dem)
    ccd = camera.ccd_names[0]
    via_camera = camera.image_to_ground(line, sample, dem, on_miss="nan")
    via_front_end = rays_to_ground(camera, ccd, line, sample, dem)
    reference = camera.image_to_ground(line, sample, clean, on_miss="nan")
    miss_cam = ~np.isfinite(via_camera).all(axis=1)
    miss_fe = ~np.isfinite(via_front_end).all(axis=1)
    # The same rays miss, and the same points are found to well under a millimetre.
    np.testing.assert_array_equal(miss_cam, miss_fe)
    assert 0 < miss_cam.sum() < len(line) // 4  # the holes do remove some points
    assert np.isfinite(reference).all()  # ... which the DEM without holes has
    np.testing.assert_allclose(via_camera[~miss_cam], via_front_end[~miss_cam], atol=1e-5, rtol=0)
    # A hole never moves a point: every point found is the hole-free DEM's point.
    np.testing.assert_allclose(via_camera[~miss_cam], reference[~miss_cam], atol=1e-4, rtol=0)
    # Only rays that come near a hole are removed: their hit on the clean DEM lies within
    # a few DEM cells of one (the path from the DEM's top down is < 2 cells long here).
    x, y, _ = clean.xyz_to_map(reference[miss_cam])
    r, c = clean.map_to_pixel(x, y)
    hole_rc = np.array(holes, dtype=float)
    dist = np.min(np.hypot(r[:, None] - hole_rc[:, 0], c[:, None] - hole_rc[:, 1]), axis=1)
    assert dist.max() < 4.0


def test_marched_rays_follow_the_same_rule(camera) -> None:
    """Oblique rays (the grid's guess declines them) and the guess agree with the rule."""
    holes = [(60, 60), (61, 60)]
    dem = _dem(holes)
    n_lines, n_samples = camera.image_size()
    gl, gs = np.meshgrid(np.linspace(1, n_lines - 1, 16), np.linspace(1, n_samples - 1, 8))
    o, d = camera.look_rays(gl.ravel(), gs.ravel())
    # Tilt the rays 35 degrees eastwards about their footprint: marched, not guessed.
    p = intersect_terrain(o, d, _dem([]))
    east = np.array([-np.sin(np.radians(LON)), np.cos(np.radians(LON)), 0.0])
    o2 = o + east * np.linalg.norm(o - p, axis=1)[:, None] * np.tan(np.radians(35))
    d2 = p - o2
    assert not np.isfinite(dem.first_hit_guess(o2, d2 / np.linalg.norm(d2, axis=1)[:, None])).any()
    hits = dem.intersect_rays(o2, d2)
    # Reference: a brute-force march in 2 cm steps with the rule written out.
    s = np.arange(0.0, 1600.0, 0.02)
    unit = d2 / np.linalg.norm(d2, axis=1)[:, None]
    s_top = ray_ellipsoid_intersection(o2, unit, dem.ellipsoid, dem.max_height_m + 5.0)
    n_miss = 0
    for k in range(len(o2)):
        pts = o2[k] + (s_top[k] + s)[:, None] * unit[k]
        lon, lat, h = xyz_to_lonlat(pts, dem.ellipsoid)
        hd = dem.height(lon, lat)
        below = h <= hd
        unknown = ~np.isfinite(hd) & (h <= dem.max_height_m)
        first = np.flatnonzero(below | unknown)
        expect_miss = first.size == 0 or unknown[first[0]]
        assert expect_miss == (not hits.hit[k]), k
        if expect_miss:
            n_miss += 1
        else:
            assert np.linalg.norm(pts[first[0]] - hits.xyz[k]) < 0.03
    assert n_miss > 0


def test_rpc_height_stepping_obeys_the_hole_rule(camera) -> None:
    """An RPC fitted to the camera misses exactly where the camera does (up to the fit)."""
    holes = [(60, 60), (61, 60), (55, 52)]
    dem = _dem(holes)
    rpc, report = fit_rpc(camera, height_range_m=(-1000.0, 1500.0))
    assert report.check_rms_px < 1e-3
    rpc_cam = RpcCamera(rpc, camera.ellipsoid, camera.latitude_kind, camera.image_size())
    line, sample = _image_points(camera, dem)
    a = camera.image_to_ground(line, sample, dem, on_miss="nan")
    b = rpc_cam.image_to_ground(line, sample, dem, on_miss="nan")
    miss_a = ~np.isfinite(a).all(axis=1)
    miss_b = ~np.isfinite(b).all(axis=1)
    assert miss_a.sum() > 0
    # The RPC's line of sight differs from the camera's by the fit error (mm), so only
    # rays that graze a hole's edge may differ.
    assert np.sum(miss_a != miss_b) <= 2
    both = ~miss_a & ~miss_b
    assert np.max(np.linalg.norm(a[both] - b[both], axis=1)) < 0.05


def test_first_crossing_rule_on_a_profile() -> None:
    """The rule on a hand-made profile: a hole above max height is harmless."""

    def profile(idx, s):
        h_path = 100.0 - s
        terrain = np.where((s > 20.0) & (s < 30.0), np.nan, 50.0)
        # Ray 1's hole is high, where the path is still above the terrain's top (80 m).
        terrain = np.where(
            (idx == 1) & (s > 5) & (s < 15), np.nan, np.where(idx == 1, 50.0, terrain)
        )
        return h_path, terrain

    s = first_crossing(profile, np.zeros(2), np.full(2, 100.0), 1.0, max_height_m=80.0, tol_m=1e-9)
    assert np.isnan(s[0])  # meets the hole at s = 20 (height 80) before the crossing
    assert s[1] == pytest.approx(50.0, abs=1e-8)
