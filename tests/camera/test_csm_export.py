"""A native strip camera written as USGS CSM line-scan ISDs and read back (issue 15, item 4).

The ISD of every CCD, read by planetref's CSM reader (which reproduces usgscsm's
arithmetic), must project the same ground points to the same image points as the native
camera, to <= 1e-3 pixel.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from planetref.camera.csm import CsmLineScanCamera, read_isd
from planetref.camera.csm.export import (
    isd_agreement_px,
    isd_file_name,
    linescan_to_isd,
    write_linescan_isds,
)
from planetref.camera.linescan import CcdGeometry, InteriorOrientation, LineRateTable
from planetref.camera.orbit import OrbitGeometry, ccd_row, orbit_camera
from planetref.errors import InputError

HEIGHTS = (-2500.0, 0.0, 3000.0)


def _strip(jitter_rad: float = 0.0):
    """A HiRIC-like three-CCD strip with a stagger, a rotated CCD, an offset principal
    point, a line-rate change halfway (two table rows) and adjusted orientation: smooth
    corrections (bias + drift of position and attitude), plus optional random attitude
    corrections per node (``jitter_rad``)."""
    ccds = list(ccd_row(3, 2048, 6000, 0.007, overlap_px=48, stagger_mm=0.35))
    ccds[2] = replace(ccds[2], angle_rad=0.002, x_mm=ccds[2].x_mm + 0.01)
    cam, facts = orbit_camera(
        OrbitGeometry(20.0, 74.0, 30.0), focal_length_mm=4640.0, ccds=tuple(ccds), n_nodes=7
    )
    period = facts["line_period_s"]
    t0 = cam.line_rates.time(0.0)
    rates = LineRateTable(((0.0, t0, period), (3000.0, t0 + 3000.0 * period, 1.07 * period)))
    nodes = cam.nodes.copy()
    u = np.linspace(-1.0, 1.0, len(nodes))[:, None]
    nodes[:, :3] += np.array([3.0, -2.0, 1.5]) + u * np.array([-4.0, 2.5, 1.0])  # metres
    nodes[:, 3:] += np.array([2e-5, -1e-5, 3e-5]) + u * np.array([1e-5, 2e-5, -1e-5])  # rad
    rng = np.random.default_rng(3)
    nodes[:, 3:] += rng.normal(scale=jitter_rad, size=(len(nodes), 3))
    # The nodes keep their epochs (the orbit stays smooth in time); their lines move.
    node_lines = rates.line(cam.line_rates.time(cam.node_lines))
    return cam.replace(
        line_rates=rates,
        node_lines=node_lines,
        nodes=nodes,
        interior=InteriorOrientation(4640.0, x0_mm=0.02, y0_mm=-0.05),
    )


def _grid(cam, ccd):
    n_lines, n_samples = cam.image_size(ccd)
    gl, gs = np.meshgrid(
        np.linspace(0.5, n_lines - 0.5, 25), np.linspace(0.5, n_samples - 0.5, 9), indexing="ij"
    )
    return gl.ravel(), gs.ravel()


def test_isds_read_back_agree_with_the_native_camera(tmp_path: Path) -> None:
    cam = _strip()
    assert isinstance(cam.ccd(cam.ccd_names[2]), CcdGeometry)
    paths = write_linescan_isds(cam, tmp_path, "strip 7")
    assert [p.name for p in paths] == [f"strip_7_{c}.json" for c in cam.ccd_names]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in paths)
    worst = 0.0
    for path, ccd in zip(paths, cam.ccd_names, strict=True):
        doc = json.loads(path.read_text())
        assert doc["name_model"] == "USGS_ASTRO_LINE_SCANNER_SENSOR_MODEL"
        assert "sun_position" in doc and doc["image_lines"] == 6000
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no time-coverage warning from the reader
            csm = CsmLineScanCamera.from_file(path)
        assert csm.image_size() == cam.image_size(ccd)
        line, sample = _grid(cam, ccd)
        for h in HEIGHTS:
            xyz = cam.image_to_ground(line, sample, h, ccd=ccd)
            back = csm.ground_to_image(xyz)
            assert back.valid.all()
            err = np.hypot(back.line - line, back.sample - sample)
            worst = max(worst, float(err.max()))
            # And the other way: the CSM camera's rays meet the same ground points.
            xyz2 = csm.image_to_ground(line, sample, h)
            assert np.max(np.linalg.norm(xyz2 - xyz, axis=1)) < 1e-3  # metres
    assert worst <= 1e-3, worst
    print(f"max |CSM - native| over {len(HEIGHTS)} heights x 225 points x 3 CCDs: {worst:.2e} px")


def test_sparser_sampling_stays_within_the_budget() -> None:
    cam = _strip()
    ccd = cam.ccd_names[1]
    isd = linescan_to_isd(cam, ccd, lines_per_sample=256.0)
    csm = CsmLineScanCamera.from_isd(isd)
    line, sample = _grid(cam, ccd)
    xyz = cam.image_to_ground(line, sample, 0.0, ccd=ccd)
    back = csm.ground_to_image(xyz)
    err = np.hypot(back.line - line, back.sample - sample)
    assert err.max() <= 1e-3
    # The check can fail: a half-line timing slip (a centre-of-pixel mistake) is seen.
    table = isd.line_scan_rate.copy()
    table[:, 1] += 0.5 * table[:, 2]
    slipped = replace(isd, line_scan_rate=table)
    # 0.5 px wherever the slipped ISD projects; at line 3000.5 (half a line past the
    # line-time table's segment boundary, a point of the check's grid) it cannot: inf
    assert isd_agreement_px(cam, ccd, slipped) >= 0.49
    back = CsmLineScanCamera.from_isd(slipped).ground_to_image(xyz)
    assert np.max(np.hypot(back.line - line, back.sample - sample)) > 0.49


def test_isd_fields_follow_the_conventions(tmp_path: Path) -> None:
    cam = _strip()
    ccd = cam.ccd_names[0]
    isd = linescan_to_isd(cam, ccd)
    # Time: t(line) = t0_k + rate_k (line - line_k + 0.5), relative to the centre time.
    lines = np.array([0.0, 10.25, 2999.9, 3000.0, 5999.5])
    k = np.searchsorted(isd.line_scan_rate[:, 0], lines, side="right") - 1
    rows = isd.line_scan_rate[k]
    t_csm = isd.center_ephemeris_time + rows[:, 1] + rows[:, 2] * (lines - rows[:, 0] + 0.5)
    np.testing.assert_allclose(t_csm, cam.line_rates.time(lines), rtol=0, atol=1e-12)
    # Positions in km at the sampled epochs, identity body rotation, unit quaternions.
    s, _ = cam.exterior(cam.line_rates.line(isd.instrument_position.times))
    np.testing.assert_allclose(isd.instrument_position.positions_km * 1000.0, s, atol=1e-6)
    np.testing.assert_array_equal(isd.body_rotation.quaternions[:, 0], 1.0)
    np.testing.assert_allclose(np.linalg.norm(isd.instrument_pointing.quaternions, axis=1), 1.0)
    # Written and read back by the strict reader unchanged.
    path = tmp_path / isd_file_name("s", ccd)
    from planetref.camera.csm import write_isd

    write_isd(isd, path)
    back = read_isd(path)
    np.testing.assert_array_equal(back.line_scan_rate, isd.line_scan_rate)
    assert back.detector_center_sample == pytest.approx(isd.detector_center_sample, abs=0)


def test_bad_arguments(tmp_path: Path) -> None:
    cam = _strip()
    with pytest.raises(InputError, match="does not exist"):
        write_linescan_isds(cam, tmp_path / "missing", "s")
    with pytest.raises(InputError, match="lines_per_sample"):
        linescan_to_isd(cam, lines_per_sample=0.0)
    with pytest.raises(InputError, match="unknown CCD"):
        linescan_to_isd(cam, "nope")


def test_node_jitter_is_met_by_denser_sampling(tmp_path: Path) -> None:
    """Random per-node attitude corrections put kinks in the native (piecewise Lagrange)
    orientation, which usgscsm's 8-point Lagrange smooths over a few epochs: the writer
    samples more densely until its own check passes, and records what it reached."""
    cam = _strip(jitter_rad=1e-6)
    ccd = cam.ccd_names[1]
    sparse = linescan_to_isd(cam, ccd)  # every 32 lines
    assert isd_agreement_px(cam, ccd, sparse) > 1e-3
    paths = write_linescan_isds(cam, tmp_path, "jitter")
    doc = json.loads(paths[1].read_text())["planetref"]
    assert doc["lines_per_sample"] < 32.0 and doc["check_max_px"] <= 1e-3
    csm = CsmLineScanCamera.from_file(paths[1])
    line, sample = _grid(cam, ccd)
    xyz = cam.image_to_ground(line, sample, 1000.0, ccd=ccd)
    back = csm.ground_to_image(xyz)
    assert np.max(np.hypot(back.line - line, back.sample - sample)) <= 1e-3


#: Brown-Conrady (k1 mm^-2, k2 mm^-4, p1, p2 mm^-1): ~1.3 px at the row's ends.
LENS = (1e-6, 1e-10, 2e-6, -3e-6)


def _distorted_strip():
    cam = _strip()
    return cam.replace(ccds=tuple(replace(c, distortion=LENS) for c in cam.ccds))


def test_a_distorted_camera_is_exported_with_radtan_and_read_back(tmp_path: Path) -> None:
    """The lens distortion is carried (usgscsm ``radtan``), not written as zero: the ISD
    read back by the CSM reader agrees with the distorted native camera to 1e-3 px."""
    cam = _distorted_strip()
    paths = write_linescan_isds(cam, tmp_path, "lens")
    worst = 0.0
    for path, ccd in zip(paths, cam.ccd_names, strict=True):
        doc = json.loads(path.read_text())
        assert list(doc["optical_distortion"]) == ["radtan"]
        assert len(doc["optical_distortion"]["radtan"]["coefficients"]) == 5
        assert doc["planetref"]["distortion_fit_max_px"] <= 1e-4
        csm = CsmLineScanCamera.from_file(path)
        line, sample = _grid(cam, ccd)
        for h in HEIGHTS:
            xyz = cam.image_to_ground(line, sample, h, ccd=ccd)
            back = csm.ground_to_image(xyz)
            assert back.valid.all()
            worst = max(worst, float(np.max(np.hypot(back.line - line, back.sample - sample))))
            xyz2 = csm.image_to_ground(line, sample, h)
            assert np.max(np.linalg.norm(xyz2 - xyz, axis=1)) < 1e-3  # metres
    assert worst <= 1e-3, worst
    # The check can fail: the same ISD without its distortion is off by about a pixel.
    ccd = cam.ccd_names[2]
    isd = linescan_to_isd(cam, ccd)
    flat = replace(isd, distortion_model="radial", distortion_coefficients=np.zeros(3))
    assert isd_agreement_px(cam, ccd, isd) <= 1e-3
    assert isd_agreement_px(cam, ccd, flat) > 0.5
    print(f"max |CSM radtan - native distorted|: {worst:.2e} px")


def test_a_distortion_radtan_cannot_reproduce_is_refused() -> None:
    cam = _strip()
    strong = cam.replace(ccds=tuple(replace(c, distortion=(1e-4, 0, 0, 0)) for c in cam.ccds))
    with pytest.raises(InputError, match="radtan"):
        linescan_to_isd(strong, cam.ccd_names[0])
