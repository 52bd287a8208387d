"""Accuracy metrics.

Adjustment metrics (the seed's Table 2)
---------------------------------------
Residuals are ``projected - observed`` in pixels with ``dx`` the sample residual and
``dy`` the line residual.

* ``RMSE = sqrt(mean(dx^2 + dy^2))`` over the inliers (radial), and per axis
  ``RMSE_x = sqrt(mean(dx^2))``, ``RMSE_y = sqrt(mean(dy^2))`` with the signed means
  ``mean(dx)``, ``mean(dy)`` (the paper's Table 2 in x and y),
* mean residual length ``mean(sqrt(dx^2 + dy^2))`` over the inliers,
* max and min of the signed residuals in x (sample) and y (line), over the inliers,
* outlier ratio ``OR = (N_total - N_inliers) / N_total`` in percent.

Geolocation error (where the true camera is known)
--------------------------------------------------
For a grid of image pixels, the ground point that the true camera sees on the terrain
is compared with the adjusted camera: in metres, the distance between the two cameras'
terrain intersections of the same pixel; in pixels, the distance between the pixel and
the adjusted camera's projection of the true ground point.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.errors import InputError

__all__ = ["geolocation_error", "image_grid", "reprojection_metrics"]

F64 = NDArray[np.float64]


def reprojection_metrics(
    dx: ArrayLike, dy: ArrayLike, inlier: ArrayLike | None = None
) -> dict[str, float | int]:
    """RMSE, mean length, signed extremes and outlier ratio of reprojection residuals.

    Args:
        dx: Sample residuals (pixels), ``(N,)``; NaN entries count as non-inliers.
        dy: Line residuals (pixels), ``(N,)``.
        inlier: Inlier flags, ``(N,)`` (default: every finite residual).

    Returns:
        ``{"rmse_px", "rmse_x_px", "rmse_y_px", "mean_x_px", "mean_y_px", "mean_px",
        "max_dx_px", "min_dx_px", "max_dy_px", "min_dy_px", "outlier_ratio_pct",
        "n_total", "n_inliers"}``: radial RMSE, per-axis RMSE and signed means (x =
        sample, y = line), mean length, signed extremes; the outlier ratio is
        ``(N_total - N_inliers) / N_total`` over the observations that entered the
        adjustment (the paper's OR). Statistics of an empty inlier set are NaN.

    Raises:
        InputError: When the arrays do not have the same length.
    """
    x = np.asarray(dx, np.float64).ravel()
    y = np.asarray(dy, np.float64).ravel()
    if x.shape != y.shape:
        raise InputError(f"dx and dy differ in length ({x.size} != {y.size})")
    finite = np.isfinite(x) & np.isfinite(y)
    keep = finite if inlier is None else np.asarray(inlier, bool).ravel() & finite
    if keep.shape != x.shape:
        raise InputError(f"inlier has {keep.size} entries for {x.size} residuals")
    n_total = int(x.size)
    n_in = int(np.count_nonzero(keep))
    xi, yi = x[keep], y[keep]
    nan = float("nan")
    length = np.hypot(xi, yi)
    return {
        "rmse_px": float(math.sqrt(np.mean(xi**2 + yi**2))) if n_in else nan,
        "rmse_x_px": float(math.sqrt(np.mean(xi**2))) if n_in else nan,
        "rmse_y_px": float(math.sqrt(np.mean(yi**2))) if n_in else nan,
        "mean_x_px": float(np.mean(xi)) if n_in else nan,
        "mean_y_px": float(np.mean(yi)) if n_in else nan,
        "mean_px": float(np.mean(length)) if n_in else nan,
        "max_dx_px": float(np.max(xi)) if n_in else nan,
        "min_dx_px": float(np.min(xi)) if n_in else nan,
        "max_dy_px": float(np.max(yi)) if n_in else nan,
        "min_dy_px": float(np.min(yi)) if n_in else nan,
        "outlier_ratio_pct": 100.0 * (n_total - n_in) / n_total if n_total else nan,
        "n_total": n_total,
        "n_inliers": n_in,
    }


def image_grid(
    camera: Any, ccd: str | None = None, n: tuple[int, int] = (21, 21)
) -> tuple[F64, F64]:
    """A regular grid of pixel centres spanning a CCD image, edge to edge.

    Args:
        camera: Any planetref camera.
        ccd: CCD name (default: the first).
        n: ``(n_lines, n_samples)`` grid nodes.

    Returns:
        ``(line, sample)`` flattened, in planetref's pixel convention.
    """
    n_lines, n_samples = camera.image_size(ccd)
    lines = np.linspace(0.5, n_lines - 0.5, int(n[0]))
    samples = np.linspace(0.5, n_samples - 0.5, int(n[1]))
    ll, ss = np.meshgrid(lines, samples, indexing="ij")
    return ll.ravel(), ss.ravel()


def geolocation_error(
    camera_adjusted: Any,
    camera_true: Any,
    *,
    ccd: str | None = None,
    terrain: Any = 0.0,
    grid: tuple[int, int] | tuple[ArrayLike, ArrayLike] = (21, 21),
) -> dict[str, float | int]:
    """Geolocation error of a camera against the true one over a grid of image pixels.

    Args:
        camera_adjusted: The camera to assess (e.g. before or after adjustment).
        camera_true: The true camera (same CCD layout and image size).
        ccd: CCD name (default: the first).
        terrain: Height in metres above the ellipsoid or a
            :class:`~planetref.camera.base.Terrain` (e.g. the DEM).
        grid: ``(n_lines, n_samples)`` grid nodes over the image, or explicit
            ``(line, sample)`` arrays (pixels).

    Returns:
        ``{"rms_m", "max_m", "rms_px", "max_px", "n"}``: metres between the two cameras'
        terrain intersections of each pixel, and pixels between each pixel and the
        adjusted camera's projection of the true ground point; ``n`` grid points used
        (those whose rays hit the terrain in both cameras).
    """
    if len(grid) == 2 and np.ndim(grid[0]) == 0:
        line, sample = image_grid(camera_true, ccd, (int(grid[0]), int(grid[1])))
    else:
        line = np.asarray(grid[0], np.float64).ravel()
        sample = np.asarray(grid[1], np.float64).ravel()
    truth = camera_true.image_to_ground(line, sample, terrain, ccd=ccd, on_miss="nan")
    est = camera_adjusted.image_to_ground(line, sample, terrain, ccd=ccd, on_miss="nan")
    ok = np.all(np.isfinite(truth), axis=1) & np.all(np.isfinite(est), axis=1)
    dist_m = np.linalg.norm(est[ok] - truth[ok], axis=1)
    ip = camera_adjusted.ground_to_image(truth[ok], ccd=ccd)
    dpx = np.hypot(ip.line - line[ok], ip.sample - sample[ok])
    dpx = dpx[np.isfinite(dpx)]
    nan = float("nan")
    return {
        "rms_m": float(np.sqrt(np.mean(dist_m**2))) if dist_m.size else nan,
        "max_m": float(np.max(dist_m)) if dist_m.size else nan,
        "rms_px": float(np.sqrt(np.mean(dpx**2))) if dpx.size else nan,
        "max_px": float(np.max(dpx)) if dpx.size else nan,
        "n": int(np.count_nonzero(ok)),
    }
