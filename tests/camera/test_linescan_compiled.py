"""The compiled (numba) line-scan kernel against the numpy reference kernel."""

import logging

import numpy as np
import pytest

from planetref.camera.linescan import compiled
from planetref.camera.orbit import OrbitGeometry, ccd_row, orbit_camera
from planetref.geometry.geodesy import ray_ellipsoid_intersection

pytestmark = pytest.mark.skipif(
    not compiled.available(), reason="numba is not installed (the numpy kernel is used)"
)


@pytest.fixture(scope="module")
def setup():
    ccds = ccd_row(3, 512, 2000, 0.010, overlap_px=16, stagger_mm=1.0)
    cam, _ = orbit_camera(
        OrbitGeometry(20.0, 74.0, 30.0), focal_length_mm=4640.0, ccds=ccds, n_nodes=8
    )
    rng = np.random.default_rng(3)
    nodes = cam.nodes.copy()
    nodes[:, :3] += rng.normal(0, 30, (8, 3))
    nodes[:, 3:] += rng.normal(0, 3e-5, (8, 3))
    cam = cam.replace(nodes=nodes)
    n = 400
    line = rng.uniform(-50, 2050, n)  # a few beyond the imaged lines, still in the span
    sample = rng.uniform(0, 512, n)
    o, d = cam.look_rays(line, sample, ccd="ccd2")
    s = ray_ellipsoid_intersection(o, d, cam.ellipsoid, rng.uniform(-3000, 3000, n))
    xyz = o + s[:, None] * d
    kern = cam.kernel
    return cam, kern, kern.eo_poly(cam.nodes), cam.interior.as_array(), cam.ccds[1], xyz, line


def _both(kern, poly, io, ccd, xyz, guess, rate):
    a = kern.project_with_partials(poly, io, ccd, xyz, guess.copy(), rate, use_compiled=True)
    b = kern.project_with_partials(poly, io, ccd, xyz, guess.copy(), rate, use_compiled=False)
    return a, b


def test_same_point_same_values_and_partials(setup):
    """From the same converged guesses both evaluate at the same line: ~1e-12 relative."""
    _, kern, poly, io, ccd, xyz, line = setup
    ref = kern.project_with_partials(poly, io, ccd, xyz, line.copy(), None, use_compiled=False)
    a, b = _both(kern, poly, io, ccd, xyz, ref.line, ref.rate)
    assert np.array_equal(a.valid, b.valid) and a.valid.all()
    assert np.array_equal(a.start, b.start)
    scale_line = np.abs(b.line).max()
    assert np.abs(a.line - b.line).max() <= 1e-12 * scale_line + 1e-9
    assert np.abs(a.sample - b.sample).max() <= 1e-12 * np.abs(b.sample).max() + 1e-9
    assert np.abs(a.rate - b.rate).max() <= 1e-12 * np.abs(b.rate).max()
    assert np.abs(a.weights - b.weights).max() <= 1e-12
    scale = np.abs(b.partials).max(axis=0)  # per row and column, (2, 15)
    err = np.abs(a.partials - b.partials).max(axis=0)
    # 1e-9 px absolute: d sample / d angle carries the offset at the root itself, which
    # is zero up to the rounding of the 3.4e6 m coordinates (~1e-10 px).
    assert np.all(err <= 1e-12 * scale + 1e-9), err / np.where(scale > 0, scale, 1)
    # The partials are not trivially zero (a test that cannot fail is a defect).
    assert scale[0, 3] > 1e4 and scale[1, 4] > 1e4  # d line / d phi, d sample / d omega


def test_points_along_the_strip_match_and_tau_gives_the_weights(setup):
    """In the adjustment's order (by line): the same values to ~1e-12 relative, and
    ``tau`` gives the Lagrange weights through the window's basis coefficients (the
    solver's moment form of the normal equations relies on it)."""
    _, kern, poly, io, ccd, xyz, line = setup
    order = np.argsort(line)
    xyz, line = xyz[order], line[order]
    ref = kern.project_with_partials(poly, io, ccd, xyz, line.copy(), None, use_compiled=False)
    a, b = _both(kern, poly, io, ccd, xyz, ref.line, ref.rate)
    assert np.abs(a.line - b.line).max() <= 1e-12 * np.abs(b.line).max() + 1e-9
    assert np.abs(a.sample - b.sample).max() <= 1e-12 * np.abs(b.sample).max() + 1e-9
    scale = np.abs(b.partials).max(axis=0)
    assert np.all(np.abs(a.partials - b.partials).max(axis=0) <= 1e-12 * scale + 1e-9)
    assert np.abs(a.tau - b.tau).max() <= 1e-12 * np.abs(b.tau).max()
    coef = kern.windows.coef[a.start]  # (m, k basis, k powers)
    w = np.einsum("mjq,mq->mj", coef, a.tau[:, None] ** np.arange(kern.k))
    assert np.abs(w - a.weights).max() < 1e-12
    assert np.abs(a.tau).max() > 0 and np.all(np.abs(a.weights.sum(axis=1) - 1.0) < 1e-12)


