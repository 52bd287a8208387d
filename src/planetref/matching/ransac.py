"""Geometric verification of matches with OpenCV's USAC (MAGSAC++).

Coordinates are used as given (planetref's corner convention); the estimated matrix maps
image-0 keypoints to image-1 keypoints in that convention.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from planetref.errors import InputError
from planetref.matching.base import Matches

__all__ = ["MIN_POINTS", "GeometricModel", "Verification", "verify_matches"]

GeometricModel = Literal["homography", "affine", "fundamental"]

MIN_POINTS: dict[str, int] = {"homography": 4, "affine": 3, "fundamental": 8}
"""Fewest matches each model needs; with fewer, no match is an inlier."""


@dataclass(frozen=True, eq=False)
class Verification:
    """Result of :func:`verify_matches`.

    Attributes:
        model: The model kind that was fitted.
        matrix: ``3x3`` homography, ``2x3`` affine or ``3x3`` fundamental matrix mapping
            image 0 to image 1 (pixels), or ``None`` when no model could be fitted.
        inliers: ``(N,)`` boolean mask over the input matches.
    """

    model: GeometricModel
    matrix: NDArray[np.float64] | None
    inliers: NDArray[np.bool_]

    @property
    def n_inliers(self) -> int:
        """Number of inliers."""
        return int(self.inliers.sum())


def verify_matches(
    matches: Matches,
    model: GeometricModel = "homography",
    *,
    threshold: float = 3.0,
    confidence: float = 0.9999,
    max_iters: int = 10_000,
) -> Verification:
    """Fit a geometric model robustly and flag the matches consistent with it.

    Args:
        matches: Matches to verify, pixels.
        model: ``"homography"`` (default; near-planar ortho/map-projected scenes),
            ``"affine"`` (6 parameters, more stable for small tiles) or ``"fundamental"``
            (epipolar geometry, for raw images with parallax).
        threshold: Inlier threshold, pixels (reprojection error for homography/affine,
            distance to the epipolar line for the fundamental matrix).
        confidence: RANSAC confidence in ``(0, 1)``.
        max_iters: Maximum number of iterations.

    Returns:
        The fitted model and the inlier mask. With fewer matches than the model needs
        (see :data:`MIN_POINTS`) or when the estimation fails, ``matrix`` is ``None`` and
        no match is an inlier.

    Raises:
        InputError: Unknown model or non-positive threshold.
    """
    if model not in MIN_POINTS:
        raise InputError(
            f"unknown model {model!r}; expected one of {', '.join(MIN_POINTS)}", field="model"
        )
    if not threshold > 0:
        raise InputError(f"must be > 0, got {threshold}", field="threshold")
    if not 0 < confidence < 1:
        raise InputError(f"must be in (0, 1), got {confidence}", field="confidence")
    n = len(matches)
    none = Verification(model, None, np.zeros(n, bool))
    if n < MIN_POINTS[model]:
        return none
    src = np.ascontiguousarray(matches.keypoints0, dtype=np.float64).reshape(-1, 1, 2)
    dst = np.ascontiguousarray(matches.keypoints1, dtype=np.float64).reshape(-1, 1, 2)
    try:
        if model == "homography":
            matrix, mask = cv2.findHomography(
                src,
                dst,
                cv2.USAC_MAGSAC,
                float(threshold),
                maxIters=int(max_iters),
                confidence=float(confidence),
            )
        elif model == "affine":
            matrix, mask = cv2.estimateAffine2D(
                src,
                dst,
                method=cv2.USAC_MAGSAC,
                ransacReprojThreshold=float(threshold),
                maxIters=int(max_iters),
                confidence=float(confidence),
            )
        else:
            matrix, mask = cv2.findFundamentalMat(
                src, dst, cv2.USAC_MAGSAC, float(threshold), float(confidence), int(max_iters)
            )
    except cv2.error:
        # degenerate configurations (all points collinear or identical) make USAC throw
        return none
    if matrix is None or mask is None or matrix.size == 0:
        return none
    if model == "fundamental" and matrix.shape != (3, 3):
        matrix = matrix[:3]  # the 7-point solver may return stacked solutions
    return Verification(model, np.asarray(matrix, np.float64), mask.reshape(-1).astype(bool))
