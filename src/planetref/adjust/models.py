"""Camera parameterisations: how the unknowns of one camera map to its projections.

The solver only sees the :class:`AdjustableCamera` protocol: a vector of local
parameters (with names, units, initial values, modes and a-priori sigmas), the
projection of ground points into one CCD with the partial derivatives of ``(line,
sample)`` with respect to the parameters and to the ground point, and the adjusted camera
built from a parameter vector. New camera types slot in by implementing the protocol and
registering a factory with :func:`register_parameterization`.

Sparse Jacobian layout
----------------------
Each observation depends on a few parameters only (the ``k`` orientation nodes of its
Lagrange window plus the interior orientation, or the handful of correction terms of a
CSM image). A parameterisation lists its *patterns*, ``pattern_columns`` of shape
``(n_patterns, q)``: the local parameter indices (``-1`` = padding) of a set of
observations that share their dependencies; :meth:`AdjustableCamera.evaluate` returns
each observation's pattern and its ``(2, q)`` block of partials (rows ``line, sample``).
The solver accumulates normal equations per pattern with dense BLAS products.

Implementations
---------------
* :class:`LineScanParameterization` - the native
  :class:`~planetref.camera.linescan.LineScanCamera`: node EOPs ``X, Y, Z`` (m) and
  ``phi, omega, kappa`` (rad), interior ``x0, y0, f`` (mm) per strip or per CCD. Its
  projection and exact analytic partials are a fused, chunked re-implementation of
  ``LineScanCamera.image_partials`` (the same model, tested against it to 1e-9) that
  avoids re-solving the image line from scratch: the previous solution's lines seed a
  chord/Newton iteration whose last step is applied linearly, so one evaluation costs
  about one pass over the model instead of five.
* :class:`CsmParameterization` - :class:`~planetref.camera.csm.CsmLineScanCamera`:
  usgscsm's per-image corrections (position offset/rate, pointing offset/rate/
  acceleration, focal length) with vectorised central finite differences of
  ``ground_to_image``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from planetref.adjust.config import AdjustConfig, CsmParameters, LineScanParameters, Mode
from planetref.camera.linescan import InteriorOrientation, LineScanCamera
from planetref.errors import AdjustmentError, InputError

log = logging.getLogger("planetref.adjust")

__all__ = [
    "AdjustableCamera",
    "CoverageIssue",
    "CsmParameterization",
    "Evaluation",
    "LineScanParameterization",
    "parameterize",
    "register_parameterization",
]

F64 = NDArray[np.float64]
MODE_CODE = {"free": 0, "weighted": 1, "fixed": 2}
#: The image line is iterated with cheap chord steps until the step is below this
#: (pixels); the model is then evaluated once with partials and the last Newton step is
#: applied to first order (exact to ~1e-12 px: the offset is linear in the line to ~1e-10
#: px over a whole pixel).
_CHORD_TOL = 1e-6


@dataclass(frozen=True, eq=False)
class Evaluation:
    """Projections of ground points into one CCD, with partials.

    Attributes:
        line: Projected line (pixels), ``(m,)``; NaN where invalid.
        sample: Projected sample, ``(m,)``.
        valid: False where the point could not be projected.
        pattern: Local pattern index of each observation, ``(m,)``.
        d_params: ``d(line, sample)/d(params of the pattern)``, ``(m, 2, q)``.
        d_ground: ``d(line, sample)/d(X, Y, Z)`` per metre, ``(m, 2, 3)``.
        line_rate: Optional per-point hint for the next evaluation (for line scanners
            ``d offset / d line``), handed back as ``rate_guess``; ``None`` if unused.
    """

    line: F64
    sample: F64
    valid: NDArray[np.bool_]
    pattern: NDArray[np.intp]
    d_params: F64
    d_ground: F64
    line_rate: F64 | None = None


@dataclass(frozen=True)
class CoverageIssue:
    """A group of parameters that too few observations determine.

    Attributes:
        label: Human-readable name (e.g. ``"node 3"``).
        indices: Local parameter indices of the group.
        count: Observations found near the group.
        required: Observations required.
    """

    label: str
    indices: tuple[int, ...]
    count: int
    required: int


@runtime_checkable
class AdjustableCamera(Protocol):
    """One camera's unknowns and projections (see the module doc).

    Attributes:
        camera_id: The camera's id in the network.
        camera: The initial camera.
        names: Local parameter names, ``(n,)``.
        units: Unit of each parameter (``"m"``, ``"rad"``, ``"mm"``...).
        x0: Initial (a priori) parameter values, ``(n,)``.
        sigma: A-priori sigma per parameter (inf: free; used when weighted).
        mode: Per parameter ``0`` free, ``1`` weighted, ``2`` fixed.
        pattern_columns: ``(n_patterns, q)`` local parameter indices, ``-1`` padding.
    """

    camera_id: str
    camera: Any
    names: tuple[str, ...]
    units: tuple[str, ...]
    x0: F64
    sigma: F64
    mode: NDArray[np.int8]
    pattern_columns: NDArray[np.intp]

    def evaluate(
        self,
        x: F64,
        xyz: F64,
        ccd: int,
        line_guess: F64,
        rate_guess: F64 | None = None,
        partials: bool = True,
    ) -> Evaluation:
        """Project points into CCD ``ccd`` with parameters ``x``, with partials.

        ``line_guess`` and ``rate_guess`` are the previous evaluation's ``line`` and
        ``line_rate`` (or the observed lines and ``None``); they may be ignored. With
        ``partials=False`` only ``line``, ``sample`` and ``valid`` are needed.
        """
        ...

    def build(self, x: F64) -> Any:
        """The camera with parameters ``x``."""
        ...

    def coverage(self, ccd: NDArray[np.intp], line: F64) -> list[CoverageIssue]:
        """Parameter groups that the observations (CCD index, line) leave weak."""
        ...

    def weaken(self, issues: list[CoverageIssue]) -> list[str]:
        """Give weak groups an a-priori weight; returns warning messages."""
        ...


_FACTORIES: list[tuple[type, Callable[..., AdjustableCamera]]] = []


def register_parameterization(
    camera_type: type, factory: Callable[[str, Any, AdjustConfig, bool], AdjustableCamera]
) -> None:
    """Register how cameras of ``camera_type`` are adjusted.

    Args:
        camera_type: The camera class (instances are matched with ``isinstance``).
        factory: ``factory(camera_id, camera, config, fixed) -> AdjustableCamera``.
    """
    _FACTORIES.insert(0, (camera_type, factory))


def parameterize(camera_id: str, camera: Any, config: AdjustConfig) -> AdjustableCamera:
    """The parameterisation of a camera under a configuration.

    Args:
        camera_id: Id of the camera in the network.
        camera: A native line-scan or CSM line-scan camera (or a registered type).
        config: The adjustment configuration.

    Raises:
        InputError: For cameras that cannot be adjusted (e.g. RPCs).
    """
    fixed = camera_id in config.fixed_cameras
    if isinstance(camera, LineScanCamera):
        return LineScanParameterization(camera_id, camera, config.linescan, fixed=fixed)
    for cls, factory in _FACTORIES:
        if isinstance(camera, cls):
            return factory(camera_id, camera, config, fixed)
    try:
        from planetref.camera.csm import CsmLineScanCamera
    except ImportError:  # pragma: no cover - the CSM module ships with planetref
        CsmLineScanCamera = None  # type: ignore[assignment,misc]
    if CsmLineScanCamera is not None and isinstance(camera, CsmLineScanCamera):
        return CsmParameterization(camera_id, camera, config.csm, fixed=fixed)
    raise InputError(
        f"camera {camera_id!r} ({type(camera).__name__}) cannot be adjusted "
        f"rigorously; use a native line-scan or CSM line-scan ISD camera "
        f"(RPCs are refitted from an adjusted rigorous model)"
    )


def _block(mode: Mode, sigma: float | None, n: int, fixed: bool) -> tuple[NDArray[np.int8], F64]:
    code = MODE_CODE["fixed" if fixed else mode]
    sig = np.full(n, np.inf if sigma is None or code != 1 else float(sigma))
    return np.full(n, code, np.int8), sig


# --------------------------------------------------------------------- native
_EO_NAMES = ("X", "Y", "Z", "phi", "omega", "kappa")
_EO_UNITS = ("m", "m", "m", "rad", "rad", "rad")
_IO_NAMES = ("x0", "y0", "f")


@dataclass(frozen=True)
class _State:
    """The model evaluated at given lines (one CCD), with everything partials need."""

    off: F64
    samp: F64
    rate: F64  # d offset / d line
    srate: F64  # d sample / d line
    w: F64  # (m, k) Lagrange weights
    start: NDArray[np.intp]
    raw: F64  # (m, 2, 12) d(offset, sample)/d(EO, interior, ground) at fixed line
    depth: F64  # W (< 0 in front of the camera)


_EMPTY_STATE = _State(
    *(np.empty(0) for _ in range(5)), np.empty(0, np.intp), np.empty(0), np.empty(0)
)


class LineScanParameterization:
    """Unknowns of a native line-scan strip: node EOPs and interior orientation.

    Local parameter vector: ``[nodes (N*6, node-major: X, Y, Z, phi, omega, kappa),
    interior (G*3: x0, y0, f)]`` with ``G = 1`` (interior scope ``strip``) or the number
    of CCDs (scope ``ccd``).

    Args:
        camera_id: The strip's id.
        camera: The initial camera.
        config: Modes and sigmas of the blocks.
        fixed: Hold every parameter fixed.
    """

    def __init__(
        self,
        camera_id: str,
        camera: LineScanCamera,
        config: LineScanParameters,
        *,
        fixed: bool = False,
    ) -> None:
        self.camera_id = camera_id
        self.camera = camera
        self.config = config
        n = camera.n_nodes
        self._n_nodes = n
        self._k = min(camera.interpolation_order, n)
        self._times = np.asarray(camera.line_rates.time(camera.node_lines), np.float64)
        n_ccd = len(camera.ccds)
        self._groups = n_ccd if config.interior.scope == "ccd" else 1
        io = camera.interior.as_array()
        self.x0 = np.concatenate([camera.nodes.ravel(), np.tile(io, self._groups)])
        names, units = [], []
        for i in range(n):
            names += [f"node{i}.{p}" for p in _EO_NAMES]
            units += list(_EO_UNITS)
        for g in range(self._groups):
            tag = "interior" if self._groups == 1 else f"interior[{camera.ccds[g].name}]"
            names += [f"{tag}.{p}" for p in _IO_NAMES]
            units += ["mm"] * 3
        self.names = tuple(names)
        self.units = tuple(units)
        mode = np.empty(len(self.x0), np.int8)
        sigma = np.empty(len(self.x0))
        pos_m, pos_s = _block(config.position.mode, config.position.sigma_m, n, fixed)
        att_m, att_s = _block(config.attitude.mode, config.attitude.sigma_rad, n, fixed)
        for j in range(3):
            mode[j : 6 * n : 6], sigma[j : 6 * n : 6] = pos_m, pos_s
            mode[3 + j : 6 * n : 6], sigma[3 + j : 6 * n : 6] = att_m, att_s
        ib = config.interior
        for g in range(self._groups):
            base = 6 * n + 3 * g
            for j, s in enumerate(
                (ib.sigma_principal_point_mm, ib.sigma_principal_point_mm, ib.sigma_focal_length_mm)
            ):
                m_, s_ = _block(ib.mode, s, 1, fixed)
                mode[base + j], sigma[base + j] = m_[0], s_[0]
        self.mode = mode
        self.sigma = sigma
        #: Linear pseudo-observations ``A (x - x0) = 0`` with weights ``w`` (or None).
        self.constraints: tuple[F64, F64] | None = None
        n_win = n - self._k + 1
        cols = np.full((n_win * self._groups, 6 * self._k + 3), -1, np.intp)
        for s in range(n_win):
            for g in range(self._groups):
                cols[s * self._groups + g, : 6 * self._k] = np.arange(6 * s, 6 * (s + self._k))
                cols[s * self._groups + g, 6 * self._k :] = 6 * n + 3 * g + np.arange(3)
        self.pattern_columns = cols
        # Within one window the Lagrange basis polynomials are fixed: tabulate their
        # coefficients in tau = t - (window centre), lowest power first, so that weights
        # and the interpolated EO become Horner evaluations (no per-point products).
        idx = np.arange(n_win)[:, None] + np.arange(self._k)[None, :]
        tn = self._times[idx]
        self._tc = tn.mean(axis=1)
        coef = np.zeros((n_win, self._k, self._k))
        for s in range(n_win):
            for j in range(self._k):
                others = np.delete(tn[s], j) - self._tc[s]
                den = np.prod(tn[s, j] - np.delete(tn[s], j))
                coef[s, j] = np.polynomial.polynomial.polyfromroots(others) / den
        self._coef = coef  # (n_win, k basis, k powers)
        spacing = np.diff(camera.node_lines)
        self._line_lo = float(camera.node_lines[0] - spacing[0])
        self._line_hi = float(camera.node_lines[-1] + spacing[-1])
        r0 = camera.frame_rotation
        self._r0 = np.ascontiguousarray(r0)

    # ----------------------------------------------------------------- pieces
    def _split(self, x: F64, ccd: int) -> tuple[F64, F64]:
        nodes = x[: 6 * self._n_nodes].reshape(self._n_nodes, 6)
        g = ccd if self._groups > 1 else 0
        io = x[6 * self._n_nodes + 3 * g : 6 * self._n_nodes + 3 * g + 3]
        return nodes, io

    def _window(self, t: F64) -> tuple[NDArray[np.intp], F64]:
        """Window start and ``tau = t - centre`` of times ``t`` (linescan's windows)."""
        k = self._k
        i = np.searchsorted(self._times, t, side="right") - 1
        start = np.clip(i - k // 2 + 1, 0, self._n_nodes - k)
        return start, t - self._tc[start]

    def _weights(self, t: F64) -> tuple[NDArray[np.intp], F64]:
        """Window start and Lagrange weights ``(m, k)`` of times ``t``."""
        start, tau = self._window(t)
        c = self._coef[start]  # (m, k, powers)
        w = c[:, :, -1].copy()
        for p in range(self._k - 2, -1, -1):
            w *= tau[:, None]
            w += c[:, :, p]
        return start, w

    def _eo_poly(self, nodes: F64) -> F64:
        """Per window, the EO as a polynomial in tau: ``(n_win, powers, 6)``."""
        idx = np.arange(len(self._coef))[:, None] + np.arange(self._k)[None, :]
        return np.einsum("sjp,sjq->spq", self._coef, nodes[idx])

    def _offset(self, poly: F64, io: F64, ccd: int, p: F64, line: F64) -> F64:
        """Detector offset (pixels) of points at given lines (no partials)."""
        return self._evaluate_at(poly, io, ccd, p, line, full=False)[0]

    def _offset_sample(
        self, poly: F64, io: F64, ccd: int, p: F64, line: F64
    ) -> tuple[F64, F64, F64]:
        """Detector offset, sample and depth ``W`` at given lines (no partials)."""
        _, st = self._evaluate_at(poly, io, ccd, p, line, full=False)
        return st.off, st.samp, st.depth

    def _state(self, poly: F64, io: F64, ccd: int, p: F64, line: F64) -> _State:
        """Offset, sample and every partial at given lines."""
        return self._evaluate_at(poly, io, ccd, p, line, full=True)[1]

    def _evaluate_at(
        self, poly: F64, io: F64, ccd: int, p: F64, line: F64, *, full: bool
    ) -> tuple[F64, _State]:
        """The collinearity at given lines; with ``full`` also every partial."""
        cam = self.camera
        c = cam.ccds[ccd]
        t = cam.line_rates.time(line)
        start, tau = self._window(t)
        pc = poly[start]  # (m, powers, 6)
        tau6 = tau[:, None]
        eo = pc[:, -1].copy()
        for q in range(self._k - 2, -1, -1):
            eo *= tau6
            eo += pc[:, q]
        d = (p - eo[:, :3]) @ self._r0  # R0^T (P - S), row-wise
        phi, omega, kappa = eo[:, 3], eo[:, 4], eo[:, 5]
        cp, sp = np.cos(phi), np.sin(phi)
        co, so = np.cos(omega), np.sin(omega)
        ck, sk = np.cos(kappa), np.sin(kappa)
        d0, d1, d2 = d[:, 0], d[:, 1], d[:, 2]
        a0 = cp * d0 + sp * d2
        a2 = -sp * d0 + cp * d2
        b1 = co * d1 + so * a2
        b2 = -so * d1 + co * a2
        u = ck * a0 + sk * b1
        v = -sk * a0 + ck * b1
        wz = b2
        x0, y0, f = io
        with np.errstate(divide="ignore", invalid="ignore"):
            inv_w = 1.0 / wz
        xn, yn = u * inv_w, v * inv_w
        x = x0 - f * xn
        y = y0 - f * yn
        sa, ca, pitch = math.sin(c.angle_rad), math.cos(c.angle_rad), c.pixel_pitch_mm
        dx, dy = x - c.x_mm, y - c.y_mm
        samp = (dx * sa + dy * ca) / pitch
        off = (dx * ca - dy * sa) / pitch
        if not full:
            return off, replace(_EMPTY_STATE, off=off, samp=samp, depth=wz)
        # d(u, v, w) for the 3 angles and the 3 ground coordinates (positions: negated).
        duvw = np.empty((len(line), 6, 3))
        # phi: d a / d phi = (a2, 0, -a0)
        bp1, bp2 = so * (-a0), co * (-a0)
        duvw[:, 3, 0] = ck * a2 + sk * bp1
        duvw[:, 3, 1] = -sk * a2 + ck * bp1
        duvw[:, 3, 2] = bp2
        # omega: d b / d omega = (0, b2, -b1)
        duvw[:, 4, 0] = sk * b2
        duvw[:, 4, 1] = ck * b2
        duvw[:, 4, 2] = -b1
        # kappa
        duvw[:, 5, 0] = v
        duvw[:, 5, 1] = -u
        duvw[:, 5, 2] = 0.0
        r0 = self._r0
        for i in range(3):
            e0, e1, e2 = r0[i, 0], r0[i, 1], r0[i, 2]
            ga0 = cp * e0 + sp * e2
            ga2 = -sp * e0 + cp * e2
            gb1 = co * e1 + so * ga2
            duvw[:, i, 0] = ck * ga0 + sk * gb1
            duvw[:, i, 1] = -sk * ga0 + ck * gb1
            duvw[:, i, 2] = -so * e1 + co * ga2
        fw = -f * inv_w
        dxq = fw[:, None] * (duvw[:, :, 0] - xn[:, None] * duvw[:, :, 2])  # (m, 6)
        dyq = fw[:, None] * (duvw[:, :, 1] - yn[:, None] * duvw[:, :, 2])
        doff = (dxq * ca - dyq * sa) / pitch
        dsmp = (dxq * sa + dyq * ca) / pitch
        # raw[:, r, :] = d(offset, sample)/dq at fixed line for q = node position (3),
        # node angles (3), interior x0, y0, f (3), ground X, Y, Z (3). Rows 0..2 of
        # doff/dsmp hold d/dP (ground); d/dS (node position) is their negative.
        raw = np.empty((len(line), 2, 12))
        raw[:, 0, 9:] = doff[:, :3]
        raw[:, 1, 9:] = dsmp[:, :3]
        raw[:, 0, :3] = -doff[:, :3]
        raw[:, 1, :3] = -dsmp[:, :3]
        raw[:, 0, 3:6] = doff[:, 3:]
        raw[:, 1, 3:6] = dsmp[:, 3:]
        raw[:, 0, 6], raw[:, 1, 6] = ca / pitch, sa / pitch
        raw[:, 0, 7], raw[:, 1, 7] = -sa / pitch, ca / pitch
        raw[:, 0, 8] = (-xn * ca + yn * sa) / pitch
        raw[:, 1, 8] = (-xn * sa - yn * ca) / pitch
        deo_dt = (self._k - 1) * pc[:, -1]
        for q in range(self._k - 2, 0, -1):
            deo_dt = deo_dt * tau6 + q * pc[:, q]
        _, w = self._weights(t)
        period = cam.line_rates.period(line)
        rate = np.einsum("mp,mp->m", raw[:, 0, :6], deo_dt) * period
        srate = np.einsum("mp,mp->m", raw[:, 1, :6], deo_dt) * period
        return off, _State(off, samp, rate, srate, w, start, raw, wz)

    def _g(self, ccd: int) -> int:
        return ccd if self._groups > 1 else 0

    def _project(
        self, poly: F64, io: F64, ccd: int, p: F64, line: F64, rate: F64 | None
    ) -> tuple[F64, F64, NDArray[np.bool_], F64]:
        """Lines, samples, validity and rates without partials (cheap evaluations)."""
        line, rate, off = self._converge(poly, io, ccd, p, line, rate)
        off, samp, depth = self._offset_sample(poly, io, ccd, p, line)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = -off / rate
        # The chord rate is exact to ~1e-4 and the step below 1e-6 px: the line is exact
        # to ~1e-10 px; the sample moves by (dsample/dline) * step, far below 1e-9 px.
        line_out = line + step
        valid = (
            np.isfinite(line_out)
            & np.isfinite(samp)
            & (depth < 0)
            & (np.abs(step) < 1e-3)
            & (line_out >= self._line_lo)
            & (line_out <= self._line_hi)
        )
        return line_out, samp, valid, rate

    def _converge(
        self, poly: F64, io: F64, ccd: int, p: F64, line: F64, rate: F64 | None
    ) -> tuple[F64, F64, F64]:
        """Chord iterations on the detector offset; returns ``(line, rate, offset)``."""
        line = np.clip(
            np.where(np.isfinite(line), line, 0.5 * (self._line_lo + self._line_hi)),
            self._line_lo,
            self._line_hi,
        )
        off = self._offset(poly, io, ccd, p, line)
        rate = np.full(len(line), np.nan) if rate is None else np.array(rate, np.float64)
        need = ~(np.isfinite(rate) & (rate != 0))
        if np.any(need):
            ia = np.flatnonzero(need)
            rate[ia] = self._offset(poly, io, ccd, p[ia], line[ia] + 1.0) - off[ia]
        with np.errstate(divide="ignore", invalid="ignore"):
            step = -off / rate
        active = np.isfinite(step) & (np.abs(step) > _CHORD_TOL)
        for _ in range(40):
            ia = np.flatnonzero(active)
            if ia.size == 0:
                break
            line[ia] = np.clip(line[ia] + step[ia], self._line_lo, self._line_hi)
            off_a = self._offset(poly, io, ccd, p[ia], line[ia])
            off[ia] = off_a
            with np.errstate(divide="ignore", invalid="ignore"):
                step[ia] = -off_a / rate[ia]
            active[ia] = np.isfinite(step[ia]) & (np.abs(step[ia]) > _CHORD_TOL)
        return line, rate, off

    def _chunk(
        self, poly: F64, io: F64, ccd: int, p: F64, line: F64, rate: F64 | None
    ) -> tuple[F64, F64, NDArray[np.bool_], NDArray[np.intp], F64, F64, F64]:
        # Cheap evaluations (offset only) first: chord steps with the rate of the previous
        # evaluation, or a one-line secant (the offset is linear in the line to ~1e-10 px
        # over a pixel), then one full evaluation with partials at the converged line.
        line, _, _ = self._converge(poly, io, ccd, p, line, rate)
        st = self._state(poly, io, ccd, p, line)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = -st.off / st.rate
        # The final Newton step is applied to first order (its square is ~1e-12 px).
        line_out = line + step
        samp_out = st.samp + st.srate * step
        valid = (
            np.isfinite(line_out)
            & np.isfinite(samp_out)
            & (st.depth < 0)
            & (np.abs(step) < 1e-3)
            & (line_out >= self._line_lo)
            & (line_out <= self._line_hi)
        )
        k = self._k
        m = len(line)
        # Implicit function theorem: dline/dq = -(d offset/dq) / (d offset/dline) and
        # dsample/dq = d sample/dq + (d sample/dline) dline/dq.
        with np.errstate(divide="ignore", invalid="ignore"):
            neg_inv_rate = -1.0 / st.rate
        imp = np.empty((m, 2, 12))
        np.multiply(st.raw[:, 0], neg_inv_rate[:, None], out=imp[:, 0])
        np.multiply(imp[:, 0], st.srate[:, None], out=imp[:, 1])
        imp[:, 1] += st.raw[:, 1]
        d_params = np.empty((m, 2, 6 * k + 3))
        np.multiply(
            imp[:, :, None, :6],
            st.w[:, None, :, None],
            out=d_params[:, :, : 6 * k].reshape(m, 2, k, 6),
        )
        d_params[:, :, 6 * k :] = imp[:, :, 6:9]
        d_ground = imp[:, :, 9:]
        pattern = st.start * self._groups + self._g(ccd)
        return line_out, samp_out, valid, pattern, d_params, d_ground, st.rate

    # ----------------------------------------------------------------- protocol
    def evaluate(
        self,
        x: F64,
        xyz: F64,
        ccd: int,
        line_guess: F64,
        rate_guess: F64 | None = None,
        partials: bool = True,
    ) -> Evaluation:
        """Project ground points into a CCD with the partials of ``(line, sample)``.

        Lines, samples and partials are exact to ~1e-9 (pixels, relative) whatever
        the guesses; good guesses only make the evaluation cheaper.

        Args:
            x: Local parameter vector.
            xyz: Ground points (metres, body-fixed), ``(m, 3)``.
            ccd: CCD index.
            line_guess: Starting lines (e.g. the observed or previously projected lines).
            rate_guess: ``d offset / d line`` of the previous evaluation
                (:attr:`Evaluation.line_rate`), or ``None``.
            partials: ``False`` projects only (``d_params`` and ``d_ground`` empty).

        Returns:
            :class:`Evaluation`; invalid rows have NaN coordinates and partials.
        """
        nodes, io = self._split(np.asarray(x, np.float64), ccd)
        p = np.asarray(xyz, np.float64)
        if not partials:
            line, samp, valid, rate = self._project(
                self._eo_poly(nodes), io, ccd, p, np.array(line_guess, np.float64), rate_guess
            )
            bad = ~valid
            line[bad] = samp[bad] = rate[bad] = np.nan
            m = len(line)
            return Evaluation(
                line,
                samp,
                valid,
                np.zeros(m, np.intp),
                np.empty((m, 2, 0)),
                np.empty((m, 2, 0)),
                rate,
            )
        line, samp, valid, pattern, dp, dg, rate = self._chunk(
            self._eo_poly(nodes), io, ccd, p, np.array(line_guess, np.float64), rate_guess
        )
        if not np.all(valid):
            bad = ~valid
            line[bad] = samp[bad] = rate[bad] = np.nan
            pattern[bad] = 0
            dp[bad] = 0.0
            dg[bad] = 0.0
        return Evaluation(line, samp, valid, pattern, dp, dg, rate)

    def build(self, x: F64) -> LineScanCamera:
        """The strip with parameters ``x`` (native camera)."""
        x = np.asarray(x, np.float64)
        nodes = x[: 6 * self._n_nodes].reshape(self._n_nodes, 6)
        io = x[6 * self._n_nodes :].reshape(self._groups, 3)
        cam = self.camera
        if self._groups == 1:
            return cam.replace(nodes=nodes, interior=InteriorOrientation.from_array(io[0]))
        # Per-CCD interior (x0_c, y0_c, f_c) is exactly a CCD moved and scaled in the
        # focal plane of the camera's own interior (x0, y0, f): with s = f_c / f,
        # x_mm' = x0 + (x_mm - x0_c) / s, y_mm' = y0 + (y_mm - y0_c) / s, pitch' = pitch / s.
        base = cam.interior
        ccds = []
        for g, c in enumerate(cam.ccds):
            x0c, y0c, fc = io[g]
            s = fc / base.focal_length_mm
            ccds.append(
                replace(
                    c,
                    x_mm=base.x0_mm + (c.x_mm - x0c) / s,
                    y_mm=base.y0_mm + (c.y_mm - y0c) / s,
                    pixel_pitch_mm=c.pixel_pitch_mm / s,
                )
            )
        return cam.replace(nodes=nodes, ccds=tuple(ccds))

    def coverage(self, ccd: NDArray[np.intp], line: F64) -> list[CoverageIssue]:
        """Nodes (not fixed) with fewer than ``min_obs_per_node`` observations near them.

        An observation is near a node when its time lies between the node's neighbours
        (the two intervals the node's Lagrange basis function peaks over).
        """
        need = self.config.min_obs_per_node
        if need <= 0 or np.all(self.mode[: 6 * self._n_nodes] == 2):
            return []
        t = self.camera.line_rates.time(np.asarray(line, np.float64))
        interval = np.searchsorted(self._times, t, side="right") - 1  # -1 .. N-1
        per_interval = np.bincount(
            np.clip(interval + 1, 0, self._n_nodes), minlength=self._n_nodes + 1
        )
        # Node i is near intervals i-1 and i (index shifted by one above).
        counts = per_interval[:-1] + per_interval[1:]
        issues = []
        for i in range(self._n_nodes):
            sl = tuple(range(6 * i, 6 * i + 6))
            if counts[i] < need and np.any(self.mode[list(sl)] != 2):
                issues.append(
                    CoverageIssue(
                        f"node {i} (line {self.camera.node_lines[i]:.1f})", sl, int(counts[i]), need
                    )
                )
        return issues

    def weaken(self, issues: list[CoverageIssue]) -> list[str]:
        """Weight weak nodes towards their initial values, or raise (config ``weak_nodes``).

        Raises:
            AdjustmentError: With ``weak_nodes = "error"``, naming every weak node.
        """
        if not issues:
            return []
        cfg = self.config
        listing = ", ".join(f"{i.label}: {i.count} < {i.required}" for i in issues)
        if cfg.weak_nodes == "error":
            raise AdjustmentError(
                f"strip {self.camera_id!r}: too few observations near orientation node(s) "
                f"{listing}; add observations, use fewer nodes, fix them, or set "
                f"linescan.weak_nodes = 'weight'"
            )
        if cfg.weak_nodes == "smooth" and self._n_nodes >= 3:
            self._smooth(issues)
            # Nodes placed beyond the imaged lines (the margin) have no observations by
            # design: that is no news. Only weak nodes inside the image are worth a warning.
            n_lines = max(c.n_lines for c in self.camera.ccds)
            inside = [
                i
                for i in issues
                if 0.0 <= float(self.camera.node_lines[i.indices[0] // 6]) <= n_lines
            ]
            margin = len(issues) - len(inside)
            if margin:
                log.info(
                    "strip %r: %d margin node(s) beyond the imaged lines follow the "
                    "corrections of their neighbours",
                    self.camera_id,
                    margin,
                )
            if not inside:
                return []
            listing = ", ".join(f"{i.label}: {i.count} < {i.required}" for i in inside)
            return [
                f"strip {self.camera_id!r}: weak node(s) inside the image follow the "
                f"corrections of their neighbours ({listing}); more matches near them "
                "(smaller tiles, another matcher) or fewer nodes would determine them"
            ]
        for issue in issues:
            for j in issue.indices:
                if self.mode[j] == 2:
                    continue
                self.mode[j] = 1
                self.sigma[j] = (
                    cfg.weak_node_position_sigma_m
                    if j % 6 < 3
                    else cfg.weak_node_attitude_sigma_rad
                )
        return [
            f"strip {self.camera_id!r}: weighted weak node(s) towards their initial "
            f"values ({listing})"
        ]

    def _smooth(self, issues: list[CoverageIssue]) -> None:
        """Zero-second-difference constraints on the corrections of weak nodes.

        Each weak node ``i`` gets, per parameter, ``d_i - 2 d_j + d_k = 0`` with ``d`` the
        correction ``x - x0`` and ``j, k`` its next two nodes towards the middle of the
        strip, so runs of weak nodes at the ends extrapolate the observed part linearly.
        """
        cfg = self.config
        n = len(self.x0)
        rows, weights = [], []
        mid = (self._n_nodes - 1) / 2.0
        for issue in issues:
            i = issue.indices[0] // 6
            step = 1 if i < mid else -1
            j, k = i + step, i + 2 * step
            if not (0 <= j < self._n_nodes and 0 <= k < self._n_nodes):
                continue
            for c in range(6):
                if self.mode[6 * i + c] == 2:
                    continue
                row = np.zeros(n)
                row[6 * i + c], row[6 * j + c], row[6 * k + c] = 1.0, -2.0, 1.0
                rows.append(row)
                sig = cfg.weak_node_smooth_sigma_m if c < 3 else cfg.weak_node_smooth_sigma_rad
                weights.append(1.0 / sig**2)
        if rows:
            a = np.array(rows)
            w = np.array(weights)
            if self.constraints is not None:
                a = np.vstack([self.constraints[0], a])
                w = np.concatenate([self.constraints[1], w])
            self.constraints = (a, w)


# ------------------------------------------------------------------------- CSM
_CSM_TERMS = (
    # (block, indices into usgscsm's 16 parameters, names)
    ("position_offset", (0, 1, 2), ("in_track", "cross_track", "radial")),
    ("position_rate", (3, 4, 5), ("in_track_rate", "cross_track_rate", "radial_rate")),
    ("pointing_offset", (6, 7, 8), ("omega", "phi", "kappa")),
    ("pointing_rate", (9, 10, 11), ("omega_rate", "phi_rate", "kappa_rate")),
    ("pointing_acceleration", (12, 13, 14), ("omega_accel", "phi_accel", "kappa_accel")),
    ("focal_length", (15,), ("focal",)),
)


class CsmParameterization:
    """usgscsm's per-image corrections of a CSM line-scan camera.

    Local parameters are the (non-fixed) correction terms in usgscsm's own units (metres,
    see :class:`~planetref.camera.csm.CsmCorrection`); sigmas from the configuration's
    physical units are converted with the image's half duration ``T``, flying height
    ``H`` and half swath ``W``: pointing ``omega, phi`` ``sigma_m = sigma_rad H``, kappa
    ``sigma_rad W``; rates ``x T``; accelerations ``x T^2``; position rate
    ``sigma_m_s T``; focal ``sigma_mm W / f``. Partials are central finite differences
    of ``ground_to_image`` (the correction enters almost linearly).

    Args:
        camera_id: The image's id.
        camera: The initial camera (its existing correction is the starting point).
        config: Modes and sigmas of the correction blocks.
        fixed: Hold every parameter fixed.
    """

    def __init__(
        self, camera_id: str, camera: Any, config: CsmParameters, *, fixed: bool = False
    ) -> None:
        self.camera_id = camera_id
        self.camera = camera
        self.config = config
        t_half, height, swath = camera.half_time_s, camera.flying_height_m, camera.half_swath_m
        f_mm = float(camera.isd.focal_length_mm)
        scale = {
            "position_offset": (1.0, 1.0, 1.0),
            "position_rate": (t_half,) * 3,
            "pointing_offset": (height, height, swath),
            "pointing_rate": (height * t_half, height * t_half, swath * t_half),
            "pointing_acceleration": (height * t_half**2, height * t_half**2, swath * t_half**2),
            "focal_length": (swath / f_mm,),
        }
        sigma_field = {
            "position_offset": "sigma_m",
            "position_rate": "sigma_m_s",
            "pointing_offset": "sigma_rad",
            "pointing_rate": "sigma_rad_s",
            "pointing_acceleration": "sigma_rad_s2",
            "focal_length": "sigma_mm",
        }
        index, names, mode, sigma = [], [], [], []
        for block, idx, labels in _CSM_TERMS:
            cfg = getattr(config, block)
            if cfg.mode == "fixed" or fixed:
                continue
            raw_sigma = getattr(cfg, sigma_field[block])
            for j, lab, sc in zip(idx, labels, scale[block], strict=True):
                index.append(j)
                names.append(f"{lab}_m")
                m_, s_ = _block(cfg.mode, None if raw_sigma is None else raw_sigma * sc, 1, False)
                mode.append(m_[0])
                sigma.append(s_[0])
        self._index = np.array(index, np.intp)
        self._base = camera.correction.as_array()
        self.names = tuple(names)
        self.units = tuple("m" for _ in names)
        self.x0 = self._base[self._index].copy()
        self.mode = np.array(mode, np.int8)
        self.sigma = np.array(sigma, np.float64)
        q = max(len(index), 1)
        cols = np.full((1, q), -1, np.intp)
        cols[0, : len(index)] = np.arange(len(index))
        self.pattern_columns = cols
        self._cache: tuple[bytes, Any] | None = None

    def _camera(self, x: F64) -> Any:
        from planetref.camera.csm import CsmCorrection

        key = np.asarray(x, np.float64).tobytes()
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1]
        full = self._base.copy()
        full[self._index] = x
        cam = self.camera.with_correction(CsmCorrection.from_array(full))
        self._cache = (key, cam)
        return cam

    def _project(self, cam: Any, xyz: F64) -> tuple[F64, F64, NDArray[np.bool_]]:
        ip = cam.ground_to_image(xyz)
        return ip.line, ip.sample, ip.valid

    def evaluate(
        self,
        x: F64,
        xyz: F64,
        ccd: int,
        line_guess: F64,
        rate_guess: F64 | None = None,
        partials: bool = True,
    ) -> Evaluation:
        """Project into the image with central-difference partials.

        Args:
            x: Local parameters (usgscsm metres).
            xyz: Ground points (metres), ``(m, 3)``.
            ccd: Must be 0 (one CCD per CSM camera).
            line_guess: Unused (the CSM model finds its own starting lines).
            rate_guess: Unused.
            partials: ``False`` projects only.
        """
        x = np.asarray(x, np.float64)
        xyz = np.asarray(xyz, np.float64)
        m = len(xyz)
        line, samp, valid = self._project(self._camera(x), xyz)
        if not partials:
            line = np.where(valid, line, np.nan)
            samp = np.where(valid, samp, np.nan)
            return Evaluation(
                line, samp, valid, np.zeros(m, np.intp), np.empty((m, 2, 0)), np.empty((m, 2, 0))
            )
        q = self.pattern_columns.shape[1]
        d_params = np.zeros((m, 2, q))
        h = self.config.fd_step_m
        for j in range(len(self._index)):
            xp, xm = x.copy(), x.copy()
            xp[j] += h
            xm[j] -= h
            lp, sp_, vp = self._project(self._camera(xp), xyz)
            lm, sm, vm = self._project(self._camera(xm), xyz)
            d_params[:, 0, j] = (lp - lm) / (2 * h)
            d_params[:, 1, j] = (sp_ - sm) / (2 * h)
            valid &= vp & vm
        cam = self._camera(x)
        g = self.config.fd_ground_step_m
        # All six ground perturbations in one call (same camera): +-g on X, Y, Z.
        shifts = np.concatenate([np.eye(3), -np.eye(3)]) * g
        lg, sg, vg = self._project(cam, (xyz[None, :, :] + shifts[:, None, :]).reshape(-1, 3))
        lg, sg, vg = lg.reshape(6, m), sg.reshape(6, m), vg.reshape(6, m)
        d_ground = np.empty((m, 2, 3))
        d_ground[:, 0, :] = ((lg[:3] - lg[3:]) / (2 * g)).T
        d_ground[:, 1, :] = ((sg[:3] - sg[3:]) / (2 * g)).T
        valid &= np.all(vg, axis=0)
        self._camera(x)  # leave the cache on the nominal parameters
        bad = ~valid
        line = np.where(valid, line, np.nan)
        samp = np.where(valid, samp, np.nan)
        d_params[bad] = 0.0
        d_ground[bad] = 0.0
        return Evaluation(line, samp, valid, np.zeros(m, np.intp), d_params, d_ground)

    def build(self, x: F64) -> Any:
        """The CSM camera with the correction ``x`` (other terms as initially)."""
        return self._camera(np.asarray(x, np.float64))

    def physical(self, x: F64) -> dict[str, float]:
        """The correction terms in physical units (m, m/s, rad, rad/s, rad/s², mm)."""
        cam = self.camera
        t_half, height, swath = cam.half_time_s, cam.flying_height_m, cam.half_swath_m
        f_mm = float(cam.isd.focal_length_mm)
        out: dict[str, float] = {}
        full = self._base.copy()
        full[self._index] = np.asarray(x, np.float64)
        for block, idx, labels in _CSM_TERMS:
            for j, lab in zip(idx, labels, strict=True):
                v = float(full[j])
                if block == "position_offset":
                    out[f"{lab}_m"] = v
                elif block == "position_rate":
                    out[f"{lab}_m_s"] = v / t_half
                elif block == "focal_length":
                    out["focal_length_correction_mm"] = -v * f_mm / swath
                else:
                    power = {"pointing_offset": 0, "pointing_rate": 1, "pointing_acceleration": 2}[
                        block
                    ]
                    lever = swath if lab.startswith("kappa") else height
                    unit = {0: "rad", 1: "rad_s", 2: "rad_s2"}[power]
                    out[f"{lab}_{unit}"] = v / (lever * t_half**power)
        return out

    def coverage(self, ccd: NDArray[np.intp], line: F64) -> list[CoverageIssue]:
        """The image as a whole needs as many observations as it has free terms."""
        free = np.flatnonzero(self.mode != 2)
        need = math.ceil(len(free) / 2) + 1 if free.size else 0
        if len(line) < need:
            return [
                CoverageIssue(
                    f"image {self.camera_id!r}", tuple(int(i) for i in free), len(line), need
                )
            ]
        return []

    def weaken(self, issues: list[CoverageIssue]) -> list[str]:
        """Too few observations for an image's correction: always an error.

        Raises:
            AdjustmentError: Naming the image and the counts.
        """
        if not issues:
            return []
        i = issues[0]
        raise AdjustmentError(
            f"image {self.camera_id!r}: {i.count} observation(s) cannot "
            f"determine its {len(i.indices)} correction term(s) "
            f"{list(self.names)}; fix the image or add observations"
        )
