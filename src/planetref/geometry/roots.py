"""Vectorised one-dimensional root finding: bracket by a grid scan, refine safely.

Sensor models find the image line of a ground point as the root of a residual
``f(line)`` (the point's distance from the detector line, in pixels). Many points are
solved at once; each has its own root. Two steps:

1. :func:`bracket_first_sign_change` scans a grid of trial values for the first
   interval where the residual changes sign (finite at both ends).
2. :func:`refine_bracketed` iterates inside the bracket: a Newton step when a slope is
   given, otherwise a secant step through the last two iterates; any step that is not
   finite or leaves the bracket is replaced by the bracket's midpoint (bisection), and
   the bracket shrinks with the sign of the residual at each iterate, so the iteration
   cannot diverge. It stops per point when the last step or the bracket is below
   ``xtol`` (or the residual is exactly zero) and accepts a root only when
   ``|f(x)| <= ftol`` there.

Residual functions take the trial values of the points still iterating and their row
indices (into the full set of points) and return the residuals (and slopes):
``f(x, rows) -> r`` or ``f(x, rows) -> (r, dr/dx)``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import NDArray

from planetref.arrays import F64

__all__ = [
    "Bracket",
    "Residual",
    "ResidualWithSlope",
    "bracket_first_sign_change",
    "refine_bracketed",
]

Rows = NDArray[np.intp]
Residual = Callable[[F64, Rows], F64]
ResidualWithSlope = Callable[[F64, Rows], tuple[F64, F64]]


@dataclass(frozen=True)
class Bracket:
    """Per point, an interval ``[lo, hi]`` whose ends' residuals differ in sign.

    Attributes:
        lo: Lower end, ``(m,)`` (NaN where none was found).
        hi: Upper end.
        f_lo: Residual at ``lo``.
        f_hi: Residual at ``hi``.
        found: Whether a sign change was found.
    """

    lo: F64
    hi: F64
    f_lo: F64
    f_hi: F64
    found: NDArray[np.bool_]

    def interpolate(self) -> F64:
        """The linear-interpolation (regula falsi) estimate inside each bracket."""
        with np.errstate(divide="ignore", invalid="ignore"):
            frac = np.where(self.f_hi != self.f_lo, self.f_lo / (self.f_lo - self.f_hi), 0.5)
        return self.lo + np.clip(frac, 0, 1) * (self.hi - self.lo)


def bracket_first_sign_change(residual: Residual, grid: F64, m: int) -> Bracket:
    """Scan ``grid`` (increasing trial values) for each point's first sign change.

    Args:
        residual: ``f(x, rows)``; called once per grid value with all ``m`` rows.
        grid: Trial values, ``(g,)``, increasing.
        m: Number of points.

    Returns:
        :class:`Bracket`; ``found`` is False where no interval with finite residuals of
        opposite sign (or a zero) exists on the grid.
    """
    rows = np.arange(m)
    f = np.stack([residual(np.full(m, float(x)), rows) for x in grid], axis=1)
    sgn = np.sign(f)
    change = (sgn[:, :-1] * sgn[:, 1:] <= 0) & np.isfinite(f[:, :-1]) & np.isfinite(f[:, 1:])
    # Along an axis of a 2-D array ``any`` gives an array (the stubs allow a scalar).
    found = cast(NDArray[np.bool_], change.any(axis=1))
    j = np.argmax(change, axis=1)
    j1 = np.minimum(j + 1, len(grid) - 1)
    return Bracket(
        lo=np.where(found, grid[j], np.nan),
        hi=np.where(found, grid[j1], np.nan),
        f_lo=f[rows, j],
        f_hi=f[rows, j1],
        found=found,
    )


def refine_bracketed(
    bracket: Bracket,
    *,
    residual: Residual | None = None,
    residual_with_slope: ResidualWithSlope | None = None,
    x0: F64 | None = None,
    xtol: float = 1e-8,
    ftol: float = 1e-6,
    max_iter: int = 60,
    stop_at_ftol: bool = False,
) -> F64:
    """Safeguarded Newton (or secant) iterations inside brackets.

    Args:
        bracket: From :func:`bracket_first_sign_change` (rows without a bracket stay NaN).
        residual: ``f(x, rows)``; used when no slope function is given (secant steps).
        residual_with_slope: ``f(x, rows) -> (r, dr/dx)``; Newton steps.
        x0: Starting values inside the brackets (default: :meth:`Bracket.interpolate`).
        xtol: Stop when the last step is below this (units of ``x``; lines: pixels).
        ftol: Accept a root only where ``|f| <= ftol`` at the returned value (units of
            the residual), so iterations that stalled at a bracket end are rejected.
        max_iter: Iteration limit per point.
        stop_at_ftol: Also stop a point as soon as ``|f| <= ftol`` (for residuals with
            rounding noise near ``ftol``, where steps below ``xtol`` may never come).

    Returns:
        The roots, ``(m,)``; NaN where none was bracketed, none converged, or the final
        residual exceeds ``ftol``.
    """
    if (residual is None) == (residual_with_slope is None):
        raise ValueError("give exactly one of residual and residual_with_slope")
    lo, hi = bracket.lo.copy(), bracket.hi.copy()
    f_lo = bracket.f_lo.copy()
    x = bracket.interpolate() if x0 is None else np.array(x0, np.float64)
    x = np.where(bracket.found, x, np.nan)
    fx = np.full(len(x), np.nan)
    # Secant memory: the previous iterate and its residual (the nearer bracket end first).
    x_prev = np.where(np.abs(bracket.f_lo) < np.abs(bracket.f_hi), lo, hi)
    f_prev = np.where(np.abs(bracket.f_lo) < np.abs(bracket.f_hi), bracket.f_lo, bracket.f_hi)
    active = np.isfinite(x)
    for _ in range(max_iter):
        ia = np.flatnonzero(active)
        if ia.size == 0:
            break
        xa = x[ia]
        with np.errstate(divide="ignore", invalid="ignore"):
            if residual_with_slope is not None:
                f, slope = residual_with_slope(xa, ia)
            else:
                f = residual(xa, ia)  # type: ignore[misc]
                slope = (f - f_prev[ia]) / (xa - x_prev[ia])
            step = -f / slope
        fx[ia] = f
        newton = xa + step
        lo_a, hi_a = lo[ia], hi[ia]
        out = ~np.isfinite(newton) | (newton < lo_a) | (newton > hi_a)
        new = np.where(out, 0.5 * (lo_a + hi_a), newton)
        same = np.sign(f) == np.sign(f_lo[ia])
        lo[ia] = np.where(same, xa, lo_a)
        f_lo[ia] = np.where(same, f, f_lo[ia])
        hi[ia] = np.where(same, hi_a, xa)
        x_prev[ia], f_prev[ia] = xa, f
        converged = (np.abs(step) < xtol) | (f == 0)
        # A converged Newton point is kept even when it lies (by less than ``xtol``)
        # outside the bracket: a root on a bracket end, where rounding gave the end's
        # residual the other sign, is found there, not replaced by the bracket's midpoint.
        new = np.where(converged, newton, new)
        done = converged
        if stop_at_ftol:
            hit = np.abs(f) <= ftol
            done |= hit
            step = np.where(hit, 0.0, step)
            new = np.where(hit, xa, new)
        # A non-finite step ends the iteration (e.g. a residual that is not defined).
        done |= ~np.isfinite(step) & ~out
        x[ia] = np.where(done & np.isfinite(step), new, np.where(done, xa, new))
        # A bracket narrower than xtol also ends the iteration (e.g. at a jump).
        active[ia[done | ((hi[ia] - lo[ia]) < xtol)]] = False
    ok = np.isfinite(x)
    if np.any(ok):
        io = np.flatnonzero(ok)
        if residual_with_slope is not None:
            f_end, _ = residual_with_slope(x[io], io)
        else:
            f_end = residual(x[io], io)  # type: ignore[misc]
        x[io[~(np.abs(f_end) <= ftol)]] = np.nan
    return x
