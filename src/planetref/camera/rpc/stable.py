"""An RPC fit without a pole near the image: the regularisation ladder.

A camera's ground-to-image mapping over a long strip is smooth but not exactly rational;
with :func:`~planetref.camera.rpc.fit.fit_rpc`'s default (very weak) Tikhonov term the
least-squares rational fit can then place a zero of a denominator near the image (``min
|D|`` ~ 1e-4: tens to thousands of pixels of error there; a real 19,456-line CTX image:
1453 px). Stronger regularisation keeps ``D`` near 1 at a cost of hundredths of a pixel.
"""

from __future__ import annotations

from typing import Any

from planetref.camera.rpc.fit import FitReport, fit_rpc
from planetref.camera.rpc.model import Rpc

__all__ = ["REGULARIZATIONS", "fit_rpc_stable"]

#: Tried in this order; the first fit with a check error < 0.05 px and ``min |D|`` > 0.5
#: ends the ladder, else the fit with the smallest maximum check error is kept.
REGULARIZATIONS = (1e-12, 1e-9, 1e-6, 1e-4)


def fit_rpc_stable(
    camera: Any,
    *,
    height_range_m: tuple[float, float],
    ccd: str | None = None,
    grid: tuple[int, int, int] = (21, 21, 7),
) -> tuple[Rpc, FitReport]:
    """Fit an RPC, strengthening the regularisation while the fit is poorly behaved.

    Args:
        camera: Any planetref camera.
        height_range_m: ``(h_min, h_max)`` the RPC must hold for (m above the ellipsoid).
        ccd: The CCD (default: the camera's first).
        grid: Fitting grid ``(n_lines, n_samples, n_heights)`` (see ``fit_rpc``).

    Returns:
        The RPC and its fit report (``regularization`` says which rung was kept).
    """
    best: tuple[Rpc, FitReport] | None = None
    for reg in REGULARIZATIONS:
        model, fit = fit_rpc(
            camera, height_range_m=height_range_m, ccd=ccd, grid=grid, regularization=reg
        )
        if best is None or fit.check_max_px < best[1].check_max_px:
            best = (model, fit)
        if fit.check_max_px < 0.05 and fit.min_abs_denominator > 0.5:
            break
    return best  # type: ignore[return-value]  # REGULARIZATIONS is not empty