def test_cold_guesses_converge_to_the_same_projection(setup):
    """From poor guesses (or none) the chord iterations differ only by rounding."""
    _, kern, poly, io, ccd, xyz, line = setup
    for guess in (line + 7.0, np.full(len(line), np.nan)):
        a, b = _both(kern, poly, io, ccd, xyz, guess, None)
        assert np.array_equal(a.valid, b.valid)
        assert np.abs(a.line - line).max() < 1e-6  # the true lines
        assert np.abs(a.line - b.line).max() < 1e-8
        assert np.abs(a.sample - b.sample).max() < 1e-8
        scale = np.abs(b.partials).max(axis=0)
        assert np.all(np.abs(a.partials - b.partials).max(axis=0) <= 1e-8 * scale + 1e-8)


def test_project_without_partials_and_invalid_points(setup):
    cam, kern, poly, io, ccd, xyz, line = setup
    p = xyz.copy()
    centre = cam.exterior(np.array([line[0]]))[0][0, :3]
    p[0] = 2.0 * centre - p[0]  # mirrored through the camera: behind it
    p[1] = xyz[1] + 3e5 * (cam.nodes[-1, :3] - cam.nodes[0, :3]) / np.linalg.norm(
        cam.nodes[-1, :3] - cam.nodes[0, :3]
    )  # 300 km along track: beyond the node span
    guess = line.copy()
    rate = None
    a = kern.project(poly, io, ccd, p, guess.copy(), rate, use_compiled=True)
    b = kern.project(poly, io, ccd, p, guess.copy(), rate, use_compiled=False)
    assert not a[2][0] and not a[2][1]
    assert np.array_equal(a[2], b[2]) and a[2][2:].all()
    ok = b[2]
    for x, y in zip(a[:2], b[:2], strict=True):
        assert np.abs(x[ok] - y[ok]).max() < 1e-8
    # The chord rate is a one-line secant: a difference of two offsets (~1e-10 px each).
    assert np.abs(a[3][ok] - b[3][ok]).max() <= 1e-9
    full = kern.project_with_partials(poly, io, ccd, p, guess.copy(), None, use_compiled=True)
    assert np.array_equal(full.valid, ok)


def test_numpy_fallback_logs_once_and_still_projects(setup, monkeypatch, caplog):
    import sys

    _, kern, poly, io, ccd, xyz, line = setup
    monkeypatch.setitem(sys.modules, "planetref.camera.linescan._numba_kernel", None)
    from planetref.runtime.optional import optional_module

    # The one loader, uncached: a twin that cannot be imported logs one line and is None.
    with caplog.at_level(logging.INFO, logger="planetref"):
        assert (
            optional_module.__wrapped__(
                "planetref.camera.linescan._numba_kernel", "compiled line-scan kernel"
            )
            is None
        )
    assert [r.message for r in caplog.records if "numpy" in r.message] and len(caplog.records) == 1
    monkeypatch.setattr(compiled, "available", lambda: False)
    a = kern.project_with_partials(poly, io, ccd, xyz, line.copy(), None)
    b = kern.project_with_partials(poly, io, ccd, xyz, line.copy(), None, use_compiled=False)
    assert np.array_equal(a.line, b.line) and np.array_equal(a.partials, b.partials)


def test_ccds_with_lens_distortion_run_on_numpy(setup):
    """The compiled twin has no lens model: distorted CCDs (simulation truths) use numpy."""
    from dataclasses import replace

    _, kern, poly, io, ccd, xyz, line = setup
    dist = replace(ccd, distortion=(2e-7, 0.0, 1e-7, 0.0))
    a = kern.project_with_partials(poly, io, dist, xyz, line.copy(), None)
    b = kern.project_with_partials(poly, io, dist, xyz, line.copy(), None, use_compiled=False)
    c = kern.project_with_partials(poly, io, ccd, xyz, line.copy(), None, use_compiled=False)
    assert np.array_equal(a.line, b.line) and np.array_equal(a.partials, b.partials)
    assert np.abs(a.sample - c.sample).max() > 1e-4  # the distortion is really applied
