"""The seed's outlier rule and the support of free tie points.

An observation is an inlier if its reprojection error (the length of its residual in
pixels) is below ``k x RMSE``, with ``RMSE = sqrt(mean(dx^2 + dy^2))`` over the current
inliers (``k = 3``). Adjustment and rejection alternate until the inlier set no longer
changes (:func:`planetref.adjust.api.adjust` drives the rounds).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

__all__ = ["classify_inliers", "robust_scale", "supported"]


def classify_inliers(
    length_px: NDArray[np.float64],
    candidates: NDArray[np.bool_],
    inlier: NDArray[np.bool_],
    k_rmse: float,
) -> tuple[NDArray[np.bool_], float]:
    """Apply the ``k x RMSE`` rule.

    Args:
        length_px: Residual length of every observation (pixels; NaN = not projectable).
        candidates: Observations that may be inliers (usable, not held out).
        inlier: The current inliers, over which the RMSE is computed.
        k_rmse: The factor ``k``.

    Returns:
        ``(new_inlier, rmse_px)``.
    """
    cur = inlier & np.isfinite(length_px)
    rmse = math.sqrt(float(np.mean(length_px[cur] ** 2))) if np.any(cur) else math.nan
    with np.errstate(invalid="ignore"):
        new = candidates & np.isfinite(length_px) & (length_px < k_rmse * rmse)
    return new, rmse


def supported(
    inlier: NDArray[np.bool_],
    obs_point: NDArray[np.intp],
    free_point: NDArray[np.bool_],
    min_obs: int,
) -> NDArray[np.bool_]:
    """Drop the observations of free points seen fewer than ``min_obs`` times.

    A free tie point's coordinates are unknowns; with fewer than two rays they are not
    determined and its observations carry no information on the cameras.

    Args:
        inlier: Current inlier flags per observation.
        obs_point: Point index per observation.
        free_point: True for points whose coordinates are free (no a-priori sigma).
        min_obs: Fewest observations of a free point.

    Returns:
        The flags with those observations cleared.
    """
    counts = np.bincount(obs_point[inlier], minlength=len(free_point))
    weak = free_point & (counts < min_obs)
    return inlier & ~weak[obs_point]


def robust_scale(length_norm: NDArray[np.float64]) -> float:
    """Scale of normalised 2-D residual lengths from their median.

    For residuals with unit standard deviation per axis the length follows a Rayleigh
    distribution whose median is ``sqrt(2 ln 2)``; the estimate is ``median /
    sqrt(2 ln 2)`` (1 for correctly weighted Gaussian residuals), robust to up to half
    outliers.

    Args:
        length_norm: ``sqrt(r^T W r)`` per observation (finite values are used).

    Returns:
        The scale (at least 1e-9, NaN for no data).
    """
    v = length_norm[np.isfinite(length_norm)]
    if not v.size:
        return math.nan
    return max(float(np.median(v)) / math.sqrt(2.0 * math.log(2.0)), 1e-9)
