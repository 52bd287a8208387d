"""The vectorised NCC matcher against the per-template reference, and its dense mode."""

from __future__ import annotations

import numpy as np

from planetref.matching.base import prepare_image, robust_normalise
from planetref.matching.ncc import NccMatcher, _box_stats, _correlate


def test_batch_equals_per_template_reference(shifted_pair):
    a, b = shifted_pair(size=160, shift=(3.3, -2.6), seed=2)
    matcher = NccMatcher(spacing=12, search_radius=8)
    got = matcher.match(a, b)
    img0, valid0 = prepare_image(a)
    img1, valid1 = prepare_image(b)
    n0, _ = robust_normalise(img0, valid0)
    n1, _ = robust_normalise(img1, valid1)
    t = matcher.template_radius
    std0, bad0 = _box_stats(n0, valid0, t)
    _, bad1 = _box_stats(n1, valid1, t)
    rows, cols = matcher._grid(n0.shape)
    ref = {}
    for r, c in zip(rows, cols, strict=True):
        if std0[r, c] < matcher.min_std or bad0[r, c]:
            continue
        hit = _correlate(n0, n1, bad1, r, c, r, c, t, 8, 0.5, 0.9, "quadratic")
        if hit is not None:
            ref[(c + 0.5, r + 0.5)] = hit
    assert len(ref) > 50
    assert {tuple(k) for k in got.keypoints0} == set(ref)
    for k0, k1, conf in zip(got.keypoints0, got.keypoints1, got.confidence, strict=True):
        x, y, v = ref[tuple(k0)]
        assert abs(k1[0] - x) < 5e-3 and abs(k1[1] - y) < 5e-3 and abs(conf - v) < 1e-3
    # and it finds the true shift
    np.testing.assert_allclose(np.median(got.displacement, axis=0), [3.3, -2.6], atol=0.05)


def test_dense_mode_one_template_per_cell(shifted_pair):
    a, b = shifted_pair(size=192, shift=(1.7, 2.2), seed=4)
    m = NccMatcher(dense_spacing_px=8, search_radius=6).match(a, b)
    cells = {(int(x // 8), int(y // 8)) for x, y in m.keypoints0}
    assert len(cells) == len(m)  # at most one per cell
    usable_cells = ((192 - 20) // 8) ** 2
    assert len(m) >= 0.8 * usable_cells
    err = np.abs(m.displacement - [1.7, 2.2])
    assert np.median(err) < 0.05 and np.percentile(err, 95) < 0.2
