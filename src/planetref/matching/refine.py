"""Sub-pixel refinement of matches, the same for every matcher.

Least-squares matching (LSM, Gruen 1985; the photogrammetric standard): the template of
``(2h + 1)^2`` pixels of image 0 around each ``points0`` is fitted to image 1 under an
affine geometric and a linear radiometric model,

    f(u, v) = r0 + r1 * g(tx + (1 + a1) u + a2 v,  ty + b1 u + (1 + b2) v),

where ``(u, v)`` is the offset of a template pixel centre from ``points0``, ``g`` is image 1
resampled bilinearly and ``(tx, ty)`` is the refined ``points1``. The 8 parameters are
solved by Gauss-Newton from ``(tx, ty) = points1``, identity affine and the radiometry that
matches the template's mean and spread. The template is read at whole pixels (no
resampling of image 0), so ``points0`` stays exactly where the matcher put it.

Precision: after convergence, ``sigma0^2 = e'e / (M - 8)`` (``M`` template pixels, ``e`` the
grey-value residuals) and the covariance ``sigma0^2 (J'J)^-1``; ``sigma_px`` is the RMS of the
standard deviations of ``tx`` and ``ty``, ``sqrt((s_x^2 + s_y^2) / 2)``, in pixels, multiplied
by the noise-correlation factor of the low-pass (see :func:`_noise_inflation`). It is an
internal (noise-driven) precision; it does not see errors common to the whole template.

A match whose LSM diverges (singular normal equations, no convergence in ``max_iter``,
an implausible affine or radiometric solution, or a move beyond ``max_shift_px``) falls
back to NCC: the ZNCC surface over integer displacements within ``ceil(max_shift_px)``
pixels of ``points1`` (image 1 resampled bilinearly at the template's offsets), peak
located by a 2-D quadratic fit to its 3x3 neighbourhood (:mod:`planetref.matching.correlation`).
Its ``sigma_px`` comes from the translation-only LSM normal equations at the NCC position.

Drops and their reasons: ``"border"`` (template or resampled window leaves an image or
touches an invalid pixel), ``"low_correlation"`` (final ZNCC below ``min_ncc``, a flat
template, or no peak in the NCC surface), ``"shift"`` (the refined point is farther than
``max_shift_px`` from the input ``points1``, or the NCC peak lies on the edge of the search
range), ``"diverged"`` (LSM diverged and the NCC fallback is not used, i.e. never with
``method="lsm"``, kept for completeness).

Everything is vectorised over matches (chunks of :data:`CHUNK` matches).
Coordinates: ``(x, y) = (sample, line)``, top-left corner of the first pixel at ``(0, 0)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field

from planetref.errors import InputError
from planetref.matching.correlation import INVALID, quadratic_peaks, zncc_surfaces
from planetref.runtime.settings import Settings

__all__ = ["RefineConfig", "RefineResult", "refine_matches"]

#: Matches processed together (memory ~ CHUNK * (2h+1)^2 * 8 * 8 bytes for the Jacobian).
CHUNK = 2048
#: Convergence: translation update below this (pixels).
TOL_PX = 2e-3
#: Convergence: affine update times ``h`` (its effect at the template edge) below this, px.
TOL_AFFINE_PX = 5e-3
#: Largest accepted affine deformation term (|a1|, |a2|, |b1|, |b2|).
MAX_AFFINE = 0.5
#: Normal matrices scaled to a unit diagonal with ``log(det)`` below this count as singular.
MIN_LOGDET = -40.0


class RefineConfig(Settings):
    """Settings of :func:`refine_matches`.

    Attributes:
        method: ``"none"``, ``"lsm"`` (falls back to NCC per match when LSM diverges) or
            ``"ncc"``.
        half_window: Template half size ``h``, pixels of image 0 (template ``2h + 1``).
            Default 10 (21 x 21, the NCC matcher's template): on the real HiRISE no-change
            pair (SIFT matches) the median distance to the robust affine field is 0.49 px
            at h = 7, 0.40 px at h = 10, 0.31 px at h = 15 (benchmarks/bench_precision.py).
        max_iter: Gauss-Newton iterations at most.
        max_shift_px: The refinement may move a point at most this far, pixels.
        min_ncc: Matches whose final ZNCC is below this are dropped.
        smooth_px: Standard deviation (pixels) of a Gaussian low-pass applied to both
            images before matching (0: none). Bilinear resampling of unsmoothed real
            texture biases sub-pixel positions towards whole pixels (measured on HiRISE:
            median error 0.09-0.12 px unsmoothed, 0.015-0.023 px at 1 px; see
            tests/matching/test_refine.py). Pixels within ``ceil(2 * smooth_px)`` of an
            invalid pixel become invalid.
    """

    method: Literal["none", "lsm", "ncc"] = "none"
    half_window: int = Field(10, ge=2, le=64)
    max_iter: int = Field(20, ge=1, le=200)
    max_shift_px: float = Field(3.0, gt=0.0, le=64.0)
    min_ncc: float = Field(0.5, ge=-1.0, le=1.0)
    smooth_px: float = Field(1.0, ge=0.0, le=8.0)


@dataclass(frozen=True)
class RefineResult:
    """Result of :func:`refine_matches`.

    Attributes:
        points1: ``(N, 2)`` float64 refined ``(x, y)`` in image 1 (the input value where
            dropped or not refined); ``points0`` stay fixed.
        sigma_px: ``(N,)`` a-posteriori precision, pixels (NaN where not refined).
        ok: ``(N,)`` bool; False = dropped.
        reason: ``(N,)`` str: ``""`` or ``"diverged" | "low_correlation" | "border" |
            "shift"``.
        method: ``(N,)`` str: ``"lsm" | "ncc" | "none"`` (what produced ``points1``).
    """

    points1: NDArray[np.float64]
    sigma_px: NDArray[np.float64]
    ok: NDArray[np.bool_]
    reason: NDArray[np.str_]
    method: NDArray[np.str_]

    def counts(self) -> dict[str, int]:
        """Number of matches per outcome: ``{"lsm", "ncc", "none", <each drop reason>}``."""
        out: dict[str, int] = {}
        for key in np.concatenate([self.method[self.ok], self.reason[~self.ok]]):
            out[str(key)] = out.get(str(key), 0) + 1
        return out


def _as_image(image: ArrayLike, which: str) -> NDArray[np.float64]:
    arr = np.asarray(image)
    if arr.ndim != 2 or not np.issubdtype(arr.dtype, np.number):
        raise InputError(f"must be a 2-D numeric array, got shape {arr.shape}", field=which)
    return arr.astype(np.float64, copy=False)


def _as_points(points: ArrayLike, which: str) -> NDArray[np.float64]:
    arr = np.asarray(points, np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise InputError(f"must have shape (N, 2), got {arr.shape}", field=which)
    return arr


def _as_mask(mask: ArrayLike | None, image: NDArray[np.float64], which: str) -> NDArray[np.bool_]:
    valid = np.isfinite(image)
    if mask is not None:
        m = np.asarray(mask, bool)
        if m.shape != image.shape:
            raise InputError(f"shape {m.shape} differs from image {image.shape}", field=which)
        valid &= m
    return valid


class _Images:
    """Image 1, its gradients and validity, resampled together (torch ``grid_sample``).

    One bilinear pass samples all four bands at float32 positions normalised to the image
    size (resolution about ``6e-8 * size`` pixels, e.g. 1e-4 px on 2000 px), several times
    faster than separate ``scipy.ndimage.map_coordinates`` calls; values return as float64.
    """

    def __init__(self, img1: NDArray[np.float64], valid1: NDArray[np.bool_]) -> None:
        import torch

        gy, gx = np.gradient(img1)
        bands = np.stack([img1, gx, gy, valid1.astype(np.float64)]).astype(np.float32)
        self.tensor = torch.from_numpy(bands)[None]
        self.h, self.w = img1.shape

    def sample(self, x, y):
        """Image 1 and its gradients at ``(x, y)`` ``(N, M)``: ``(g, gx, gy, defined)``."""
        import torch
        import torch.nn.functional as F

        grid = np.empty((*x.shape, 2), np.float32)
        grid[..., 0] = 2.0 * x / self.w - 1.0
        grid[..., 1] = 2.0 * y / self.h - 1.0
        with torch.inference_mode():
            out = F.grid_sample(
                self.tensor,
                torch.from_numpy(grid)[None],
                mode="bilinear",
                padding_mode="border",
                align_corners=False,
            )[0].numpy()
        g, gx, gy, v = out.astype(np.float64)
        ok = (x >= 0.5) & (x <= self.w - 0.5) & (y >= 0.5) & (y <= self.h - 0.5)
        ok &= v >= 1.0 - 1e-4
        return np.where(ok, g, 0.0), gx, gy, ok


def _templates(
    img0: NDArray[np.float64], valid0: NDArray[np.bool_], p0: NDArray[np.float64], h: int
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """Templates at whole pixels around ``p0``: ``(f (N, M), u (N, M), v (N, M), inside)``."""
    k = np.arange(-h, h + 1)
    kx, ky = np.meshgrid(k, k)
    kx, ky = kx.ravel(), ky.ravel()
    col = np.floor(p0[:, 0]).astype(np.int64)
    row = np.floor(p0[:, 1]).astype(np.int64)
    h0, w0 = img0.shape
    inside = (col - h >= 0) & (row - h >= 0) & (col + h < w0) & (row + h < h0)
    cc = np.where(inside, col, h)[:, None] + kx
    rr = np.where(inside, row, h)[:, None] + ky
    cc = np.clip(cc, 0, w0 - 1)
    rr = np.clip(rr, 0, h0 - 1)
    f = img0[rr, cc]
    inside &= valid0[rr, cc].all(axis=1)
    u = cc + 0.5 - p0[:, :1]
    v = rr + 0.5 - p0[:, 1:]
    return f, u, v, inside


def _solve(normal: NDArray[np.float64], rhs: NDArray[np.float64]):
    """Batched solve of ``normal @ x = rhs``; ``(x, ok)`` with ok False where singular."""
    scale = np.sqrt(np.maximum(np.einsum("nii->ni", normal), 1e-300))
    ns = normal / scale[:, :, None] / scale[:, None, :]
    ok = np.isfinite(ns).all(axis=(1, 2))
    ns = np.where(ok[:, None, None], ns, np.eye(normal.shape[1]))
    sign, logdet = np.linalg.slogdet(ns)  # unit diagonal: det in (0, 1], tiny = degenerate
    ok &= (sign > 0) & (logdet > MIN_LOGDET)
    ns = np.where(ok[:, None, None], ns, np.eye(normal.shape[1]))
    inv = np.linalg.inv(ns) / scale[:, :, None] / scale[:, None, :]
    x = np.einsum("nij,nj->ni", inv, rhs)
    return x, inv, ok


def _jacobian(g, gx, gy, r1, u, v) -> NDArray[np.float64]:
    """``(N, 8, M)`` Jacobian of ``r0 + r1 g(affine(u, v))`` w.r.t. tx a1 a2 ty b1 b2 r0 r1."""
    jac = np.empty((g.shape[0], 8, g.shape[1]))
    np.multiply(r1, gx, out=jac[:, 0])
    np.multiply(r1, gy, out=jac[:, 3])
    np.multiply(jac[:, 0], u, out=jac[:, 1])
    np.multiply(jac[:, 0], v, out=jac[:, 2])
    np.multiply(jac[:, 3], u, out=jac[:, 4])
    np.multiply(jac[:, 3], v, out=jac[:, 5])
    jac[:, 6] = 1.0
    jac[:, 7] = g
    return jac


def _gram(jac: NDArray[np.float64]) -> NDArray[np.float64]:
    """Batched ``J'J`` of ``(N, K, M)`` Jacobians (parameters first)."""
    return jac @ jac.transpose(0, 2, 1)


def _zncc(f: NDArray[np.float64], g: NDArray[np.float64]) -> NDArray[np.float64]:
    fc = f - f.mean(axis=1, keepdims=True)
    gc = g - g.mean(axis=1, keepdims=True)
    den = np.sqrt(np.sum(fc * fc, axis=1) * np.sum(gc * gc, axis=1))
    return np.sum(fc * gc, axis=1) / np.where(den > 0, den, np.inf)


def _lsm_chunk(f, u, v, p1, images: _Images, cfg: RefineConfig):
    """LSM of one chunk. Returns ``(points1, sigma, status)``; status is a reason or ``""``."""
    n, m = f.shape
    h = cfg.half_window
    status = np.full(n, "", dtype=object)
    par = np.zeros((n, 8))  # tx a1 a2 ty b1 b2 r0 r1
    par[:, 0], par[:, 3] = p1[:, 0], p1[:, 1]
    g, _, _, ok = images.sample(p1[:, :1] + u, p1[:, 1:] + v)
    fs, gs = f.std(axis=1), g.std(axis=1)
    par[:, 7] = np.where(gs > 0, fs / np.where(gs > 0, gs, 1.0), 1.0)
    par[:, 6] = f.mean(axis=1) - par[:, 7] * g.mean(axis=1)
    active = np.ones(n, bool)
    converged = np.zeros(n, bool)
    for _ in range(cfg.max_iter):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        p = par[idx]
        uu, vv = u[idx], v[idx]
        x = p[:, :1] + (1 + p[:, 1:2]) * uu + p[:, 2:3] * vv
        y = p[:, 3:4] + p[:, 4:5] * uu + (1 + p[:, 5:6]) * vv
        g, gx, gy, ok = images.sample(x, y)
        bad = ~ok.all(axis=1)
        r1 = p[:, 7:8]
        e = f[idx] - p[:, 6:7] - r1 * g
        jac = _jacobian(g, gx, gy, r1, uu, vv)
        normal = _gram(jac)
        rhs = (jac @ e[:, :, None])[:, :, 0]
        delta, _, solvable = _solve(normal, rhs)
        p = p + np.where(solvable[:, None], delta, 0.0)
        moved = np.hypot(p[:, 0] - p1[idx, 0], p[:, 3] - p1[idx, 1])
        affine = np.abs(p[:, [1, 2, 4, 5]]).max(axis=1)
        wild = (
            ~solvable
            | ~np.isfinite(p).all(axis=1)
            | (affine > MAX_AFFINE)
            | (p[:, 7] <= 0)
            | (moved > cfg.max_shift_px)
        )
        par[idx] = p
        status[idx[bad]] = "border"
        status[idx[~bad & wild]] = "diverged"
        small = (np.abs(delta[:, [0, 3]]).max(axis=1) < TOL_PX) & (
            np.abs(delta[:, [1, 2, 4, 5]]).max(axis=1) * h < TOL_AFFINE_PX
        )
        done = ~bad & ~wild & small
        converged[idx[done]] = True
        active[idx[bad | wild | done]] = False
    status[active] = "diverged"
    out = np.column_stack([par[:, 0], par[:, 3]])
    sigma = np.full(n, np.nan)
    idx = np.flatnonzero(converged)
    if idx.size:
        p = par[idx]
        uu, vv = u[idx], v[idx]
        x = p[:, :1] + (1 + p[:, 1:2]) * uu + p[:, 2:3] * vv
        y = p[:, 3:4] + p[:, 4:5] * uu + (1 + p[:, 5:6]) * vv
        g, gx, gy, ok = images.sample(x, y)
        r1 = p[:, 7:8]
        e = f[idx] - p[:, 6:7] - r1 * g
        jac = _jacobian(g, gx, gy, r1, uu, vv)
        _, inv, solvable = _solve(_gram(jac), np.zeros((idx.size, 8)))
        s0sq = np.sum(e * e, axis=1) / (m - 8)
        sigma[idx] = np.sqrt(s0sq * (inv[:, 0, 0] + inv[:, 3, 3]) / 2)
        low = _zncc(f[idx], g) < cfg.min_ncc
        status[idx[low]] = "low_correlation"
        status[idx[~ok.all(axis=1)]] = "border"
        sigma[idx[~solvable]] = np.nan
    return out, sigma, status


def _ncc_chunk(f, u, v, p1, images: _Images, cfg: RefineConfig):
    """NCC refinement of one chunk: ``(points1, sigma, status)``."""
    n = f.shape[0]
    h = cfg.half_window
    r = int(np.ceil(cfg.max_shift_px))
    side = 2 * h + 1
    big = 2 * (h + r) + 1
    k = np.arange(-(h + r), h + r + 1, dtype=np.float64)
    kx, ky = np.meshgrid(k, k)
    # window offsets: the template offsets (u, v) continued by whole pixels on every side
    u0 = u[:, :1] - (-h)  # u of template column -h, plus h: offset of the centre column
    v0 = v[:, :1] - (-h)
    wx = p1[:, :1, None] + u0[:, :, None] + kx[None]
    wy = p1[:, 1:, None] + v0[:, :, None] + ky[None]
    win, _, _, defined = images.sample(
        np.broadcast_to(wx, (n, big, big)).reshape(n, -1),
        np.broadcast_to(wy, (n, big, big)).reshape(n, -1),
    )
    win = win.reshape(n, big, big)
    defined = defined.reshape(n, big, big)
    surf = zncc_surfaces(f.reshape(n, side, side), win)
    undefined = np.zeros((n, big + 1, big + 1))
    undefined[:, 1:, 1:] = np.cumsum(np.cumsum(~defined, axis=1), axis=2)
    holes = (
        undefined[:, side:, side:]
        - undefined[:, :-side, side:]
        - undefined[:, side:, :-side]
        + undefined[:, :-side, :-side]
    )
    surf[holes > 0] = INVALID
    flat = surf.reshape(n, -1)
    best = flat.argmax(axis=1)
    i, j = np.divmod(best, 2 * r + 1)
    peak = flat[np.arange(n), best]
    status = np.full(n, "", dtype=object)
    edge = (i == 0) | (j == 0) | (i == 2 * r) | (j == 2 * r)
    ii, jj = np.clip(i, 1, 2 * r - 1), np.clip(j, 1, 2 * r - 1)
    rows = ii[:, None, None] + np.arange(-1, 2)[None, :, None]
    cols = jj[:, None, None] + np.arange(-1, 2)[None, None, :]
    patch = surf[np.arange(n)[:, None, None], rows, cols]
    dx, dy, _, found = quadratic_peaks(patch)
    status[~found | (peak < cfg.min_ncc)] = "low_correlation"
    status[(patch <= INVALID).any(axis=(1, 2)) | (peak <= INVALID)] = "border"
    status[edge & (peak > INVALID)] = "shift"
    out = p1 + np.column_stack([j - r + dx, i - r + dy])
    # precision from the translation-only LSM normal equations at the NCC position
    g, gx, gy, ok = images.sample(out[:, :1] + u, out[:, 1:] + v)
    design = np.stack([np.ones_like(g), g], axis=1)
    coef, _, _ = _solve(_gram(design), (design @ f[:, :, None])[:, :, 0])
    r0, r1 = coef[:, :1], coef[:, 1:]
    e = f - r0 - r1 * g
    jac = np.stack([r1 * gx, r1 * gy, np.ones_like(g), g], axis=1)
    _, inv, solvable = _solve(_gram(jac), np.zeros((n, 4)))
    s0sq = np.sum(e * e, axis=1) / (f.shape[1] - 4)
    sigma = np.where(solvable, np.sqrt(s0sq * (inv[:, 0, 0] + inv[:, 1, 1]) / 2), np.nan)
    status[(status == "") & ~ok.all(axis=1)] = "border"
    return out, sigma, status


def _smoothed(
    image: NDArray[np.float64], valid: NDArray[np.bool_], sigma: float
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Gaussian low-pass of the valid pixels (invalid ones filled with the valid mean)."""
    fill = float(image[valid].mean()) if valid.any() else 0.0
    image = np.where(valid, image, fill)
    if sigma <= 0:
        return image, valid
    from scipy import ndimage

    out = ndimage.gaussian_filter(image, sigma, mode="nearest", truncate=3.0)
    if not valid.all():
        reach = int(np.ceil(2 * sigma))
        valid = ~ndimage.binary_dilation(~valid, np.ones((2 * reach + 1,) * 2, bool))
    return out, valid


def _noise_inflation(sigma: float) -> float:
    """Factor on the a-posteriori sigma for noise correlated by the Gaussian low-pass.

    After smoothing with kernel ``k`` (sum 1), white noise has variance ``sum(k^2)`` and
    neighbouring residuals are no longer independent; for a signal smooth at the kernel's
    scale the least-squares covariance computed as if they were is too small by the
    factor ``1 / sum(k^2)`` (in variance). ``k`` is separable: ``sum(k2d^2) = sum(k1d^2)^2``.
    """
    if sigma <= 0:
        return 1.0
    from scipy import ndimage

    impulse = np.zeros(2 * int(np.ceil(3 * sigma)) + 3)
    impulse[len(impulse) // 2] = 1.0
    k = ndimage.gaussian_filter1d(impulse, sigma, truncate=3.0)
    return float(1.0 / np.sum(k * k))


def refine_matches(
    image0: ArrayLike,
    image1: ArrayLike,
    points0: ArrayLike,
    points1: ArrayLike,
    config: RefineConfig,
    valid0: ArrayLike | None = None,
    valid1: ArrayLike | None = None,
) -> RefineResult:
    """Refine ``points1`` to sub-pixel precision; ``points0`` stay fixed.

    Args:
        image0: 2-D image the templates are taken from, any numeric dtype.
        image1: 2-D image searched, in the same pixel scale as ``image0``.
        points0: ``(N, 2)`` ``(x, y)`` in image 0, corner convention (centres at +0.5).
        points1: ``(N, 2)`` approximate matches in image 1.
        config: Method and window settings.
        valid0: Optional validity mask of image 0 (non-finite pixels are always invalid).
        valid1: Optional validity mask of image 1.

    Returns:
        The refined points, precision, kept mask, drop reasons and method per match.

    Raises:
        InputError: Malformed images, points or masks.
    """
    img0 = _as_image(image0, "image0")
    img1 = _as_image(image1, "image1")
    p0 = _as_points(points0, "points0")
    p1 = _as_points(points1, "points1")
    if len(p0) != len(p1):
        raise InputError(f"points0 and points1 differ in length: {len(p0)} vs {len(p1)}")
    n = len(p0)
    out = p1.copy()
    sigma = np.full(n, np.nan)
    ok = np.ones(n, bool)
    reason = np.full(n, "", dtype=object)
    method = np.full(n, "none", dtype=object)
    if config.method == "none" or n == 0:
        return RefineResult(out, sigma, ok, reason.astype(str), method.astype(str))
    v0 = _as_mask(valid0, img0, "valid0")
    v1 = _as_mask(valid1, img1, "valid1")
    img0, v0 = _smoothed(img0, v0, config.smooth_px)
    img1, v1 = _smoothed(img1, v1, config.smooth_px)
    images = _Images(img1, v1)
    inflation = _noise_inflation(config.smooth_px)
    h = config.half_window
    for start in range(0, n, CHUNK):
        sl = slice(start, min(n, start + CHUNK))
        f, u, v, inside = _templates(img0, v0, p0[sl], h)
        status = np.where(inside, "", "border").astype(object)
        flat = inside & (f.std(axis=1) <= 1e-9 * (1.0 + np.abs(f).max(axis=1)))
        status[flat] = "low_correlation"
        todo = np.flatnonzero(status == "")
        pts = p1[sl].copy()
        sig = np.full(len(pts), np.nan)
        how = np.full(len(pts), "none", dtype=object)
        if config.method == "lsm" and todo.size:
            q, s, st = _lsm_chunk(f[todo], u[todo], v[todo], p1[sl][todo], images, config)
            pts[todo], sig[todo], status[todo], how[todo] = q, s, st, "lsm"
            todo = todo[st == "diverged"]
        if todo.size:
            q, s, st = _ncc_chunk(f[todo], u[todo], v[todo], p1[sl][todo], images, config)
            pts[todo], sig[todo], status[todo], how[todo] = q, s, st, "ncc"
        moved = np.hypot(*(pts - p1[sl]).T)
        status[(status == "") & (moved > config.max_shift_px)] = "shift"
        good = status == ""
        out[sl] = np.where(good[:, None], pts, p1[sl])
        sigma[sl] = np.where(good, sig * inflation, np.nan)
        ok[sl] = good
        reason[sl] = status
        method[sl] = np.where(good, how, "none")
    return RefineResult(out, sigma, ok, reason.astype(str), method.astype(str))
