"""A native line-scan strip as adjustment unknowns: node EOPs, interior, CCD placement.

:class:`LineScanParameterization` adjusts a
:class:`~planetref.camera.linescan.LineScanCamera`: node EOPs ``X, Y, Z`` (m) and
``phi, omega, kappa`` (rad), the interior ``x0, y0, f`` (mm) per strip or per CCD, and
optionally each CCD's placement in the focal plane ``x_mm, y_mm`` (mm), ``angle_rad``.
Projections and exact analytic partials come from the camera's own kernel
(:mod:`planetref.camera.linescan.kernel`), seeded with the previous solution's lines
and rates so that one evaluation costs about one pass over the model.
"""

from __future__ import annotations

import copy
import logging
from dataclasses import replace
from typing import cast

import numpy as np
from numpy.typing import NDArray

from planetref.adjust.config import LineScanParameters
from planetref.adjust.models.protocol import CoverageIssue, Evaluation, mode_and_sigma
from planetref.arrays import F64
from planetref.camera.linescan import CcdGeometry, InteriorOrientation, LineScanCamera, compiled
from planetref.camera.linescan.kernel import RAW_COLUMNS
from planetref.errors import AdjustmentError, InputError

__all__ = ["LineScanParameterization"]

log = logging.getLogger("planetref.adjust")

_EO_NAMES = ("X", "Y", "Z", "phi", "omega", "kappa")
_EO_UNITS = ("m", "m", "m", "rad", "rad", "rad")
_IO_NAMES = ("x0", "y0", "f")
_CCD_NAMES = ("x_mm", "y_mm", "angle_rad")
_CCD_UNITS = ("mm", "mm", "rad")


