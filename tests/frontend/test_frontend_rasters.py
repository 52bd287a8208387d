"""Windowed CCD image and reference ortho readers: windows, no-data, ISIS specials."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
from affine import Affine

from planetref.errors import CrsError, InputError, MissingFileError
from planetref.raster.image import (
    ISIS_VALID_RANGE,
    CcdImage,
    isis_valid_mask,
    masked_block_mean,
)
from planetref.raster.ortho import ReferenceOrtho, RefWindow

ISIS_NULL4 = float(np.array([0xFF7FFFFB], np.uint32).view(np.float32)[0])
ISIS_HRS4 = float(np.array([0xFF7FFFFF], np.uint32).view(np.float32)[0])


def test_ccd_window_reads_and_masks(tmp_path, write_geotiff):
    data = np.arange(60, dtype=np.float32).reshape(6, 10) + 1.0
    data[1, 1] = np.nan
    data[2, 2] = ISIS_NULL4
    data[3, 3] = ISIS_HRS4
    data[4, 4] = -9999.0
    write_geotiff(tmp_path / "ccd.tif", data, nodata=-9999.0)
    with CcdImage(tmp_path / "ccd.tif") as img:
        assert img.shape == (6, 10)
        vals, valid = img.read(-1, -2, 8, 14)
    assert vals.shape == valid.shape == (8, 14)
    # Outside the image: invalid and zero.
    assert not valid[0].any() and not valid[-1].any() and not valid[:, :2].any()
    inner = valid[1:7, 2:12]
    expect = np.ones((6, 10), bool)
    for r, c in [(1, 1), (2, 2), (3, 3), (4, 4)]:
        expect[r, c] = False
    np.testing.assert_array_equal(inner, expect)
    np.testing.assert_array_equal(vals[1:7, 2:12][expect], data[expect])
    assert np.all(vals[~valid] == 0)


def test_ccd_isis_integer_specials_and_array_source():
    raw = np.array([[0, 1, 2, 3], [65522, 65534, 65535, 1000]], np.uint16)
    img = CcdImage(raw, isis_special=True)
    _, valid = img.read(0, 0, 2, 4)
    np.testing.assert_array_equal(valid, [[False, False, False, True], [True, False, False, True]])
    # Without the flag an unsigned array has no special values.
    assert CcdImage(raw).read(0, 0, 2, 4)[1].all()
    assert isis_valid_mask(np.array([-32768, -32752, 0], np.int16)).tolist() == [False, True, True]
    assert set(ISIS_VALID_RANGE) >= {"uint8", "int16", "uint16", "float32"}


def test_ccd_errors(tmp_path):
    with pytest.raises(MissingFileError):
        CcdImage(tmp_path / "none.tif")
    with pytest.raises(InputError):
        CcdImage(np.zeros((2, 2, 2)))
    with pytest.raises(InputError):
        CcdImage(np.zeros((4, 4))).read(0, 0, 0, 3)


def test_masked_block_mean_ignores_invalid_pixels():
    data = np.array([[1, 3, 100, 5], [5, 7, 5, 5], [-1e30, 2, 8, 8]], np.float32)
    valid = np.ones(data.shape, bool)
    valid[0, 2] = False  # an outlier that must not enter the mean
    valid[2, 0] = False
    mean, ok = masked_block_mean(data, valid, 2)
    assert mean.shape == (2, 2)
    np.testing.assert_allclose(mean, [[4.0, 5.0], [2.0, 8.0]])
    assert ok.all()
    # Half-valid trailing block with min fraction 0.6: invalid.
    _, ok = masked_block_mean(data, valid, 2, min_valid_fraction=0.6)
    assert ok.tolist() == [[True, True], [False, True]]


@pytest.mark.parametrize("factor", [2, 5, 9, 11])
@pytest.mark.parametrize("share_valid", [1.0, 0.8])
def test_masked_block_mean_equals_numpy(factor: int, share_valid: float) -> None:
    """Block means (the all-valid fast path and the masked one) equal a numpy reduction.

    Shapes that are not multiples of the factor have trailing partial blocks, averaged
    over the pixels they have; factor 11 is one whose 121 ones times 1/121 is not 1 in
    float32.
    """
    rng = np.random.default_rng(factor)
    h, w = 7 * factor + 3, 5 * factor + factor - 1
    data = rng.uniform(0, 4000, (h, w)).astype(np.float32)
    valid = rng.random((h, w)) < share_valid
    mean, ok = masked_block_mean(np.where(valid, data, 0).astype(np.float32), valid, factor)
    hb, wb = -(-h // factor), -(-w // factor)
    pad = ((0, hb * factor - h), (0, wb * factor - w))
    blocks = lambda a: np.pad(a, pad).reshape(hb, factor, wb, factor).sum(axis=(1, 3))  # noqa: E731
    s = blocks(np.where(valid, data, 0).astype(np.float64))
    n = blocks(valid.astype(np.float64))
    size = blocks(np.ones((h, w)))
    expect_ok = n >= 0.5 * size - 1e-9
    np.testing.assert_array_equal(ok, expect_ok)
    np.testing.assert_allclose(mean[ok], (s / np.maximum(n, 1))[ok], rtol=2e-6)
    assert not mean[~ok].any()


def test_block_mean_read_in_strips_equals_whole():
    rng = np.random.default_rng(0)
    data = rng.normal(size=(37, 23)).astype(np.float32)
    data[5:9, 3:7] = np.nan
    img = CcdImage(data)
    a, va = img.read_block_mean(-3, 2, 40, 20, 4, max_pixels=50)
    b, vb = masked_block_mean(*img.read(-3, 2, 40, 20), 4)
    np.testing.assert_allclose(a, b, rtol=1e-6)
    np.testing.assert_array_equal(va, vb)


def test_reference_windows_and_factor(tmp_path, write_geotiff):
    data = np.arange(100, dtype=np.float32).reshape(10, 10)
    data[0, 0] = -9999.0
    t = Affine(5.0, 0, 1000.0, 0, -5.0, 2000.0)
    crs = rasterio.crs.CRS.from_user_input("IAU_2015:49910")
    write_geotiff(tmp_path / "ref.tif", data, nodata=-9999.0, crs=crs, transform=t)
    with ReferenceOrtho(tmp_path / "ref.tif") as ref:
        assert ref.shape == (10, 10)
        win = RefWindow(-2, -2, 6, 6)
        vals, valid = ref.read(win)
        assert not valid[:2].any() and not valid[:, :2].any() and not valid[2, 2]
        np.testing.assert_array_equal(vals[3:, 3:], data[1:4, 1:4])
        coarse = RefWindow(0, 0, 5, 5, factor=2)
        m, ok = ref.read(coarse)
        # The first block averages its three valid pixels only.
        assert m[0, 0] == pytest.approx((1 + 10 + 11) / 3)
        assert ok.all()
        # Window pixel (0.5, 0.5) of the coarse window is the centre of a 2x2 block.
        col, row = coarse.to_ref_pixel(0.5, 0.5)
        assert (col, row) == (1.0, 1.0)
        x, y = ref.pixel_to_map(col, row)
        assert (x, y) == (1005.0, 1995.0)
        np.testing.assert_allclose(ref.map_to_pixel(x, y), (1.0, 1.0))
        assert ref.window_transform(coarse) @ (0.5, 0.5) == (1005.0, 1995.0)
        gx, gy = ref.ground_sampling_m()
        assert gx == pytest.approx(5.0, rel=1e-3) and gy == pytest.approx(5.0, rel=1e-3)


def test_reference_needs_crs(tmp_path, write_geotiff):
    write_geotiff(
        tmp_path / "nocrs.tif", np.zeros((4, 4), np.float32), transform=Affine(1, 0, 0, 0, -1, 0)
    )
    with pytest.raises(CrsError):
        ReferenceOrtho(tmp_path / "nocrs.tif")


def test_ref_window_geometry():
    w = RefWindow.around(10.2, 20.7, 50.1, 60.0, pad_px=5, factor=4)
    assert (w.col0, w.row0) == (5, 15)
    assert w.bounds_px[2] >= 56 and w.bounds_px[3] >= 65
    assert w.shifted(2.6, -1.4).col0 == 8 and w.shifted(2.6, -1.4).row0 == 14
    p = RefWindow(0, 0, 10, 10, 2).padded(3)
    assert p.to_tuple() == (-4, -4, 14, 14, 2)
    np.testing.assert_allclose(p.from_ref_pixel(*p.to_ref_pixel(3.3, 1.1)), (3.3, 1.1))
    with pytest.raises(InputError):
        RefWindow(0, 0, 0, 3)


@pytest.mark.parametrize("factor", [2, 5, 11])
def test_block_mean_of_whole_valid_blocks_equals_general_way(factor: int) -> None:
    """All-valid float32 data (whole blocks straight from the area resize) equal the
    general way (float64 input: counts, division, validity) bit for bit, partial blocks too.
    """
    rng = np.random.default_rng(factor)
    for h, w in [(6 * factor, 4 * factor), (6 * factor + 1, 4 * factor + factor - 1)]:
        data = rng.uniform(0, 4000, (h, w)).astype(np.float32)
        valid = np.ones((h, w), bool)
        for frac in (0.5, 1.0):
            fast, ok_fast = masked_block_mean(data, valid, factor, frac)
            slow, ok_slow = masked_block_mean(data.astype(np.float64), valid, factor, frac)
            assert fast.dtype == slow.dtype == np.float32
            np.testing.assert_array_equal(ok_fast, ok_slow)
            np.testing.assert_array_equal(fast, slow)


def test_window_inside_equals_window_across_the_edge():
    """A window wholly inside the image (read without a zeroed copy) equals the same
    pixels of a window that crosses the edge; no-data pixels are 0 and invalid in both."""
    rng = np.random.default_rng(2)
    data = rng.integers(0, 4000, (30, 40)).astype(np.uint16)
    data[4, 5] = 7
    img = CcdImage(data, nodata=7)
    inside, v_inside = img.read(0, 0, 12, 15)
    across, v_across = img.read(-2, -3, 14, 18)
    assert inside.dtype == np.float32 and v_inside.dtype == bool
    np.testing.assert_array_equal(inside, across[2:, 3:])
    np.testing.assert_array_equal(v_inside, v_across[2:, 3:])
    assert not v_inside[4, 5] and inside[4, 5] == 0.0 and v_inside.sum() == 12 * 15 - 1
    inside[0, 0] = -1.0  # the result is a copy: the array behind the reader is untouched
    assert img.read(0, 0, 1, 1)[0][0, 0] == float(data[0, 0])
