"""Levenberg-Marquardt bundle adjustment on the reduced normal equations.

Unknowns: the camera parameters ``c`` of every :class:`~planetref.adjust.models.
AdjustableCamera` (concatenated into one global vector) and the coordinates ``X_j`` of
the ground points that are not fixed. Observations: ``r_m = projected(line, sample) -
observed`` with per-axis weights ``1/sigma^2`` times a robust IRLS weight; fixed and
weighted parameters and weighted points add pseudo-observations ``(p - p0)/sigma``.

The engine is split by concept: :mod:`planetref.adjust.linearization` (residuals and
normal equations accumulated per pattern), :mod:`planetref.adjust.schur` (elimination
of the points, reduced camera system, back-substitution),
:mod:`planetref.adjust.statistics` (rank check, sigma0, covariance) and
:mod:`planetref.adjust.robust` (robust losses). This module holds the set-up and the
Levenberg-Marquardt driver: damping is Marquardt's (``lambda x diag``) on the full
system, points included, with Nielsen's update of ``lambda``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from planetref.adjust.config import SolverConfig
from planetref.adjust.linearization import (
    Layout,
    Linearization,
    LinearizationMixin,
    chunk_shares,
    group_order,
    run_shares,
)
from planetref.adjust.lm_steps import (
    ANDERSON_DEPTH,
    CORRECT_MAX_LAMBDA,
    LmReport,
    anderson_correction,
    cost_resolution,
)
from planetref.adjust.models import AdjustableCamera, Evaluation
from planetref.adjust.robust import robust_rho
from planetref.adjust.schur import Iterate, SchurMixin, Structure
from planetref.adjust.statistics import StatisticsMixin
from planetref.arrays import F64
from planetref.control.network import Network, PointFrames, PointMatrices
from planetref.errors import AdjustmentError
from planetref.runtime.threads import compute_threads

__all__ = ["BundleSolver", "LmReport", "robust_rho"]

log = logging.getLogger("planetref.adjust")
#: Steps below this many sigmas that do not lower the cost are rounding noise.
_STEP_FLOOR_SIGMA = 1e-6
#: Relative cost decrease below which a robust (IRLS) run stops.
_IRLS_FTOL = 1e-9


class BundleSolver(LinearizationMixin, SchurMixin, StatisticsMixin):
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
        #: Accumulate the normal equations compiled (numba) when available; ``False``
        #: runs the numpy reference.
        self.compiled_normal = True
        self._active_cache: dict[
            tuple[int, int], tuple[NDArray[np.intp] | None, NDArray[np.intp]]
        ] = {}
        self.x0 = np.concatenate([m.x0 for m in models]) if p else np.zeros(0)
        self.names = [f"{m.camera_id}:{n}" for m in models for n in m.names]
        self.units = [u for m in models for u in m.units]
        self.refresh_modes()
        sig = network.point_sigma_m
        # Column by column: numpy's reductions along a length-3 axis are slow on (P, 3).
        zero = [sig[:, k] == 0 for k in range(3)]
        fixed_pt = zero[0] & zero[1] & zero[2]
        partial = (zero[0] | zero[1] | zero[2]) & ~fixed_pt
        if np.any(partial):
            i = int(np.flatnonzero(partial)[0])
            raise AdjustmentError(
                f"point {network.point_ids[i]!r}: a sigma of 0 (fixed) on "
                f"some axes only is not supported"
            )
        self.point_fixed = fixed_pt
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
        self._structure_cache: tuple[NDArray[np.intp], Structure] | None = None
        self.tie_spare = None

    # ------------------------------------------------------------------ setup
    def set_point_sigma(self, sigma_m: F64) -> None:
        """Set the a-priori sigmas of the points, ``(P, 3)`` in each point's sigma frame.

        0 and inf (fixed and free) must stay where they were: only the weights of
        weighted points change (variance component estimation).
        """
        sig = _read_only(sigma_m)
        self.point_sigma = sig
        # The weighted points (0 < sigma < inf on some axis), column by column: no (P, 3)
        # temporaries for a network of fixed or free points only.
        ok = [(sig[:, k] > 0) & (sig[:, k] < np.inf) for k in range(3)]
        on = np.flatnonzero(ok[0] | ok[1] | ok[2])
        s_on = sig[on]
        # 1/sigma^2 where 0 < sigma < inf, else 0.
        with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
            w = 1.0 / (s_on * s_on)
        w[~((s_on > 0) & (s_on < np.inf))] = 0.0
        #: Per-axis weights in the sigma frame, indexed like ``(P, 3)`` (zero for the
        #: fixed and free points: only weighted ones are held).
        self.point_prior_axis_w = PointMatrices(len(sig), on, w)
        fr = self.net.point_frame_matrices(on)
        #: Weight matrices ``R^T diag(w) R`` in body-fixed XYZ, indexed like ``(P, 3, 3)``.
        self.point_prior_w = PointMatrices(
            len(sig),
            on,
            np.einsum("pki,pk,pkj->pij", fr, w, fr),
            index=self.point_prior_axis_w.index,
        )

    @property
    def point_frame(self) -> PointFrames:
        """Rotations from body-fixed XYZ to each point's sigma frame.

        Indexed like ``(P, 3, 3)``, computed for the indexed points only
        (:meth:`~planetref.control.network.Network.point_frame_matrices`).
        """
        return PointFrames(self.net)

    def set_obs_sigma(self, sigma_px: F64) -> None:
        """Set the sigmas of the image measures, ``(M, 2)`` pixels (line, sample)."""
        self.obs_sigma = _read_only(sigma_px)
        self.obs_w0 = 1.0 / self.obs_sigma**2  # (M, 2), line then sample
        self._structure_cache = None

    def release_layout(self) -> None:
        """Drop the cached layout and groups of the last observation set.

        They are rebuilt on the next linearisation; letting them go before work that
        no longer linearises keeps the per-observation copies out of its memory peak.
        """
        self._structure_cache = None
        self._group_cache = None

    def set_models(self, models: list[AdjustableCamera]) -> None:
        """Adjust with other parameterisations of the same cameras (weak groups weighted).

        Args:
            models: One per camera, same order and parameter counts as at construction.

        Raises:
            ValueError: A model's parameter count differs (a programming error).
        """
        sizes = [len(m.x0) for m in models]
        if sizes != list(np.diff(self.offsets)):
            raise ValueError(f"parameter counts {sizes} differ from {list(np.diff(self.offsets))}")
        self.models = list(models)
        self.refresh_modes()

    def refresh_modes(self) -> None:
        """Read modes, sigmas and constraints from the models."""
        self.mode = (
            np.concatenate([m.mode for m in self.models]) if self.n_params else np.zeros(0, np.int8)
        )
        self.sigma = (
            np.concatenate([m.sigma for m in self.models]) if self.n_params else np.zeros(0)
        )
        self.active = np.flatnonzero(self.mode != 2)
        self._active_tables()
        with np.errstate(divide="ignore"):
            self.prior_w = np.where(self.mode == 1, 1.0 / self.sigma**2, 0.0)
        # Linear pseudo-observations A (c - x0) = 0 of the models (e.g. smooth weak
        # nodes), gathered into one global matrix; their normal contribution is A^T W A.
        rows, weights = [], []
        for i, m in enumerate(self.models):
            con = m.constraints
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

    def _camera_gradient(self, lin: Linearization, c: F64) -> F64:
        """Gradient of the cost w.r.t. the camera parameters (observations and priors)."""
        p = self.n_params
        grad = lin.g_c[:p] + self.prior_w * (c - self.x0)
        if self.con_n is not None:
            grad = grad + self.con_n @ (c - self.x0)
        return grad

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

        One group per (camera, CCD) and kind of point: the observations of fixed points,
        then those of unknown points (eliminated by the Schur complement). Within a group
        the positions are sorted by the whole part of the observed line (stable: ties
        keep the order of ``obs``): observations that share a Lagrange window (a
        pattern) then form contiguous runs, so the normal equations accumulate from
        array views instead of gathered copies, and long runs take the moment form of
        the compiled accumulation (mixed, the two kinds would break every run: the
        observations of fixed points also sum into their slot's matrix).
        """
        cached = self._group_cache
        if cached is not None and np.array_equal(cached[0], obs):
            return cached[1]
        net = self.net
        base = 2 * max(len(cam.ccd_names) for cam in net.cameras)
        unknown = ~self.point_fixed.take(net.obs_point.take(obs))
        key = (net.obs_camera[obs].astype(np.int64) * base + 2 * net.obs_ccd[obs]) + unknown
        order = group_order(key, net.obs_line[obs])
        ks = key[order]
        cut = np.flatnonzero(np.diff(ks)) + 1
        out = []
        for seg in np.split(order, cut):
            if seg.size:
                k = int(key[seg[0]])
                out.append((k // base, (k % base) // 2, seg))
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
        groups = self._groups(obs)
        pos = np.concatenate([g[2] for g in groups]) if groups else np.zeros(0, np.intp)
        stops = np.cumsum([len(g) for _, _, g in groups], dtype=np.intp)
        ranges = [
            (mi, ccd, int(b - len(g)), int(b))
            for (mi, ccd, g), b in zip(groups, stops, strict=True)
        ]
        parts = chunk_shares(ranges, self.cfg.chunk_size)

        def run(k: int) -> None:
            for mi, ccd, a, b in parts[k]:
                sel = pos[a:b]
                o = obs[sel]
                ev = self.models[mi].evaluate(
                    c[self.offsets[mi] : self.offsets[mi + 1]],
                    xyz[self.net.obs_point[o]],
                    ccd,
                    self.line_guess[o],
                    rate_guess=self.rate_guess[o],
                    partials=False,
                )
                line[sel], sample[sel], valid[sel] = ev.line, ev.sample, ev.valid
                self._remember(o, ev)  # disjoint rows per chunk

        run_shares(len(parts), run, compute_threads(self.cfg.threads))
        return line, sample, valid

    def _remember(self, o: NDArray[np.intp], ev: Evaluation) -> None:
        """Keep an evaluation's lines (and rates) as the next starting guesses."""
        self.line_guess[o] = np.where(ev.valid, ev.line, self.line_guess[o])
        if ev.line_rate is not None:
            self.rate_guess[o] = np.where(ev.valid, ev.line_rate, np.nan)

    # --------------------------------------------------------------- LM loop
    def _structure(self, obs: NDArray[np.intp], guesses: bool = True) -> Structure:
        """Layout and tie-point structure of an observation set (cached for the last set).

        Args:
            obs: Observation indices.
            guesses: Refresh a cached layout's line and rate guesses from the solver's
                (``False`` when the caller sets them itself or evaluates nothing; see
                :meth:`refresh_guesses`).
        """
        obs = np.asarray(obs, np.intp)
        if self._structure_cache is not None and np.array_equal(self._structure_cache[0], obs):
            st = self._structure_cache[1]
            if guesses:
                self.refresh_guesses(st.lay)
            return st
        lay = self._layout(obs)
        pts = lay.point
        # The general case first: it gives ``chunks`` its type.
        if lay.fixed_xyz is None:
            unknown = np.unique(pts[~self.point_fixed[pts]])
            umap = np.full(self.net.n_points, -1, np.intp)
            umap[unknown] = np.arange(len(unknown))
            tie_pos, chunks, n_tie = self._tie_structure(lay.obs, umap[pts], len(unknown))
        else:  # every point fixed: nothing to eliminate
            unknown = np.zeros(0, np.intp)
            tie_pos, chunks, n_tie = np.full(len(lay.obs), -1, np.intp), [], 0
        st = Structure(lay, unknown, tie_pos, chunks, n_tie)
        self._structure_cache = (obs.copy(), st)
        return st

    def refresh_guesses(self, lay: Layout) -> None:
        """Copy the solver's guesses into a layout: they may have improved since it was built."""
        self.line_guess.take(lay.obs, out=lay.line_guess)
        self.rate_guess.take(lay.obs, out=lay.rate_guess)

    def linearize(self, c: F64, xyz: F64, obs: NDArray[np.intp], xyz0: F64) -> Linearization:
        """Residuals, validity and normal-equation pieces of ``obs`` at ``(c, xyz)``.

        With the plain least-squares loss the result can be handed to :meth:`run` as its
        first linearisation (``initial=``), sparing one pass over the observations.
        """
        t0, c0 = time.perf_counter(), time.process_time()
        st = self._structure(obs)
        lin = self._linearize(c, xyz, st.lay, st.tie_pos, st.n_tie, st.unknown, xyz0)
        if np.all(lin.valid):
            self.line_guess[lin.obs] = lin.line
        else:
            self.line_guess[lin.obs] = np.where(lin.valid, lin.line, self.line_guess[lin.obs])
        self.rate_guess[lin.obs] = lin.rate
        lin.seconds = time.perf_counter() - t0
        lin.cpu_seconds = time.process_time() - c0
        return lin

    def run(
        self,
        c: F64,
        xyz: F64,
        obs: NDArray[np.intp],
        xyz0: F64,
        *,
        initial: Linearization | None = None,
        check_rank: bool = True,
    ) -> tuple[F64, F64, LmReport, Linearization, dict[str, object]]:
        """Minimise the cost over the observations ``obs`` from ``(c, xyz)``.

        Args:
            c: Initial global parameter vector.
            xyz: Initial coordinates of every network point, ``(P, 3)``.
            obs: Observation indices taking part.
            xyz0: A priori point coordinates (for weighted points).
            initial: A linearisation of exactly these observations at ``(c, xyz)`` with
                the current loss (from :meth:`linearize`), reused instead of a new pass.
                Handed over: once a step replaces it, its tie arrays are reused
                (:meth:`retire`).
            check_rank: Check the rank of the reduced system first (``False`` when only
                the weights changed since a run that checked it: the rank cannot change).

        Returns:
            ``(c, xyz, report, final linearisation, statistics)``.

        Raises:
            AdjustmentError: Degenerate normal equations or divergence.
        """
        t_start = time.perf_counter()
        c_start = time.process_time()
        cfg = self.cfg
        net = self.net
        # With an initial linearisation the guesses are set from it below.
        st = self._structure(obs, guesses=initial is None)
        lay, unknown, tie_pos, chunks, n_tie = st.lay, st.unknown, st.tie_pos, st.chunks, st.n_tie
        obs = lay.obs
        self._unknown_ids = unknown
        # A copy where points move (steps make new arrays; the caller's stays as it was).
        xyz = xyz.copy() if len(unknown) else xyz
        c = c.copy()
        rep = LmReport()

        def linearize(cc: F64, xx: F64) -> Linearization:
            rep.evaluations += 1
            return self._linearize(cc, xx, lay, tie_pos, n_tie, unknown, xyz0)

        if initial is not None and np.array_equal(initial.obs, obs):
            lin, initial = initial, None  # held once: it goes when a step replaces it
            # Made outside, but part of this run's work (its time too).
            rep.evaluations += 1
            t_start -= lin.seconds
            c_start -= lin.cpu_seconds
        else:
            if initial is not None:  # not of these observations: start from the solver's
                self.refresh_guesses(lay)
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
        if check_rank:
            self._check_rank(Iterate(lin, chunks, c, xyz, xyz0, unknown), "initial")
        # A later outlier round starts near the optimum: keep the damping it ended with.
        lam = cfg.initial_lambda if self.last_lambda is None else self.last_lambda
        nu = 2.0
        it = 0
        # ``(c_j, f_j)`` of the previous consecutive accepted undamped iterations: the
        # iterate and its plain camera step (:func:`anderson_correction`).
        history: list[tuple[F64, F64]] = []
        correct = True  # False right after a corrected step was rejected
        last_s: tuple[Linearization, F64] | None = None
        while it < cfg.max_iterations:
            at = Iterate(lin, chunks, c, xyz, xyz0, unknown)
            s_mat, rhs, d_c, blocks = self._reduced(at, lam)
            # Undamped at the final iterate, it is the statistics' S too.
            last_s = (lin, s_mat) if lam == 0.0 else None
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
            # Damping of 1e-6 of the diagonal or less leaves the Gauss-Newton step as it is.
            gn_step = delta_c if lam <= CORRECT_MAX_LAMBDA and correct else None
            corr = anderson_correction(history, c, gn_step, s_mat)
            correct = True
            if corr is not None:
                # The model's gain is that of the plain step (what the convergence and
                # damping rules read); with the points following (back substitution)
                # it is the reduced model's ``rhs . dc - dc^T S dc / 2``.
                pred = float(rhs @ delta_c) - 0.5 * float(delta_c @ s_mat @ delta_c)
                delta_c = delta_c + corr  # a new array: gn_step stays the plain step
            dx, bx, dd = self._back_substitute(lin, chunks, blocks, delta_c, len(unknown))
            if corr is None:
                grad_c = self._camera_gradient(lin, c)
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
            if len(unknown):
                xyz_new = xyz.copy()
                xyz_new[unknown] += dx
            else:
                xyz_new = xyz  # nothing moves (every point fixed): no copy of (P, 3)
            # The models read the guesses and never write them: a rejected step leaves
            # them as they are, an accepted one replaces them below.
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
                if gn_step is None:
                    history.clear()
                else:  # the iterate left behind and its plain step
                    history[:] = [*history[-(ANDERSON_DEPTH - 1) :], (c, gn_step)]
                self.retire(lin)
                c, xyz, lin = c_new, xyz_new, new
                _take_guesses(lay, new)
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
            elif np.isfinite(new.cost) and max(pred, -actual) <= cost_resolution(lin):
                # Neither the predicted gain nor the rise is above what the projections
                # can resolve in the cost: the comparison says nothing, while the step
                # is the (nearly) Gauss-Newton step of an almost linear problem. Take it
                # and stop (rejecting it would leave the solution wherever the cost's
                # rounding noise happened to stop it).
                it += 1
                self.retire(lin)
                c, xyz, lin = c_new, xyz_new, new
                _take_guesses(lay, new)
                rep.history.append((it, lin.cost, lam))
                rep.converged, rep.reason = True, "step gain below the cost's resolution"
                break
            else:
                history.clear()
                self.retire(new)
                if corr is not None:
                    # Not judged by a corrected step: the plain one comes next.
                    correct = False
                    continue
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
        self.tie_spare = None  # not held beyond the run
        undamped = last_s[1] if last_s is not None and last_s[0] is lin else None
        stats = self._statistics(Iterate(lin, chunks, c, xyz, xyz0, unknown), undamped)
        rep.seconds = time.perf_counter() - t_start
        rep.cpu_seconds = time.process_time() - c_start
        return c, xyz, rep, lin, stats


def _take_guesses(lay: Layout, lin: Linearization) -> None:
    """Start the next evaluation from ``lin``'s lines and rates where it is valid."""
    np.copyto(lay.line_guess, lin.line, where=lin.valid)
    lay.rate_guess[:] = np.where(lin.valid, lin.rate, np.nan)


def _read_only(a: F64) -> F64:
    """A read-only float64 view of ``a`` (no copy where it is float64 already).

    The solver only replaces its sigma arrays, never writes into them: a view spares
    the copy (tens of MB at a million observations) and a write would raise instead of
    changing the caller's array.
    """
    view = np.asarray(a, np.float64).view()
    view.flags.writeable = False
    return view
