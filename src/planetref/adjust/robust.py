"""Robust losses of the bundle adjustment (IRLS weights)."""

from __future__ import annotations

import numpy as np

from planetref.arrays import F64
from planetref.errors import AdjustmentError

__all__ = ["robust_rho"]


def robust_rho(s: F64, loss: str, t: F64 | float) -> tuple[F64, F64]:
    """Robust loss of squared normalised residuals and its derivative (the IRLS weight).

    Args:
        s: Squared normalised residual lengths ``r^T W r`` (dimensionless).
        loss: ``"linear"``, ``"huber"`` or ``"cauchy"``.
        t: Threshold in normalised units (residual length where the loss turns robust).

    Returns:
        ``(rho(s), rho'(s))``; ``rho(s) = s`` for small ``s`` for every loss.
    """
    if loss == "linear":
        return s, np.ones_like(s)
    t2 = np.asarray(t, np.float64) ** 2
    if loss == "huber":
        root = np.sqrt(s)
        big = s > t2
        with np.errstate(divide="ignore", invalid="ignore"):
            rho = np.where(big, 2.0 * np.sqrt(t2) * root - t2, s)
            w = np.where(big, np.sqrt(t2) / root, 1.0)
        return rho, w
    if loss == "cauchy":
        return t2 * np.log1p(s / t2), 1.0 / (1.0 + s / t2)
    raise AdjustmentError(f"unknown robust loss {loss!r}")
