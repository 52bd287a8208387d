import json
import math

import numpy as np
import pytest

from planetref.camera.linescan import (
    InteriorOrientation,
    LineRateTable,
    LineScanCamera,
)
from planetref.camera.orbit import OrbitGeometry, ccd_row, orbit_camera
from planetref.errors import InputError, MissingFileError, UnsupportedFormatError
from planetref.geometry.geodesy import MARS_IAU2015_SPHERE, xyz_to_lonlat
from planetref.geometry.lagrange import lagrange_window as _lagrange
from planetref.geometry.rotations import rotation_matrix, rotation_matrix_derivatives


def make_camera(perturbed=True, n_nodes=6, n_lines=1000, n_samples=512, order=4, seed=0):
    ccds = ccd_row(3, n_samples, n_lines, 0.010, overlap_px=16, stagger_mm=1.0)
    cam, _ = orbit_camera(
        OrbitGeometry(20.0, 74.0, 30.0),
        focal_length_mm=4640.0,
        ccds=ccds,
        n_nodes=n_nodes,
        interpolation_order=order,
    )
    if perturbed:
        rng = np.random.default_rng(seed)
        nodes = cam.nodes.copy()
        # A bias plus a smooth-ish per-node wobble, as real attitude errors look.
        nodes[:, :3] += rng.normal(0, 50, 3) + rng.normal(0, 1.0, (n_nodes, 3))
        nodes[:, 3:] += rng.normal(0, 1e-4, 3) + rng.normal(0, 2e-6, (n_nodes, 3))
        cam = cam.replace(nodes=nodes, interior=InteriorOrientation(4640.0, 0.3, -0.2))
    return cam


@pytest.fixture(scope="module")
def cam():
    return make_camera()


def random_pixels(cam, ccd, n, seed=1):
    rng = np.random.default_rng(seed)
    n_lines, n_samples = cam.image_size(ccd)
    return rng.uniform(0, n_lines, n), rng.uniform(0, n_samples, n)


@pytest.mark.parametrize("ccd", ["ccd1", "ccd2", "ccd3"])
@pytest.mark.parametrize("height", [-4000.0, 0.0, 2500.0])
def test_image_ground_image_round_trip(cam, ccd, height):
    line, sample = random_pixels(cam, ccd, 3000)
    xyz = cam.image_to_ground(line, sample, height, ccd=ccd)
    _, _, h = xyz_to_lonlat(xyz, cam.ellipsoid)
    assert np.abs(h - height).max() < 1e-4
    ip = cam.ground_to_image(xyz, ccd=ccd)
    assert ip.valid.all() and ip.in_image.all()
    assert np.abs(ip.line - line).max() < 1e-6
    assert np.abs(ip.sample - sample).max() < 1e-6


def test_ground_image_ground_round_trip(cam):
    line, sample = random_pixels(cam, "ccd2", 500)
    xyz = cam.image_to_ground(line, sample, 100.0, ccd="ccd2")
    ip = cam.ground_to_image(xyz, ccd="ccd2")
    back = cam.image_to_ground(ip.line, ip.sample, 100.0, ccd="ccd2")
    assert np.abs(back - xyz).max() < 1e-4  # metres


def test_gsd_and_ccd_layout():
    cam = make_camera(perturbed=False)
    # Neighbouring samples on the ground are about one GSD (265 km * 10 um / 4.64 m) apart.
    xyz = cam.image_to_ground([500.5, 500.5], [100.5, 101.5], 0.0, ccd="ccd2")
    assert np.linalg.norm(xyz[1] - xyz[0]) == pytest.approx(265e3 * 0.010 / 4640, rel=0.01)
    # Overlapping CCDs: the last samples of ccd1 see what the first samples of ccd2 see,
    # at a different line because ccd2 is staggered 1 mm (100 lines) along track.
    p = cam.image_to_ground([600.5], [512 - 8.0], 0.0, ccd="ccd1")
    ip = cam.ground_to_image(p, ccd="ccd2")
    assert ip.sample[0] == pytest.approx(8.0, abs=0.05)
    assert abs(ip.line[0] - (600.5 - 100)) < 1.5


