"""Levenberg-Marquardt bundle adjustment on the reduced normal equations.

Unknowns: the camera parameters ``c`` of every :class:`~planetref.adjust.models.
AdjustableCamera` (concatenated into one global vector) and the coordinates ``X_j`` of
the ground points that are not fixed. Observations: ``r_m = projected(line, sample) -
observed`` with per-axis weights ``1/sigma^2`` times a robust IRLS weight; fixed and
weighted parameters and weighted points add pseudo-observations ``(p - p0)/sigma``.

Per iteration the residuals and Jacobians are evaluated vectorised in chunks; the normal
equations are accumulated per *pattern* (observations that depend on the same
parameters) with dense BLAS products, so nothing of size ``M x n_params`` is ever formed.
Point unknowns are eliminated per point by the Schur complement (3x3 blocks, vectorised);
the reduced camera system (at most a few hundred unknowns) is Jacobi-scaled and solved
densely by Cholesky; points are back-substituted. Damping is Marquardt's (``lambda x
diag``) on the full system, points included, with Nielsen's update of ``lambda``.

After convergence: ``sigma0 = sqrt(v^T P v / dof)``, camera covariance ``sigma0^2
S^-1`` with ``S`` the undamped reduced matrix, correlations. A rank-deficient reduced
system raises :class:`~planetref.errors.AdjustmentError` naming the parameters that the
observations do not determine.
"""

from __future__ import annotations

import itertools
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from planetref.adjust.config import SolverConfig
from planetref.adjust.models import AdjustableCamera, Evaluation
from planetref.adjust.problem import Network
from planetref.errors import AdjustmentError

__all__ = ["BundleSolver", "LmReport", "robust_rho"]

log = logging.getLogger("planetref.adjust")
F64 = NDArray[np.float64]
#: Steps below this many sigmas that do not lower the cost are rounding noise.
_STEP_FLOOR_SIGMA = 1e-6
#: Relative cost decrease below which a robust (IRLS) run stops.
_IRLS_FTOL = 1e-9


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


@dataclass
class LmReport:
    """What one Levenberg-Marquardt run did.

    Attributes:
        iterations: Accepted iterations.
        evaluations: Model evaluations (accepted and rejected steps).
        converged: True when a convergence criterion was met.
        reason: Why it stopped.
        cost_initial: Cost at the start (half the weighted robust sum of squares).
        cost_final: Cost at the end.
        history: ``(iteration, cost, lambda)`` per accepted step.
        seconds: Wall time.
    """

    iterations: int = 0
    evaluations: int = 0
    converged: bool = False
    reason: str = ""
    cost_initial: float = float("nan")
    cost_final: float = float("nan")
    history: list[tuple[int, float, float]] = field(default_factory=list)
    seconds: float = 0.0


@dataclass
class _TieChunk:
    """Observations of a contiguous range of unknown points (complete points)."""

    obs: NDArray[np.intp]  # positions in the linearisation's tie arrays
    pt: NDArray[np.intp]  # local point index (0..n_pts-1) per observation
    pts: NDArray[np.intp]  # global unknown-point indices of the chunk
    pair_a: NDArray[np.intp]  # observation pairs within points (chunk-local)
    pair_b: NDArray[np.intp]
    starts: NDArray[np.intp]  # first observation of each point (chunk-local)


@dataclass
class _Linearization:
    cost: float
    r: F64  # (M, 2) residuals (line, sample)
    valid: NDArray[np.bool_]
    line: F64  # projected lines
    sample: F64
    s: F64  # squared normalised residuals
    weight: F64  # (M, 2) effective weights (robust x 1/sigma^2)
    n_cc: F64  # (P+1, P+1) sum A^T W A
    g_c: F64  # (P+1,) sum A^T W r
    a_t: F64  # (Mt, 2, q) camera partials of observations on unknown points
    b_t: F64  # (Mt, 2, 3)
    gpat_t: NDArray[np.intp]
    weight_t: F64  # (Mt, 2) weights in the order of a_t
    r_t: F64  # (Mt, 2) residuals in the order of a_t (0 where invalid)
    rate: F64  # (M,) the models' line-rate hints (NaN if none)
    obs: NDArray[np.intp]  # network observation index of each row


@dataclass
class _Structure:
    lay: _Layout
    unknown: NDArray[np.intp]  # network indices of the points whose XYZ are unknowns
    tie_pos: NDArray[np.intp]  # per layout row: row in the tie arrays, or -1
    chunks: list[_TieChunk]
    n_tie: int


@dataclass
class _Layout:
    """The observations of one LM run in a contiguous order.

    Every (camera, CCD) group is a contiguous range sorted by line, and the
    per-observation data are gathered once (random gathers from network-wide arrays
    would otherwise dominate each pass).
    """

    obs: NDArray[np.intp]  # network observation indices, in layout order
    ranges: list[tuple[int, int, int, int]]  # (model, ccd, start, stop)
    point: NDArray[np.intp]
    line: F64  # observed
    sample: F64
    w0: F64  # (M, 2) 1/sigma^2
    fixed_xyz: F64 | None  # (M, 3) when every point is fixed
    line_guess: F64
    rate_guess: F64


