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
terrain intersections of the same pixel; in pixels, that ground displacement expressed
in the true camera's pixel footprint at that pixel (the local affine map of image to
ground, from the true camera's intersections half a pixel either side along the line and
the sample direction, all inside the image).

The pixel figure is not the adjusted camera's projection of the true ground point: a
badly adjusted camera (free or extrapolated orientation nodes at a strip end) can have a
second, spurious solution of the line equation far outside the image, and a projection
landing there reported ~1400 px where the ground points were 25 m (10 px) apart. The
footprint conversion evaluates both cameras only at pixels inside the image, so
``rms_px`` is ``rms_m`` in units of the local true GSD.
"""

from __future__ import annotations

import math
from typing import Any, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.arrays import F64
from planetref.errors import InputError
from planetref.runtime.optional import optional_module

__all__ = [
    "geolocation_error",
    "ground_offset_px",
    "grouped_reprojection_metrics",
    "image_grid",
    "reprojection_metrics",
]


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
    n_in = int(np.count_nonzero(keep))
    xi, yi = x[keep], y[keep]
    if not n_in:
        return _metric_dict(int(x.size), 0, [math.nan] * 6, [math.nan] * 4)
    sums = [
        np.sum(xi**2 + yi**2),
        np.sum(xi**2),
        np.sum(yi**2),
        np.sum(xi),
        np.sum(yi),
        np.sum(np.hypot(xi, yi)),
    ]
    return _metric_dict(int(x.size), n_in, sums, [np.max(xi), np.min(xi), np.max(yi), np.min(yi)])


def grouped_reprojection_metrics(
    dx: F64, dy: F64, inlier: NDArray[np.bool_], group: NDArray[np.intp], n_groups: int
) -> list[dict[str, float | int]]:
    """:func:`reprojection_metrics` of many groups of residuals in one pass.

    Equal bit for bit to ``reprojection_metrics(dx[m], dy[m], inlier[m])`` with ``m``
    the rows of each group (compiled, :mod:`planetref.adjust._numba_metrics`; without numba,
    that loop itself).

    Args:
        dx: Sample residuals (pixels), ``(N,)``.
        dy: Line residuals (pixels), ``(N,)``.
        inlier: Inlier flags, ``(N,)``.
        group: Group codes, ``(L, N)``: each row one partition of the residuals (a
            residual belongs to at most one group per row; ``-1``: none); codes are
            ``< n_groups`` and unique over the rows.
        n_groups: Number of groups.

    Returns:
        One metrics dict per group code.
    """
    group = np.atleast_2d(np.asarray(group, np.intp))
    fn = optional_module("planetref.adjust._numba_metrics", "compiled reprojection metrics")
    if fn is None:
        out: list[dict[str, float | int]] = [{} for _ in range(n_groups)]
        for row in group:
            for g in np.unique(row[row >= 0]):
                m = row == g
                out[int(g)] = reprojection_metrics(dx[m], dy[m], inlier[m])
        empty = reprojection_metrics(np.zeros(0), np.zeros(0))
        return [d or dict(empty) for d in out]
    n_total, n_in, sums, ext = fn.group_sums(
        np.asarray(dx, np.float64), np.asarray(dy, np.float64), inlier, group, n_groups
    )
    return [
        _metric_dict(int(n_total[g]), int(n_in[g]), sums[g].tolist(), ext[g].tolist())
        for g in range(n_groups)
    ]


def _metric_dict(
    n_total: int, n_in: int, sums: list[Any], ext: list[Any]
) -> dict[str, float | int]:
    """The metrics from the sums and extremes of ``n_in`` inliers among ``n_total``.

    ``sums``: of ``x^2 + y^2, x^2, y^2, x, y, hypot(x, y)``; ``ext``: ``(max x, min x,
    max y, min y)``.
    """
    nan = float("nan")
    s_r2, s_x2, s_y2, s_x, s_y, s_len = (float(v) for v in sums)
    return {
        "rmse_px": math.sqrt(s_r2 / n_in) if n_in else nan,
        "rmse_x_px": math.sqrt(s_x2 / n_in) if n_in else nan,
        "rmse_y_px": math.sqrt(s_y2 / n_in) if n_in else nan,
        "mean_x_px": s_x / n_in if n_in else nan,
        "mean_y_px": s_y / n_in if n_in else nan,
        "mean_px": s_len / n_in if n_in else nan,
        "max_dx_px": float(ext[0]) if n_in else nan,
        "min_dx_px": float(ext[1]) if n_in else nan,
        "max_dy_px": float(ext[2]) if n_in else nan,
        "min_dy_px": float(ext[3]) if n_in else nan,
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
        terrain intersections of each pixel, and that displacement in the true camera's
        pixels (:func:`ground_offset_px`); ``n`` grid points used (those whose rays hit
        the terrain in both cameras).
    """
    if len(grid) == 2 and np.ndim(grid[0]) == 0:
        # Scalars (ndim 0): the ``(n_lines, n_samples)`` form, whatever their number type.
        counts = cast(tuple[int, int], grid)
        line, sample = image_grid(camera_true, ccd, (int(counts[0]), int(counts[1])))
    else:
        line = np.asarray(grid[0], np.float64).ravel()
        sample = np.asarray(grid[1], np.float64).ravel()
    truth = camera_true.image_to_ground(line, sample, terrain, ccd=ccd, on_miss="nan")
    est = camera_adjusted.image_to_ground(line, sample, terrain, ccd=ccd, on_miss="nan")
    ok = np.all(np.isfinite(truth), axis=1) & np.all(np.isfinite(est), axis=1)
    dist_m = np.linalg.norm(est[ok] - truth[ok], axis=1)
    dpx = ground_offset_px(camera_true, line[ok], sample[ok], est[ok] - truth[ok], ccd, terrain)
    dpx = dpx[np.isfinite(dpx)]
    nan = float("nan")
    return {
        "rms_m": float(np.sqrt(np.mean(dist_m**2))) if dist_m.size else nan,
        "max_m": float(np.max(dist_m)) if dist_m.size else nan,
        "rms_px": float(np.sqrt(np.mean(dpx**2))) if dpx.size else nan,
        "max_px": float(np.max(dpx)) if dpx.size else nan,
        "n": int(np.count_nonzero(ok)),
    }