def test_outside_image_and_behind_camera(cam):
    # A point beyond the last line but within the node span projects, flagged outside.
    n_lines, n_samples = cam.image_size("ccd2")
    xyz = cam.image_to_ground(
        [n_lines + 20.0, 10.0], [n_samples / 2, n_samples + 40.0], 0.0, ccd="ccd2"
    )
    ip = cam.ground_to_image(xyz, ccd="ccd2")
    assert ip.valid.all() and not ip.in_image.any()
    assert ip.line[0] == pytest.approx(n_lines + 20.0, abs=1e-6)
    assert ip.sample[1] == pytest.approx(n_samples + 40.0, abs=1e-6)
    # The antipode is behind the camera; a point far away along track is not in time span.
    s, _ = cam.exterior([500.0])
    far = np.stack([1.5 * s[0], s[0] + np.array([0, 0, 2e6])])
    ip = cam.ground_to_image(far, ccd="ccd2")
    assert not ip.valid.any()
    assert np.isnan(ip.line).all() and np.isnan(ip.sample).all()


def test_ray_that_misses_the_body(cam):
    # A camera turned to look at the horizon: rays above the limb miss.
    nodes = cam.nodes.copy()
    nodes[:, 3] += math.radians(90.0)
    side = cam.replace(nodes=nodes)
    from planetref.errors import GeometryError

    with pytest.raises(GeometryError, match="misses"):
        side.image_to_ground([10.0], [10.0], 0.0)
    out = side.image_to_ground([10.0], [10.0], 0.0, on_miss="nan")
    assert np.isnan(out).all()


def test_lagrange_reproduces_cubic_and_nodes():
    times = np.array([0.0, 1.0, 2.5, 3.0, 4.5, 6.0])
    t = np.linspace(-0.5, 6.5, 301)
    idx, w, dw = _lagrange(times, t, 4)
    f = lambda x: 2 - x + 0.5 * x**2 - 0.1 * x**3  # noqa: E731
    df = lambda x: -1 + x - 0.3 * x**2  # noqa: E731
    assert np.abs((w * f(times[idx])).sum(1) - f(t)).max() < 1e-12
    assert np.abs((dw * f(times[idx])).sum(1) - df(t)).max() < 1e-10
    idx, w, _ = _lagrange(times, times, 4)
    assert np.abs((w * times[idx] ** 0).sum(1) - 1).max() < 1e-12
    assert np.abs(w.max(1) - 1).max() < 1e-12  # exact at nodes


def test_rotation_derivatives_finite_difference():
    angles = np.array([0.3, -0.2, 1.1])
    _, *d = rotation_matrix_derivatives(*angles)
    for j in range(3):
        h = np.zeros(3)
        h[j] = 1e-6
        fd = (rotation_matrix(*(angles + h)) - rotation_matrix(*(angles - h))) / 2e-6
        assert np.abs(fd - d[j]).max() < 1e-9
    r = rotation_matrix(*angles)
    assert np.abs(r @ r.T - np.eye(3)).max() < 1e-14 and np.linalg.det(r) == pytest.approx(1)


def _fd_image(cam, xyz, ccd, line_guess, make):
    def project(delta):
        ip = make(delta).ground_to_image(xyz, ccd=ccd, line_guess=line_guess)
        return np.stack([ip.line, ip.sample], axis=1)

    return project


@pytest.mark.parametrize("ccd", ["ccd1", "ccd3"])
def test_partials_match_finite_differences(cam, ccd):
    line, sample = random_pixels(cam, ccd, 40, seed=5)
    xyz = cam.image_to_ground(line, sample, 300.0, ccd=ccd)
    part = cam.image_partials(xyz, ccd=ccd)
    assert np.abs(part.line - line).max() < 1e-6
    dense = part.dense_nodes(cam.n_nodes)
    for q in range(cam.n_nodes * 6):
        h = 0.1 if q % 6 < 3 else 1e-6
        n1, n2 = cam.nodes.copy(), cam.nodes.copy()
        n1.flat[q] += h
        n2.flat[q] -= h
        a = cam.replace(nodes=n1).ground_to_image(xyz, ccd=ccd, line_guess=part.line)
        b = cam.replace(nodes=n2).ground_to_image(xyz, ccd=ccd, line_guess=part.line)
        fd = np.stack([a.line - b.line, a.sample - b.sample], axis=1) / (2 * h)
        scale = max(np.abs(fd).max(), 1e-3)
        assert np.abs(fd - dense[:, :, q]).max() < 1e-4 * scale, f"node parameter {q}"
    io = cam.interior.as_array()
    for j, h in enumerate((1e-4, 1e-4, 1e-2)):  # mm; f needs a larger step to be resolved
        i1, i2 = io.copy(), io.copy()
        i1[j] += h
        i2[j] -= h
        a = cam.replace(interior=InteriorOrientation.from_array(i1)).ground_to_image(xyz, ccd=ccd)
        b = cam.replace(interior=InteriorOrientation.from_array(i2)).ground_to_image(xyz, ccd=ccd)
        fd = np.stack([a.line - b.line, a.sample - b.sample], axis=1) / (2 * h)
        assert np.abs(fd - part.d_interior[:, :, j]).max() < 1e-4 * np.abs(fd).max()
    for j in range(3):
        h = 0.1
        x1, x2 = xyz.copy(), xyz.copy()
        x1[:, j] += h
        x2[:, j] -= h
        a, b = cam.ground_to_image(x1, ccd=ccd), cam.ground_to_image(x2, ccd=ccd)
        fd = np.stack([a.line - b.line, a.sample - b.sample], axis=1) / (2 * h)
        assert np.abs(fd - part.d_ground[:, :, j]).max() < 1e-5 * np.abs(fd).max()


