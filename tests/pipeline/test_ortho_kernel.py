"""The compiled orthoimage kernels against their numpy/OpenCV reference.

The reference is what the orthoimages were made with before the kernels:
``bilinear_lattice`` in float64, float32 maps, ``cv2.remap`` (bilinear, NaN border) and
``PixelType.cast``. The kernels are bound to it pixel for pixel; the stated tolerance is
1e-3 DN of the float output (bit-identical with this machine's OpenCV 5, which computes
``fma`` lerps with unquantised fractions).
"""

from __future__ import annotations

import numpy as np
import pytest
import rasterio

from planetref.products import ortho_strip
from planetref.products.ortho_strip import PixelType, orthorectify_strip
from planetref.products.orthoimage import _cell, bilinear_lattice

kernel = pytest.importorskip("planetref.products._numba_ortho")
cv2 = pytest.importorskip("cv2")

TOL_DN = 1e-3
#: OpenCV 4 quantises remap positions to 1/32 pixel; OpenCV 5 (and the kernel) does not.
OPENCV_EXACT = int(cv2.__version__.split(".")[0]) >= 5
needs_exact_remap = pytest.mark.skipif(
    not OPENCV_EXACT, reason="OpenCV < 5 quantises remap positions to 1/32 pixel"
)


def _remap_reference(raw, l_lo, ml, ms, n_lines, n_samples):
    """The reference path's sampling (ortho_strip._resample_reference), as it is there."""
    with np.errstate(invalid="ignore"):
        inside = (ml > -1) & (ml < n_lines + 1) & (ms > -1) & (ms < n_samples + 1)
    mx = ms - np.float32(0.5)
    my = ml - np.float32(l_lo + 0.5)
    mx[~inside] = -10.0
    my[~inside] = -10.0
    out = cv2.remap(
        raw, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan
    )
    dist = np.minimum(ms, np.float32(n_samples) - ms)
    dist[np.isnan(out)] = -np.inf
    return out, dist


def _bilinear64(raw, l_lo, ml, ms):
    """Bilinear samples in float64 at exact positions (an independent implementation)."""
    x = ms.astype(np.float64) - 0.5
    y = ml.astype(np.float64) - (l_lo + 0.5)
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = x - x0, y - y0
    i, j = y0.astype(int), x0.astype(int)
    r = raw.astype(np.float64)
    return (r[i, j] * (1 - fx) + r[i, j + 1] * fx) * (1 - fy) + (
        r[i + 1, j] * (1 - fx) + r[i + 1, j + 1] * fx
    ) * fy


@needs_exact_remap
@pytest.mark.parametrize("width", [61, 64, 257])
def test_resample_kernel_matches_cv2_remap(width):
    rng = np.random.default_rng(width)
    n_lines, n_samples, l_lo = 400, 90, 37
    raw = (rng.random((120, n_samples)) * 4000.0).astype(np.float32)
    raw[rng.random(raw.shape) < 0.01] = np.nan  # invalid raw pixels
    shape = (33, width)
    # Positions over the window, its borders (support leaving it) and beyond the image.
    ml = (l_lo - 3 + rng.random(shape) * 126).astype(np.float32)
    ms = (rng.random(shape) * (n_samples + 6) - 3).astype(np.float32)
    ml[0, :8] = np.float32(l_lo + 0.5)  # exactly on a raw pixel centre, first row
    ms[1, :8] = np.float32(n_samples - 0.5)  # on the last sample's centre
    ms[2, :8] = np.float32(0.5)
    ml[3, :8] = np.nan  # projection failed
    ref, ref_dist = _remap_reference(raw, l_lo, ml.copy(), ms.copy(), n_lines, n_samples)
    out = np.empty(shape, np.float32)
    dist = np.empty(shape, np.float32)
    kernel.resample_bilinear(raw, l_lo, ml, ms, n_lines, n_samples, out, dist, True)
    nan = np.isnan(ref)
    assert np.array_equal(np.isnan(out), nan)
    assert 0.1 < nan.mean() < 0.9  # both valid and NaN pixels are tested
    assert float(np.max(np.abs(out[~nan] - ref[~nan]))) <= TOL_DN
    assert np.array_equal(dist, ref_dist)
    # And float64 bilinear interpolation at the same positions, to float32 rounding.
    exact = _bilinear64(raw, l_lo, ml[~nan], ms[~nan])
    assert float(np.max(np.abs(out[~nan] - exact))) <= 2e-3


def _lattice(rng, n_r, n_c):
    lat = rng.normal(0.0, 1.0, (n_r, n_c)).cumsum(0).cumsum(1) * 50.0 + 100.0
    return lat


