"""The line-scan projection-and-partials kernel: ground -> (line, sample), written once.

Both :class:`~planetref.camera.linescan.model.LineScanCamera` (``ground_to_image``,
``image_partials``) and the adjustment's
:class:`~planetref.adjust.models.linescan.LineScanParameterization` call this module, so
a change to the line-scan model is made here only. The model is documented in
:mod:`planetref.camera.linescan.model`.

Evaluation at a trial line
--------------------------
At a trial image line ``l`` the exterior orientation is interpolated (Lagrange, in
time, from window polynomials of the node values: :class:`LagrangeWindows`), the
ground point ``P`` is rotated into the camera frame ``[U, V, W] = (R0 R)^T (P - S)``
(:func:`rotate_to_camera`), projected into the focal plane ``x = x0 - f U/W``,
``y = y0 - f V/W`` (mm) and mapped onto the CCD: ``sample`` along the array and
``offset``, the distance from the array in pixels (zero when line ``l`` images ``P``).
With ``full`` evaluation the kernel also returns, at the fixed line, the partials of
``(offset, sample)`` (rows in that order) w.r.t. (columns, :data:`RAW_COLUMNS`):
the interpolated EO ``X, Y, Z, phi, omega, kappa``; the interior ``x0, y0, f``; the
ground ``X, Y, Z``; the CCD placement ``x_mm, y_mm, angle_rad``; and the derivatives of
offset and sample along the line (``rate``, ``srate``, per pixel).

Projection
----------
The image line solves ``offset(l) = 0``. From a guess (the observed line, or the
previous solution) chord steps with a fixed slope (the previous rate, or a one-line
secant) run until the step is below :data:`CHORD_TOL`; then one full evaluation gives
the partials and the last Newton step is applied to first order (the offset is linear
in the line to ~1e-10 px over a pixel, so the result is exact to ~1e-12 px). Without a
guess, :meth:`LineScanKernel.search_lines` brackets the root on a grid over the node
span and refines it with safeguarded Newton steps (:mod:`planetref.geometry.roots`).

Partials of the projection follow from the implicit-function theorem:
``dline/dq = -(d offset/dq) / (d offset/dline)`` and
``dsample/dq = d sample/dq + (d sample/dline) dline/dq``; rows of every output partial
are ``(line, sample)``.

A CCD with lens distortion (simulation truths only, :mod:`~planetref.camera.linescan.lens`)
maps the ideal ``(x, y)`` to its detector position before the placement (exact within
:func:`~planetref.camera.linescan.lens.clip_radius_mm`): offset and sample are exact, the
partials ignore the distortion's Jacobian (relative error ~1e-3).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

import planetref.camera.linescan.compiled as compiled
from planetref.arrays import F64
from planetref.camera.linescan.lens import clip_radius_mm, detector_position
from planetref.geometry.lagrange import LagrangeWindows
from planetref.geometry.roots import bracket_first_sign_change, refine_bracketed
from planetref.geometry.rotations import rotate_to_camera

if TYPE_CHECKING:
    from planetref.camera.linescan.sensor import CcdGeometry, LineRateTable

__all__ = [
    "CHORD_TOL",
    "RAW_COLUMNS",
    "KernelState",
    "LineScanKernel",
    "Projection",
]


#: Chord iterations on the line stop when the step is below this (pixels).
CHORD_TOL = 1e-6
#: A projection is valid only when the last (first-order) Newton step is below this (px).
STEP_VALID = 1e-3
#: Column slices of the raw and implicit partials.
RAW_COLUMNS = {
    "eo": slice(0, 6),
    "position": slice(0, 3),
    "attitude": slice(3, 6),
    "interior": slice(6, 9),
    "ground": slice(9, 12),
    "ccd": slice(12, 15),
}
N_RAW = 15


@dataclass(frozen=True)
class KernelState:
    """The model evaluated at given lines (one CCD).

    Attributes:
        offset: Detector offset (pixels), ``(m,)``.
        sample: Sample (pixels).
        depth: Camera-frame ``W`` (< 0 in front of the camera).
        rate: ``d offset / d line`` (full evaluations only).
        srate: ``d sample / d line`` (full evaluations only).
        start: Lagrange window start of each point (full evaluations only).
        weights: Lagrange weights ``(m, k)`` (full evaluations only).
        raw: ``(m, 2, 15)`` ``d(offset, sample)/dq`` at the fixed line, columns
            :data:`RAW_COLUMNS` (full evaluations only).
        tau: Time (s) relative to the window's centre (full evaluations only).
    """

    offset: F64
    sample: F64
    depth: F64
    rate: F64 | None = None
    srate: F64 | None = None
    start: NDArray[np.intp] | None = None
    weights: F64 | None = None
    raw: F64 | None = None
    tau: F64 | None = None


@dataclass(frozen=True)
class Projection:
    """Projected points with the partials of ``(line, sample)``.

    Attributes:
        line: Line (pixels), ``(m,)``; meaningful where ``valid``.
        sample: Sample (pixels).
        valid: In front of the camera, converged and within the node span.
        rate: ``d offset / d line`` (a hint for the next projection).
        start: Lagrange window start (first node index) of each point.
        weights: Lagrange weights ``(m, k)``.
        partials: ``(m, 2, 15)`` ``d(line, sample)/dq``, columns :data:`RAW_COLUMNS`;
            the EO columns are w.r.t. the *interpolated* EO (times ``weights`` for a
            node's own parameters, see :meth:`LineScanKernel.node_partials`).
        tau: Time (s) of each point relative to its window's centre:
            ``weights[:, j] = sum_q windows.coef[start, j, q] tau^q``
            (:class:`~planetref.geometry.lagrange.LagrangeWindows`).
    """

    line: F64
    sample: F64
    valid: NDArray[np.bool_]
    rate: F64
    start: NDArray[np.intp]
    weights: F64
    partials: F64
    tau: F64


class LineScanKernel:
    """Projection of ground points for one camera's time model and frame.

    Holds what does not change when the camera is adjusted: the line -> time table,
    the node times (Lagrange window tables) and the frame rotation ``R0``. Node values,
    interior orientation and CCD placement are arguments.

    Args:
        line_rates: The camera's line -> time table.
        node_lines: Image lines of the orientation nodes, increasing.
        interpolation_order: Lagrange order ``k``.
        frame_rotation: ``R0``, ``(3, 3)``.
    """

    def __init__(
        self,
        line_rates: LineRateTable,
        node_lines: F64,
        interpolation_order: int,
        frame_rotation: F64,
    ) -> None:
        self.line_rates = line_rates
        node_lines = np.asarray(node_lines, np.float64)
        self.windows = LagrangeWindows(line_rates.time(node_lines), interpolation_order)
        self.k = self.windows.k
        spacing = np.diff(node_lines)
        #: Lines are searched (and projections valid) within one node spacing beyond
        #: the first and last node.
        self.line_lo = float(node_lines[0] - spacing[0])
        self.line_hi = float(node_lines[-1] + spacing[-1])
        self.r0 = np.ascontiguousarray(frame_rotation, dtype=np.float64)
        starts, t0, period = line_rates._arrays
        #: What the compiled kernel needs: line-rate rows, Lagrange tables, ``R0``.
        self._tables = tuple(
            np.ascontiguousarray(a, np.float64)
            for a in (
                starts,
                t0,
                period,
                self.windows.times,
                self.windows.centre,
                self.windows.coef,
                self.r0,
            )
        )

    def runs_compiled(self, use: bool | None, ccd: CcdGeometry) -> bool:
        """Whether a projection with ``use_compiled=use`` into ``ccd`` runs compiled."""
        return self._compiled(use, ccd)

    def _compiled(self, use: bool | None, ccd: CcdGeometry) -> bool:
        """Whether to run the compiled kernel (``None``: when numba is available).

        CCDs with lens distortion (simulation truths only) always run on numpy.
        """
        if any(ccd.distortion) or use is False:
            return False
        return compiled.available()

    def _run_compiled(
        self, poly: F64, io: F64, ccd: CcdGeometry, p: F64, line: F64, rate: F64 | None, full: bool
    ) -> tuple[NDArray[Any], ...]:  # mixed dtypes, see compiled.project_points
        return compiled.project_points(
            self._tables,
            self.k,
            (self.line_lo, self.line_hi),
            poly,
            io,
            (ccd.x_mm, ccd.y_mm, ccd.angle_rad, ccd.pixel_pitch_mm),
            p,
            line,
            rate,
            full=full,
            chord_tol=CHORD_TOL,
            step_valid=STEP_VALID,
        )

    # ------------------------------------------------------------------ evaluation
    def eo_poly(self, nodes: F64) -> F64:
        """Per Lagrange window, the EO as polynomials in time: ``(n_win, k, 6)``."""
        return self.windows.polynomials(np.asarray(nodes, np.float64))

    def exterior(self, poly: F64, line: F64) -> F64:
        """Interpolated EO ``(m, 6)`` (``X, Y, Z`` m, ``phi, omega, kappa`` rad) at lines."""
        start, tau = self.windows.window(self.line_rates.time(line))
        return self.windows.evaluate(poly, start, tau)[0]

    def state(
        self, poly: F64, io: F64, ccd: CcdGeometry, p: F64, line: F64, *, full: bool
    ) -> KernelState:
        """The collinearity at given lines (see the module doc).

        Args:
            poly: :meth:`eo_poly` of the node values.
            io: Interior ``[x0, y0, f]`` (mm).
            ccd: The CCD (placement and pitch are read from it).
            p: Ground points (m, body-fixed), ``(m, 3)``.
            line: Trial lines, ``(m,)``.
            full: Also compute every partial.
        """
        t = self.line_rates.time(line)
        win = self.windows
        start, tau = win.window(t)
        eo, deo_dt = win.evaluate(poly, start, tau, derivative=full)
        cf = rotate_to_camera(
            eo[:, 3], eo[:, 4], eo[:, 5], p - eo[:, :3], r0=self.r0, derivatives=full
        )
        x0, y0, f = io
        with np.errstate(divide="ignore", invalid="ignore"):
            inv_w = 1.0 / cf.w
        xn, yn = cf.u * inv_w, cf.v * inv_w
        sa, ca, pitch = math.sin(ccd.angle_rad), math.cos(ccd.angle_rad), ccd.pixel_pitch_mm
        if any(ccd.distortion):
            r_clip = clip_radius_mm(
                ccd.x_mm, ccd.y_mm, ccd.angle_rad, ccd.n_samples * ccd.pixel_pitch_mm
            )
            xd, yd = detector_position(x0 - f * xn, y0 - f * yn, ccd.distortion, r_clip)
            dx, dy = xd - ccd.x_mm, yd - ccd.y_mm
        else:
            dx = x0 - f * xn - ccd.x_mm
            dy = y0 - f * yn - ccd.y_mm
        samp = (dx * sa + dy * ca) / pitch
        off = (dx * ca - dy * sa) / pitch
        if not full or cf.jacobian is None or deo_dt is None:
            return KernelState(off, samp, cf.w)
        jac = cf.jacobian  # (m, 6, 3): d(u, v, w)/d(P; phi, omega, kappa)
        # d(x, y)/dq = -f/W (d(U, V)/dq - (U, V)/W dW/dq); the CCD's rotation and pitch
        # are folded into two per-point factors.
        fw = -f * inv_w / pitch
        c_ca, c_sa = (fw * ca)[:, None], (fw * sa)[:, None]
        jz = jac[:, :, 2]
        dxq = jac[:, :, 0] - xn[:, None] * jz  # (m, 6), times -f/W: d x / dq
        dyq = jac[:, :, 1] - yn[:, None] * jz
        doff = dxq * c_ca - dyq * c_sa
        dsmp = dxq * c_sa + dyq * c_ca
        raw = np.empty((len(line), 2, N_RAW))
        raw[:, 0, 9:12] = doff[:, :3]
        raw[:, 1, 9:12] = dsmp[:, :3]
        np.negative(doff[:, :3], out=raw[:, 0, :3])  # d/dS = -d/dP
        np.negative(dsmp[:, :3], out=raw[:, 1, :3])
        raw[:, 0, 3:6] = doff[:, 3:]
        raw[:, 1, 3:6] = dsmp[:, 3:]
        raw[:, 0, 6], raw[:, 1, 6] = ca / pitch, sa / pitch
        raw[:, 0, 7], raw[:, 1, 7] = -sa / pitch, ca / pitch
        raw[:, 0, 8] = (-xn * ca + yn * sa) / pitch
        raw[:, 1, 8] = (-xn * sa - yn * ca) / pitch
        raw[:, 0, 12], raw[:, 1, 12] = -ca / pitch, -sa / pitch
        raw[:, 0, 13], raw[:, 1, 13] = sa / pitch, -ca / pitch
        raw[:, 0, 14] = -samp
        raw[:, 1, 14] = off
        _, w, _ = win.basis(start, tau)
        period = self.line_rates.period(line)
        rate = np.einsum("mp,mp->m", raw[:, 0, :6], deo_dt) * period
        srate = np.einsum("mp,mp->m", raw[:, 1, :6], deo_dt) * period
        return KernelState(off, samp, cf.w, rate, srate, start, w, raw, tau)

    def offset(self, poly: F64, io: F64, ccd: CcdGeometry, p: F64, line: F64) -> F64:
        """Detector offset (pixels) of points at given lines (no partials)."""
        return self.state(poly, io, ccd, p, line, full=False).offset

    # ------------------------------------------------------------------ line search
    def converge(
        self, poly: F64, io: F64, ccd: CcdGeometry, p: F64, line: F64, rate: F64 | None
    ) -> tuple[F64, F64]:
        """Chord iterations on the detector offset from guesses.

        Args:
            poly: :meth:`eo_poly`.
            io: Interior ``[x0, y0, f]``.
            ccd: The CCD.
            p: Ground points, ``(m, 3)``.
            line: Starting lines (NaN: the middle of the node span).
            rate: Fixed slopes ``d offset / d line`` (NaN or ``None``: a one-line secant).

        Returns:
            ``(line, rate)``: the lines after the last chord step (clipped to the node
            span) and the slopes used.
        """
        line = np.clip(
            np.where(np.isfinite(line), line, 0.5 * (self.line_lo + self.line_hi)),
            self.line_lo,
            self.line_hi,
        )
        off = self.offset(poly, io, ccd, p, line)
        rate = np.full(len(line), np.nan) if rate is None else np.array(rate, np.float64)
        need = ~(np.isfinite(rate) & (rate != 0))
        if np.any(need):
            ia = np.flatnonzero(need)
            rate[ia] = self.offset(poly, io, ccd, p[ia], line[ia] + 1.0) - off[ia]
        with np.errstate(divide="ignore", invalid="ignore"):
            step = -off / rate
        active = np.isfinite(step) & (np.abs(step) > CHORD_TOL)
        for _ in range(40):
            ia = np.flatnonzero(active)
            if ia.size == 0:
                break
            line[ia] = np.clip(line[ia] + step[ia], self.line_lo, self.line_hi)
            off_a = self.offset(poly, io, ccd, p[ia], line[ia])
            with np.errstate(divide="ignore", invalid="ignore"):
                step[ia] = -off_a / rate[ia]
            active[ia] = np.isfinite(step[ia]) & (np.abs(step[ia]) > CHORD_TOL)
        return line, rate

    def search_lines(
        self, poly: F64, io: F64, ccd: CcdGeometry, p: F64, *, n_grid: int = 33
    ) -> F64:
        """Lines of points without a guess: grid bracket over the node span, then Newton.

        The offset changes sign once as a point passes under the CCD; the grid spans
        the node lines plus one spacing at each end. Roots are refined to 1e-8 line
        and accepted where ``|offset| <= 1e-6`` px.

        Returns:
            Lines ``(m,)``; NaN where no root lies within the span.
        """

        def residual(x: F64, rows: NDArray[np.intp]) -> F64:
            return self.offset(poly, io, ccd, p[rows], x)

        def with_slope(x: F64, rows: NDArray[np.intp]) -> tuple[F64, F64]:
            st = self.state(poly, io, ccd, p[rows], x, full=True)
            return st.offset, np.asarray(st.rate)

        grid = np.linspace(self.line_lo, self.line_hi, n_grid)
        bracket = bracket_first_sign_change(residual, grid, len(p))
        return refine_bracketed(bracket, residual_with_slope=with_slope, xtol=1e-8, ftol=1e-6)

    # ------------------------------------------------------------------ projection
    def _valid(self, line: F64, samp: F64, depth: F64, step: F64) -> NDArray[np.bool_]:
        return (
            np.isfinite(line)
            & np.isfinite(samp)
            & (depth < 0)
            & (np.abs(step) < STEP_VALID)
            & (line >= self.line_lo)
            & (line <= self.line_hi)
        )

    def project(
        self,
        poly: F64,
        io: F64,
        ccd: CcdGeometry,
        p: F64,
        line: F64,
        rate: F64 | None,
        *,
        use_compiled: bool | None = None,
    ) -> tuple[F64, F64, NDArray[np.bool_], F64]:
        """Lines, samples, validity and rates from guesses, without partials.

        ``use_compiled``: run the compiled twin (:mod:`~planetref.camera.linescan.
        compiled`); ``None`` (default) when numba is available, ``False`` this numpy
        reference.
        """
        if self._compiled(use_compiled, ccd):
            ln, smp, ok, rt = self._run_compiled(poly, io, ccd, p, line, rate, False)
            return ln, smp, ok, rt
        line, rate = self.converge(poly, io, ccd, p, line, rate)
        st = self.state(poly, io, ccd, p, line, full=False)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = -st.offset / rate
        # The chord rate is exact to ~1e-4 and the step below 1e-6 px: the line is exact
        # to ~1e-10 px; the sample moves by (dsample/dline) * step, far below 1e-9 px.
        line_out = line + step
        return line_out, st.sample, self._valid(line_out, st.sample, st.depth, step), rate

    def project_with_partials(
        self,
        poly: F64,
        io: F64,
        ccd: CcdGeometry,
        p: F64,
        line: F64,
        rate: F64 | None,
        *,
        use_compiled: bool | None = None,
    ) -> Projection:
        """Project from guesses and return every partial (see the module doc).

        ``use_compiled``: as in :meth:`project`.
        """
        if self._compiled(use_compiled, ccd):
            return Projection(*self._run_compiled(poly, io, ccd, p, line, rate, True))
        line, _ = self.converge(poly, io, ccd, p, line, rate)
        st = self.state(poly, io, ccd, p, line, full=True)
        raw, rate_, srate = st.raw, np.asarray(st.rate), np.asarray(st.srate)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = -st.offset / rate_
            neg_inv_rate = -1.0 / rate_
        # The final Newton step is applied to first order (its square is ~1e-12 px).
        line_out = line + step
        samp_out = st.sample + srate * step
        imp = np.empty((len(line), 2, N_RAW))
        np.multiply(raw[:, 0], neg_inv_rate[:, None], out=imp[:, 0])  # type: ignore[index]
        np.multiply(imp[:, 0], srate[:, None], out=imp[:, 1])
        imp[:, 1] += raw[:, 1]  # type: ignore[index]
        return Projection(
            line_out,
            samp_out,
            self._valid(line_out, samp_out, st.depth, step),
            rate_,
            np.asarray(st.start),
            np.asarray(st.weights),
            imp,
            np.asarray(st.tau),
        )

    def node_partials(self, proj: Projection, out: F64 | None = None) -> F64:
        """``d(line, sample)/d(node EO)`` of each point's window nodes, ``(m, 2, k, 6)``.

        Args:
            proj: A projection with partials.
            out: Optional ``(m, 2, k, 6)`` array to write into.
        """
        m = len(proj.line)
        if out is None:
            out = np.empty((m, 2, self.k, 6))
        np.multiply(proj.partials[:, :, None, :6], proj.weights[:, None, :, None], out=out)
        return out
