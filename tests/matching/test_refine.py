"""Sub-pixel refinement (LSM with NCC fallback): recovery of known shifts and affine maps.

image1 is image0 warped by a known affine map ``x1 = A x0 + t`` (cubic interpolation of a
band-limited texture, so the warp itself is nearly exact), plus gain/offset and noise; the
refinement starts from the true point plus up to +-1.5 px of error per axis.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from planetref.errors import InputError
from planetref.matching._synthetic import texture
from planetref.matching.refine import RefineConfig, RefineResult, refine_matches

A_SHIFT = (np.eye(2), np.array([3.37, -2.61]))
A_AFFINE = (np.array([[1.03, 0.04], [-0.03, 0.98]]), np.array([-1.73, 2.29]))


def _warp(base: np.ndarray, pad: int, size: int, a: np.ndarray, t: np.ndarray) -> np.ndarray:
    """image1 on a size x size grid with image1(A x + t) = base_crop(x)."""
    yy, xx = np.mgrid[0:size, 0:size] + 0.5
    x1 = np.stack([xx.ravel(), yy.ravel()])
    x0 = np.linalg.inv(a) @ (x1 - t[:, None])
    coords = [x0[1] - 0.5 + pad, x0[0] - 0.5 + pad]
    return ndimage.map_coordinates(base, coords, order=3, mode="reflect").reshape(size, size)


def _case(base, pad, size, warp, n=300, noise=0.0, seed=3):
    a, t = warp
    img0 = base[pad : pad + size, pad : pad + size]
    img1 = 0.7 * _warp(base, pad, size, a, t) + 0.2 * base.std()
    rng = np.random.default_rng(seed)
    if noise:
        img0 = img0 + noise * rng.standard_normal(img0.shape)
        img1 = img1 + noise * rng.standard_normal(img1.shape)
    p0 = rng.uniform(24, size - 24, (n, 2))
    true1 = p0 @ a.T + t
    start1 = true1 + rng.uniform(-1.5, 1.5, (n, 2))
    return img0, img1, p0, true1, start1


def _errors(res: RefineResult, true1: np.ndarray) -> np.ndarray:
    return np.hypot(*(res.points1 - true1)[res.ok].T)


@pytest.mark.parametrize("warp", [A_SHIFT, A_AFFINE], ids=["shift", "affine"])
def test_lsm_recovers_known_warp_on_synthetic_texture(warp):
    base = texture(200, seed=5, pad=32)
    img0, img1, p0, true1, start1 = _case(base, 32, 200, warp)
    res = refine_matches(img0, img1, p0, start1, RefineConfig(method="lsm"))
    err = _errors(res, true1)
    assert res.ok.mean() >= 0.98
    assert set(res.method[res.ok]) == {"lsm"}
    assert np.median(err) <= 0.02
    assert np.percentile(err, 95) <= 0.05
    # the initial error was up to 2 px: the refinement really moved the points
    assert np.median(np.hypot(*(start1 - true1).T)) > 0.5


def test_lsm_recovers_known_warp_on_real_hirise_texture(hirise_dir):
    from planetref.cli.match import read_band

    img, valid = read_band(hirise_dir / "no_change_before.cub")
    base = img[-300:, -300:].astype(np.float64)  # rows 0-94 hold ISIS NULL pixels
    assert valid[-300:, -300:].all()
    base = (base - base.mean()) / base.std()
    for warp in (A_SHIFT, A_AFFINE):
        img0, img1, p0, true1, start1 = _case(base, 50, 200, warp, n=200)
        res = refine_matches(img0, img1, p0, start1, RefineConfig(method="lsm"))
        err = _errors(res, true1)
        assert res.ok.mean() >= 0.9
        assert np.median(err) <= 0.03
        assert np.percentile(err, 90) <= 0.05
        # without the low-pass, bilinear resampling of this texture is biased
        raw = refine_matches(img0, img1, p0, start1, RefineConfig(method="lsm", smooth_px=0))
        assert np.median(_errors(raw, true1)) > 2 * np.median(err)


def test_ncc_method_and_fallback_are_sub_pixel():
    base = texture(200, seed=6, pad=32)
    img0, img1, p0, true1, start1 = _case(base, 32, 200, A_SHIFT)
    ncc = refine_matches(img0, img1, p0, start1, RefineConfig(method="ncc"))
    assert set(ncc.method[ncc.ok]) == {"ncc"}
    err = _errors(ncc, true1)
    assert ncc.ok.mean() >= 0.95 and np.median(err) <= 0.15
    # one Gauss-Newton step cannot converge from 1.5 px away: LSM falls back to NCC
    fallback = refine_matches(img0, img1, p0, start1, RefineConfig(method="lsm", max_iter=1))
    assert (fallback.method[fallback.ok] == "ncc").mean() > 0.9
    np.testing.assert_allclose(fallback.points1[fallback.ok], ncc.points1[fallback.ok])


@pytest.mark.parametrize("smooth", [0.0, 1.0])
def test_sigma_px_matches_the_empirical_scatter(smooth):
    base = texture(240, seed=7, pad=32)
    noise = 0.08 * base.std()
    img0, img1, p0, true1, start1 = _case(base, 32, 240, A_SHIFT, n=400, noise=noise)
    res = refine_matches(img0, img1, p0, start1, RefineConfig(method="lsm", smooth_px=smooth))
    d = (res.points1 - true1)[res.ok]
    empirical = np.sqrt(np.mean(d**2))  # RMS per axis
    predicted = np.sqrt(np.mean(res.sigma_px[res.ok] ** 2))
    assert 0.5 <= predicted / empirical <= 2.0
    assert np.all(np.isfinite(res.sigma_px[res.ok]))
    assert np.all(np.isnan(res.sigma_px[~res.ok]))


def test_drops_carry_reasons():
    base = texture(160, seed=8, pad=32)
    img0, img1, p0, true1, start1 = _case(base, 32, 160, A_SHIFT, n=40)
    unrelated = texture(160, seed=99, pad=0)[:160, :160]
    p0b = np.array([[2.0, 80.0], [80.0, 157.5]])  # template leaves image 0
    pts0 = np.vstack([p0, p0b])
    pts1 = np.vstack([start1, p0b])
    res = refine_matches(img0, img1, pts0, pts1, RefineConfig(method="lsm"))
    assert list(res.reason[-2:]) == ["border", "border"]
    assert res.ok[:-2].mean() >= 0.95
    # against an unrelated image nothing survives, and each drop says why
    bad = refine_matches(img0, unrelated, p0, start1, RefineConfig(method="lsm"))
    assert bad.ok.mean() <= 0.1
    assert set(bad.reason[~bad.ok]) <= {"low_correlation", "shift", "diverged", "border"}
    # a max_shift below the true error: the points cannot move that far
    tight = refine_matches(img0, img1, p0, start1, RefineConfig(method="lsm", max_shift_px=0.2))
    far = np.hypot(*(start1 - true1).T) > 0.4
    assert not tight.ok[far].any()
    # invalid pixels in image 1 under the window
    valid1 = np.ones_like(img1, bool)
    valid1[:, 80:] = False
    masked = refine_matches(img0, img1, p0, start1, RefineConfig(method="lsm"), valid1=valid1)
    right = start1[:, 0] > 78
    assert not masked.ok[right].any() and set(masked.reason[right]) == {"border"}
    assert masked.ok[start1[:, 0] < 60].mean() >= 0.9
    # counts add up
    counts = res.counts()
    assert sum(counts.values()) == len(pts0) and counts["border"] == 2


def test_none_and_validation():
    img = texture(64, seed=1, pad=0)
    pts = np.array([[30.2, 31.7]])
    res = refine_matches(img, img, pts, pts + 0.3, RefineConfig())
    assert res.ok.all() and res.method[0] == "none" and np.isnan(res.sigma_px[0])
    np.testing.assert_array_equal(res.points1, pts + 0.3)
    empty = refine_matches(img, img, np.empty((0, 2)), np.empty((0, 2)), RefineConfig(method="lsm"))
    assert empty.points1.shape == (0, 2)
    with pytest.raises(InputError):
        refine_matches(img, img, pts, np.empty((2, 2)), RefineConfig(method="lsm"))
    with pytest.raises(InputError):
        refine_matches(img[0], img, pts, pts, RefineConfig(method="lsm"))
    with pytest.raises(ValueError):
        RefineConfig(method="bogus")
    with pytest.raises(ValueError):
        RefineConfig(half_widow=3)
