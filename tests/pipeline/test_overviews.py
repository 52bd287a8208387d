"""Overviews computed while an output is written: GDAL's AVERAGE, bit for bit."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import rasterio
from rasterio.enums import Resampling
from rasterio.transform import from_origin
from rasterio.windows import Window

from planetref.products import _numba_ortho as kernel
from planetref.products.overviews import (
    OverviewPyramid,
    halve_reference,
    overview_factors,
    padded_size,
)

CASES = [("uint16", 65535.0), ("uint8", 255.0), ("int16", -32768.0), ("float32", float("nan"))]


def _pixels(dtype: str, nodata: float, shape: tuple[int, int], seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if dtype == "float32":
        a = rng.uniform(-3000.0, 3000.0, shape).astype(np.float32)
    elif dtype == "int16":
        a = rng.integers(-3000, 3001, shape).astype(np.int16)
    else:
        a = rng.integers(0, 250, shape).astype(dtype)
    hole = rng.random(shape) < 0.3  # scattered nodata: blocks of 1-3 valid pixels
    hole[:, : shape[1] // 5] = True  # and a band without any
    a[hole] = nodata
    return a


@pytest.mark.parametrize(("dtype", "nodata"), CASES)
def test_compiled_halving_equals_the_reference(dtype, nodata):
    a = _pixels(dtype, nodata, (64, 96), 1)
    if dtype == "int16":
        # Ties on both sides of zero: GDAL rounds half away from zero.
        a[0, :4] = [-3, -4, 5, 6]  # means -3.5 and 5.5 over the first 2 x 2 blocks
        a[1, :4] = [-3, -4, 5, 6]
    out = np.empty((32, 48), a.dtype)
    kernel.halve_rows(a, nodata, dtype != "float32", out)
    ref = halve_reference(a, nodata)
    assert np.array_equal(out, ref, equal_nan=dtype == "float32")
    if dtype == "int16":
        assert ref[0, :2].tolist() == [-4, 6]


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize(("dtype", "nodata"), CASES)
def test_pyramid_equals_gdal_average(tmp_path, dtype, nodata, compiled):
    # 1024 x 768 with factors 2, 4, 8 (a smaller side of at least 96 per level).
    width, height = 1024, 768
    factors = overview_factors(width, height, min_side=96)
    assert factors == [2, 4, 8]
    a = _pixels(dtype, nodata, (height, width), 2)
    profile = {
        "driver": "GTiff",
        "width": width,
        "height": height,
        "count": 1,
        "dtype": dtype,
        "nodata": nodata,
        "tiled": True,
        "blockxsize": 256,
        "blockysize": 256,
        "compress": "deflate",
        "transform": from_origin(1000.0, 2000.0, 1.0, 1.0),
    }
    mine = tmp_path / "mine.tif"
    pyr = OverviewPyramid(
        width, height, factors, dtype, nodata, tmp_path, kernel if compiled else None
    )
    with rasterio.open(mine, "w", **profile) as ds:
        ds.build_overviews(factors, Resampling.nearest)  # empty directories, filled below
        r0 = 0
        for n in (3, 5, 1, 255, 256, 248):  # odd blocks: rows wait for their pair
            ds.write(a[r0 : r0 + n], 1, window=Window(0, r0, width, n))
            pyr.push(a[r0 : r0 + n])
            r0 += n
        assert r0 == height
    pyr.write_into(mine)
    pyr.close()
    # GDAL's own overviews of the same pixels.
    gdal = tmp_path / "gdal.tif"
    with rasterio.open(gdal, "w", **profile) as ds:
        ds.write(a, 1)
        ds.build_overviews(factors, Resampling.average)
    with rasterio.open(mine) as m, rasterio.open(gdal) as g:
        assert m.overviews(1) == g.overviews(1) == factors
        assert np.array_equal(m.read(1), a, equal_nan=True)
    for k in range(len(factors)):
        with rasterio.open(mine, overview_level=k) as m, rasterio.open(gdal, overview_level=k) as g:
            x, y = m.read(1), g.read(1)
            assert x.shape == (height >> (k + 1), width >> (k + 1))
            assert np.array_equal(x, y, equal_nan=True), f"level {k}"
            valid = ~np.isnan(x) if dtype == "float32" else x != nodata
            assert 0.5 < valid.mean() < 0.9  # the test sees valid and nodata pixels
    # The spool files were anonymous: only the two outputs are left.
    assert sorted(p.name for p in tmp_path.iterdir()) == ["gdal.tif", "mine.tif"]


def test_pyramid_refuses_what_it_cannot_make_exactly(tmp_path):
    with pytest.raises(ValueError, match="multiple of 4"):
        OverviewPyramid(1022, 512, [2, 4], "uint8", 255, tmp_path)
    with pytest.raises(ValueError, match="2, 4, 8"):
        OverviewPyramid(1024, 512, [2, 8], "uint8", 255, tmp_path)
    path = tmp_path / "short.tif"
    profile = {"driver": "GTiff", "width": 64, "height": 64, "count": 1, "dtype": "uint8"}
    profile["transform"] = from_origin(0.0, 64.0, 1.0, 1.0)
    with rasterio.open(path, "w", **profile) as ds:
        ds.build_overviews([2], Resampling.nearest)
    pyr = OverviewPyramid(64, 64, [2], "uint8", 255, tmp_path)
    pyr.push(np.zeros((63, 64), np.uint8))  # one row short: a row waits for its pair
    with pytest.raises(ValueError, match="31 of 32 rows"):
        pyr.write_into(path)
    pyr.close()
    copy = tmp_path / "copy.tif"
    shutil.copy(path, copy)
    other = OverviewPyramid(128, 64, [2], "uint8", 255, tmp_path)
    other.push(np.zeros((64, 128), np.uint8))
    with pytest.raises(ValueError, match="not 64 x 32"):
        other.write_into(copy)  # the file's level is 32 x 32
    other.close()


def test_padded_size_is_divisible_by_its_own_factors():
    assert overview_factors(4090, 5000) == [2, 4, 8]
    # Padding to 8 makes 4096 x 5000, which has a level at 16: padded again to 16.
    assert padded_size(4090, 5000) == (4096, 5008)
    assert overview_factors(4096, 5008) == [2, 4, 8, 16]
    assert padded_size(511, 9000) == (511, 9000)  # no overview, no padding
    assert padded_size(513, 513) == (514, 514)
    for w in range(500, 5000, 37):
        for h in (512, 777, 4097):
            pw, ph = padded_size(w, h)
            top = max(overview_factors(pw, ph), default=1)
            assert pw % top == 0 and ph % top == 0 and 0 <= pw - w < 2 * top
