"""True geolocation error in pixels: the true camera's footprint, never an extrapolation."""

import numpy as np
import pytest

from planetref.adjust.metrics import geolocation_error, image_grid
from planetref.camera.orbit import OrbitGeometry, ccd_row, orbit_camera


@pytest.fixture(scope="module")
def camera():
    ccds = ccd_row(1, 512, 3000, 0.010, overlap_px=0, stagger_mm=0.0)
    cam, _ = orbit_camera(
        OrbitGeometry(20.0, 74.0, 30.0), focal_length_mm=4640.0, ccds=ccds, n_nodes=6
    )
    return cam


def _gsd(cam):
    g = cam.image_to_ground(np.array([1500.0, 1500.0]), np.array([256.0, 257.0]), 0.0)
    return float(np.linalg.norm(g[1] - g[0]))


class _Recorder:
    """A camera proxy recording every image line it is asked about."""

    def __init__(self, cam):
        self.cam, self.lines = cam, []

    def __getattr__(self, name):
        return getattr(self.cam, name)

    def image_to_ground(self, line, sample, *args, **kw):
        self.lines.append(np.asarray(line, float))
        return self.cam.image_to_ground(line, sample, *args, **kw)

    def ground_to_image(self, xyz, **kw):
        ip = self.cam.ground_to_image(xyz, **kw)
        self.lines.append(ip.line)
        return ip


@pytest.mark.parametrize("angle, delta", [(3, 1e-3), (4, 1e-3), (3, 5e-3)])
def test_pixels_are_the_ground_error_in_true_pixels(camera, angle, delta):
    """A bent strip end (last node's attitude off by 1-5 mrad): px x GSD == metres.

    The old figure (the adjusted camera's projection of the true ground point) gave
    53 px for 57 m at 0.57 m/px with the 1 mrad bend in angle 3 and 115 px for 286 m
    with 5 mrad: its line solution on the bent end is not the pixel's displacement.
    """
    nodes = camera.nodes.copy()
    nodes[-1, angle] += delta
    bent = camera.replace(nodes=nodes)
    rec = _Recorder(camera)
    g = geolocation_error(bent, rec, terrain=0.0)
    assert g["rms_m"] > 50.0
    assert g["rms_px"] * _gsd(camera) == pytest.approx(g["rms_m"], rel=0.01)
    assert g["max_px"] * _gsd(camera) == pytest.approx(g["max_m"], rel=0.02)
    lines = np.concatenate(rec.lines)
    assert lines.min() >= 0.0 and lines.max() <= camera.image_size(None)[0]


def test_small_smooth_error_agrees_with_the_projection(camera):
    """For a bias-like error both definitions agree (to 1 %)."""
    nodes = camera.nodes.copy()
    nodes[:, :3] += (30.0, -20.0, 10.0)
    nodes[:, 3:] += (2e-5, -3e-5, 1e-5)
    shifted = camera.replace(nodes=nodes)
    g = geolocation_error(shifted, camera, terrain=0.0)
    line, sample = image_grid(camera)
    ip = shifted.ground_to_image(camera.image_to_ground(line, sample, 0.0))
    old = float(np.sqrt(np.mean((ip.line - line) ** 2 + (ip.sample - sample) ** 2)))
    assert g["rms_px"] == pytest.approx(old, rel=0.01)
    assert g["rms_px"] > 10.0
