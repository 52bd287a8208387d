"""Lens distortion of the true camera: exact both ways, written to file, as configured."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from planetref.camera.linescan import LineScanCamera
from planetref.camera.linescan.lens import detector_position, displacement, ideal_position
from planetref.errors import InputError
from planetref.simulate.config import load_config
from planetref.simulate.orbit import build_strip_cameras
from planetref.simulate.scene import stream

NO_LENS = {"truth_mismatch": {"radial_k1_px": 0.0, "radial_k2_px": 0.0, "decentering_px": 0.0}}


def _truth(cfg):  # type: ignore[no-untyped-def]
    return build_strip_cameras(cfg, cfg.strips[0], stream(0, "strip", 0), stream(0, "mismatch", 0))


def test_inverse_and_displacement_formula() -> None:
    rng = np.random.default_rng(3)
    x, y = rng.uniform(-9.0, 9.0, 500), rng.uniform(-9.0, 9.0, 500)
    k = (3e-5, -2e-8, 4e-6, -7e-6)
    xi, yi = ideal_position(x, y, k)
    xd, yd = detector_position(xi, yi, k, r_clip=13.0)
    np.testing.assert_allclose(xd, x, atol=1e-12)
    np.testing.assert_allclose(yd, y, atol=1e-12)
    # Independent check of the radial term: along the y axis only k1 y^3 + k2 y^5.
    dx, dy = displacement(np.zeros(1), np.array([5.0]), (k[0], k[1], 0.0, 0.0))
    assert dx[0] == 0.0 and dy[0] == pytest.approx(k[0] * 125.0 + k[1] * 3125.0, rel=1e-12)


def test_distorted_truth_projects_exactly_and_round_trips_through_json(tmp_path: Path) -> None:
    sc = _truth(load_config("tiny", difficulty="hard"))
    cam = sc.truth
    assert all(any(c.distortion) for c in cam.ccds)
    assert not any(any(c.distortion) for c in sc.initial.ccds)  # never in the initial camera
    rng = np.random.default_rng(0)
    for c in cam.ccds:
        line = rng.uniform(0.0, c.n_lines, 300)
        sample = rng.uniform(0.0, c.n_samples, 300)
        g = cam.image_to_ground(line, sample, 150.0, ccd=c.name)
        ip = cam.ground_to_image(g, ccd=c.name)
        assert np.max(np.hypot(ip.line - line, ip.sample - sample)) < 1e-8
    path = tmp_path / "truth.json"
    cam.to_json(path)
    back = LineScanCamera.from_json(path)
    assert [c.distortion for c in back.ccds] == [c.distortion for c in cam.ccds]
    # An undistorted camera's file has no distortion entry (older files read unchanged).
    sc.initial.to_json(tmp_path / "initial.json")
    doc = json.loads((tmp_path / "initial.json").read_text())
    assert all("distortion" not in c for c in doc["ccds"])
    with pytest.raises(InputError, match="distortion"):
        replace(cam.ccds[0], distortion=(1.0, float("nan"), 0.0, 0.0))


@pytest.mark.parametrize("k1_px, k2_px", [(1.0, 0.0), (0.0, 0.5), (-1.5, 0.25)])
def test_radial_distortion_has_the_configured_size_at_the_field_edge(k1_px, k2_px) -> None:
    """At the row's end farthest from the axis the truth's image moves by k1 + k2 px."""
    over = {
        "truth_mismatch": {
            "radial_k1_px": k1_px,
            "radial_k2_px": k2_px,
            "decentering_px": 0.0,
            "ccd_offset_px": 0.0,
            "ccd_rotation_urad": 0.0,
            "ccd_scale_ppm": 0.0,
        }
    }
    lens = _truth(load_config("tiny", over)).truth
    flat = {**over["truth_mismatch"], **NO_LENS["truth_mismatch"]}
    plain = _truth(load_config("tiny", {"truth_mismatch": flat})).truth
    # The far end of the last CCD: the ground that the distorted truth's edge pixel sees
    # is where the undistorted truth sees k1 + k2 px further out along the row.
    c = lens.ccds[-1]
    line = np.array([0.5 * c.n_lines])  # on a search-grid node (see the test below)
    g = lens.image_to_ground(line, np.array([float(c.n_samples)]), 0.0, ccd=c.name)
    moved = plain.ground_to_image(g, ccd=c.name).sample[0] - c.n_samples
    assert abs(moved) == pytest.approx(abs(k1_px + k2_px), abs=1e-4)


def test_round_trip_on_search_grid_lines_and_image_edges() -> None:
    """Ground points whose true line is a line of the search grid (or the image's first
    or last line) project back there: rounding may give the residual at the grid line
    either sign, and the root on the bracket's end must still be accepted."""
    cam = _truth(load_config("tiny")).truth
    kern = cam.kernel
    grid = np.linspace(kern.line_lo, kern.line_hi, 33)  # search_lines' default grid
    for c in cam.ccds:
        inside = grid[(grid >= 0.0) & (grid <= c.n_lines)]
        lines = np.concatenate([inside, [0.0, float(c.n_lines), 0.5 * c.n_lines]])
        line = np.repeat(lines, 3)
        sample = np.tile([0.0, 0.5 * c.n_samples, float(c.n_samples)], len(lines))
        g = cam.image_to_ground(line, sample, 0.0, ccd=c.name)
        ip = cam.ground_to_image(g, ccd=c.name)
        assert ip.valid.all(), line[~ip.valid]
        assert np.max(np.abs(ip.line - line)) < 1e-6
        assert np.max(np.abs(ip.sample - sample)) < 1e-6
