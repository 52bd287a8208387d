"""A compiled (numba) twin of the line-scan projection kernel, one point per loop step.

The maths is that of :mod:`planetref.camera.linescan.kernel` (the reference: tests check
that both give the same lines, samples, validity and partials to ~1e-12 relative):
chord iterations on the detector offset from the guesses, one full evaluation with every
partial at the last line, the final Newton step to first order, the implicit-function
partials. The numpy kernel evaluates each step over whole arrays; here every point runs
its own scalar loop in registers, with no temporary arrays, which is what makes the
adjustment's linearisation cheap.

numba is imported lazily (:func:`available`); when it is missing the kernel falls back
to numpy with one log line. Compiled functions are cached on disk (``cache=True``);
numba writes the cache next to this file or, on a read-only install, into its user
cache directory (``NUMBA_CACHE_DIR`` overrides both).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.arrays import F64
from planetref.runtime.optional import optional_module

__all__ = ["available", "fill_partials", "project_points", "warm_up"]


def _compiled() -> Any:
    """The compiled functions (a namespace), or ``None`` when numba cannot be imported."""
    return optional_module(
        "planetref.camera.linescan._numba_kernel",
        "compiled line-scan kernel",
        check=_smoke_test,
    )


def _smoke_test(mod: Any) -> None:
    """Compile (or load from the cache) by projecting one point of a trivial camera."""
    k = 2
    tables = (
        np.zeros(1),
        np.zeros(1),
        np.ones(1),
        np.array([0.0, 10.0]),
        np.array([5.0]),
        np.array([[[0.5, -0.1], [0.5, 0.1]]]),
        np.eye(3),
    )
    poly = np.zeros((1, k, 6))
    poly[0, 0, 2] = 1000.0  # camera 1 km above the origin, looking down -z
    one = np.ones(1)
    for full in (False, True):
        mod.project(
            *tables, k, -10.0, 20.0, poly, np.array([0.0, 0.0, 100.0]),
            np.array([0.0, 0.0, 0.0, 0.01, 0.0, 1.0]), np.zeros((1, 3)), one * 5.0,
            one * np.nan, full, 1e-6, 1e-3, np.empty(1), np.empty(1), np.empty(1, np.bool_),
            np.empty(1), np.empty(1, np.intp), np.empty((1, k)), np.empty((1, 2, 15)),
            np.empty(1),
        )  # fmt: skip
    mod.fill_partials(np.zeros((1, 2, 15)), np.ones((1, k)), True, np.empty((1, 2, 6 * k + 6)),
                      np.empty((1, 2, 3)))  # fmt: skip


def available() -> bool:
    """True when the compiled kernel can be used (numba imports and compiles).

    The first call of a process loads the kernel from numba's cache (or compiles it).
    """
    return _compiled() is not None


def warm_up() -> bool:
    """Load (or compile) the kernel now; same as :func:`available`."""
    return available()


def project_points(
    tables: tuple[F64, ...],
    k: int,
    span: tuple[float, float],
    poly: F64,
    io: F64,
    ccd: tuple[float, float, float, float],
    p: F64,
    line: F64,
    rate: F64 | None,
    *,
    full: bool,
    chord_tol: float,
    step_valid: float,
) -> tuple[NDArray[Any], ...]:
    """Project points with the compiled kernel (see the module doc).

    Args:
        tables: ``(rate_starts, rate_t0, rate_period, node_times, window_centre,
            window_coef, r0)``: the line-rate table, the Lagrange tables and ``R0``.
        k: Lagrange order.
        span: ``(line_lo, line_hi)``, the searchable lines.
        poly: EO window polynomials ``(n_win, k, 6)``.
        io: Interior ``[x0, y0, f]`` (mm).
        ccd: ``(x_mm, y_mm, angle_rad, pixel_pitch_mm)``.
        p: Ground points ``(m, 3)`` (m, body-fixed).
        line: Line guesses ``(m,)`` (NaN: middle of the span).
        rate: Offset slopes ``(m,)`` or ``None`` (NaN: a one-line secant).
        full: Also return the window starts, weights and the ``(m, 2, 15)`` partials.
        chord_tol: Chord iterations stop below this step (px).
        step_valid: A projection is valid when the final Newton step is below this.

    Returns:
        Arrays of several dtypes (``valid`` bool, ``start`` intp, the rest float64):
        ``(line, sample, valid, rate)`` and, with ``full``, ``start``, ``weights``,
        ``partials``, ``tau``; the meanings are those of
        :meth:`~planetref.camera.linescan.kernel.LineScanKernel.project` and
        :meth:`~planetref.camera.linescan.kernel.LineScanKernel.project_with_partials`.
    """
    fn = _compiled()
    m = len(p)
    rate_in = np.full(m, np.nan) if rate is None else np.ascontiguousarray(rate, np.float64)
    out_line = np.empty(m)
    out_samp = np.empty(m)
    out_valid = np.empty(m, np.bool_)
    out_rate = np.empty(m)
    if full:
        start = np.empty(m, np.intp)
        weights = np.empty((m, k))
        partials = np.empty((m, 2, 15))
        tau = np.empty(m)
    else:
        start = np.empty(0, np.intp)
        weights = np.empty((0, k))
        partials = np.empty((0, 2, 15))
        tau = np.empty(0)
    fn.project(
        *tables,
        k,
        float(span[0]),
        float(span[1]),
        np.ascontiguousarray(poly, np.float64),
        np.ascontiguousarray(io, np.float64),
        np.array([*ccd, math.sin(ccd[2]), math.cos(ccd[2])], np.float64),
        np.ascontiguousarray(p, np.float64),
        np.ascontiguousarray(line, np.float64),
        rate_in,
        full,
        chord_tol,
        step_valid,
        out_line,
        out_samp,
        out_valid,
        out_rate,
        start,
        weights,
        partials,
        tau,
    )
    if full:
        return out_line, out_samp, out_valid, out_rate, start, weights, partials, tau
    return out_line, out_samp, out_valid, out_rate


def fill_partials(imp: F64, weights: F64, placement: bool, dp: F64, dg: F64) -> None:
    """Write an adjustment's pattern partials from a projection's, compiled.

    The twin of the numpy code in
    :meth:`~planetref.adjust.models.linescan.LineScanParameterization.evaluate`:
    ``dp[:, :, 6 j + c] = imp[:, :, c] * weights[:, j]`` (node ``j`` of the window, EO
    column ``c``), then the interior ``x0, y0, f`` (and, with ``placement``, the CCD
    placement) columns; ``dg`` gets the ground columns.

    Args:
        imp: ``(m, 2, 15)`` partials of a :class:`~planetref.camera.linescan.kernel.
            Projection`.
        weights: Its Lagrange weights ``(m, k)``.
        placement: Whether ``dp`` has the three placement columns.
        dp: Output ``(m, 2, 6 k + 3 [+ 3])``.
        dg: Output ``(m, 2, 3)``.
    """
    _compiled().fill_partials(
        np.ascontiguousarray(imp), np.ascontiguousarray(weights), placement, dp, dg
    )
