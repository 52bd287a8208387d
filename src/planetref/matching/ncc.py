"""Area-based matching by normalised cross-correlation (the photogrammetric baseline).

Templates of ``(2t + 1)^2`` pixels are taken on a regular grid of image 0, skipped when
their standard deviation (on the robustly normalised image, range about ``[0, 1]``) is
below ``min_std`` or when they touch an invalid pixel, and searched in image 1 within
``search_radius`` pixels of the predicted position with OpenCV's ``TM_CCOEFF_NORMED``
(zero-mean NCC, invariant to gain and offset). Candidate positions whose window touches
an invalid pixel of image 1 are excluded. The integer peak must be a strict interior
maximum above ``min_ncc``; a peak is ambiguous (rejected) when another local maximum of the
correlation surface, more than 2 pixels away, reaches ``ambiguity_ratio`` times its value.
The sub-pixel position comes from a least-squares 2-D quadratic fitted to the 3x3
neighbourhood of the peak (``subpixel="quadratic"``) or from independent parabolas along
each axis (``subpixel="parabola"``), and the confidence is the fitted peak NCC.

Coordinates: template centre pixel ``(row r, column c)`` is reported at ``(c + 0.5, r + 0.5)``
(planetref's corner convention) and its match at the same place plus the fitted offset.
"""

from __future__ import annotations

from typing import ClassVar, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from planetref.errors import InputError
from planetref.matching.base import BaseMatcher, Matches

__all__ = ["NccMatcher", "refine_matches_ncc"]

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

    Raises:
        InputError: A parameter out of range.
    """

    name: ClassVar[str] = "ncc"

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
    ) -> None:
        super().__init__()
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
            rows, cols = self._grid(image0.shape)
            keep = (std0[rows, cols] >= self.min_std) & ~bad0[rows, cols]
            rows, cols = rows[keep], cols[keep]
            dx0, dy0 = self.initial_offset
            k0, k1, conf = [], [], []
            for r, c in zip(rows.tolist(), cols.tolist(), strict=True):
                hit = _correlate(
                    image0,
                    image1,
                    bad1,
                    r,
                    c,
                    round(r + dy0),
                    round(c + dx0),
                    t,
                    self.search_radius,
                    self.min_ncc,
                    self.ambiguity_ratio,
                    self.subpixel,
                )
                if hit is not None:
                    k0.append((c + 0.5, r + 0.5))
                    k1.append(hit[:2])
                    conf.append(hit[2])
        if not k0:
            return Matches.empty()
        return Matches(np.asarray(k0), np.asarray(k1), np.asarray(conf))


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