class BundleSolver:
    """The LM engine over a fixed set of parameterised cameras and a network.

    Args:
        network: Cameras, points and observations.
        models: One parameterisation per camera of the network, same order.
        config: Solver settings.
        progress: Optional callback ``progress(message)`` called once per iteration.
    """

    def __init__(
        self,
        network: Network,
        models: list[AdjustableCamera],
        config: SolverConfig,
        progress: Callable[[str], None] | None = None,
    ) -> None:
        self.net = network
        self.models = models
        self.cfg = config
        self.progress = progress
        sizes = [len(m.x0) for m in models]
        self.offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.intp)
        self.n_params = int(self.offsets[-1])
        p = self.n_params
        self.q = max(m.pattern_columns.shape[1] for m in models)
        pat = [len(m.pattern_columns) for m in models]
        self.pat_offsets = np.concatenate([[0], np.cumsum(pat)]).astype(np.intp)
        cols = np.full((int(self.pat_offsets[-1]), self.q), p, np.intp)
        for i, m in enumerate(models):
            pc = m.pattern_columns
            blk = np.where(pc >= 0, pc + self.offsets[i], p)
            cols[self.pat_offsets[i] : self.pat_offsets[i + 1], : pc.shape[1]] = blk
        self.cols = cols
        self._active_cache: dict[
            tuple[int, int], tuple[NDArray[np.intp] | None, NDArray[np.intp]]
        ] = {}
        self.x0 = np.concatenate([m.x0 for m in models]) if p else np.zeros(0)
        self.names = [f"{m.camera_id}:{n}" for m in models for n in m.names]
        self.units = [u for m in models for u in m.units]
        self.refresh_modes()
        sig = network.point_sigma_m
        fixed_pt = np.all(sig == 0, axis=1)
        partial = np.any(sig == 0, axis=1) & ~fixed_pt
        if np.any(partial):
            i = int(np.flatnonzero(partial)[0])
            raise AdjustmentError(
                f"point {network.point_ids[i]!r}: a sigma of 0 (fixed) on "
                f"some axes only is not supported"
            )
        self.point_fixed = fixed_pt
        #: Rotation from body-fixed XYZ to the frame of each point's sigmas, (P, 3, 3).
        self.point_frame = network.point_frame_matrices()
        self.set_point_sigma(sig)
        self.set_obs_sigma(network.obs_sigma_px)
        self.line_guess = network.obs_line.copy()
        self.rate_guess = np.full(network.n_obs, np.nan)
        self.loss = config.loss
        self.threshold: F64 | float = np.inf
        self.last_lambda: float | None = None
        self._group_cache: (
            tuple[NDArray[np.intp], list[tuple[int, int, NDArray[np.intp]]]] | None
        ) = None
        self._structure_cache: tuple[NDArray[np.intp], _Structure] | None = None

    # ------------------------------------------------------------------ setup
    def set_point_sigma(self, sigma_m: F64) -> None:
        """Set the a-priori sigmas of the points, ``(P, 3)`` in each point's sigma frame.

        0 and inf (fixed and free) must stay where they were: only the weights of
        weighted points change (variance component estimation).
        """
        sig = np.asarray(sigma_m, np.float64)
        self.point_sigma = sig.copy()
        with np.errstate(divide="ignore"):
            w = np.where(np.isfinite(sig) & (sig > 0), 1.0 / sig**2, 0.0)
        #: Per-axis weights in the sigma frame, (P, 3).
        self.point_prior_axis_w = w
        #: Weight matrices ``R^T diag(w) R`` in body-fixed XYZ, (P, 3, 3).
        self.point_prior_w = np.einsum("pki,pk,pkj->pij", self.point_frame, w, self.point_frame)

    def set_obs_sigma(self, sigma_px: F64) -> None:
        """Set the sigmas of the image measures, ``(M, 2)`` pixels (line, sample)."""
        self.obs_sigma = np.array(sigma_px, np.float64)
        self.obs_w0 = 1.0 / self.obs_sigma**2  # (M, 2), line then sample
        self._structure_cache = None

    def refresh_modes(self) -> None:
        """Re-read modes and sigmas from the models (after weak groups were weighted)."""
        self.mode = (
            np.concatenate([m.mode for m in self.models]) if self.n_params else np.zeros(0, np.int8)
        )
        self.sigma = (
            np.concatenate([m.sigma for m in self.models]) if self.n_params else np.zeros(0)
        )
        self.active = np.flatnonzero(self.mode != 2)
        with np.errstate(divide="ignore"):
            self.prior_w = np.where(self.mode == 1, 1.0 / self.sigma**2, 0.0)
        # Linear pseudo-observations A (c - x0) = 0 of the models (e.g. smooth weak
        # nodes), gathered into one global matrix; their normal contribution is A^T W A.
        rows, weights = [], []
        for i, m in enumerate(self.models):
            con = getattr(m, "constraints", None)
            if con is None:
                continue
            a_loc, w_loc = con
            a = np.zeros((len(a_loc), self.n_params))
            a[:, self.offsets[i] : self.offsets[i + 1]] = a_loc
            rows.append(a)
            weights.append(np.asarray(w_loc, np.float64))
        if rows:
            self.con_a = np.vstack(rows)
            self.con_w = np.concatenate(weights)
            self.con_n = self.con_a.T @ (self.con_w[:, None] * self.con_a)
        else:
            self.con_a = np.zeros((0, self.n_params))
            self.con_w = np.zeros(0)
            self.con_n = None

    def _prior_cost(self, c: F64) -> float:
        """``0.5 (c - x0)^T (P + A^T W A) (c - x0)``: a-priori weights and constraints."""
        dc = c - self.x0
        cost = 0.5 * float(np.sum(self.prior_w * dc * dc))
        if self.con_n is not None:
            cost += 0.5 * float(dc @ self.con_n @ dc)
        return cost

    def cameras(self, c: F64) -> list[object]:
        """The cameras built from a global parameter vector."""
        return [
            m.build(c[self.offsets[i] : self.offsets[i + 1]]) for i, m in enumerate(self.models)
        ]

    def _groups(self, obs: NDArray[np.intp]) -> list[tuple[int, int, NDArray[np.intp]]]:
        """``(model, ccd, positions into obs)`` groups.

        Within a group the positions are sorted by observed line: observations that
        share a Lagrange window (a pattern) then form contiguous runs, so the normal
        equations accumulate from array views instead of gathered copies.
        """
        cached = self._group_cache
        if cached is not None and np.array_equal(cached[0], obs):
            return cached[1]
        net = self.net
        base = max(len(cam.ccd_names) for cam in net.cameras)
        key = net.obs_camera[obs].astype(np.int64) * base + net.obs_ccd[obs]
        order = np.lexsort((net.obs_line[obs], key))
        ks = key[order]
        cut = np.flatnonzero(np.diff(ks)) + 1
        out = []
        for seg in np.split(order, cut):
            if seg.size:
                k = int(key[seg[0]])
                out.append((k // base, k % base, seg))
        self._group_cache = (obs.copy(), out)
        return out

    # ------------------------------------------------------------ projection
    def project(
        self, c: F64, xyz: F64, obs: NDArray[np.intp]
    ) -> tuple[F64, F64, NDArray[np.bool_]]:
        """Projected ``(line, sample, valid)`` of observations ``obs`` (no partials).

        Args:
            c: Global parameter vector.
            xyz: Point coordinates for every network point, ``(P, 3)``.
            obs: Observation indices.
        """
        m = len(obs)
        line = np.full(m, np.nan)
        sample = np.full(m, np.nan)
        valid = np.zeros(m, bool)
        cs = self.cfg.chunk_size
        for mi, ccd, pos in self._groups(obs):
            model = self.models[mi]
            x = c[self.offsets[mi] : self.offsets[mi + 1]]
            for a in range(0, len(pos), cs):
                sel = pos[a : a + cs]
                o = obs[sel]
                ev = model.evaluate(
                    x,
                    xyz[self.net.obs_point[o]],
                    ccd,
                    self.line_guess[o],
                    rate_guess=self.rate_guess[o],
                    partials=False,
                )
                line[sel], sample[sel], valid[sel] = ev.line, ev.sample, ev.valid
                self._remember(o, ev)
        return line, sample, valid

    def _remember(self, o: NDArray[np.intp], ev: Evaluation) -> None:
        """Keep an evaluation's lines (and rates) as the next starting guesses."""
        self.line_guess[o] = np.where(ev.valid, ev.line, self.line_guess[o])
        if ev.line_rate is not None:
            self.rate_guess[o] = np.where(ev.valid, ev.line_rate, np.nan)

    # -------------------------------------------------------------- linearise
    def _layout(self, obs: NDArray[np.intp]) -> _Layout:
        groups = self._groups(obs)
        order = np.concatenate([g[2] for g in groups]) if groups else np.zeros(0, np.intp)
        obs = obs[order]
        ranges = []
        a = 0
        for mi, ccd, pos in groups:
            ranges.append((mi, ccd, a, a + len(pos)))
            a += len(pos)
        net = self.net
        point = net.obs_point[obs]
        fixed = np.all(self.point_fixed[point])
        return _Layout(
            obs,
            ranges,
            point,
            net.obs_line[obs],
            net.obs_sample[obs],
            self.obs_w0[obs],
            net.point_xyz[point] if fixed else None,
            self.line_guess[obs],
            self.rate_guess[obs],
        )

    def _linearize(
        self,
        c: F64,
        xyz: F64,
        lay: _Layout,
        tie_pos: NDArray[np.intp],
        n_tie: int,
        unknown: NDArray[np.intp],
        xyz0: F64,
    ) -> _Linearization:
        p = self.n_params
        m = len(lay.obs)
        q = self.q
        r = np.full((m, 2), np.nan)
        valid = np.zeros(m, bool)
        line = np.full(m, np.nan)
        sample = np.full(m, np.nan)
        s_all = np.full(m, np.inf)
        weight = np.zeros((m, 2))
        rate = np.full(m, np.nan)
        n_cc = np.zeros((p + 1, p + 1))
        g_c = np.zeros(p + 1)
        a_t = np.zeros((n_tie, 2, q))
        b_t = np.zeros((n_tie, 2, 3))
        gpat_t = np.zeros(n_tie, np.intp)
        cs = self.cfg.chunk_size
        thr = self.threshold
        thr_l = thr if np.ndim(thr) == 0 else np.asarray(thr)[lay.obs]
        pxyz = lay.fixed_xyz if lay.fixed_xyz is not None else xyz[lay.point]
        robust = self.loss != "linear"
        for mi, ccd, a0, b0 in lay.ranges:
            model = self.models[mi]
            x = c[self.offsets[mi] : self.offsets[mi + 1]]
            for a in range(a0, b0, cs):
                b = min(a + cs, b0)
                ev = model.evaluate(
                    x, pxyz[a:b], ccd, lay.line_guess[a:b], rate_guess=lay.rate_guess[a:b]
                )
                if ev.line_rate is not None:
                    rate[a:b] = ev.line_rate
                res = r[a:b]
                np.subtract(ev.line, lay.line[a:b], out=res[:, 0])
                np.subtract(ev.sample, lay.sample[a:b], out=res[:, 1])
                w0 = lay.w0[a:b]
                s = np.einsum("mr,mr->m", res * res, w0)
                ok = ev.valid
                we = weight[a:b]
                if robust:
                    _, rw = robust_rho(s, self.loss, thr_l if np.ndim(thr_l) == 0 else thr_l[a:b])
                    np.multiply(w0, rw[:, None], out=we)
                else:
                    we[:] = w0
                if not np.all(ok):
                    we[~ok] = 0.0
                    s[~ok] = np.inf
                res_ok = np.where(ok[:, None], res, 0.0)
                valid[a:b], s_all[a:b] = ok, s
                line[a:b], sample[a:b] = ev.line, ev.sample
                gp = ev.pattern + self.pat_offsets[mi]
                d = ev.d_params
                qm = d.shape[2]
                self._accumulate(n_cc, g_c, d, we, we * res_ok, gp, qm)
                if n_tie:
                    tp = tie_pos[a:b]
                    is_t = tp >= 0
                    if np.any(is_t):
                        a_t[tp[is_t], :, :qm] = d[is_t]
                        b_t[tp[is_t]] = ev.d_ground[is_t]
                        gpat_t[tp[is_t]] = gp[is_t]
        if robust:
            rho, _ = robust_rho(np.where(valid, s_all, 0.0), self.loss, thr_l)
        else:
            rho = np.where(valid, s_all, 0.0)
        cost = 0.5 * float(np.sum(rho)) if np.all(valid) else math.inf
        cost += self._prior_cost(c)
        if len(unknown):
            dx = xyz[unknown] - xyz0[unknown]
            cost += 0.5 * _quadratic(self.point_prior_w[unknown], dx)
        inv = np.empty(n_tie, np.intp)
        sel = tie_pos >= 0
        inv[tie_pos[sel]] = np.flatnonzero(sel)
        return _Linearization(
            cost,
            r,
            valid,
            line,
            sample,
            s_all,
            weight,
            n_cc,
            g_c,
            a_t,
            b_t,
            gpat_t,
            weight[inv],
            np.where(valid[inv, None], r[inv], 0.0),
            rate,
            lay.obs,
        )

    def _accumulate(
        self, n_cc: F64, g_c: F64, d: F64, we: F64, wr: F64, gp: NDArray[np.intp], qm: int
    ) -> None:
        """``N += sum A^T W A`` and ``g += sum A^T W r``, per run of equal patterns.

        Runs are contiguous (observations sorted by line), so every product works on
        views; the few observations whose window differs from their neighbours' simply
        form short runs of their own. Only a pattern's active columns enter the products
        (fixed parameters map to the sink index and would only add zeros to discarded
        entries): with most parameters fixed that is a fraction of the flops.
        """
        m = len(gp)
        cut = np.concatenate([[0], np.flatnonzero(np.diff(gp)) + 1, [m]])
        for a, b in itertools.pairwise(cut):
            loc, cols = self._active_columns(int(gp[a]), qm)
            if len(cols) == 0:
                continue
            da = d[a:b] if loc is None else d[a:b][:, :, loc]
            blk = np.tensordot(da, da * we[a:b, :, None], axes=([0, 1], [0, 1]))
            n_cc[np.ix_(cols, cols)] += blk
            # Columns within a pattern are distinct, so a fancy-index add is exact.
            g_c[cols] += np.tensordot(da, wr[a:b], axes=([0, 1], [0, 1]))

    def _active_columns(
        self, pattern: int, qm: int
    ) -> tuple[NDArray[np.intp] | None, NDArray[np.intp]]:
        """Local indices (None: all) and global columns of a pattern's free parameters."""
        cache = self._active_cache
        key = (pattern, qm)
        if key not in cache:
            cols = self.cols[pattern, :qm]
            free = cols != self.n_params
            loc = None if free.all() else np.flatnonzero(free)
            cache[key] = (loc, cols if loc is None else cols[loc])
        return cache[key]

    # ------------------------------------------------------------------ Schur
    def _tie_structure(
        self, obs: NDArray[np.intp], unknown_of_obs: NDArray[np.intp], n_unknown: int
    ) -> tuple[NDArray[np.intp], list[_TieChunk], int]:
        """Tie positions of observations and chunks of complete points with pairs."""
        is_t = unknown_of_obs >= 0
        t_obs = np.flatnonzero(is_t)
        order = t_obs[np.argsort(unknown_of_obs[t_obs], kind="stable")]
        tie_pos = np.full(len(obs), -1, np.intp)
        tie_pos[order] = np.arange(len(order))
        pt_sorted = unknown_of_obs[order]
        chunks = []
        if len(order):
            counts = np.bincount(pt_sorted, minlength=n_unknown)
            starts = np.concatenate([[0], np.cumsum(counts)])
            target = max(self.cfg.chunk_size // 2, 1)
            lo_pt = 0
            while lo_pt < n_unknown:
                hi_pt = int(np.searchsorted(starts, starts[lo_pt] + target, side="right")) - 1
                hi_pt = max(min(hi_pt, n_unknown), lo_pt + 1)
                a, b = int(starts[lo_pt]), int(starts[hi_pt])
                if b > a:
                    loc = pt_sorted[a:b] - lo_pt
                    cnt = counts[lo_pt:hi_pt][loc]
                    first = (starts[lo_pt:hi_pt] - a)[loc]
                    pa = np.repeat(np.arange(b - a), cnt)
                    within = np.arange(len(pa)) - np.repeat(np.cumsum(cnt) - cnt, cnt)
                    pb = np.repeat(first, cnt) + within
                    chunks.append(
                        _TieChunk(
                            np.arange(a, b),
                            loc,
                            np.arange(lo_pt, hi_pt),
                            pa,
                            pb,
                            (starts[lo_pt:hi_pt] - a).astype(np.intp),
                        )
                    )
                lo_pt = hi_pt
        return tie_pos, chunks, len(order)

    def _reduced(
        self,
        lin: _Linearization,
        chunks: list[_TieChunk],
        lam: float,
        c: F64,
        xyz: F64,
        xyz0: F64,
        unknown: NDArray[np.intp],
    ) -> tuple[F64, F64, F64, list[tuple[F64, F64, F64]]]:
        """Reduced camera system ``(S, rhs, D_c)`` and per-chunk point blocks."""
        p = self.n_params
        s_mat = lin.n_cc.copy()
        diag = np.arange(p)
        s_mat[diag, diag] += self.prior_w
        grad = lin.g_c.copy()
        grad[:p] += self.prior_w * (c - self.x0)
        if self.con_n is not None:
            s_mat[:p, :p] += self.con_n
            grad[:p] += self.con_n @ (c - self.x0)
        d_c = s_mat[diag, diag].copy()
        if lam:
            s_mat[diag, diag] += lam * d_c
        rhs = -grad
        blocks = []
        n_pat = len(self.cols)
        for ch in chunks:
            a = lin.a_t[ch.obs]
            b = lin.b_t[ch.obs]
            we = lin.weight_t[ch.obs]
            r = lin.r_t[ch.obs]
            wb = b * we[:, :, None]
            # Observations are sorted by point: per-point sums are segment reductions.
            v = np.add.reduceat(
                b[:, 0, :, None] * wb[:, 0, None, :] + b[:, 1, :, None] * wb[:, 1, None, :],
                ch.starts,
                axis=0,
            )
            gx = np.add.reduceat(
                wb[:, 0] * r[:, 0, None] + wb[:, 1] * r[:, 1, None], ch.starts, axis=0
            )
            gpts = unknown[ch.pts]
            pw = self.point_prior_w[gpts]
            v += pw
            gx += np.einsum("pij,pj->pi", pw, xyz[gpts] - xyz0[gpts])
            d_x = v[:, [0, 1, 2], [0, 1, 2]].copy()
            if lam:
                v[:, [0, 1, 2], [0, 1, 2]] += lam * d_x
            try:
                vinv = np.linalg.inv(v)
                chol = np.linalg.cholesky(0.5 * (vinv + np.transpose(vinv, (0, 2, 1))))
            except np.linalg.LinAlgError:
                bad = _first_singular(v)
                raise AdjustmentError(
                    f"point {self.net.point_ids[self._unknown_ids[gpts[bad]]]!r}: its "
                    f"coordinates are not determined by its observations (rays parallel or "
                    f"too few); give it an a-priori sigma or remove it"
                ) from None
            # y = A^T W B per observation, (m, q, 3); z = y L with L L^T = V^-1.
            y = a[:, 0, :, None] * wb[:, 0, None, :] + a[:, 1, :, None] * wb[:, 1, None, :]
            z = np.matmul(y, chol[ch.pt])
            bx = -gx
            vb = np.matmul(vinv, bx[:, :, None])[:, :, 0]
            contrib = np.matmul(y, vb[ch.pt][:, :, None])[:, :, 0]
            gcols = self.cols[lin.gpat_t[ch.obs]]
            rhs_full = np.bincount(gcols.ravel(), weights=contrib.ravel(), minlength=p + 1)
            rhs = rhs - rhs_full
            ga = lin.gpat_t[ch.obs][ch.pair_a]
            gb = lin.gpat_t[ch.obs][ch.pair_b]
            keep = ga <= gb
            pa, pb, ga, gb = ch.pair_a[keep], ch.pair_b[keep], ga[keep], gb[keep]
            key = ga.astype(np.int64) * n_pat + gb
            order = np.argsort(key, kind="stable")
            ks = key[order]
            cut = np.flatnonzero(np.diff(ks)) + 1
            for seg in np.split(order, cut):
                if not seg.size:
                    continue
                ka, kb = int(ga[seg[0]]), int(gb[seg[0]])
                blk = np.tensordot(z[pa[seg]], z[pb[seg]], axes=([0, 2], [0, 2]))
                ca, cb = self.cols[ka], self.cols[kb]
                s_mat[np.ix_(ca, cb)] -= blk
                if ka != kb:
                    s_mat[np.ix_(cb, ca)] -= blk.T
            blocks.append((vinv, bx, d_x))
            del y, z
        return s_mat[:p, :p], rhs[:p], d_c, blocks

    def _back_substitute(
        self,
        lin: _Linearization,
        chunks: list[_TieChunk],
        blocks: list[tuple[F64, F64, F64]],
        delta_c: F64,
        n_unknown: int,
    ) -> tuple[F64, F64, F64]:
        """Point steps ``dX = V^-1 (b_x - W^T dc)`` and their gradient/diagonal terms."""
        dx = np.zeros((n_unknown, 3))
        bx_all = np.zeros((n_unknown, 3))
        dd_all = np.zeros((n_unknown, 3))
        dc_pad = np.concatenate([delta_c, [0.0]])
        for ch, (vinv, bx, d_x) in zip(chunks, blocks, strict=True):
            a = lin.a_t[ch.obs]
            b = lin.b_t[ch.obs]
            we = lin.weight_t[ch.obs]
            gcols = self.cols[lin.gpat_t[ch.obs]]
            adc = np.matmul(a, dc_pad[gcols][:, :, None])[:, :, 0]  # A dc, (m, 2)
            wb = b * we[:, :, None]
            wtdc = np.add.reduceat(
                wb[:, 0] * adc[:, 0, None] + wb[:, 1] * adc[:, 1, None], ch.starts, axis=0
            )
            dx[ch.pts] = np.matmul(vinv, (bx - wtdc)[:, :, None])[:, :, 0]
            bx_all[ch.pts] = bx
            dd_all[ch.pts] = d_x
        return dx, bx_all, dd_all

    def _solve_reduced(self, s_mat: F64, rhs: F64) -> tuple[F64, F64]:
        """Step of the active parameters and their unit-weight sigmas ``sqrt(S^-1_ii)``."""
        act = self.active
        delta = np.zeros(self.n_params)
        scale = np.full(self.n_params, np.inf)
        if not act.size:
            return delta, scale
        sa = s_mat[np.ix_(act, act)]
        d = np.sqrt(np.abs(np.diag(sa)))
        d = np.where(d > 0, d, 1.0)
        sh = sa / d[:, None] / d[None, :]
        factor = scipy.linalg.cho_factor(sh, lower=False, check_finite=False)
        delta[act] = scipy.linalg.cho_solve(factor, rhs[act] / d, check_finite=False) / d
        # diag(S^-1) from the triangular factor: S^-1 = U^-1 U^-T, row norms of U^-1.
        u_inv = scipy.linalg.solve_triangular(
            factor[0], np.eye(len(act)), lower=False, check_finite=False
        )
        scale[act] = np.sqrt(np.einsum("ij,ij->i", u_inv, u_inv)) / d
        return delta, scale

    # --------------------------------------------------------------- LM loop
    def _structure(self, obs: NDArray[np.intp]) -> _Structure:
        """Layout and tie-point structure of an observation set (cached for the last set)."""
        obs = np.asarray(obs, np.intp)
        if self._structure_cache is not None and np.array_equal(self._structure_cache[0], obs):
            st = self._structure_cache[1]
            # Fresh guesses: they may have improved since the structure was built.
            st.lay.line_guess[:] = self.line_guess[st.lay.obs]
            st.lay.rate_guess[:] = self.rate_guess[st.lay.obs]
            return st
        lay = self._layout(obs)
        pts = lay.point
        unknown = np.unique(pts[~self.point_fixed[pts]])
        umap = np.full(self.net.n_points, -1, np.intp)
        umap[unknown] = np.arange(len(unknown))
        tie_pos, chunks, n_tie = self._tie_structure(lay.obs, umap[pts], len(unknown))
        st = _Structure(lay, unknown, tie_pos, chunks, n_tie)
        self._structure_cache = (obs.copy(), st)
        return st

    def linearize(self, c: F64, xyz: F64, obs: NDArray[np.intp], xyz0: F64) -> _Linearization:
        """Residuals, validity and normal-equation pieces of ``obs`` at ``(c, xyz)``.

        With the plain least-squares loss the result can be handed to :meth:`run` as its
        first linearisation (``initial=``), sparing one pass over the observations.
        """
        st = self._structure(obs)
        lin = self._linearize(c, xyz, st.lay, st.tie_pos, st.n_tie, st.unknown, xyz0)
        self.line_guess[lin.obs] = np.where(lin.valid, lin.line, self.line_guess[lin.obs])
        self.rate_guess[lin.obs] = lin.rate
        return lin

    def run(
        self,
        c: F64,
        xyz: F64,
        obs: NDArray[np.intp],
        xyz0: F64,
        *,
        initial: _Linearization | None = None,
    ) -> tuple[F64, F64, LmReport, _Linearization, dict[str, object]]:
        """Minimise the cost over the observations ``obs`` from ``(c, xyz)``.

        Args:
            c: Initial global parameter vector.
            xyz: Initial coordinates of every network point, ``(P, 3)``.
            obs: Observation indices taking part.
            xyz0: A priori point coordinates (for weighted points).
            initial: A linearisation of exactly these observations at ``(c, xyz)`` with
                the current loss (from :meth:`linearize`), reused instead of a new pass.

        Returns:
            ``(c, xyz, report, final linearisation, statistics)``.

        Raises:
            AdjustmentError: Degenerate normal equations or divergence.
        """
        t_start = time.perf_counter()
        cfg = self.cfg
        net = self.net
        st = self._structure(obs)
        lay, unknown, tie_pos, chunks, n_tie = st.lay, st.unknown, st.tie_pos, st.chunks, st.n_tie
        obs = lay.obs
        self._unknown_ids = unknown
        xyz = xyz.copy()
        c = c.copy()
        rep = LmReport()

        def linearize(cc: F64, xx: F64) -> _Linearization:
            rep.evaluations += 1
            return self._linearize(cc, xx, lay, tie_pos, n_tie, unknown, xyz0)

        if initial is not None and np.array_equal(initial.obs, obs):
            lin = initial
            rep.evaluations += 1  # made outside, but part of this run's work
        else:
            lin = linearize(c, xyz)
        if not np.all(lin.valid):
            bad = np.flatnonzero(~lin.valid)
            raise AdjustmentError(
                f"{bad.size} observation(s) cannot be projected with the "
                f"initial cameras (first: {net.obs_ids[obs[bad[0]]]!r})"
            )
        lay.line_guess[:] = lin.line
        lay.rate_guess[:] = lin.rate
        rep.cost_initial = lin.cost
        self._check_rank(lin, chunks, c, xyz, xyz0, unknown, "initial")
        # A later outlier round starts near the optimum: keep the damping it ended with.
        lam = cfg.initial_lambda if self.last_lambda is None else self.last_lambda
        nu = 2.0
        it = 0
        while it < cfg.max_iterations:
            s_mat, rhs, d_c, blocks = self._reduced(lin, chunks, lam, c, xyz, xyz0, unknown)
            try:
                delta_c, sig_c = self._solve_reduced(s_mat, rhs)
            except np.linalg.LinAlgError:
                lam = max(lam * nu, cfg.min_lambda * 10.0)
                nu *= 2.0
                if lam > cfg.max_lambda:
                    raise AdjustmentError(
                        "the damped normal equations are not positive "
                        "definite at any damping; the problem is "
                        "degenerate"
                    ) from None
                continue
            dx, bx, dd = self._back_substitute(lin, chunks, blocks, delta_c, len(unknown))
            grad_c = _camera_gradient(lin, self, c)
            pred = 0.5 * (
                lam * float(np.sum(d_c * delta_c**2))
                - float(grad_c @ delta_c)
                + lam * float(np.sum(dd * dx**2))
                + float(np.sum(bx * dx))
            )
            # IRLS (a robust loss) converges only linearly: stop at a looser floor.
            ftol = cfg.ftol if self.loss == "linear" else max(cfg.ftol, _IRLS_FTOL)
            if it > 0 and lam <= 10.0 * cfg.min_lambda and pred <= ftol * max(lin.cost, 1e-300):
                # The Gauss-Newton step would gain less than ftol: evaluating it would
                # cost a full pass over the observations for nothing.
                rep.converged, rep.reason = True, "predicted cost decrease below ftol"
                break
            c_new = c + delta_c
            xyz_new = xyz.copy()
            xyz_new[unknown] += dx
            saved = lay.line_guess.copy()
            saved_rate = lay.rate_guess.copy()
            new = linearize(c_new, xyz_new)
            actual = lin.cost - new.cost
            step_c = np.abs(delta_c) / sig_c
            step_x = np.abs(dx) * np.sqrt(np.maximum(dd, 0.0))
            step = max(float(step_c.max(initial=0.0)), float(step_x.max(initial=0.0)))
            if np.isfinite(new.cost) and actual > 0:
                rho = actual / pred if pred > 0 else 1.0
                # Nielsen's update, but allowed to fall by 10x per step and to reach 0:
                # adjustment problems are nearly linear yet badly conditioned (positions
                # against attitudes), and any damping left slows the weak directions down
                # to linear convergence; pure Gauss-Newton converges quadratically.
                lam *= max(0.1, 1.0 - (2.0 * rho - 1.0) ** 3)
                if lam < cfg.min_lambda:
                    lam = 0.0
                nu = 2.0
                it += 1
                c, xyz, lin = c_new, xyz_new, new
                lay.line_guess[:] = np.where(new.valid, new.line, saved)
                lay.rate_guess[:] = np.where(new.valid, new.rate, np.nan)
                rep.history.append((it, lin.cost, lam))
                if self.progress is not None:
                    self.progress(
                        f"iteration {it}: cost {lin.cost:.6g}, lambda {lam:.2g}, "
                        f"step {step:.3g} sigma"
                    )
                if actual <= ftol * max(lin.cost, 1e-300):
                    rep.converged, rep.reason = True, "relative cost change below ftol"
                    break
                if step <= cfg.xtol:
                    rep.converged, rep.reason = True, "step below xtol"
                    break
            else:
                lay.line_guess[:] = saved
                lay.rate_guess[:] = saved_rate
                # A rejected step that is tiny, or predicted to gain nothing, means the
                # cost is at its floor of rounding (projections are exact to ~1e-9 px).
                if np.isfinite(new.cost) and (
                    step <= _STEP_FLOOR_SIGMA or pred <= 1e-14 * lin.cost
                ):
                    rep.converged, rep.reason = True, "no further decrease possible"
                    break
                lam = max(lam * nu, cfg.min_lambda * 10.0)
                nu *= 2.0
                if lam > cfg.max_lambda:
                    raise AdjustmentError(
                        f"Levenberg-Marquardt diverged: the cost ({lin.cost:.6g}) did not "
                        f"decrease even with damping {lam:.2g}; check the observations and "
                        f"the initial cameras"
                    )
        else:
            rep.reason = f"maximum of {cfg.max_iterations} iterations reached"
        self.line_guess[obs] = lay.line_guess
        self.rate_guess[obs] = lay.rate_guess
        rep.iterations = it
        rep.cost_final = lin.cost
        self.last_lambda = min(lam, cfg.initial_lambda)
        stats = self._statistics(lin, chunks, c, xyz, xyz0, unknown)
        rep.seconds = time.perf_counter() - t_start
        return c, xyz, rep, lin, stats

    # ------------------------------------------------------------ statistics
    def _check_rank(
        self,
        lin: _Linearization,
        chunks: list[_TieChunk],
        c: F64,
        xyz: F64,
        xyz0: F64,
        unknown: NDArray[np.intp],
        when: str,
    ) -> None:
        act = self.active
        if not act.size:
            return
        # Parameters that no observation (and no prior) touches at all.
        full_diag = np.diag(lin.n_cc)[: self.n_params][act] + self.prior_w[act]
        if self.con_n is not None:
            full_diag = full_diag + np.diag(self.con_n)[act]
        zero = np.flatnonzero(~(full_diag > 0))
        if zero.size:
            names = [self.names[act[i]] for i in zero[:8]]
            raise AdjustmentError(
                f"{zero.size} parameter(s) have no observations at all ({when} cameras): "
                f"{', '.join(names)}{' ...' if zero.size > 8 else ''}; fix them or give them "
                f"an a-priori sigma"
            )
        s_mat, _, _, _ = self._reduced(lin, chunks, 0.0, c, xyz, xyz0, unknown)
        sa = s_mat[np.ix_(act, act)]
        # Scaled by the diagonal before the point elimination: a parameter that the
        # points absorb entirely (a datum defect) shows up as a (near-)zero eigenvalue.
        d = np.sqrt(full_diag)
        sh = sa / d[:, None] / d[None, :]
        ev, vec = np.linalg.eigh(0.5 * (sh + sh.T))
        rcond = max(ev[0], 0.0) / ev[-1] if ev[-1] > 0 else 0.0
        if not rcond > self.cfg.min_rcond:
            weights = np.abs(vec[:, 0])
            top = np.argsort(weights)[::-1][:6]
            names = [f"{self.names[act[i]]} ({weights[i]:.2f})" for i in top if weights[i] > 0.05]
            raise AdjustmentError(
                f"the reduced normal matrix is singular (reciprocal condition "
                f"{rcond:.2g} < {self.cfg.min_rcond:g}, {when} cameras): the observations do "
                f"not determine a combination of {', '.join(names)}; fix or weight these "
                f"parameters (e.g. a datum: a fixed camera or control points)"
            )

    def _statistics(
        self,
        lin: _Linearization,
        chunks: list[_TieChunk],
        c: F64,
        xyz: F64,
        xyz0: F64,
        unknown: NDArray[np.intp],
    ) -> dict[str, object]:
        p = self.n_params
        s_mat, _, _, _ = self._reduced(lin, chunks, 0.0, c, xyz, xyz0, unknown)
        act = self.active
        # v^T P v with the final (robust) weights, plus the pseudo-observations.
        vtpv = float(np.sum(lin.weight * np.where(lin.valid[:, None], lin.r, 0.0) ** 2))
        vtpv += 2.0 * self._prior_cost(c)
        n_prior = int(np.count_nonzero(self.prior_w)) + len(self.con_w)
        if len(unknown):
            dx = xyz[unknown] - xyz0[unknown]
            vtpv += _quadratic(self.point_prior_w[unknown], dx)
            n_prior += int(np.count_nonzero(self.point_prior_axis_w[unknown]))
        n_obs = 2 * int(np.count_nonzero(lin.valid))
        n_unk = len(act) + 3 * len(unknown)
        dof = n_obs + n_prior - n_unk
        if dof <= 0:
            raise AdjustmentError(
                f"no redundancy: {n_obs // 2} observations ({n_obs} equations) and {n_prior} "
                f"a-priori constraints for {n_unk} unknowns; add observations or fix "
                f"parameters"
            )
        sigma0 = math.sqrt(vtpv / dof)
        cov = np.zeros((p, p))
        cofactor = np.zeros((p, p))
        if act.size:
            sa = s_mat[np.ix_(act, act)]
            d = np.sqrt(np.abs(np.diag(sa)))
            d = np.where(d > 0, d, 1.0)
            sh = sa / d[:, None] / d[None, :]
            try:
                factor = scipy.linalg.cho_factor(sh, lower=False, check_finite=False)
                inv = scipy.linalg.cho_solve(factor, np.eye(len(act)), check_finite=False)
            except np.linalg.LinAlgError:
                self._check_rank(lin, chunks, c, xyz, xyz0, unknown, "adjusted")
                raise AdjustmentError(
                    "the reduced normal matrix is not positive definite at the solution"
                ) from None
            cofactor[np.ix_(act, act)] = inv / d[:, None] / d[None, :]
            cov = sigma0**2 * cofactor
        sig = np.sqrt(np.diag(cov))
        with np.errstate(divide="ignore", invalid="ignore"):
            corr = cov / sig[:, None] / sig[None, :]
        corr[~np.isfinite(corr)] = 0.0
        return {
            "sigma0": sigma0,
            "dof": dof,
            "vtpv": vtpv,
            "covariance": cov,
            "cofactor": cofactor,
            "sigma": sig,
            "correlation": corr,
            "n_unknowns": n_unk,
            "n_equations": n_obs + n_prior,
        }


def _quadratic(w: F64, dx: F64) -> float:
    """``sum_p dx_p^T W_p dx_p`` of per-point 3x3 weights."""
    return float(np.einsum("pi,pij,pj->", dx, w, dx))


def _camera_gradient(lin: _Linearization, solver: BundleSolver, c: F64) -> F64:
    """Gradient of the cost w.r.t. the camera parameters (observations and priors)."""
    p = solver.n_params
    grad = lin.g_c[:p] + solver.prior_w * (c - solver.x0)
    if solver.con_n is not None:
        grad = grad + solver.con_n @ (c - solver.x0)
    return grad


def _first_singular(v: F64) -> int:
    for i in range(len(v)):
        try:
            np.linalg.cholesky(v[i])
        except np.linalg.LinAlgError:
            return i
    return 0
