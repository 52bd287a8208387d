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


def test_partial_templates_reach_the_edge_of_the_valid_area(shifted_pair):
    """Templates cut by image 0's no-data area correlate over their valid pixels only."""
    a, b = shifted_pair(size=192, shift=(1.7, 2.2), seed=4)
    mask0 = np.ones(a.shape, bool)
    mask0[:, 120:] = False  # a straight edge at column 120
    yy, xx = np.mgrid[0 : a.shape[0], 0 : a.shape[1]]
    mask0 &= yy >= 40 + 0.3 * xx  # and a slanted one
    t = 10
    got = {}
    for frac in (1.0, 0.5):
        m = NccMatcher(dense_spacing_px=4, search_radius=6, min_template_valid=frac)
        got[frac] = m.match(a, b, mask0)
    whole, part = got[1.0], got[0.5]
    x, y = part.keypoints0[:, 0], part.keypoints0[:, 1]
    # Whole templates stop a radius short of the edge; partial ones reach it.
    assert whole.keypoints0[:, 0].max() < 120 - t
    assert x.max() > 118 and (x > 120 - t).sum() >= 30
    assert mask0[np.floor(y).astype(int), np.floor(x).astype(int)].all()
    # Every whole-template match is kept, to the bit (cells prefer whole templates).
    common = {tuple(k) for k in whole.keypoints0}
    assert common <= {tuple(k) for k in part.keypoints0}
    # The partial ones are as accurate as the whole ones on this pure shift.
    edge = np.array([tuple(k) not in common for k in part.keypoints0])
    assert edge.sum() >= 60
    err = np.abs(part.displacement[edge] - [1.7, 2.2])
    err_whole = np.abs(whole.displacement - [1.7, 2.2])
    print(
        f"whole {len(whole)} median {np.median(err_whole):.3f}; "
        f"partial {edge.sum()} median {np.median(err):.3f} p95 {np.percentile(err, 95):.3f}"
    )
    assert np.median(err) < 0.05 and np.percentile(err, 95) < 0.2