@pytest.mark.parametrize("n_r, n_c", [(5, 9), (1, 6), (4, 1)])
def test_lattice_maps_match_bilinear_lattice(n_r, n_c):
    rng = np.random.default_rng(n_r * 10 + n_c)
    lat_l, lat_s = _lattice(rng, n_r, n_c), _lattice(rng, n_r, n_c)
    if n_r > 1 and n_c > 1:
        lat_l[1, 2] = np.nan  # a failed node: NaN only where it has a weight
    step_r, step_c, rows, cols = 16, 8, 70, 77
    ir, fr = _cell((np.arange(rows) + 0.5) / step_r, n_r)
    ic, fc = _cell((np.arange(cols) + 0.5) / step_c, n_c)
    fr[::7] = 0.0  # on lattice rows
    fc[::5] = 1.0
    ref_l = bilinear_lattice(lat_l, ir, fr, ic, fc).astype(np.float32)
    ref_s = bilinear_lattice(lat_s, ir, fr, ic, fc).astype(np.float32)
    ml = np.empty((rows, cols), np.float32)
    ms = np.empty((rows, cols), np.float32)
    n_lines, n_samples = 260, 240
    found, lo, hi = kernel.lattice_maps(lat_l, lat_s, ir, fr, ic, fc, n_lines, n_samples, ml, ms)
    np.testing.assert_array_equal(ml, ref_l)  # bit-identical, NaN where the reference is
    np.testing.assert_array_equal(ms, ref_s)
    with np.errstate(invalid="ignore"):
        inside = (ref_l > -1) & (ref_l < n_lines + 1) & (ref_s > -1) & (ref_s < n_samples + 1)
    assert found == bool(inside.any())
    if found:
        assert (lo, hi) == (float(ref_l[inside].min()), float(ref_l[inside].max()))


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int16])
def test_cast_kernel_matches_pixel_type(dtype):
    rng = np.random.default_rng(3)
    pt = PixelType.of(dtype)
    info = np.iinfo(dtype)
    v = rng.uniform(info.min - 10.0, info.max + 10.0, (40, 50)).astype(np.float32)
    v[::3, ::4] = np.nan
    v[1, :6] = [0.5, 1.5, 2.5, -0.5, info.max, info.min]  # halves round to even
    out = np.empty(v.shape, dtype)
    kernel.cast_block(v, pt.lo, pt.hi, pt.nodata, out)
    np.testing.assert_array_equal(out, pt.cast(v))


@needs_exact_remap
def test_compiled_orthoimages_equal_the_reference(tiny_scene, tmp_path, monkeypatch):
    """One CCD of the tiny scene through both paths: the same file, pixel for pixel."""
    from planetref.camera.io import load_camera
    from planetref.raster.image import CcdImage
    from planetref.scene.inputs import open_reference
    from planetref.scene.manifest import load_manifest

    m, root = load_manifest(tiny_scene)
    ref, dem = open_reference(m, root)
    c = m.strips[0].ccds[1]
    cam = load_camera(m.resolve(root, c.camera))
    ccd = c.camera_ccd or c.name
    images = {ccd: CcdImage(m.resolve(root, c.image))}

    def run(name):
        res = orthorectify_strip(
            images,
            cam,
            dem,
            ref.crs,
            {ccd: tmp_path / f"{name}.tif"},
            gsd_m=1.0,
            overviews=False,
            threads=2,
        )
        with rasterio.open(res.ccds[ccd]) as ds:
            return ds.read(1), ds.nodata

    new, nodata = run("compiled")
    monkeypatch.setattr(ortho_strip, "_kernel", lambda: None)
    old, _ = run("reference")
    assert np.array_equal(new, old)
    assert 0.3 < np.mean(new != nodata) < 1.0


def test_raw_windows_reuse_the_previous_window():
    """Overlapping windows (forwards, backwards, nested, disjoint) equal direct reads."""
    from planetref.raster.image import CcdImage

    rng = np.random.default_rng(5)
    arr = rng.integers(0, 4000, (300, 23)).astype(np.uint16)
    arr[rng.random(arr.shape) < 0.02] = 0  # nodata -> NaN
    image = CcdImage(arr, nodata=0)
    job = ortho_strip._CcdJob("c", image, None, 0, 0, None, 300, 23, read_align=16)
    reads = []
    real = image.read

    def counted(r, c, h, w):
        reads.append(h)
        return real(r, c, h, w)

    image.read = counted
    windows = [(0, 50), (20, 90), (60, 120), (130, 170), (100, 150), (90, 140), (95, 130)]
    windows += [(280, 300), (270, 295)]
    for lo, hi in windows:
        raw, valid = real(lo, 0, hi - lo, 23)
        want = np.where(valid, raw, np.float32(np.nan)).astype(np.float32)
        got = job.raw(lo, hi)
        assert got.flags.c_contiguous and got.dtype == np.float32
        np.testing.assert_array_equal(got, want)
    # Runs aligned to 16 lines: [0, 64), [64, 96), [96, 128), [128, 176) (disjoint),
    # [96, 128) (moving up), [80, 96), nothing (inside), [272, 300) (the image's end),
    # [256, 272).
    assert reads == [64, 32, 32, 48, 32, 16, 28, 16]