def ground_offset_px(
    camera: Any, line: F64, sample: F64, offset_m: F64, ccd: str | None, terrain: Any
) -> F64:
    """Length in pixels of ground displacements, in a camera's local pixel footprint.

    At each pixel ``(line, sample)`` the camera's terrain intersections half a pixel
    before and after along each image axis (clipped to the image, so the camera is never
    evaluated outside it) give the local ground vectors of one line and one sample; the
    displacement is solved in that basis by least squares (its component off the local
    ground surface is ignored).

    Args:
        camera: The reference (true) camera.
        line: Line coordinates, ``(N,)``.
        sample: Sample coordinates, ``(N,)``.
        offset_m: Body-fixed ground displacements at those pixels, ``(N, 3)`` metres.
        ccd: CCD name.
        terrain: Height or terrain, as for ``image_to_ground``.

    Returns:
        ``(N,)`` lengths in pixels (NaN where an intersection missed).
    """
    n_lines, n_samples = camera.image_size(ccd)
    line = np.asarray(line, np.float64)
    sample = np.asarray(sample, np.float64)
    l0, l1 = np.clip(line - 0.5, 0.0, n_lines), np.clip(line + 0.5, 0.0, n_lines)
    s0, s1 = np.clip(sample - 0.5, 0.0, n_samples), np.clip(sample + 0.5, 0.0, n_samples)
    lines = np.concatenate([l0, l1, line, line])
    samples = np.concatenate([sample, sample, s0, s1])
    g = camera.image_to_ground(lines, samples, terrain, ccd=ccd, on_miss="nan").reshape(4, -1, 3)
    with np.errstate(invalid="ignore", divide="ignore"):
        d_line = (g[1] - g[0]) / (l1 - l0)[:, None]
        d_sample = (g[3] - g[2]) / (s1 - s0)[:, None]
    basis = np.stack([d_line, d_sample], axis=-1)  # (N, 3, 2): metres per pixel
    out = np.full(len(line), np.nan)
    good = np.all(np.isfinite(basis), axis=(1, 2)) & np.all(np.isfinite(offset_m), axis=1)
    if np.any(good):
        b = basis[good]
        normal = np.einsum("nki,nkj->nij", b, b)
        rhs = np.einsum("nki,nk->ni", b, np.asarray(offset_m, np.float64)[good])
        uv = np.linalg.solve(normal, rhs[..., None])[..., 0]
        out[good] = np.hypot(uv[:, 0], uv[:, 1])
    return out
