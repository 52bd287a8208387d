"""Matches, input preparation and normalisation."""

from __future__ import annotations

import numpy as np
import pytest

from planetref.errors import InputError
from planetref.matching.base import (
    MatcherSpec,
    Matches,
    keypoints_on_valid_pixels,
    prepare_image,
    robust_normalise,
)
from planetref.matching.tiling import deduplicate, tile_windows


def test_matches_validates_and_copies():
    k0 = np.array([[1.0, 2.0], [3.0, 4.0]])
    m = Matches(k0, k0 + 1, [0.5, 0.25])
    k0[0, 0] = 99
    assert m.keypoints0[0, 0] == 1.0
    assert m.keypoints0.dtype == np.float64 and m.confidence.dtype == np.float64
    assert len(m) == 2
    with pytest.raises(ValueError):
        m.keypoints0[0, 0] = 5.0  # read-only
    with pytest.raises(InputError):
        Matches(np.zeros((3, 2)), np.zeros((2, 2)), np.zeros(3))
    with pytest.raises(InputError):
        Matches(np.zeros((3, 3)), np.zeros((3, 3)), np.zeros(3))
    with pytest.raises(InputError):
        Matches(np.array([[np.nan, 0.0]]), np.zeros((1, 2)), np.zeros(1))


def test_matches_empty_select_concatenate_shift():
    e = Matches.empty()
    assert len(e) == 0
    assert (
        e.keypoints0.shape == (0, 2) and e.keypoints1.shape == (0, 2) and e.confidence.shape == (0,)
    )
    m = Matches(np.arange(6.0).reshape(3, 2), np.arange(6.0).reshape(3, 2) + 1, [0.1, 0.2, 0.3])
    assert len(m.select(np.array([True, False, True]))) == 2
    assert m.select([2]).confidence.tolist() == [0.3]
    assert len(m.select(np.array([], dtype=int))) == 0
    with pytest.raises(InputError):
        m.select(np.array([True, False]))
    both = Matches.concatenate([m, e, m])
    assert len(both) == 6
    s = m.shifted((10, 20), (1, 2))
    np.testing.assert_allclose(s.keypoints0[0], [10, 21])
    np.testing.assert_allclose(s.keypoints1[0], [2, 4])
    np.testing.assert_allclose(m.displacement, 1.0)
    assert m.to_array().shape == (3, 5)


def test_prepare_image_combines_masks():
    img = np.arange(16, dtype=np.int16).reshape(4, 4).astype(np.float32)
    img[0, 0] = np.nan
    mask = np.ones((4, 4), bool)
    mask[1, 1] = False
    out, valid = prepare_image(np.ma.masked_equal(img, 6.0), mask)
    assert out.dtype == np.float32
    assert not valid[0, 0] and not valid[1, 1] and not valid[1, 2] and valid[2, 2]
    with pytest.raises(InputError):
        prepare_image(np.zeros((2, 2, 2)))
    with pytest.raises(InputError):
        prepare_image(np.zeros((4, 4)), np.ones((3, 3), bool))
    with pytest.raises(InputError):
        prepare_image(np.zeros((4, 4), bool))


def test_robust_normalise_ignores_invalid_pixels():
    rng = np.random.default_rng(0)
    img = rng.uniform(100, 200, (64, 64)).astype(np.float32)
    valid = np.ones_like(img, bool)
    img[:10] = -3.4028226e38  # ISIS NULL
    valid[:10] = False
    norm, flat = robust_normalise(img, valid)
    assert not flat
    assert norm.dtype == np.float32
    assert 0.0 <= norm.min() and norm.max() <= 1.0
    # statistics of the valid part only: its median maps near 0.5, no-data gets that fill
    assert abs(np.median(norm[valid]) - 0.5) < 0.05
    assert np.allclose(norm[~valid], np.median(norm[valid]), atol=0.02)
    flat_img, is_flat = robust_normalise(
        np.full((32, 32), 7.0, np.float32), np.ones((32, 32), bool)
    )
    assert is_flat and not flat_img.any()


def test_keypoints_on_valid_pixels_uses_corner_convention():
    valid = np.ones((4, 5), bool)
    valid[1, 2] = False  # pixel row 1, column 2 covers x in [2, 3), y in [1, 2)
    kp = np.array(
        [[2.5, 1.5], [2.0, 1.0], [2.999, 1.999], [3.0, 1.5], [-0.1, 0], [5.0, 0], [4.99, 3.99]]
    )
    assert keypoints_on_valid_pixels(kp, valid).tolist() == [
        False,
        False,
        False,
        True,
        False,
        False,
        True,
    ]


def test_matcher_spec_rejects_unknown_paradigm():
    with pytest.raises(InputError):
        MatcherSpec("x", "x", "magic", (), lambda **_: None)  # type: ignore[arg-type]


def test_tiles_cover_and_dedup():
    covered = np.zeros((1000, 700), int)
    for r, c, nr, nc in tile_windows((1000, 700), 256, 32):
        assert nr <= 256 and nc <= 256
        covered[r : r + nr, c : c + nc] += 1
    assert covered.min() >= 1
    k = np.array([[1.0, 1.0], [1.2, 1.0], [10.0, 10.0]])
    m = Matches(k, k + 2, [0.5, 0.9, 0.1])
    d = deduplicate(m, 0.5)
    assert len(d) == 2
    assert d.confidence.tolist() == [0.9, 0.1]


def test_deduplicate_equals_greedy_reference():
    """Visiting only close pairs keeps exactly the greedy survivors (confidence order)."""
    from scipy.spatial import cKDTree

    def greedy(m: Matches, radius: float) -> Matches:
        order = np.argsort(-m.confidence, kind="stable")
        pts = np.column_stack([m.keypoints0, m.keypoints1])[order]
        tree = cKDTree(pts)
        removed = np.zeros(len(pts), bool)
        for i in range(len(pts)):
            if not removed[i]:
                for j in tree.query_ball_point(pts[i], radius):
                    removed[j] |= j > i
        return m.select(order[~removed])

    rng = np.random.default_rng(11)
    n_removed = 0
    for _ in range(40):
        n = int(rng.integers(2, 200))
        k0 = np.round(rng.uniform(0, 15, (n, 2)), 1)  # coarse grid: many near-duplicates
        k1 = k0 + np.round(rng.uniform(0, 2, (n, 2)), 1)
        m = Matches(k0, k1, np.round(rng.uniform(0, 1, n), 1))
        for radius in (1e-3, 0.5, 1.5):
            got, want = deduplicate(m, radius), greedy(m, radius)
            np.testing.assert_array_equal(got.keypoints0, want.keypoints0)
            np.testing.assert_array_equal(got.keypoints1, want.keypoints1)
            np.testing.assert_array_equal(got.confidence, want.confidence)
            n_removed += n - len(got)
    assert n_removed > 100