class LineScanParameterization:
    """Unknowns of a native line-scan strip.

    Local parameter vector: ``[nodes (N*6, node-major: X, Y, Z, phi, omega, kappa),
    interior (G*3: x0, y0, f), placement (C*3: x_mm, y_mm, angle_rad)]`` with ``G = 1``
    (interior scope ``strip``) or the number of CCDs (scope ``ccd``), and ``C`` the
    number of CCDs when ``ccd_placement`` is not ``fixed`` (else no placement block).

    Patterns: one per (Lagrange window, CCD group); a CCD group is every CCD when the
    interior is per CCD or placements are estimated, else one group for all CCDs.

    Args:
        camera_id: The strip's id.
        camera: The initial camera.
        config: Modes and sigmas of the blocks.
        fixed: Hold every parameter fixed.

    Raises:
        InputError: When ``ccd_placement.reference_ccd`` names no CCD of the camera.
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
        #: ``False`` runs the numpy reference kernel (tests, benchmarks); ``True`` the
        #: compiled one where it applies (numba available, no lens distortion).
        self.compiled_partials = True
        self.config = config
        self._kernel = camera.kernel
        #: The EO polynomials of the last node values (a pass evaluates every chunk
        #: of a CCD at the same parameters): ``(nodes, poly)``.
        self._poly: tuple[F64, F64] | None = None
        n = camera.n_nodes
        self._n_nodes = n
        self._k = self._kernel.k
        n_ccd = len(camera.ccds)
        self._groups = n_ccd if config.interior.scope == "ccd" else 1
        place = config.ccd_placement
        self._placement = place.mode != "fixed"
        self._n_place = n_ccd if self._placement else 0
        self._pattern_groups = n_ccd if (self._groups > 1 or self._placement) else 1
        io = camera.interior.as_array()
        placement = np.array([[c.x_mm, c.y_mm, c.angle_rad] for c in camera.ccds])
        self.x0 = np.concatenate(
            [camera.nodes.ravel(), np.tile(io, self._groups), placement[: self._n_place].ravel()]
        )
        names, units = [], []
        for i in range(n):
            names += [f"node{i}.{p}" for p in _EO_NAMES]
            units += list(_EO_UNITS)
        for g in range(self._groups):
            tag = "interior" if self._groups == 1 else f"interior[{camera.ccds[g].name}]"
            names += [f"{tag}.{p}" for p in _IO_NAMES]
            units += ["mm"] * 3
        for c in camera.ccds[: self._n_place]:
            names += [f"ccd[{c.name}].{p}" for p in _CCD_NAMES]
            units += list(_CCD_UNITS)
        self.names = tuple(names)
        self.units = tuple(units)
        mode = np.empty(len(self.x0), np.int8)
        sigma = np.empty(len(self.x0))
        pos_m, pos_s = mode_and_sigma(config.position.mode, config.position.sigma_m, n, fixed)
        att_m, att_s = mode_and_sigma(config.attitude.mode, config.attitude.sigma_rad, n, fixed)
        for j in range(3):
            mode[j : 6 * n : 6], sigma[j : 6 * n : 6] = pos_m, pos_s
            mode[3 + j : 6 * n : 6], sigma[3 + j : 6 * n : 6] = att_m, att_s
        ib = config.interior
        for g in range(self._groups):
            base = 6 * n + 3 * g
            for j, s in enumerate(
                (ib.sigma_principal_point_mm, ib.sigma_principal_point_mm, ib.sigma_focal_length_mm)
            ):
                m_, s_ = mode_and_sigma(ib.mode, s, 1, fixed)
                mode[base + j], sigma[base + j] = m_[0], s_[0]
        self._place_base = 6 * n + 3 * self._groups
        if self._placement:
            if place.reference_ccd is not None and place.reference_ccd not in camera.ccd_names:
                raise InputError(
                    f"ccd_placement.reference_ccd {place.reference_ccd!r} is not a CCD of "
                    f"strip {camera_id!r} ({list(camera.ccd_names)})"
                )
            for i, c in enumerate(camera.ccds):
                hold = fixed or c.name == place.reference_ccd
                base = self._place_base + 3 * i
                for j, s in enumerate(
                    (place.sigma_offset_mm, place.sigma_offset_mm, place.sigma_angle_rad)
                ):
                    m_, s_ = mode_and_sigma(place.mode, s, 1, hold)
                    mode[base + j], sigma[base + j] = m_[0], s_[0]
        self.mode = mode
        self.sigma = sigma
        #: Linear pseudo-observations ``A (x - x0) = 0`` with weights ``w`` (or None).
        self.constraints: tuple[F64, F64] | None = None
        n_win = self._kernel.windows.n_windows
        npg = self._pattern_groups
        q = 6 * self._k + 3 + (3 if self._placement else 0)
        cols = np.full((n_win * npg, q), -1, np.intp)
        for s in range(n_win):
            for pg in range(npg):
                row = cols[s * npg + pg]
                row[: 6 * self._k] = np.arange(6 * s, 6 * (s + self._k))
                row[6 * self._k : 6 * self._k + 3] = 6 * n + 3 * self._group(pg) + np.arange(3)
                if self._placement:
                    row[6 * self._k + 3 :] = self._place_base + 3 * pg + np.arange(3)
        self.pattern_columns = cols

    # ----------------------------------------------------------------- pieces
    def _group(self, ccd: int) -> int:
        return ccd if self._groups > 1 else 0

    def _split(self, x: F64, ccd: int) -> tuple[F64, F64, CcdGeometry]:
        """Node values, interior ``[x0, y0, f]`` and the CCD at parameters ``x``."""
        nodes = x[: 6 * self._n_nodes].reshape(self._n_nodes, 6)
        base = 6 * self._n_nodes + 3 * self._group(ccd)
        c = self.camera.ccds[ccd]
        if self._placement:
            xc, yc, ac = x[self._place_base + 3 * ccd : self._place_base + 3 * ccd + 3]
            c = replace(c, x_mm=float(xc), y_mm=float(yc), angle_rad=float(ac))
        return nodes, x[base : base + 3], c

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
        nodes, io, c = self._split(np.asarray(x, np.float64), ccd)
        p = np.asarray(xyz, np.float64)
        kern = self._kernel
        poly = self._eo_poly(nodes)
        guess = np.array(line_guess, np.float64)
        m = len(p)
        if not partials:
            line, samp, valid, rate = kern.project(poly, io, c, p, guess, rate_guess)
            bad = ~valid
            line[bad] = samp[bad] = rate[bad] = np.nan
            return Evaluation(
                line,
                samp,
                valid,
                np.zeros(m, np.intp),
                np.empty((m, 2, 0)),
                np.empty((m, 2, 0)),
                rate,
            )
        use_compiled = None if self.compiled_partials else False
        proj = kern.project_with_partials(
            poly, io, c, p, guess, rate_guess, use_compiled=use_compiled
        )
        pg = ccd if self._pattern_groups > 1 else 0
        pattern = proj.start * self._pattern_groups + pg
        line, samp, valid, rate = proj.line, proj.sample, proj.valid, proj.rate
        if kern.runs_compiled(use_compiled, c):
            # Factored: the solver's compiled linearisation multiplies the node columns
            # out as it reads them (compiled.fill_partials writes them if asked for).
            imp = proj.partials
            if not np.all(valid):
                bad = ~valid
                line[bad] = samp[bad] = rate[bad] = np.nan
                pattern[bad] = 0
                imp[bad] = 0.0
                proj.weights[bad] = 0.0
            # With the weights' polynomial form (basis) the solver accumulates runs of a
            # window as moments of tau (``linearize_rows``).
            factors = _Factors(
                imp,
                proj.weights,
                self._placement,
                *self._column_map(),
                basis=(proj.tau, proj.start, kern.windows.coef),
            )
            return Evaluation(line, samp, valid, pattern, None, None, rate, factors=factors)
        # The numpy reference of compiled.fill_partials.
        dp = np.empty((m, 2, self.pattern_columns.shape[1]))
        k6 = 6 * self._k
        kern.node_partials(proj, out=dp[:, :, :k6].reshape(m, 2, self._k, 6))
        dp[:, :, k6 : k6 + 3] = proj.partials[:, :, RAW_COLUMNS["interior"]]
        if self._placement:
            dp[:, :, k6 + 3 :] = proj.partials[:, :, RAW_COLUMNS["ccd"]]
        dg = proj.partials[:, :, RAW_COLUMNS["ground"]]
        if not np.all(valid):
            bad = ~valid
            line[bad] = samp[bad] = rate[bad] = np.nan
            pattern[bad] = 0
            dp[bad] = 0.0
            dg[bad] = 0.0
        return Evaluation(line, samp, valid, pattern, dp, dg, rate)

    def _column_map(self) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        """``(src, node)`` of each pattern column (see :class:`_Factors`)."""
        k6 = 6 * self._k
        q = self.pattern_columns.shape[1]
        col = np.arange(q)
        src = np.where(col < k6, col % 6, col - k6 + RAW_COLUMNS["interior"].start)
        if self._placement:
            tail = col >= k6 + 3
            src[tail] = col[tail] - k6 - 3 + RAW_COLUMNS["ccd"].start
        node = np.where(col < k6, col // 6, -1)
        return src.astype(np.intp), node.astype(np.intp)

    def _eo_poly(self, nodes: F64) -> F64:
        """:meth:`~planetref.camera.linescan.kernel.LineScanKernel.eo_poly`, kept per nodes."""
        last = self._poly
        if last is not None and np.array_equal(last[0], nodes):
            return last[1]
        poly = self._kernel.eo_poly(nodes)
        self._poly = (nodes.copy(), poly)
        return poly

    def build(self, x: F64) -> LineScanCamera:
        """The strip with parameters ``x`` (native camera)."""
        x = np.asarray(x, np.float64)
        nodes = x[: 6 * self._n_nodes].reshape(self._n_nodes, 6)
        io = x[6 * self._n_nodes : self._place_base].reshape(self._groups, 3)
        cam = self.camera
        ccds = [self._split(x, i)[2] for i in range(len(cam.ccds))]
        if self._groups == 1:
            return cam.replace(
                nodes=nodes, interior=InteriorOrientation.from_array(io[0]), ccds=tuple(ccds)
            )
        # Per-CCD interior (x0_c, y0_c, f_c) is exactly a CCD moved and scaled in the
        # focal plane of the camera's own interior (x0, y0, f): with s = f_c / f,
        # x_mm' = x0 + (x_mm - x0_c) / s, y_mm' = y0 + (y_mm - y0_c) / s, pitch' = pitch / s.
        base = cam.interior
        for g, c in enumerate(ccds):
            x0c, y0c, fc = io[g]
            s = fc / base.focal_length_mm
            ccds[g] = replace(
                c,
                x_mm=base.x0_mm + (c.x_mm - x0c) / s,
                y_mm=base.y0_mm + (c.y_mm - y0c) / s,
                pixel_pitch_mm=c.pixel_pitch_mm / s,
            )
        return cam.replace(nodes=nodes, ccds=tuple(ccds))

    def coverage(self, ccd: NDArray[np.intp], line: F64) -> list[CoverageIssue]:
        """Nodes (not fixed) with fewer than ``min_obs_per_node`` observations near them.

        An observation is near the node whose interpolation weight dominates at its time:
        the nearest node. (Counting it for both nodes around it, as before, let a node
        whose observations all lie half a spacing or more away pass while the
        observations hardly determine it, e.g. the last node when the matches stop short
        of the strip end; its attitude was then free and the adjustment singular.)
        """
        need = self.config.min_obs_per_node
        if need <= 0 or np.all(self.mode[: 6 * self._n_nodes] == 2):
            return []
        line = np.asarray(line, np.float64)
        if self._n_nodes < 2:
            counts = np.array([len(line)])
        else:
            # Nearest node in time: node j owns the times up to the midpoint after it;
            # the midpoints as lines (time is monotonic in the line), one search per
            # observation.
            times = np.asarray(self._kernel.windows.times, np.float64)
            mid = self.camera.line_rates.line(0.5 * (times[:-1] + times[1:]))
            nearest = np.searchsorted(mid, line, side="left")
            counts = np.bincount(nearest, minlength=self._n_nodes)
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

    def weaken(self, issues: list[CoverageIssue]) -> tuple[LineScanParameterization, list[str]]:
        """Weight weak nodes towards their initial values, or raise (config ``weak_nodes``).

        Returns:
            ``(model, warnings)``: a new parameterisation with the weak nodes weighted
            (``weak_nodes = "weight"``) or smoothed (``"smooth"``), this one unchanged;
            ``self`` when there are no issues.

        Raises:
            AdjustmentError: With ``weak_nodes = "error"``, naming every weak node.
        """
        if not issues:
            return self, []
        cfg = self.config
        listing = ", ".join(f"{i.label}: {i.count} < {i.required}" for i in issues)
        if cfg.weak_nodes == "error":
            raise AdjustmentError(
                f"strip {self.camera_id!r}: too few observations near orientation node(s) "
                f"{listing}; add observations, use fewer nodes, fix them, or set "
                f"linescan.weak_nodes = 'weight'"
            )
        if cfg.weak_nodes == "smooth" and self._n_nodes >= 3:
            new = self._with(self.mode, self.sigma, self._smooth(issues))
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
                return new, []
            listing = ", ".join(f"{i.label}: {i.count} < {i.required}" for i in inside)
            return new, [
                f"strip {self.camera_id!r}: weak node(s) inside the image follow the "
                f"corrections of their neighbours ({listing}); more matches near them "
                "(smaller tiles, another matcher) or fewer nodes would determine them"
            ]
        mode, sigma = self.mode.copy(), self.sigma.copy()
        for issue in issues:
            for j in issue.indices:
                if mode[j] == 2:
                    continue
                mode[j] = 1
                sigma[j] = (
                    cfg.weak_node_position_sigma_m
                    if j % 6 < 3
                    else cfg.weak_node_attitude_sigma_rad
                )
        return self._with(mode, sigma, self.constraints), [
            f"strip {self.camera_id!r}: weighted weak node(s) towards their initial "
            f"values ({listing})"
        ]

    def rigid(self) -> LineScanParameterization:
        """A copy whose nodes share one correction (a rigid shift and rotation).

        Adds, per parameter and pair of consecutive nodes, ``d_i - d_{i+1} = 0`` (``d``
        the correction ``x - x0``) within the weak-node smoothing sigmas (as good as
        exact), to this model's own constraints. Used for a first solve from a far
        start (:attr:`~planetref.adjust.config.SolverConfig.rigid_start`).
        """
        cfg = self.config
        n = len(self.x0)
        rows, weights = [], []
        for i in range(self._n_nodes - 1):
            for c in range(6):
                if self.mode[6 * i + c] == 2 or self.mode[6 * (i + 1) + c] == 2:
                    continue
                row = np.zeros(n)
                row[6 * i + c], row[6 * (i + 1) + c] = 1.0, -1.0
                rows.append(row)
                sig = cast(
                    float,
                    cfg.weak_node_smooth_sigma_m if c < 3 else cfg.weak_node_smooth_sigma_rad,
                )
                weights.append(1.0 / sig**2)
        if not rows:
            return self
        a = np.array(rows)
        w = np.array(weights)
        if self.constraints is not None:
            a = np.vstack([self.constraints[0], a])
            w = np.concatenate([self.constraints[1], w])
        return self._with(self.mode, self.sigma, (a, w))

    def _with(
        self, mode: NDArray[np.int8], sigma: F64, constraints: tuple[F64, F64] | None
    ) -> LineScanParameterization:
        """A copy with other modes, sigmas and constraints (the camera etc. are shared)."""
        new = copy.copy(self)
        new.mode, new.sigma, new.constraints = mode, sigma, constraints
        new._poly = None
        return new

    def _smooth(self, issues: list[CoverageIssue]) -> tuple[F64, F64] | None:
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
                # Typed ``float | None`` like every unit field, but with float defaults;
                # a None (Python API only, TOML has no null) fails on ``**`` as before.
                sig = cast(
                    float,
                    cfg.weak_node_smooth_sigma_m if c < 3 else cfg.weak_node_smooth_sigma_rad,
                )
                weights.append(1.0 / sig**2)
        if not rows:
            return self.constraints
        a = np.array(rows)
        w = np.array(weights)
        if self.constraints is not None:
            a = np.vstack([self.constraints[0], a])
            w = np.concatenate([self.constraints[1], w])
        return a, w


class _Factors:
    """A line scanner's partials in factored form (see :class:`Evaluation` ``factors``).

    ``d_params[i, r, 6 j + c] = imp[i, r, c] * weights[i, j]`` for node ``j`` of the
    window and EO column ``c``; the interior (and placement) columns are columns of
    ``imp``; ``d_ground`` is ``imp``'s ground columns (:attr:`ground`). ``basis``:
    ``(tau, start, coef)`` with ``weights[i, j] = sum_q coef[start[i], j, q] tau[i]^q``,
    or ``None``.
    """

    __slots__ = ("basis", "imp", "node", "placement", "src", "weights")
    #: ``d_ground``'s columns in ``imp`` (those ``compiled.fill_partials`` copies).
    ground = np.arange(RAW_COLUMNS["ground"].start, RAW_COLUMNS["ground"].stop, dtype=np.intp)

    def __init__(
        self,
        imp: F64,
        weights: F64,
        placement: bool,
        src: NDArray[np.intp],
        node: NDArray[np.intp],
        *,
        basis: tuple[F64, NDArray[np.intp], F64] | None = None,
    ) -> None:
        self.imp, self.weights, self.placement = imp, weights, placement
        self.src, self.node, self.basis = src, node, basis

    def expand(self, rows: NDArray[np.bool_] | None = None) -> tuple[F64, F64]:
        """``(d_params (m, 2, q), d_ground (m, 2, 3))`` (compiled.fill_partials).

        Args:
            rows: Only these rows (a mask); ``None``: all.
        """
        imp = self.imp if rows is None else self.imp[rows]
        w = self.weights if rows is None else self.weights[rows]
        m = len(imp)
        dp = np.empty((m, 2, len(self.src)))
        dg = np.empty((m, 2, 3))
        compiled.fill_partials(imp, w, self.placement, dp, dg)
        return dp, dg
