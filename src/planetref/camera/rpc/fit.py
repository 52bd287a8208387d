"""Fitting an RPC to any camera (:func:`fit_rpc`) by linear least squares.

The camera is sampled on a grid of image points at several heights; the rational
polynomials are solved for with the denominators linearised and iterated (the standard
"terrain-independent" RPC fit). The solves run with a single-threaded BLAS
(:func:`planetref.runtime.blas.single_threaded_blas`): its threads gain nothing on these
small systems and fight torch's and other processes' threads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from planetref.camera.base import Camera
from planetref.camera.rpc.model import N_TERMS, Rpc
from planetref.camera.rpc.terms import terms
from planetref.errors import (
    GeometryError,
    InputError,
)
from planetref.geometry.geodesy import (
    lonlat_to_xyz,
    wrap_longitude,
    xyz_to_lonlat,
)
from planetref.runtime.blas import single_threaded_blas

__all__ = ["FitReport", "fit_rpc"]


# --------------------------------------------------------------------------- fitting


@dataclass(frozen=True)
class FitReport:
    """How well a fitted RPC reproduces the camera it was fitted to.

    Errors are ground -> image: the ground points that the rigorous camera localises
    from a grid of image points at several heights are projected with the fitted RPC
    and compared with the grid, in pixels, per image axis and as 2-D distances.

    Attributes:
        fit_rms_line_px: RMS line error on the fitting grid.
        fit_rms_sample_px: RMS sample error on the fitting grid.
        fit_max_px: Largest 2-D error on the fitting grid.
        check_rms_line_px: RMS line error on the check grid (cell centres of the fitting
            grid, at more heights, so no check point was used in the fit).
        check_rms_sample_px: RMS sample error on the check grid.
        check_max_px: Largest 2-D error on the check grid.
        check_max_ground_m: Largest distance (metres) between the rigorous ground point
            and the fitted RPC's localisation of the same image point and height, on the
            check grid (image -> ground direction).
        min_abs_denominator: Smallest ``|denominator|`` of the fitted RPC over both
            grids (values far below 1 warn of a pole near the image).
        n_fit: Number of fitting points (after dropping points the camera could not
            localise).
        n_check: Number of check points.
        n_dropped: Grid points the camera could not localise (on_miss NaN).
        iterations: Reweighting iterations used.
        regularization: The Tikhonov parameter used.
    """

    fit_rms_line_px: float
    fit_rms_sample_px: float
    fit_max_px: float
    check_rms_line_px: float
    check_rms_sample_px: float
    check_max_px: float
    check_max_ground_m: float
    min_abs_denominator: float
    n_fit: int
    n_check: int
    n_dropped: int
    iterations: int
    regularization: float

    @property
    def fit_rms_px(self) -> float:
        """2-D RMS error on the fitting grid, pixels."""
        return math.hypot(self.fit_rms_line_px, self.fit_rms_sample_px)

    @property
    def check_rms_px(self) -> float:
        """2-D RMS error on the check grid, pixels."""
        return math.hypot(self.check_rms_line_px, self.check_rms_sample_px)

    def summary(self) -> str:
        """A one-line human-readable summary."""
        return (
            f"RPC fit: fit RMS {self.fit_rms_px:.3g} px (max {self.fit_max_px:.3g}), "
            f"check RMS {self.check_rms_px:.3g} px (max {self.check_max_px:.3g}, "
            f"{self.check_max_ground_m:.3g} m), {self.n_fit} fit / {self.n_check} check "
            f"points, {self.iterations} iterations"
        )


@dataclass
class _Samples:
    line: NDArray[np.float64] = field(default_factory=lambda: np.empty(0))
    sample: NDArray[np.float64] = field(default_factory=lambda: np.empty(0))
    lon: NDArray[np.float64] = field(default_factory=lambda: np.empty(0))
    lat: NDArray[np.float64] = field(default_factory=lambda: np.empty(0))
    h: NDArray[np.float64] = field(default_factory=lambda: np.empty(0))
    xyz: NDArray[np.float64] = field(default_factory=lambda: np.empty((0, 3)))
    dropped: int = 0


def _sample_camera(
    camera: Camera,
    ccd: str | None,
    lines: NDArray[np.float64],
    samples: NDArray[np.float64],
    heights: NDArray[np.float64],
) -> _Samples:
    grid_l, grid_s = np.meshgrid(lines, samples, indexing="ij")
    ll, ss = grid_l.ravel(), grid_s.ravel()
    out_l, out_s, out_xyz, out_h = [], [], [], []
    for h in heights:
        xyz = np.asarray(
            camera.image_to_ground(
                ll,
                ss,
                terrain=float(h),
                ccd=ccd,
                on_miss="nan",
            ),
            dtype=np.float64,
        )
        out_l.append(ll)
        out_s.append(ss)
        out_xyz.append(xyz.reshape(-1, 3))
        out_h.append(np.full(ll.size, h))
    xyz = np.concatenate(out_xyz)
    ok = np.all(np.isfinite(xyz), axis=1)
    lon, lat, hh = xyz_to_lonlat(xyz[ok], camera.ellipsoid, camera.latitude_kind)
    return _Samples(
        np.concatenate(out_l)[ok],
        np.concatenate(out_s)[ok],
        lon,
        lat,
        hh,
        xyz[ok],
        int((~ok).sum()),
    )


def _solve_rational(
    T: NDArray[np.float64], y: NDArray[np.float64], reg: float, max_iter: int
) -> tuple[NDArray[np.float64], NDArray[np.float64], int]:
    # Tao & Hu (2001): linearise y = N/D as N - y*D = 0 with D's constant term fixed to
    # 1, weight each equation by 1/D of the previous solution so that the residual
    # tends to the true y - N/D, and regularise with a ridge term. The augmented least
    # squares problem is solved directly (better conditioned than normal equations).
    n = T.shape[0]
    A = np.hstack([T, -y[:, None] * T[:, 1:]])
    ridge = math.sqrt(reg) * np.eye(A.shape[1])
    w = np.ones(n)
    best: tuple[float, NDArray[np.float64], NDArray[np.float64]] | None = None
    used = 0
    for it in range(1, max_iter + 1):
        used = it
        Aw = np.vstack([A * (w / math.sqrt(n))[:, None], ridge])
        bw = np.concatenate([y * w / math.sqrt(n), np.zeros(A.shape[1])])
        x, *_ = np.linalg.lstsq(Aw, bw, rcond=None)
        num = x[:N_TERMS]
        den = np.concatenate([[1.0], x[N_TERMS:]])
        d = T @ den
        with np.errstate(divide="ignore", invalid="ignore"):
            rms = float(np.sqrt(np.mean((T @ num / d - y) ** 2)))
        if not math.isfinite(rms):
            break
        if best is not None and rms >= best[0] * (1 - 1e-3):
            if rms < best[0]:
                best = (rms, num, den)
            break
        best = (rms, num, den)
        w = 1.0 / np.where(np.abs(d) > 1e-12, d, 1e-12)
    if best is None:
        raise GeometryError("RPC fit failed: the least-squares problem has no finite solution")
    return best[1], best[2], used


def fit_rpc(
    camera: Camera,
    *,
    height_range_m: tuple[float, float],
    ccd: str | None = None,
    grid: tuple[int, int, int] = (21, 21, 7),
    regularization: float = 1e-12,
    max_iter: int = 10,
) -> tuple[Rpc, FitReport]:
    """Fit a terrain-independent RPC00B to any planetref camera.

    The camera is sampled on a 3-D grid: ``n_lines x n_samples`` image points spanning
    the image from edge to edge, each localised with ``camera.image_to_ground(...,
    terrain=h)`` at ``n_heights`` heights spanning ``height_range_m``. The ground points
    are converted to lon/lat/h with the camera's ellipsoid and latitude kind (which the
    RPC then uses), normalised, and the line and sample rational polynomials are solved
    separately by linear least squares with Tikhonov regularisation and iterative
    reweighting by the previous denominator (Tao & Hu 2001). The check grid is the set
    of cell centres of the image grid at ``2 * n_heights + 1`` heights.

    Args:
        camera: Any object implementing :class:`~planetref.camera.base.Camera`.
        height_range_m: ``(h_min, h_max)``, metres above the camera's ellipsoid, the
            heights the RPC must be valid for (``h_max > h_min``).
        ccd: Which CCD to fit (default: the camera's first).
        grid: ``(n_lines, n_samples, n_heights)`` of the fitting grid (at least
            ``(4, 4, 3)``; 39 unknowns per axis).
        regularization: Tikhonov parameter on the normalised coefficients, relative to
            the mean squared (weighted) equation. Small values (1e-14 to 1e-8) barely
            bias a well-determined fit and keep near-degenerate denominators (a camera
            that is almost affine in height) close to 1.
        max_iter: Maximum reweighting iterations.

    Returns:
        ``(rpc, report)``. The RPC's image offsets/scales put the image centre at 0 and
        the edges at ±1; the ground ones do the same for the sampled ground extent.

    Raises:
        InputError: For an invalid grid or height range.
        GeometryError: If the camera localises too few grid points or the fit fails.
    """
    try:
        h_min, h_max = (float(v) for v in height_range_m)
    except (TypeError, ValueError):
        raise InputError(
            f"expected (h_min, h_max), got {height_range_m!r}", field="height_range_m"
        ) from None
    if not (math.isfinite(h_min) and math.isfinite(h_max) and h_max > h_min):
        raise InputError(
            f"need finite h_max > h_min, got {height_range_m!r}", field="height_range_m"
        )
    try:
        n_l, n_s, n_h = (int(v) for v in grid)
    except (TypeError, ValueError):
        raise InputError(
            f"expected (n_lines, n_samples, n_heights), got {grid!r}", field="grid"
        ) from None
    if n_l < 4 or n_s < 4 or n_h < 3:
        raise InputError(f"grid must be at least (4, 4, 3), got {grid!r}", field="grid")
    if not (math.isfinite(regularization) and regularization >= 0):
        raise InputError(f"must be finite and >= 0, got {regularization}", field="regularization")

    n_lines, n_samples = camera.image_size(ccd)
    lines = np.linspace(0.0, n_lines, n_l)
    samples = np.linspace(0.0, n_samples, n_s)
    heights = np.linspace(h_min, h_max, n_h)
    fit = _sample_camera(camera, ccd, lines, samples, heights)
    if fit.line.size < 2 * 39:
        raise GeometryError(
            f"the camera localised only {fit.line.size} of "
            f"{n_l * n_s * n_h} grid points; at least 78 are needed"
        )

    lon_ref = float(np.median(fit.lon))
    dlon = wrap_longitude(fit.lon - lon_ref)
    lon_lo, lon_hi = float(dlon.min()), float(dlon.max())
    lat_lo, lat_hi = float(fit.lat.min()), float(fit.lat.max())
    long_off = float(wrap_longitude(lon_ref + 0.5 * (lon_lo + lon_hi)))
    lat_off = 0.5 * (lat_lo + lat_hi)
    long_scale = 0.5 * (lon_hi - lon_lo)
    lat_scale = 0.5 * (lat_hi - lat_lo)
    if not (long_scale > 0 and lat_scale > 0):
        raise GeometryError("the sampled ground points span no area; cannot fit an RPC")
    height_off, height_scale = 0.5 * (h_min + h_max), 0.5 * (h_max - h_min)
    # Raw RPC image coordinates have the first pixel centre at 0 (planetref: 0.5).
    line_off, line_scale = 0.5 * n_lines - 0.5, 0.5 * n_lines
    samp_off, samp_scale = 0.5 * n_samples - 0.5, 0.5 * n_samples

    def normalised(s: _Samples) -> NDArray[np.float64]:
        return terms(
            wrap_longitude(s.lon - long_off) / long_scale,
            (s.lat - lat_off) / lat_scale,
            (s.h - height_off) / height_scale,
        )

    T = normalised(fit)
    rn = (fit.line - 0.5 - line_off) / line_scale
    cn = (fit.sample - 0.5 - samp_off) / samp_scale
    # Small dense solves: BLAS threads gain nothing and fight torch's (and other
    # processes') threads, so the solves run single-threaded.
    with single_threaded_blas():
        line_num, line_den, it_l = _solve_rational(T, rn, regularization, max_iter)
        samp_num, samp_den, it_s = _solve_rational(T, cn, regularization, max_iter)
    rpc = Rpc(
        line_off=line_off,
        samp_off=samp_off,
        lat_off=lat_off,
        long_off=long_off,
        height_off=height_off,
        line_scale=line_scale,
        samp_scale=samp_scale,
        lat_scale=lat_scale,
        long_scale=long_scale,
        height_scale=height_scale,
        line_num_coeff=tuple(line_num),
        line_den_coeff=tuple(line_den),
        samp_num_coeff=tuple(samp_num),
        samp_den_coeff=tuple(samp_den),
    )

    check_lines = 0.5 * (lines[:-1] + lines[1:])
    check_samples = 0.5 * (samples[:-1] + samples[1:])
    check_heights = np.linspace(h_min, h_max, 2 * n_h + 1)
    chk = _sample_camera(camera, ccd, check_lines, check_samples, check_heights)

    def errors(s: _Samples) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        pl, ps = rpc.project(s.lon, s.lat, s.h)
        return pl - s.line, ps - s.sample

    fl, fs = errors(fit)
    cl, cs = errors(chk)
    back_lon, back_lat = rpc.localize(chk.line, chk.sample, chk.h)
    back = lonlat_to_xyz(
        back_lon,
        back_lat,
        chk.h,
        camera.ellipsoid,
        camera.latitude_kind,
    )
    ground_err = np.linalg.norm(back - chk.xyz, axis=1)
    dens = np.concatenate([normalised(fit), normalised(chk)]) @ np.stack(
        [rpc._coeff_array[:, 1], rpc._coeff_array[:, 3]], axis=1
    )

    def rms(v: NDArray[np.float64]) -> float:
        return float(np.sqrt(np.mean(v**2))) if v.size else float("nan")

    def vmax(v: NDArray[np.float64]) -> float:
        return float(np.max(v)) if v.size else float("nan")

    report = FitReport(
        fit_rms_line_px=rms(fl),
        fit_rms_sample_px=rms(fs),
        fit_max_px=vmax(np.hypot(fl, fs)),
        check_rms_line_px=rms(cl),
        check_rms_sample_px=rms(cs),
        check_max_px=vmax(np.hypot(cl, cs)),
        check_max_ground_m=float(np.max(ground_err)) if ground_err.size else float("nan"),
        min_abs_denominator=float(np.min(np.abs(dens))),
        n_fit=int(fit.line.size),
        n_check=int(chk.line.size),
        n_dropped=fit.dropped + chk.dropped,
        iterations=max(it_l, it_s),
        regularization=float(regularization),
    )
    return rpc, report