def test_partials_only_touch_the_lagrange_window(cam):
    xyz = cam.image_to_ground([10.0, 990.0], [200.0, 200.0], 0.0, ccd="ccd2")
    part = cam.image_partials(xyz, ccd="ccd2")
    assert part.node_index.shape == (2, 4)
    assert part.node_index[0].tolist() == [0, 1, 2, 3]
    assert part.node_index[1].tolist() == [2, 3, 4, 5]


def test_json_round_trip(tmp_path, cam):
    path = cam.to_json(tmp_path / "cam.json")
    back = LineScanCamera.from_json(path)
    assert back.to_dict() == cam.to_dict()
    line, sample = random_pixels(cam, "ccd3", 100)
    assert np.array_equal(
        back.image_to_ground(line, sample, 0.0, ccd="ccd3"),
        cam.image_to_ground(line, sample, 0.0, ccd="ccd3"),
    )
    doc = json.loads(path.read_text())
    assert doc["format"] == "planetref-linescan" and doc["version"] == 1
    assert not list(tmp_path.glob(".*tmp"))  # no temporary file left behind


def _write(tmp_path, doc, name="cam.json"):
    p = tmp_path / name
    p.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return p


@pytest.mark.parametrize(
    "mutate, field",
    [
        (lambda d: d["interior"].pop("focal_length_mm"), "interior.focal_length_mm"),
        (lambda d: d["interior"].__setitem__("focal_length_mm", -1.0), "interior.focal_length_mm"),
        (lambda d: d["orientation"]["nodes"][2].__setitem__(3, "NaN"), "orientation.nodes.2.3"),
        (lambda d: d["orientation"]["nodes"].pop(), "orientation.nodes"),
        (lambda d: d["ccds"][0].__setitem__("pixel_pitch_um", 10), "ccds.0.pixel_pitch_um"),
        (lambda d: d.__setitem__("version", 7), "version"),
        (lambda d: d["frame_rotation"].__setitem__(0, [2.0, 0.0, 0.0]), "frame_rotation"),
        (lambda d: d["line_rates"][0].__setitem__(2, 0.0), "line_rates"),
    ],
)
def test_bad_camera_files(tmp_path, cam, mutate, field):
    doc = cam.to_dict()
    mutate(doc)
    p = _write(tmp_path, json.dumps(doc).replace('"NaN"', "NaN"))
    with pytest.raises(InputError) as exc:
        LineScanCamera.from_json(p)
    msg = str(exc.value)
    assert str(p) in msg and field in msg and "\n" not in msg


