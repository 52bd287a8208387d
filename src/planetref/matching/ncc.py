"""Area-based matching by normalised cross-correlation (the photogrammetric baseline).

Templates of ``(2t + 1)^2`` pixels are taken on a regular grid of image 0, skipped when
their standard deviation (on the robustly normalised image, range about ``[0, 1]``) is
below ``min_std`` or when they touch an invalid pixel, and searched in image 1 within
``search_radius`` pixels of the predicted position with OpenCV's ``TM_CCOEFF_NORMED``
(zero-mean NCC, invariant to gain and offset). Where image 0 ends (the edge of a CCD's
footprint in an orthorectified tile), a template centred on a valid pixel may be partial:
with at least ``min_template_valid`` of its pixels valid, its NCC is taken over those
pixels only (masked ZNCC), so matches reach the very edge of the valid area instead of
stopping ``t`` pixels short of it. Candidate positions whose window touches
an invalid pixel of image 1 are excluded. The integer peak must be a strict interior
maximum above ``min_ncc``; a peak is ambiguous (rejected) when another local maximum of the
correlation surface, more than 2 pixels away, reaches ``ambiguity_ratio`` times its value.
The sub-pixel position comes from a least-squares 2-D quadratic fitted to the 3x3
neighbourhood of the peak (``subpixel="quadratic"``) or from independent parabolas along
each axis (``subpixel="parabola"``), and the confidence is the fitted peak NCC.

Speed: in dense mode (the fine stage) the templates overlap by about 90 % and share one
predicted displacement, so their correlations are computed together by compiled running
sums (:func:`correlate_shared`, numba), exact in float64, instead of one OpenCV FFT per
template (:func:`correlate_batch`, the numpy reference, float32, within ~2e-4 of the
exact ZNCC): 3.1x fewer CPU seconds per front-end tile on 4 simulated hiric-strip tiles,
2.7x on the tiny scene's (``benchmarks/bench_ncc.py``, ``benchmarks/results/``), the same
matches to OpenCV's rounding.

Coordinates: template centre pixel ``(row r, column c)`` is reported at ``(c + 0.5, r + 0.5)``
(planetref's corner convention) and its match at the same place plus the fitted offset.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any, ClassVar, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from planetref.errors import InputError
from planetref.matching.base import BaseMatcher, Matches

__all__ = ["NccMatcher", "correlate_batch", "correlate_shared", "refine_matches_ncc"]

Subpixel = Literal["quadratic", "parabola"]

_INVALID = -2.0  # below any NCC value


def _box_stats(image: NDArray[np.float32], valid: NDArray[np.bool_], radius: int):
    """Per-pixel std and invalid count of the ``(2r+1)^2`` window centred there."""
    k = (2 * radius + 1, 2 * radius + 1)
    img = image.astype(np.float64)
    mean = cv2.boxFilter(img, -1, k, normalize=True, borderType=cv2.BORDER_REFLECT)
    sq = cv2.boxFilter(img * img, -1, k, normalize=True, borderType=cv2.BORDER_REFLECT)
    std = np.sqrt(np.maximum(sq - mean * mean, 0.0))
    bad = cv2.boxFilter(
        (~valid).astype(np.float64), -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT
    )
    return std, bad > 0.5


def _partial_stats(image: NDArray[np.float32], valid: NDArray[np.bool_], radius: int):
    """Per-pixel std over the valid pixels of the ``(2r+1)^2`` window, and their share."""
    k = (2 * radius + 1, 2 * radius + 1)
    v = valid.astype(np.float64)
    img = np.where(valid, image, 0.0).astype(np.float64)
    share = cv2.boxFilter(v, -1, k, normalize=True, borderType=cv2.BORDER_CONSTANT)
    s1 = cv2.boxFilter(img, -1, k, normalize=True, borderType=cv2.BORDER_CONSTANT)
    s2 = cv2.boxFilter(img * img, -1, k, normalize=True, borderType=cv2.BORDER_CONSTANT)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = s1 / share
        std = np.sqrt(np.maximum(s2 / share - mean * mean, 0.0))
    return np.where(share > 0, std, 0.0), share


# least-squares quadratic on a 3x3 patch: f = a + b x + c y + d x^2 + e x y + g y^2
_XX, _YY = np.meshgrid([-1.0, 0.0, 1.0], [-1.0, 0.0, 1.0])
_DESIGN = np.column_stack(
    [np.ones(9), _XX.ravel(), _YY.ravel(), _XX.ravel() ** 2, (_XX * _YY).ravel(), _YY.ravel() ** 2]
)
_PINV = np.linalg.pinv(_DESIGN)


def _subpixel_peak(
    patch: NDArray[np.float64], method: Subpixel
) -> tuple[float, float, float] | None:
    """Sub-pixel peak ``(dx, dy, value)`` of a 3x3 correlation patch centred on its maximum."""
    if method == "quadratic":
        a, b, c, d, e, g = _PINV @ patch.ravel()
        det = 4.0 * d * g - e * e
        if d < 0 and det > 0:
            dx = (-2.0 * g * b + e * c) / det
            dy = (-2.0 * d * c + e * b) / det
            if abs(dx) <= 1.0 and abs(dy) <= 1.0:
                value = a + b * dx + c * dy + d * dx * dx + e * dx * dy + g * dy * dy
                return dx, dy, value
        # degenerate fit: fall back to the per-axis parabolas
    fm, f0, fp = patch[1, 0], patch[1, 1], patch[1, 2]
    gm, gp = patch[0, 1], patch[2, 1]
    den_x = fm - 2.0 * f0 + fp
    den_y = gm - 2.0 * f0 + gp
    if den_x >= 0 or den_y >= 0:
        return None
    dx = 0.5 * (fm - fp) / den_x
    dy = 0.5 * (gm - gp) / den_y
    if abs(dx) > 1.0 or abs(dy) > 1.0:
        return None
    value = f0 - 0.25 * (fm - fp) * dx - 0.25 * (gm - gp) * dy
    return dx, dy, value


def _correlate(
    image0: NDArray[np.float32],
    image1: NDArray[np.float32],
    bad1: NDArray[np.bool_],
    r0: int,
    c0: int,
    r1: int,
    c1: int,
    t: int,
    radius: int,
    min_ncc: float,
    ambiguity_ratio: float,
    subpixel: Subpixel,
) -> tuple[float, float, float] | None:
    """Match the template centred on image-0 pixel (r0, c0) around image-1 pixel (r1, c1).

    Returns ``(x1, y1, ncc)`` of the match in corner-convention pixels, or None.
    """
    h1, w1 = image1.shape
    top, left = max(r1 - radius, t), max(c1 - radius, t)
    bottom, right = min(r1 + radius, h1 - 1 - t), min(c1 + radius, w1 - 1 - t)
    if bottom - top < 2 or right - left < 2:
        return None
    templ = image0[r0 - t : r0 + t + 1, c0 - t : c0 + t + 1]
    search = image1[top - t : bottom + t + 1, left - t : right + t + 1]
    res = cv2.matchTemplate(search, templ, cv2.TM_CCOEFF_NORMED).astype(np.float64)
    res[~np.isfinite(res)] = _INVALID  # flat search windows
    res[bad1[top : bottom + 1, left : right + 1]] = _INVALID
    i, j = np.unravel_index(int(np.argmax(res)), res.shape)
    peak = res[i, j]
    if peak < min_ncc or i == 0 or j == 0 or i == res.shape[0] - 1 or j == res.shape[1] - 1:
        return None
    patch = res[i - 1 : i + 2, j - 1 : j + 2]
    if np.any(patch <= _INVALID):
        return None
    if ambiguity_ratio < 1.0 and res.size > 9:
        dil = cv2.dilate(res.astype(np.float32), np.ones((3, 3), np.uint8)).astype(np.float64)
        maxima = (res >= dil) & (res > _INVALID)
        ii, jj = np.nonzero(maxima)
        far = (np.abs(ii - i) > 2) | (np.abs(jj - j) > 2)
        if far.any() and res[ii[far], jj[far]].max() >= ambiguity_ratio * peak:
            return None
    sub = _subpixel_peak(patch, subpixel)
    if sub is None:
        return None
    dx, dy, value = sub
    return left + j + dx + 0.5, top + i + dy + 0.5, float(min(value, 1.0))


class NccMatcher(BaseMatcher):
    """Grid-template normalised cross-correlation matcher.

    Args:
        template_radius: Half size ``t`` of the square template, pixels (size ``2t + 1``).
        spacing: Grid step between template centres in image 0, pixels.
        search_radius: Largest displacement searched from the predicted position, pixels.
        min_std: Minimum template standard deviation on the normalised image (``[0, 1]``
            range); flatter templates are skipped as low-texture.
        min_ncc: Minimum correlation peak.
        ambiguity_ratio: Reject a peak when another local maximum (more than 2 px away)
            reaches this fraction of it; ``1.0`` disables the test.
        subpixel: ``"quadratic"`` (2-D least-squares quadratic on 3x3) or ``"parabola"``.
        initial_offset: Predicted displacement ``(dx, dy)`` of image 1 relative to image 0,
            pixels; the search is centred there.
        dense_spacing_px: Dense mode: image 0 is cut into cells of this many pixels and
            each cell contributes one template, centred on its most textured usable pixel
            (largest template standard deviation, at least ``min_std``; a whole template
            before a partial one). ``None``: templates on the regular ``spacing`` grid.
        min_template_valid: Smallest share of valid pixels of a template centred on a
            valid pixel next to invalid ones (the edge of the valid area); its NCC is taken
            over its valid pixels only. ``1.0``: whole templates only (matches stop
            ``template_radius`` pixels short of the edge).

    Raises:
        InputError: A parameter out of range.
    """

    name: ClassVar[str] = "ncc"
    pixel_options: ClassVar[tuple[str, ...]] = ("template_radius",)
    search_option: ClassVar[str | None] = "search_radius"
    support_option: ClassVar[str | None] = "template_radius"
    coarse_defaults: ClassVar[Mapping[str, Any]] = MappingProxyType({"spacing": 8})

    def __init__(
        self,
        *,
        template_radius: int = 10,
        spacing: int = 16,
        search_radius: int = 16,
        min_std: float = 0.02,
        min_ncc: float = 0.5,
        ambiguity_ratio: float = 0.9,
        subpixel: Subpixel = "quadratic",
        initial_offset: tuple[float, float] = (0.0, 0.0),
        dense_spacing_px: int | None = None,
        min_template_valid: float = 0.5,
    ) -> None:
        super().__init__()
        if not 0.0 < float(min_template_valid) <= 1.0:
            raise InputError(
                f"must be in (0, 1], got {min_template_valid}", field="min_template_valid"
            )
        self.min_template_valid = float(min_template_valid)
        if dense_spacing_px is not None and int(dense_spacing_px) < 1:
            raise InputError(f"must be >= 1, got {dense_spacing_px}", field="dense_spacing_px")
        self.dense_spacing_px = None if dense_spacing_px is None else int(dense_spacing_px)
        if int(template_radius) < 2:
            raise InputError(f"must be >= 2, got {template_radius}", field="template_radius")
        if int(spacing) < 1:
            raise InputError(f"must be >= 1, got {spacing}", field="spacing")
        if int(search_radius) < 2:
            raise InputError(f"must be >= 2, got {search_radius}", field="search_radius")
        if not -1.0 <= float(min_ncc) <= 1.0:
            raise InputError(f"must be in [-1, 1], got {min_ncc}", field="min_ncc")
        if not 0.0 < float(ambiguity_ratio) <= 1.0:
            raise InputError(f"must be in (0, 1], got {ambiguity_ratio}", field="ambiguity_ratio")
        if subpixel not in ("quadratic", "parabola"):
            raise InputError(
                f"must be 'quadratic' or 'parabola', got {subpixel!r}", field="subpixel"
            )
        self.template_radius = int(template_radius)
        self.spacing = int(spacing)
        self.search_radius = int(search_radius)
        self.min_std = float(min_std)
        self.min_ncc = float(min_ncc)
        self.ambiguity_ratio = float(ambiguity_ratio)
        self.subpixel: Subpixel = subpixel
        self.initial_offset = (float(initial_offset[0]), float(initial_offset[1]))

    def _grid(self, shape: tuple[int, int]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        t, s = self.template_radius, self.spacing
        axes = []
        for n in shape:
            span = n - 2 * t - 1
            if span < 0:
                return np.empty(0, np.int64), np.empty(0, np.int64)
            count = span // s + 1
            start = t + (span - (count - 1) * s) // 2  # centre the grid
            axes.append(start + s * np.arange(count))
        rr, cc = np.meshgrid(axes[0], axes[1], indexing="ij")
        return rr.ravel(), cc.ravel()

    def _dense_grid(
        self, score: NDArray[np.float64]
    ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """One template per ``dense_spacing_px`` cell: its best-scoring pixel (score >= 0)."""
        s = int(self.dense_spacing_px)  # type: ignore[arg-type]
        h, w = score.shape
        hc, wc = -(-h // s), -(-w // s)
        padded = np.full((hc * s, wc * s), -1.0)
        padded[:h, :w] = score
        cells = padded.reshape(hc, s, wc, s).transpose(0, 2, 1, 3).reshape(hc, wc, s * s)
        best = cells.argmax(axis=2)
        ok = np.take_along_axis(cells, best[..., None], axis=2)[..., 0] >= 0.0
        ci, cj = np.nonzero(ok)
        di, dj = np.divmod(best[ci, cj], s)
        return ci * s + di, cj * s + dj

    def _match_normalised(
        self,
        image0: NDArray[np.float32],
        valid0: NDArray[np.bool_],
        image1: NDArray[np.float32],
        valid1: NDArray[np.bool_],
    ) -> Matches:
        t = self.template_radius
        with self._timed("forward"):
            std0, bad0 = _box_stats(image0, valid0, t)
            _, bad1 = _box_stats(image1, valid1, t)
            h0, w0 = image0.shape
            rr, cc = np.mgrid[0:h0, 0:w0]
            inside = (rr >= t) & (rr < h0 - t) & (cc >= t) & (cc < w0 - t)
            whole = ~bad0 & inside & (std0 >= self.min_std)
            # Whole templates score 2 + std, partial ones (at the edge of the valid area)
            # their std over valid pixels: a cell prefers a whole template.
            score = np.where(whole, 2.0 + std0, -1.0)
            if self.min_template_valid < 1.0:
                std_p, share = _partial_stats(image0, valid0, t)
                partial = bad0 & inside & valid0 & (share >= self.min_template_valid - 1e-9)
                partial &= std_p >= self.min_std
                score = np.where(partial, std_p, score)
            if self.dense_spacing_px is None:
                rows, cols = self._grid(image0.shape)
                keep = score[rows, cols] >= 0.0
                rows, cols = rows[keep], cols[keep]
            else:
                rows, cols = self._dense_grid(score)
            dx0, dy0 = self.initial_offset
            # Dense templates overlap: the compiled path shares their products.
            correlate = correlate_batch if self.dense_spacing_px is None else correlate_shared
            out = correlate(
                image0,
                image1,
                bad1,
                rows,
                cols,
                np.round(rows + dy0).astype(np.int64),
                np.round(cols + dx0).astype(np.int64),
                self,
                valid0=valid0 if self.min_template_valid < 1.0 else None,
            )
        x1, y1, conf, ok = out
        if not ok.any():
            return Matches.empty()
        k0 = np.column_stack([cols[ok] + 0.5, rows[ok] + 0.5])
        return Matches(k0, np.column_stack([x1[ok], y1[ok]]), conf[ok])


#: Templates correlated together by :func:`correlate_batch` (memory ~ CHUNK x window^2 x 8 B).
CHUNK = 512


def correlate_batch(
    image0: NDArray[np.float32],
    image1: NDArray[np.float32],
    bad1: NDArray[np.bool_],
    r0: NDArray[np.int64],
    c0: NDArray[np.int64],
    r1: NDArray[np.int64],
    c1: NDArray[np.int64],
    settings: NccMatcher,
    valid0: NDArray[np.bool_] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """Vectorised template search: the batched equivalent of :func:`_correlate`.

    Template ``n`` is centred on image-0 pixel ``(r0[n], c0[n])`` and searched around image-1
    pixel ``(r1[n], c1[n])`` within ``settings.search_radius``; candidate centres whose window
    leaves image 1 or touches an invalid pixel (``bad1``) are excluded. Peak, ambiguity and
    sub-pixel rules are those of :class:`NccMatcher`. With ``valid0`` (image 0's valid
    mask), a template that covers invalid pixels is correlated over its valid pixels only.

    Returns:
        ``(x1, y1, ncc, ok)`` per template, corner-convention pixels.
    """
    from scipy import ndimage

    from planetref.matching.correlation import quadratic_peaks, zncc_surfaces

    t, radius = settings.template_radius, settings.search_radius
    n = len(r0)
    x1 = np.zeros(n)
    y1 = np.zeros(n)
    conf = np.zeros(n)
    ok = np.zeros(n, bool)
    if n == 0:
        return x1, y1, conf, ok
    side, big, span = 2 * t + 1, 2 * (t + radius) + 1, 2 * radius + 1
    m = t + radius
    img1 = np.pad(image1.astype(np.float64), m, mode="edge")
    # a candidate centre is usable when its window is inside image 1 and all valid
    h1, w1 = image1.shape
    rr, cc = np.mgrid[0:h1, 0:w1]
    inside = (rr >= t) & (rr < h1 - t) & (cc >= t) & (cc < w1 - t)
    blocked = np.pad(bad1 | ~inside, radius, constant_values=True)
    ko = np.arange(side)
    kw = np.arange(big)
    ks = np.arange(span)
    reachable = (r1 >= 0) & (r1 < h1) & (c1 >= 0) & (c1 < w1)
    r1 = np.clip(r1, 0, h1 - 1)
    c1 = np.clip(c1, 0, w1 - 1)
    for start in range(0, n, CHUNK):
        sl = slice(start, min(n, start + CHUNK))
        templ = image0[(r0[sl] - t)[:, None, None] + ko[:, None], (c0[sl] - t)[:, None, None] + ko]
        # search window rows r1 - radius - t ... r1 + radius + t, in padded coordinates (+m)
        win = img1[r1[sl][:, None, None] + kw[:, None], c1[sl][:, None, None] + kw]
        masks = None
        if valid0 is not None:
            masks = valid0[
                (r0[sl] - t)[:, None, None] + ko[:, None], (c0[sl] - t)[:, None, None] + ko
            ]
        res = zncc_surfaces(templ, win, masks)
        # candidate centre (r1 - radius + i, c1 - radius + j) -> blocked index (+radius)
        res[blocked[r1[sl][:, None, None] + ks[:, None], c1[sl][:, None, None] + ks]] = _INVALID
        flat = res.reshape(len(res), -1)
        best = flat.argmax(axis=1)
        i, j = np.divmod(best, span)
        peak = flat[np.arange(len(res)), best]
        good = (peak >= settings.min_ncc) & (i > 0) & (j > 0) & (i < span - 1) & (j < span - 1)
        ii, jj = np.clip(i, 1, span - 2), np.clip(j, 1, span - 2)
        idx = np.arange(len(res))[:, None, None]
        patch = res[
            idx, ii[:, None, None] + np.arange(-1, 2)[:, None], jj[:, None, None] + np.arange(-1, 2)
        ]
        good &= ~(patch <= _INVALID).any(axis=(1, 2))
        if settings.ambiguity_ratio < 1.0 and span * span > 9:
            dil = ndimage.maximum_filter(res, size=(1, 3, 3), mode="nearest")
            maxima = (res >= dil) & (res > _INVALID)
            near = (np.abs(ks[None, :, None] - i[:, None, None]) <= 2) & (
                np.abs(ks[None, None, :] - j[:, None, None]) <= 2
            )
            rival = np.where(maxima & ~near, res, _INVALID).reshape(len(res), -1).max(axis=1)
            good &= ~(rival >= settings.ambiguity_ratio * peak)
        dx, dy, value, found = quadratic_peaks(patch, settings.subpixel)
        good &= found
        x1[sl] = c1[sl] - radius + j + dx + 0.5
        y1[sl] = r1[sl] - radius + i + dy + 0.5
        conf[sl] = np.minimum(value, 1.0)
        ok[sl] = good & reachable[sl]
    return x1, y1, conf, ok


#: Templates correlated together by :func:`correlate_shared` (memory: BAND x
#: (2 search_radius + 1)^2 x 4 B, 45 MB at the fine stage's 105 x 105 surfaces).
BAND = 1024
#: Block of template centres sharing one set of running sums (rows, columns): the sums
#: cost ``(2t + 2 rows) x (columns + 2t)`` per displacement, about 70 products
#: per template and displacement at the fine stage's 41 px templates every 4 px.
BLOCK = (96, 128)
MASKED_BLOCK = (96, 128)


def correlate_shared(
    image0: NDArray[np.float32],
    image1: NDArray[np.float32],
    bad1: NDArray[np.bool_],
    r0: NDArray[np.int64],
    c0: NDArray[np.int64],
    r1: NDArray[np.int64],
    c1: NDArray[np.int64],
    settings: NccMatcher,
    valid0: NDArray[np.bool_] | None = None,
    *,
    compiled: bool = True,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """:func:`correlate_batch` with the templates' overlap shared (compiled), same results.

    Dense templates a few pixels apart cover nearly the same pixels, and they all look
    for the same displacement range when their predicted positions differ from their
    centres by one offset (the dense fine stage). They then go through
    :mod:`planetref.matching._numba_ncc`: one pass of box sums of products per candidate
    displacement for a block of templates, instead of one FFT correlation per template
    (whole templates and, with ``valid0``, partial ones by OpenCV's masked rule); the
    surfaces are the exact ZNCC to float32 rounding (the reference's OpenCV FFT is
    within ~2e-4 of it) and the peak rules are the reference's. Scattered offsets,
    templates not inside image 0, or numba missing (``compiled=False``, or the import
    fails): :func:`correlate_batch` itself.

    Returns:
        ``(x1, y1, ncc, ok)`` per template, corner-convention pixels.
    """
    from planetref.matching.correlation import quadratic_peaks
    from planetref.runtime.optional import optional_module

    mod = optional_module("planetref.matching._numba_ncc", "compiled NCC") if compiled else None
    n = len(r0)
    t, radius = settings.template_radius, settings.search_radius
    h0, w0 = image0.shape
    h1, w1 = image1.shape
    dr, dc = r1 - r0, c1 - c0
    if (
        mod is None
        or n == 0
        or np.ptp(dr) > 0
        or np.ptp(dc) > 0
        or r0.min() < t
        or c0.min() < t
        or r0.max() >= h0 - t
        or c0.max() >= w0 - t
    ):
        return correlate_batch(image0, image1, bad1, r0, c0, r1, c1, settings, valid0)
    side, span = 2 * t + 1, 2 * radius + 1
    x1 = np.zeros(n)
    y1 = np.zeros(n)
    conf = np.zeros(n)
    ok = np.zeros(n, bool)
    partial = np.zeros(n, bool)
    if valid0 is not None:
        holes = cv2.boxFilter(
            (~valid0).astype(np.float64),
            -1,
            (side, side),
            normalize=False,
            borderType=cv2.BORDER_CONSTANT,
        )
        partial = holes[r0, c0] > 0.5
    d_r, d_c = int(dr[0]), int(dc[0])
    # image 1's region that the search windows read, zeros outside image 1 (blocked)
    top = int(r0.min()) + d_r - radius - t
    left = int(c0.min()) + d_c - radius - t
    bottom = int(r0.max()) + d_r + radius + t + 1
    right = int(c0.max()) + d_c + radius + t + 1
    b = np.zeros((bottom - top, right - left))
    blocked = np.ones(b.shape, bool)
    rr, cc = np.mgrid[0:h1, 0:w1]
    inside = (rr >= t) & (rr < h1 - t) & (cc >= t) & (cc < w1 - t)
    sr0, sr1 = max(top, 0), min(bottom, h1)
    sc0, sc1 = max(left, 0), min(right, w1)
    if sr1 > sr0 and sc1 > sc0:
        part = image1[sr0:sr1, sc0:sc1].astype(np.float64)
        # ZNCC ignores a constant: centred images keep the running sums well conditioned.
        b[sr0 - top : sr1 - top, sc0 - left : sc1 - left] = np.nan_to_num(
            part - np.nanmean(part), nan=0.0, posinf=0.0, neginf=0.0
        )
        blocked[sr0 - top : sr1 - top, sc0 - left : sc1 - left] = (
            bad1[sr0:sr1, sc0:sc1] | ~inside[sr0:sr1, sc0:sc1]
        )
    ko = np.arange(side)
    # candidate centre (r0 + d_r - radius + i, ...) in the region's indices
    off_r, off_c = d_r - radius - top, d_c - radius - left
    surf = np.empty((min(BAND, n), span, span), np.float32)

    def finish(sel: NDArray[np.int64], res: NDArray[np.float32]) -> None:
        m = len(sel)
        pi = np.empty(m, np.int64)
        pj = np.empty(m, np.int64)
        peak = np.empty(m)
        patch = np.empty((m, 3, 3))
        good = np.empty(m, bool)
        mod.surface_peaks(
            res, settings.min_ncc, settings.ambiguity_ratio, pi, pj, peak, patch, good
        )
        dx, dy, value, found = quadratic_peaks(patch, settings.subpixel)
        x1[sel] = c1[sel] - radius + pj + dx + 0.5
        y1[sel] = r1[sel] - radius + pi + dy + 0.5
        conf[sel] = np.minimum(value, 1.0)
        reach = (r1[sel] >= 0) & (r1[sel] < h1) & (c1[sel] >= 0) & (c1[sel] < w1)
        ok[sel] = good & found & reach

    def is_flat(tv: NDArray[np.float32], wt: NDArray[np.bool_] | None) -> NDArray[np.bool_]:
        """The reference's flat-template rule (:func:`zncc_surfaces`)."""
        flat = tv.reshape(len(tv), -1).astype(np.float64)
        w = np.ones_like(flat) if wt is None else wt.reshape(len(tv), -1)
        cnt = np.maximum(w.sum(axis=1), 1)
        mean = (flat * w).sum(axis=1) / cnt
        spread = np.sqrt(((flat - mean[:, None]) ** 2 * w).sum(axis=1) / cnt)
        return spread <= 1e-7 * (1.0 + np.abs(flat * w).max(axis=1))

    # Image 0 centred too, non-finite values to 0: invalid pixels enter the running sums
    # but no whole template's box; partial templates read image 0 times its validity.
    a = np.nan_to_num(image0.astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    a -= a.mean()
    box = (side, side)
    s1 = cv2.boxFilter(b, -1, box, normalize=False, borderType=cv2.BORDER_CONSTANT)
    bb = b * b
    s2 = cv2.boxFilter(bb, -1, box, normalize=False, borderType=cv2.BORDER_CONSTANT)

    def blocks(
        sel: NDArray[np.int64], size: tuple[int, int]
    ) -> tuple[NDArray[np.int64], list[tuple[int, int]]]:
        """``sel`` ordered by block of centres, row and column, and each block's span.

        Blocks of ``size`` (rows, columns) of centres (spans of at most BAND templates): the
        running sums cover only the rows and columns around a block's templates.
        """
        key = (r0[sel] // size[0]) * (w0 // size[1] + 1) + c0[sel] // size[1]
        order = sel[np.lexsort((c0[sel], r0[sel], key))]
        key = np.sort(key)
        cuts = np.r_[0, np.flatnonzero(np.diff(key)) + 1, len(order)]
        spans = []
        for s, e in itertools.pairwise(cuts):
            spans += [(q, min(e, q + BAND)) for q in range(s, e, BAND)]
        return order, spans

    def stats(order: NDArray[np.int64], av: NDArray[np.float64], w: NDArray[np.bool_] | None):
        """Template mean and norm over the (valid) pixels, 0 norm for a flat one."""
        sl_r = (r0[order] - t)[:, None, None] + ko[:, None]
        sl_c = (c0[order] - t)[:, None, None] + ko
        vals = av[sl_r, sl_c].reshape(len(order), -1)
        wt = np.ones_like(vals) if w is None else w[sl_r, sl_c].reshape(len(order), -1)
        cnt = wt.sum(axis=1)
        mean = (vals * wt).sum(axis=1) / cnt
        norm = np.sqrt((((vals - mean[:, None]) * wt) ** 2).sum(axis=1))
        tv = image0[sl_r, sl_c].astype(np.float32)
        flat = is_flat(tv, None if w is None else w[sl_r, sl_c])
        return mean, np.where(flat, 0.0, norm), cnt

    # Whole templates: OpenCV's unmasked rule; partial ones (cut by image 0's no-data):
    # its masked rule, with the sums of image 1 over each template's valid pixels.
    for masked in (False, True):
        sel = np.flatnonzero(partial == masked)
        if len(sel) == 0:
            continue
        order, spans = blocks(sel, MASKED_BLOCK if masked else BLOCK)
        rows, cols = r0[order], c0[order]
        tmean = np.empty(len(order))
        tnorm = np.empty(len(order))
        count = np.empty(len(order))
        v = valid0.astype(np.float64) if masked else None  # type: ignore[union-attr]
        av = a * v if v is not None else a
        for s in range(0, len(order), CHUNK):
            sl = slice(s, s + CHUNK)
            tmean[sl], tnorm[sl], count[sl] = stats(order[sl], av, valid0 if masked else None)
        for s, e in spans:
            res = surf[: e - s]
            if masked:
                mod.band_surfaces_masked(
                    av, v, b, bb, rows, cols, s, e, t, span, off_r, off_c,
                    tmean, tnorm, count, blocked, res,
                )  # fmt: skip
            else:
                mod.band_surfaces(
                    av, b, rows, cols, s, e, t, span, off_r, off_c, tmean, tnorm, s1, s2,
                    blocked, res,
                )  # fmt: skip
            finish(order[s:e], res)
    return x1, y1, conf, ok


def refine_matches_ncc(
    image0: NDArray[np.float32],
    valid0: NDArray[np.bool_],
    image1: NDArray[np.float32],
    valid1: NDArray[np.bool_],
    matches: Matches,
    *,
    template_radius: int = 7,
    search_radius: int = 3,
    min_ncc: float = 0.5,
    min_std: float = 0.01,
    subpixel: Subpixel = "quadratic",
) -> Matches:
    """Polish approximate matches to sub-pixel accuracy with local NCC.

    Each image-0 keypoint is moved to the centre of the pixel it lies in, its image-1
    keypoint by the same amount (the displacement is locally constant), and the template
    around that pixel is correlated within ``search_radius`` pixels of the moved image-1
    keypoint. Matches that fail (flat template, invalid pixels, weak, ambiguous or
    border peak) are dropped. The confidence becomes the NCC peak.

    Args:
        image0: Normalised image 0 (see :func:`~planetref.matching.base.robust_normalise`).
        valid0: Valid-pixel mask of image 0.
        image1: Normalised image 1.
        valid1: Valid-pixel mask of image 1.
        matches: Approximate matches, corner-convention pixels.
        template_radius: Half template size, pixels.
        search_radius: Search half-width around the approximate match, pixels.
        min_ncc: Minimum correlation peak.
        min_std: Minimum template standard deviation (normalised units).
        subpixel: Peak interpolation, see :class:`NccMatcher`.

    Returns:
        The refined matches (a subset, in the input order).
    """
    t = int(template_radius)
    if len(matches) == 0:
        return matches
    std0, bad0 = _box_stats(image0, valid0, t)
    _, bad1 = _box_stats(image1, valid1, t)
    h0, w0 = image0.shape
    k0 = matches.keypoints0
    c0 = np.floor(k0[:, 0]).astype(np.int64)
    r0 = np.floor(k0[:, 1]).astype(np.int64)
    moved1 = matches.keypoints1 + (np.column_stack([c0, r0]) + 0.5 - k0)
    out0, out1, conf = [], [], []
    for idx in range(len(matches)):
        r, c = int(r0[idx]), int(c0[idx])
        if not (t <= r < h0 - t and t <= c < w0 - t) or bad0[r, c] or std0[r, c] < min_std:
            continue
        hit = _correlate(
            image0,
            image1,
            bad1,
            r,
            c,
            int(np.floor(moved1[idx, 1])),
            int(np.floor(moved1[idx, 0])),
            t,
            int(search_radius),
            min_ncc,
            1.0,
            subpixel,
        )
        if hit is not None:
            out0.append((c + 0.5, r + 0.5))
            out1.append(hit[:2])
            conf.append(hit[2])
    if not out0:
        return Matches.empty()
    return Matches(np.asarray(out0), np.asarray(out1), np.asarray(conf))
