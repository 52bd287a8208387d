"""Image-space bias of RPCs: partials, the corrected camera, refined RPCs in every format."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rasterio

from planetref.camera.base import ConstantHeight
from planetref.camera.rpc import MARS_BODY, Rpc, RpcCamera, read_rpc_body, write_rpc
from planetref.camera.rpc.bias import BiasedRpcCamera, RpcBias, refined_rpc, write_refined_rpc
from planetref.errors import InputError
from planetref.geometry.geodesy import (
    EARTH_WGS84,
    MARS_IAU2015_ELLIPSOID,
    MARS_IAU2015_SPHERE,
    lonlat_to_xyz,
    lonlat_xyz_jacobian,
    xyz_to_lonlat,
)

pytestmark = pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")

SIZE = (1200, 1000)


def _rpc() -> Rpc:
    """A push-broom-like RPC (oblique, with height and denominator terms), Mars-sized."""
    # Small cubic terms, so that every term's partial derivative is exercised.
    z = tuple(2e-4 * (-1) ** i / (i + 1) for i in range(10))
    return Rpc(
        line_off=599.5,
        samp_off=499.5,
        lat_off=18.2,
        long_off=77.9,
        height_off=-2000.0,
        line_scale=600.0,
        samp_scale=500.0,
        lat_scale=0.05,
        long_scale=0.045,
        height_scale=3000.0,
        line_num_coeff=(0.002, 0.05, -1.02, 0.08, 0.003, 0.001, -0.002, 0.004, 0.002, 1e-4, *z),
        line_den_coeff=(1.0, 0.002, -0.001, 0.003, *(1e-4,) * 16),
        samp_num_coeff=(-0.004, 1.01, 0.06, -0.12, -0.002, 0.003, 0.001, 0.001, -0.003, 1e-4, *z),
        samp_den_coeff=(1.0, -0.001, 0.002, 0.002, *(-1e-4,) * 16),
    )


def _camera() -> RpcCamera:
    return RpcCamera(_rpc(), MARS_IAU2015_ELLIPSOID, "planetocentric", SIZE, name="ccd1")


AFFINE = (3.2, -2.5, 1.4, 0.6, -0.9, 2.1)


def _ground(cam: RpcCamera, n: int = 40, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    line, sample = rng.uniform(0, SIZE[0], n), rng.uniform(0, SIZE[1], n)
    h = rng.uniform(-4000, 0, n)
    return lonlat_to_xyz(*cam.localize(line, sample, h), h, cam.ellipsoid, cam.latitude_kind)


@pytest.mark.parametrize("ellipsoid", [MARS_IAU2015_ELLIPSOID, EARTH_WGS84])
@pytest.mark.parametrize("kind", ["planetocentric", "planetographic"])
def test_lonlat_jacobian_matches_finite_differences(ellipsoid, kind):
    rng = np.random.default_rng(3)
    u = rng.normal(size=(50, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    xyz = u * (ellipsoid.semi_major_m + rng.uniform(-5000, 20000, (50, 1)))
    jac = lonlat_xyz_jacobian(xyz, ellipsoid, kind)
    h = 1.0  # truncation error ~(h/R)^2, round-off ~1e-16 R/h: both far below the bounds
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        plus = np.stack(xyz_to_lonlat(xyz + e, ellipsoid, kind), axis=1)
        minus = np.stack(xyz_to_lonlat(xyz - e, ellipsoid, kind), axis=1)
        fd = (plus - minus) / (2 * h)
        # Rows: degrees per metre (~1.7e-5 on Mars: 1e-12 is 6e-8 relative) and metres
        # per metre.
        err = np.abs(jac[:, :, k] - fd)
        assert np.max(err[:, :2]) < 1e-12 and np.max(err[:, 2]) < 1e-8, np.max(err, axis=0)
    # Planetocentric and geodetic latitude rows differ on an oblate body (by up to 0.6 %).
    if kind == "planetocentric" and not ellipsoid.is_sphere:
        geo = lonlat_xyz_jacobian(xyz, ellipsoid, "planetographic")
        assert np.max(np.abs(jac[:, 1] - geo[:, 1])) > 1e-3 * np.max(np.abs(geo[:, 1]))


def test_rpc_partials_match_finite_differences():
    rpc = _rpc()
    rng = np.random.default_rng(1)
    lon = rpc.long_off + rng.uniform(-0.04, 0.04, 30)
    lat = rpc.lat_off + rng.uniform(-0.05, 0.05, 30)
    h = rng.uniform(-5000, 1000, 30)
    line, sample, d = rpc.project_with_partials(lon, lat, h)
    np.testing.assert_array_equal(np.stack([line, sample]), np.stack(rpc.project(lon, lat, h)))
    steps = (1e-6, 1e-6, 0.01)
    for k, step in enumerate(steps):
        args_p = [lon, lat, h]
        args_m = [lon, lat, h]
        args_p[k] = args_p[k] + step
        args_m[k] = args_m[k] - step
        fd = (np.stack(rpc.project(*args_p)) - np.stack(rpc.project(*args_m))) / (2 * step)
        np.testing.assert_allclose(d[:, :, k], fd.T, rtol=1e-6, atol=1e-9)


def test_biased_camera_round_trips_and_inverts_exactly():
    cam = _camera()
    bias = RpcBias(SIZE, AFFINE)
    bc = BiasedRpcCamera(cam, bias)
    rng = np.random.default_rng(2)
    line, sample = rng.uniform(0, SIZE[0], 200), rng.uniform(0, SIZE[1], 200)
    raw = bias.invert(line, sample)
    np.testing.assert_allclose(np.stack(bias.apply(*raw)), np.stack([line, sample]), atol=1e-10)
    # A height (RPC inverted at that height) and a terrain of another body (the march).
    for terrain in (-1500.0, ConstantHeight(MARS_IAU2015_SPHERE, -1500.0)):
        xyz = bc.image_to_ground(line, sample, terrain)
        ip = bc.ground_to_image(xyz)
        assert np.max(np.hypot(ip.line - line, ip.sample - sample)) < 1e-7
    # The correction moves the image by the coefficients: at the centre by (a0, b0).
    xyz = cam.image_to_ground([SIZE[0] / 2], [SIZE[1] / 2], -1000.0)
    ip0, ip1 = cam.ground_to_image(xyz), bc.ground_to_image(xyz)
    assert ip1.line[0] - ip0.line[0] == pytest.approx(AFFINE[0], abs=1e-9)
    assert ip1.sample[0] - ip0.sample[0] == pytest.approx(AFFINE[1], abs=1e-9)
    with pytest.raises(InputError, match="6 finite"):
        RpcBias(SIZE, (1.0, np.nan, 0, 0, 0, 0))


def test_refined_rpc_exact_shift_and_refit_far_below_a_hundredth_pixel():
    cam = _camera()
    xyz = _ground(cam, 400)
    shifted = BiasedRpcCamera(cam, RpcBias(SIZE, (2.75, -1.5, 0, 0, 0, 0)))
    rpc, report = refined_rpc(shifted)
    assert report is None
    assert rpc.line_off == cam.rpc.line_off + 2.75 and rpc.samp_off == cam.rpc.samp_off - 1.5
    ref = RpcCamera(rpc, cam.ellipsoid, cam.latitude_kind, SIZE).ground_to_image(xyz)
    want = shifted.ground_to_image(xyz)
    assert np.max(np.abs(ref.line - want.line)) < 1e-9
    assert np.max(np.abs(ref.sample - want.sample)) < 1e-9
    for coeffs in (AFFINE, (1.0, -2.0, 4.0, -3.0, 0.0, 0.0)):  # affine; shift+drift
        biased = BiasedRpcCamera(cam, RpcBias(SIZE, coeffs))
        rpc, report = refined_rpc(biased)
        print(coeffs, report.summary())
        assert report.check_max_px < 1e-3
        got = RpcCamera(rpc, cam.ellipsoid, cam.latitude_kind, SIZE).ground_to_image(xyz)
        want = biased.ground_to_image(xyz)
        assert np.max(np.hypot(got.line - want.line, got.sample - want.sample)) < 1e-3


def test_refined_rpc_refits_through_the_ladder_and_stops_at_its_first_rung():
    """A well-behaved refit is the plain fit bit for bit (the ladder's first rung)."""
    from planetref.camera.rpc.fit import fit_rpc
    from planetref.camera.rpc.stable import REGULARIZATIONS

    biased = BiasedRpcCamera(_camera(), RpcBias(SIZE, AFFINE))
    rpc, report = refined_rpc(biased)
    h0, hs = biased.rpc.height_off, abs(biased.rpc.height_scale)
    plain, plain_report = fit_rpc(biased, height_range_m=(h0 - hs, h0 + hs), grid=(21, 21, 9))
    assert report.regularization == REGULARIZATIONS[0] == plain_report.regularization
    for name in ("line_num_coeff", "line_den_coeff", "samp_num_coeff", "samp_den_coeff"):
        assert np.array_equal(getattr(rpc, name), getattr(plain, name))
    assert report.check_max_px == plain_report.check_max_px


def _input_file(kind: str, folder: Path, write_geotiff) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    if kind == "geotiff":
        path = write_geotiff(
            folder / "scene.tif", np.arange(SIZE[0] * SIZE[1], dtype=np.uint16).reshape(SIZE)
        )
        write_rpc(_rpc(), path, body=MARS_BODY)
        return path
    path = folder / ("scene.RPB" if kind == "rpb" else "scene_RPC.TXT")
    return write_rpc(_rpc(), path, body=MARS_BODY)


@pytest.mark.parametrize("kind", ["rpb", "txt", "geotiff"])
def test_refined_rpc_written_in_the_inputs_format_never_over_it(tmp_path, kind, write_geotiff):
    src = _input_file(kind, tmp_path / "in", write_geotiff)
    before = src.read_bytes()
    cam = RpcCamera.from_file(src, image_size=SIZE)
    assert cam.source == src
    biased = BiasedRpcCamera(cam, RpcBias(SIZE, AFFINE))
    paths, report = write_refined_rpc(biased, tmp_path / "out", "scene")
    (out,) = paths
    assert out.name == {"rpb": "scene.RPB", "txt": "scene_RPC.TXT", "geotiff": "scene.tif"}[kind]
    assert report["method"] == "refit" and report["format"] == kind
    assert report["check_max_px"] < 1e-3
    assert read_rpc_body(out) == MARS_BODY
    back = RpcCamera.from_file(out, image_size=SIZE)
    assert back.ellipsoid == MARS_BODY.ellipsoid
    xyz = _ground(cam)
    got, want = back.ground_to_image(xyz), biased.ground_to_image(xyz)
    assert np.max(np.hypot(got.line - want.line, got.sample - want.sample)) < 1e-3
    if kind == "geotiff":  # the image itself is copied unchanged
        with rasterio.open(out) as a, rasterio.open(src) as b:
            np.testing.assert_array_equal(a.read(), b.read())
    assert src.read_bytes() == before
    # Writing into the input's own folder under the input's name is refused.
    stem = src.name.removesuffix("_RPC.TXT").rsplit(".", 1)[0]
    with pytest.raises(InputError, match="over its input"):
        write_refined_rpc(biased, src.parent, stem)
    assert src.read_bytes() == before