def test_unreadable_camera_files(tmp_path, cam):
    with pytest.raises(MissingFileError, match="camera file not found"):
        LineScanCamera.from_json(tmp_path / "absent.json")
    text = json.dumps(cam.to_dict())
    p = _write(tmp_path, text[: len(text) // 2])
    with pytest.raises(InputError, match=r"not valid JSON \(.* at line 1, column \d+\)"):
        LineScanCamera.from_json(p)
    p = _write(tmp_path, json.dumps({"hello": 1}))
    with pytest.raises(UnsupportedFormatError, match="not a planetref line-scan camera"):
        LineScanCamera.from_json(p)


def test_line_rate_table_piecewise():
    t = LineRateTable(((0.0, 10.0, 0.001), (100.0, 10.2, 0.002)))
    assert t.time([0.0, 50.0, 100.0, 150.0]).tolist() == pytest.approx([10.0, 10.05, 10.2, 10.3])
    assert t.line(t.time([3.0, 120.0])) == pytest.approx([3.0, 120.0])
    with pytest.raises(InputError):
        LineRateTable(((0.0, 0.0, -1.0),))


def test_constructor_validation(cam):
    with pytest.raises(InputError, match="CCD names"):
        cam.replace(ccds=(cam.ccds[0], cam.ccds[0]))
    with pytest.raises(InputError, match="nodes"):
        cam.replace(nodes=cam.nodes[:, :5])
    with pytest.raises(InputError, match="unknown CCD"):
        cam.ground_to_image(np.zeros((1, 3)), ccd="nope")


def test_nodes_are_read_only(cam):
    with pytest.raises(ValueError):
        cam.nodes[0, 0] = 1.0


def test_sphere_camera_sees_the_scene_centre():
    cam = make_camera(perturbed=False)
    xyz = cam.image_to_ground([500.0], [cam.image_size("ccd2")[1] / 2 + 0.0], 0.0, ccd="ccd2")
    lon, lat, _ = xyz_to_lonlat(xyz, MARS_IAU2015_SPHERE)
    # ccd2 is staggered by 100 lines, so line 500 - 100 is the centre time.
    assert lat[0] == pytest.approx(20.0, abs=0.01) and lon[0] == pytest.approx(74.0, abs=0.01)


@pytest.mark.parametrize("perturbed, limit_px", [(False, 1e-4), (True, 1.0)])
def test_fit_rpc_to_rigorous_camera(perturbed, limit_px):
    """RPCs reproduce a smooth orbit almost exactly; attitude wobble is what they cannot."""
    from planetref.camera.rpc import fit_rpc

    cam = make_camera(perturbed=perturbed, n_lines=4000, n_samples=2048)
    _, report = fit_rpc(cam, ccd="ccd3", height_range_m=(-5000.0, 3000.0), grid=(15, 15, 5))
    assert report.check_max_px < limit_px
    if perturbed:
        assert report.check_rms_px > 1e-3  # the wobble is real and measured, not hidden


class _RidgeTerrain:
    """Ridges 400 m high every 800 m across the scene (a rough Terrain for ray casting)."""

    def __init__(self, ellipsoid):
        self.ellipsoid = ellipsoid
        self.min_height_m, self.max_height_m = -500.0, 500.0

    @property
    def sampling_m(self):
        return 10.0

    def height(self, lon_deg, lat_deg):
        x = np.radians(np.asarray(lon_deg)) * self.ellipsoid.semi_major_m
        return 400.0 * np.sin(2 * np.pi * x / 800.0) + 0.0 * np.asarray(lat_deg)


def test_image_to_dem_round_trip(cam):
    terrain = _RidgeTerrain(cam.ellipsoid)
    line, sample = random_pixels(cam, "ccd1", 300, seed=9)
    xyz = cam.image_to_ground(line, sample, terrain, ccd="ccd1")
    lon, lat, h = xyz_to_lonlat(xyz, cam.ellipsoid)
    assert np.abs(h - terrain.height(lon, lat)).max() < 1e-3  # on the surface
    ip = cam.ground_to_image(xyz, ccd="ccd1")
    assert np.abs(ip.line - line).max() < 1e-6 and np.abs(ip.sample - sample).max() < 1e-6
    # Relief moves the ground point along the ray: compare with the flat intersection.
    flat = cam.image_to_ground(line, sample, 0.0, ccd="ccd1")
    assert np.linalg.norm(flat - xyz, axis=1).max() > 1.0


@pytest.mark.parametrize("ccd", ["ccd1", "ccd3"])
def test_ccd_placement_partials_match_finite_differences(cam, ccd):
    from dataclasses import replace

    line, sample = random_pixels(cam, ccd, 40, seed=8)
    xyz = cam.image_to_ground(line, sample, -500.0, ccd=ccd)
    part = cam.image_partials(xyz, ccd=ccd)
    i = cam.ccd_names.index(ccd)
    for j, (name, h) in enumerate((("x_mm", 1e-4), ("y_mm", 1e-4), ("angle_rad", 1e-6))):

        def moved(delta, name=name):
            ccds = list(cam.ccds)
            ccds[i] = replace(ccds[i], **{name: getattr(ccds[i], name) + delta})
            ip = cam.replace(ccds=tuple(ccds)).ground_to_image(xyz, ccd=ccd, line_guess=line)
            return np.stack([ip.line, ip.sample], axis=1)

        fd = (moved(h) - moved(-h)) / (2 * h)
        assert np.abs(fd).max() > 1.0  # pixels per mm or per radian: not a vacuous check
        assert np.abs(fd - part.d_ccd[:, :, j]).max() < 1e-5 * np.abs(fd).max(), name
    # A focal-plane shift along the array moves the sample by -1/pitch per mm when the
    # array is unrotated, and the line not at all to first order.
    c = cam.ccd(ccd)
    if c.angle_rad == 0.0:
        np.testing.assert_allclose(part.d_ccd[:, 1, 1], -1.0 / c.pixel_pitch_mm, rtol=1e-9)
