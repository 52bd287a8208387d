"""The dense NCC matcher's compiled shared-sum path against its numpy/OpenCV reference."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.lib.stride_tricks import sliding_window_view

from planetref.matching import correlation
from planetref.matching.base import prepare_image, robust_normalise
from planetref.matching.ncc import NccMatcher, _box_stats, correlate_batch, correlate_shared
from planetref.runtime.optional import optional_module

compiled = optional_module("planetref.matching._numba_ncc", "compiled NCC")
needs_numba = pytest.mark.skipif(compiled is None, reason="numba is not available")


def exact_zncc(templates, windows, masks=None):
    """float64 ZNCC by direct sums (no FFT) with OpenCV's ``TM_CCOEFF_NORMED`` rules.

    Whole template: a window without variance gives 0 (OpenCV's guard); partial
    template (masked): means and variances over its valid pixels, undefined where the
    window has no variance there.
    """
    t = np.asarray(templates, np.float64)
    w = np.asarray(windows, np.float64)
    n, a, b = t.shape
    m = np.ones(t.shape) if masks is None else np.asarray(masks, np.float64)
    out = np.empty((n, w.shape[1] - a + 1, w.shape[2] - b + 1))
    for k in range(n):
        cnt = m[k].sum()
        tc = (t[k] - (t[k] * m[k]).sum() / cnt) * m[k]
        view = sliding_window_view(w[k], (a, b))
        s1 = (view * m[k]).sum(axis=(2, 3))
        s2 = (view * view * m[k]).sum(axis=(2, 3))
        num = (view * tc).sum(axis=(2, 3))
        den = np.sqrt(np.maximum(s2 - s1 * s1 / cnt, 0.0)) * np.sqrt((tc * tc).sum())
        with np.errstate(invalid="ignore", divide="ignore"):
            v = num / den
        if cnt < a * b:
            out[k] = np.where(den > 0, v, correlation.INVALID)
        else:
            guard = np.where(np.abs(num) < 1.125 * den, np.sign(num), 0.0)
            out[k] = np.where(np.abs(num) < den, v, guard)
    vals = t.reshape(n, -1)
    wt = m.reshape(n, -1)
    mean = (vals * wt).sum(axis=1) / wt.sum(axis=1)
    spread = np.sqrt(((vals - mean[:, None]) ** 2 * wt).sum(axis=1) / wt.sum(axis=1))
    out[spread <= 1e-7 * (1.0 + np.abs(vals * wt).max(axis=1))] = correlation.INVALID
    return np.clip(out, correlation.INVALID, 1.0)


def setup(a, b, matcher, mask0=None, mask1=None):
    """Normalised images, the dense matcher's template centres and image 1's exclusions."""
    img0, valid0 = prepare_image(a, mask0)
    img1, valid1 = prepare_image(b, mask1)
    n0, _ = robust_normalise(img0, valid0)
    n1, _ = robust_normalise(img1, valid1)
    t = matcher.template_radius
    std0, bad0 = _box_stats(n0, valid0, t)
    _, bad1 = _box_stats(n1, valid1, t)
    h, w = n0.shape
    rr, cc = np.mgrid[0:h, 0:w]
    inside = (rr >= t) & (rr < h - t) & (cc >= t) & (cc < w - t)
    score = np.where(~bad0 & inside & (std0 >= matcher.min_std), 2.0 + std0, -1.0)
    rows, cols = matcher._dense_grid(score)
    return n0, valid0, n1, bad1, rows, cols


def random_pair(size, seed):
    rng = np.random.default_rng(seed)
    a = rng.random((size, size)).astype(np.float32)
    b = np.roll(a, (2, -1), axis=(0, 1)) + 0.05 * rng.standard_normal((size, size))
    return a, b.astype(np.float32)


def grid_in(valid0, t, step):
    """Template centres every ``step`` pixels on valid pixels, and which are partial."""
    h, w = valid0.shape
    rr, cc = np.mgrid[t : h - t : step, t : w - t : step]
    rows, cols = rr.ravel(), cc.ravel()
    keep = valid0[rows, cols]
    rows, cols = rows[keep], cols[keep]
    partial = ~np.array(
        [
            valid0[r - t : r + t + 1, c - t : c + t + 1].all()
            for r, c in zip(rows, cols, strict=True)
        ]
    )
    return rows, cols, partial


def slanted_mask(shape):
    """Image 0's valid area: below a slanted line (the edge of a CCD's footprint)."""
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
    return yy >= 10 + 0.4 * xx


@needs_numba
@pytest.mark.parametrize("kind", ["texture", "random"])
def test_compiled_equals_exact_float64_reference(shifted_pair, monkeypatch, kind):
    """Same peaks as the reference fed with exact float64 surfaces (OpenCV's are float32),
    whole and partial templates, no-data in image 1 and a flat template."""
    if kind == "texture":
        a, b = shifted_pair(size=112, shift=(1.6, -2.3), seed=5)
    else:
        a, b = random_pair(112, 7)
    mask1 = np.ones(b.shape, bool)
    mask1[60:70, 20:50] = False  # no-data in image 1: candidate windows touching it excluded
    matcher = NccMatcher(template_radius=6, search_radius=7, dense_spacing_px=3)
    n0, valid0, n1, bad1, _, _ = setup(a, b, matcher, slanted_mask(a.shape), mask1)
    rows, cols, partial = grid_in(valid0, 6, 3)
    # one flat whole template: its surface is invalid in both
    n0 = n0.copy()
    f = np.flatnonzero(~partial)[40]
    n0[rows[f] - 6 : rows[f] + 7, cols[f] - 6 : cols[f] + 7] = 0.25
    got = correlate_shared(n0, n1, bad1, rows, cols, rows, cols, matcher, valid0)
    monkeypatch.setattr(correlation, "zncc_surfaces", exact_zncc)
    ref = correlate_batch(n0, n1, bad1, rows, cols, rows, cols, matcher, valid0)
    assert partial.sum() > 50 and ref[3][partial].sum() > 30 and ref[3][~partial].sum() > 300
    assert not ref[3][f] and not got[3][f]
    np.testing.assert_array_equal(got[3], ref[3])
    ok = ref[3]
    np.testing.assert_allclose(got[0][ok], ref[0][ok], atol=1e-4, rtol=0)
    np.testing.assert_allclose(got[1][ok], ref[1][ok], atol=1e-4, rtol=0)
    np.testing.assert_allclose(got[2][ok], ref[2][ok], atol=1e-6, rtol=0)


@needs_numba
def test_compiled_close_to_opencv_reference(shifted_pair):
    """Against the shipped reference (OpenCV's float32 FFT, masked for partial templates):
    the same matches within its rounding noise, whole and partial templates."""
    a, b = shifted_pair(size=128, shift=(2.4, 1.3), seed=9)
    matcher = NccMatcher(template_radius=7, search_radius=6, dense_spacing_px=3)
    n0, valid0, n1, bad1, _, _ = setup(a, b, matcher, mask0=slanted_mask(a.shape))
    rows, cols, partial = grid_in(valid0, 7, 3)
    assert partial.sum() > 50 and (~partial).sum() > 500
    got = correlate_shared(n0, n1, bad1, rows, cols, rows, cols, matcher, valid0)
    ref = correlate_batch(n0, n1, bad1, rows, cols, rows, cols, matcher, valid0)
    assert (got[3] != ref[3]).sum() <= 2  # a peak at a threshold may flip
    for part in (partial, ~partial):
        both = part & got[3] & ref[3]
        assert both.sum() > 40
        d = np.hypot(got[0][both] - ref[0][both], got[1][both] - ref[1][both])
        assert np.median(d) < 1e-3 and d.max() < 0.02
        assert np.abs(got[2][both] - ref[2][both]).max() < 5e-4
    # and the matches find the true shift
    disp = np.column_stack([got[0] - cols - 0.5, got[1] - rows - 0.5])[got[3]]
    np.testing.assert_allclose(np.median(disp, axis=0), [2.4, 1.3], atol=0.05)


def test_without_numba_the_reference_runs(shifted_pair):
    a, b = shifted_pair(size=96, shift=(1.2, 0.7), seed=3)
    matcher = NccMatcher(template_radius=5, search_radius=5, dense_spacing_px=4)
    n0, _, n1, bad1, rows, cols = setup(a, b, matcher)
    got = correlate_shared(n0, n1, bad1, rows, cols, rows, cols, matcher, compiled=False)
    ref = correlate_batch(n0, n1, bad1, rows, cols, rows, cols, matcher)
    for g, r in zip(got, ref, strict=True):
        np.testing.assert_array_equal(g, r)


@needs_numba
def test_scattered_offsets_and_unreachable_predictions(shifted_pair):
    """Predictions that are not one offset from the centres take the reference; a
    uniform offset that leaves image 1 gives no match."""
    a, b = shifted_pair(size=96, shift=(1.2, 0.7), seed=3)
    matcher = NccMatcher(template_radius=5, search_radius=5, dense_spacing_px=4)
    n0, _, n1, bad1, rows, cols = setup(a, b, matcher)
    r1 = rows + (np.arange(len(rows)) % 2)
    got = correlate_shared(n0, n1, bad1, rows, cols, r1, cols, matcher)
    ref = correlate_batch(n0, n1, bad1, rows, cols, r1, cols, matcher)
    for g, r in zip(got, ref, strict=True):
        np.testing.assert_array_equal(g, r)
    far = correlate_shared(n0, n1, bad1, rows, cols, rows + 500, cols, matcher)
    assert not far[3].any()
