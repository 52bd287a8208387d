"""The sub-pixel bias benchmark's pairs have the true displacement it says they have.

The benchmark (benchmarks/bench_subpixel_bias.py) builds shifted copies of a texture by
block means and the front end's two image styles; if its ``t`` were off by a fraction of
a pixel, every matcher would show that fraction as a bias. A ramp checks the block means
exactly; SIFT (sub-pixel accurate, no weights) checks every pair style on a texture.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"


@pytest.fixture(scope="module")
def bench():
    sys.path.insert(0, str(BENCH))
    try:
        import bench_subpixel_bias

        yield bench_subpixel_bias
    finally:
        sys.path.remove(str(BENCH))


@pytest.fixture(scope="module")
def texture():
    rng = np.random.default_rng(0)
    t = ndimage.gaussian_filter(rng.normal(size=(1000, 1000)), 3.0)
    return 1000.0 + 200.0 * t / t.std()


def test_block_means_shift_a_ramp_by_d_over_k(bench):
    ramp = np.tile(np.arange(200, dtype=np.float64), (200, 1))  # value = texture column
    for k, d in ((4, 0), (4, 1), (4, 3), (5, 2)):
        (pair,) = bench.shift_pairs(ramp, k, [(d, 0)], 32)
        # pixel i of image1 shows what image0 shows at i + d / k: t = -d / k
        assert pair.t == (-d / k, -0.0)
        np.testing.assert_allclose(pair.image1 - pair.image0, d, atol=1e-4)  # d columns
        np.testing.assert_allclose(np.diff(pair.image0[0]), k, atol=1e-4)  # k per pixel


def _sift_bias(bench, pairs):
    from planetref.matching.registry import get_matcher

    m = get_matcher("sift")
    means = []
    for p in pairs:
        e, _ = bench.errors(m, p)
        assert len(e) > 50, p.label
        means.append(e.mean(axis=0))
    return np.array(means)


def test_sift_finds_no_bias_on_the_phase_pairs(bench, texture):
    means = _sift_bias(bench, bench.build_pairs("phases", texture, 4, 160))
    assert np.abs(means).max() < 0.05
    assert np.abs(means.mean(axis=0)).max() < 0.02


def test_sift_finds_no_bias_on_the_front_end_pairs(bench, texture):
    # the CCD side (2 x 2 blocks, bilinear) against the 8-bit 5 m reference upsampled x2
    means = _sift_bias(bench, bench.build_pairs("frontend", texture, 4, 160))
    assert np.abs(means).max() < 0.08
    assert np.abs(means.mean(axis=0)).max() < 0.04
