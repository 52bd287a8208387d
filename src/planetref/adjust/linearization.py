"""Linearisation of the observations: residuals, weights and normal equations per pattern.

One pass over the observations of an LM run (:class:`LinearizationMixin`, mixed into
:class:`~planetref.adjust.solver.BundleSolver`): the models evaluate residuals and
partials in chunks of one (camera, CCD) group; the normal equations of the camera
parameters are accumulated per *pattern* (observations that depend on the same
parameters) with dense BLAS products over the pattern's active columns only, so
nothing of size ``M x n_params`` is ever formed; the partials of observations on
unknown points are kept (tie arrays) for the Schur complement
(:mod:`planetref.adjust.schur`).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from planetref.adjust.robust import robust_rho
from planetref.arrays import F64
from planetref.runtime.optional import optional_module
from planetref.runtime.threads import compute_threads

if TYPE_CHECKING:
    from planetref.adjust.config import SolverConfig
    from planetref.adjust.models import AdjustableCamera, Evaluation
    from planetref.control.network import Network, PointMatrices

__all__ = ["LinearizationMixin", "chunk_shares", "group_kernels", "run_shares"]


@dataclass
class Linearization:
    cost: float
    r: F64  # (M, 2) residuals (line, sample)
    valid: NDArray[np.bool_]
    line: F64  # projected lines
    s: F64  # squared normalised residuals
    weight: F64  # (M, 2) effective weights (robust x 1/sigma^2); the layout's w0 when equal
    n_cc: F64  # (P+1, P+1) sum A^T W A
    g_c: F64  # (P+1,) sum A^T W r
    a_t: F64  # (Mt, 2, q) camera partials of observations on unknown points
    b_t: F64  # (Mt, 2, 3)
    gpat_t: NDArray[np.intp]
    weight_t: F64  # (Mt, 2) weights in the order of a_t
    r_t: F64  # (Mt, 2) residuals in the order of a_t (0 where invalid)
    rate: F64  # (M,) the models' line-rate hints (NaN if none)
    obs: NDArray[np.intp]  # network observation index of each row
    slot_n: F64  # (n_slot, P_m + 1, P_m + 1) A^T W A per slot (see Layout.slot)
    loss: str  # the loss its weights were made with
    seconds: float = 0.0  # wall and CPU time of a linearisation made by ``linearize``
    cpu_seconds: float = 0.0


@dataclass
class Layout:
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
    #: Per row, the slot of an observation of a fixed point: one per (point kind,
    #: camera, CCD), the image groups of the variance components; -1 for observations
    #: of unknown points (or when the slot matrices would be too large).
    slot: NDArray[np.intp]
    slot_obs: NDArray[np.intp]  # one network observation of each slot
    slot_size: int  # P_m + 1 of the largest model


#: Largest total size of the per-slot normal matrices (bytes); beyond it the redundancy
#: numbers are computed from a fresh evaluation instead.
_SLOT_BYTES = 64 * 2**20


class LinearizationMixin:
    """Linearisation of a :class:`~planetref.adjust.solver.BundleSolver`.

    Uses the solver's ``net``, ``models``, ``offsets``, ``pat_offsets``, ``cols``,
    ``n_params``, ``q``, ``cfg``, ``point_fixed``, ``obs_w0``, ``point_prior_w``,
    ``line_guess``, ``rate_guess``, ``loss``, ``threshold``, ``_groups``,
    ``_prior_cost`` and ``_active_cache``.
    """

    # The host's state and methods used here, set by BundleSolver (a typed contract;
    # annotations only, nothing is defined at run time).
    net: Network
    models: list[AdjustableCamera]
    cfg: SolverConfig
    offsets: NDArray[np.intp]
    pat_offsets: NDArray[np.intp]
    cols: NDArray[np.intp]
    n_params: int
    q: int
    mode: NDArray[np.int8]
    compiled_normal: bool
    point_fixed: NDArray[np.bool_]
    obs_w0: F64
    point_prior_w: PointMatrices
    line_guess: F64
    rate_guess: F64
    loss: str
    threshold: F64 | float
    _active_cache: dict[tuple[int, int], tuple[NDArray[np.intp] | None, NDArray[np.intp]]]
    #: The tie arrays ``(a_t, b_t, gpat_t)`` of a retired linearisation, or ``None``
    #: (:meth:`retire`): the next linearisation writes into them.
    tie_spare: tuple[F64, F64, NDArray[np.intp]] | None
    _groups: Callable[[NDArray[np.intp]], list[tuple[int, int, NDArray[np.intp]]]]
    _prior_cost: Callable[[F64], float]

    def _layout(self, obs: NDArray[np.intp]) -> Layout:
        groups = self._groups(obs)
        order = np.concatenate([g[2] for g in groups]) if groups else np.zeros(0, np.intp)
        obs = obs[order]
        ranges = []
        a = 0
        for mi, ccd, pos in groups:
            ranges.append((mi, ccd, a, a + len(pos)))
            a += len(pos)
        net = self.net
        # ``take`` along axis 0: numpy's fancy indexing of (M, 2) and (M, 3) arrays is
        # several times slower than of 1-D ones.
        point = net.obs_point.take(obs)
        fixed_rows = self.point_fixed.take(point)
        fixed = np.all(fixed_rows)
        # Independent gathers (random reads that release the GIL): in two threads when
        # there are two. Their results differ in type (arrays, the slots tuple, None):
        # each meets its declared type in Layout's fields.
        jobs: dict[str, Callable[[], Any]] = {
            "slots": lambda: self._slots(obs, point, fixed_rows, ranges),
            "xyz": lambda: net.point_xyz.take(point, axis=0) if fixed else None,
            "w0": lambda: self.obs_w0.take(obs, axis=0),
            "line": lambda: net.obs_line.take(obs),
            "sample": lambda: net.obs_sample.take(obs),
            "guess": lambda: self.line_guess.take(obs),
            "rate": lambda: self.rate_guess.take(obs),
        }
        if compute_threads(self.cfg.threads) > 1 and len(obs) > 100_000:
            with ThreadPoolExecutor(1, thread_name_prefix="planetref-layout") as ex:
                far = {k: ex.submit(jobs[k]) for k in ("slots", "w0", "xyz")}
                out = {k: f() for k, f in jobs.items() if k not in far}
                out |= {k: f.result() for k, f in far.items()}
        else:
            out = {k: f() for k, f in jobs.items()}
        slot, slot_obs, size = out["slots"]
        return Layout(
            obs,
            ranges,
            point,
            out["line"],
            out["sample"],
            out["w0"],
            out["xyz"],
            out["guess"],
            out["rate"],
            slot,
            slot_obs,
            size,
        )

    def _slots(
        self,
        obs: NDArray[np.intp],
        point: NDArray[np.intp],
        fixed_rows: NDArray[np.bool_],
        ranges: list[tuple[int, int, int, int]],
    ) -> tuple[NDArray[np.intp], NDArray[np.intp], int]:
        """Slots of the rows of a layout (see :attr:`Layout.slot`), one observation each.

        ``ranges``: the layout's ``(model, ccd, start, stop)`` groups, which give every
        row's image without gathering the network's camera and CCD columns.
        """
        net = self.net
        _, kind = net.point_kind_codes
        base = max(len(cam.ccd_names) for cam in net.cameras)
        n_img = len(net.cameras) * base
        image = np.repeat(
            np.array([mi * base + ccd for mi, ccd, _, _ in ranges], np.intp),
            [b - a for _, _, a, b in ranges],
        )
        key = kind.take(point) * n_img + image
        size = int(np.max(np.diff(self.offsets), initial=0)) + 1
        present = np.bincount(key[fixed_rows], minlength=int(key.max(initial=0)) + 1) > 0
        n_slot = int(np.count_nonzero(present))
        if n_slot * size * size * 8 > _SLOT_BYTES or not np.any(fixed_rows):
            return np.full(len(obs), -1, np.intp), np.zeros(0, np.intp), size
        dense = (np.cumsum(present) - 1).astype(np.intp)
        slot = dense.take(key)
        slot[~fixed_rows] = -1
        slot_obs = np.zeros(n_slot, np.intp)
        on = np.flatnonzero(fixed_rows)[::-1]
        slot_obs[slot[on]] = obs[on]  # an observation of each slot
        return slot, slot_obs, size

    def _linearize(
        self,
        c: F64,
        xyz: F64,
        lay: Layout,
        tie_pos: NDArray[np.intp],
        n_tie: int,
        unknown: NDArray[np.intp],
        xyz0: F64,
    ) -> Linearization:
        p = self.n_params
        m = len(lay.obs)
        q = self.q
        # Every row is written by its chunk.
        r = np.empty((m, 2))
        valid = np.empty(m, bool)
        line = np.empty(m)
        s_all = np.empty(m)
        robust = self.loss != "linear"
        # With the plain loss the weights are the a-priori ones (0 on invalid rows): they
        # are taken from the layout after the pass, and each chunk writes its copy into
        # a scratch of its share (16 bytes per observation less per linearisation).
        weight = np.empty((m, 2)) if robust else None
        scratch: dict[int, F64] = {}
        rate = np.full(m, np.nan)
        n_cc = np.zeros((p + 1, p + 1))
        g_c = np.zeros(p + 1)
        n_slot, size = len(lay.slot_obs), lay.slot_size
        slot_n = np.zeros((n_slot, size, size))
        fn = self.normal_kernels()
        # The compiled scatter writes every element of the tie rows: a retired
        # linearisation's arrays serve again (no fresh pages for tens of MB per pass).
        spare, self.tie_spare = self.tie_spare, None
        if fn is not None and spare is not None and spare[0].shape == (n_tie, 2, q):
            a_t, b_t, gpat_t = spare
        else:
            a_t = np.zeros((n_tie, 2, q))
            b_t = np.zeros((n_tie, 2, 3))
            gpat_t = np.zeros(n_tie, np.intp)
        thr = self.threshold
        thr_l = thr if np.ndim(thr) == 0 else np.asarray(thr)[lay.obs]
        pxyz = lay.fixed_xyz if lay.fixed_xyz is not None else xyz[lay.point]
        parts = self.chunk_parts(lay)
        # One normal matrix per share (contiguous chunks; not per thread), summed in
        # order below; every other output is a disjoint slice of the layout.
        acc = [(n_cc, g_c, slot_n)] + [
            (np.zeros_like(n_cc), np.zeros_like(g_c), np.zeros_like(slot_n)) for _ in parts[1:]
        ]

        if fn is not None:
            loss_code = fn.LOSS_CODES.get(self.loss)
            if loss_code is None:
                robust_rho(np.zeros(1), self.loss, 1.0)  # raises: unknown loss
            thr_c = np.atleast_1d(np.asarray(thr_l, np.float64))

        def weights_out(k: int, a: int, b: int) -> F64:
            if weight is not None:
                return weight[a:b]
            buf = scratch.get(k)
            if buf is None or len(buf) < b - a:
                buf = scratch[k] = np.empty((self.cfg.chunk_size, 2))
            return buf[: b - a]

        def work(k: int, mi: int, a: int, b: int, ev: Evaluation) -> None:
            if ev.line_rate is not None:
                rate[a:b] = ev.line_rate
            gp = ev.pattern + self.pat_offsets[mi]
            if fn is not None:
                # The compiled twin of everything below (the numpy reference).
                n_k, g_k, s_k = acc[k]
                fn.linearize_rows(
                    (ev.line, ev.sample, ev.valid),
                    (lay.line[a:b], lay.sample[a:b], lay.w0[a:b]),
                    loss_code,
                    thr_c if thr_c.size == 1 else thr_c[a:b],
                    _partial_factors(ev),
                    gp,
                    (self.act_n, self.act_loc, self.act_col),
                    (lay.slot[a:b], s_k, int(self.offsets[mi])),
                    (n_k, g_k),
                    (r[a:b], s_all[a:b], weights_out(k, a, b)),
                )
                valid[a:b], line[a:b] = ev.valid, ev.line
                _tie_rows(ev, a, b, gp)
                return
            res = r[a:b]
            np.subtract(ev.line, lay.line[a:b], out=res[:, 0])
            np.subtract(ev.sample, lay.sample[a:b], out=res[:, 1])
            w0 = lay.w0[a:b]
            s = np.einsum("mr,mr->m", res * res, w0)
            ok = ev.valid
            we = weights_out(k, a, b)
            if robust:
                _, rw = robust_rho(
                    s, self.loss, thr_l if np.ndim(thr_l) == 0 else np.asarray(thr_l)[a:b]
                )
                np.multiply(w0, rw[:, None], out=we)
            else:
                we[:] = w0
            if np.all(ok):
                res_ok = res
            else:
                we[~ok] = 0.0
                s[~ok] = np.inf
                res_ok = np.where(ok[:, None], res, 0.0)
            valid[a:b], s_all[a:b] = ok, s
            line[a:b] = ev.line
            d = ev.d_params
            n_k, g_k, s_k = acc[k]
            sl = (lay.slot[a:b], s_k, int(self.offsets[mi]))
            self._accumulate(n_k, g_k, d, we, we * res_ok, gp, d.shape[2], sl)
            _tie_rows(ev, a, b, gp)

        def _tie_rows(ev: Evaluation, a: int, b: int, gp: NDArray[np.intp]) -> None:
            # The partials of observations of unknown points, for the Schur complement.
            if n_tie:
                tp = tie_pos[a:b]
                if fn is not None:
                    # Compiled: straight from the factors into the tie rows.
                    f = ev.factors
                    if f is not None:
                        fac = (f.imp, f.weights, f.src, f.node)
                        grd = (f.imp, f.ground)
                    else:
                        d = ev.d_params
                        fac = _plain_factors(d)
                        grd = (ev.d_ground, _GROUND_COLUMNS)
                    fn.tie_rows(fac, grd, tp, gp, (a_t, b_t, gpat_t))
                    return
                is_t = tp >= 0
                if np.any(is_t):
                    if ev.factors is not None and not np.all(is_t):
                        d, dg = ev.factors.expand(is_t)  # the tie rows only
                    else:
                        d, dg = ev.d_params[is_t], ev.d_ground[is_t]
                    a_t[tp[is_t], :, : d.shape[2]] = d
                    b_t[tp[is_t]] = dg
                    gpat_t[tp[is_t]] = gp[is_t]

        self.map_chunks(lay, parts, c, pxyz, work)
        for n_k, g_k, s_k in acc[1:]:
            n_cc += n_k
            g_c += g_k
            slot_n += s_k
        if robust:
            rho, _ = robust_rho(np.where(valid, s_all, 0.0), self.loss, thr_l)
        else:
            rho = np.where(valid, s_all, 0.0)
        all_valid = bool(np.all(valid))
        cost = 0.5 * float(np.sum(rho)) if all_valid else math.inf
        if weight is None:
            weight = lay.w0 if all_valid else np.where(valid[:, None], lay.w0, 0.0)
        cost += self._prior_cost(c)
        if len(unknown):
            dx = xyz[unknown] - xyz0[unknown]
            cost += 0.5 * quadratic(self.point_prior_w[unknown], dx)
        inv = np.empty(n_tie, np.intp)
        sel = tie_pos >= 0
        inv[tie_pos[sel]] = np.flatnonzero(sel)
        return Linearization(
            cost,
            r,
            valid,
            line,
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
            slot_n,
            self.loss,
        )

    def retire(self, lin: Linearization) -> None:
        """Hand a linearisation that nothing reads any more back for its tie arrays.

        The next :meth:`_linearize` of the same shape writes into them instead of new
        arrays (tens of MB at 1e5 tie observations). Only its owner may retire it: its
        ``a_t``, ``b_t`` and ``gpat_t`` are overwritten.
        """
        if len(lin.a_t):
            self.tie_spare = (lin.a_t, lin.b_t, lin.gpat_t)

    def chunk_parts(self, lay: Layout) -> list[list[tuple[int, int, int, int]]]:
        """The layout's chunks ``(model, ccd, start, stop)`` in contiguous shares.

        ``cfg.chunk_size`` observations per chunk, never across a (camera, CCD) range;
        see :func:`chunk_shares`.
        """
        return chunk_shares(lay.ranges, self.cfg.chunk_size)

    def map_chunks(
        self,
        lay: Layout,
        parts: list[list[tuple[int, int, int, int]]],
        c: F64,
        pxyz: F64,
        work: Callable[[int, int, int, int, Evaluation], None],
    ) -> None:
        """Evaluate the models (projection and partials) chunk by chunk over a layout.

        The one loop over the observations that the linearisation and the redundancy
        numbers share: ``work(share, model, start, stop, evaluation)`` is called for
        every chunk of ``parts`` (:meth:`chunk_parts`), the shares in ``--threads`` threads
        (:func:`run_shares`). ``work`` must write only to its rows ``start:stop`` and to
        accumulators of its own share.

        Args:
            lay: The layout (observed lines, guesses).
            parts: The shares of chunks.
            c: Global camera vector.
            pxyz: Ground coordinates of every layout row, ``(M, 3)``.
            work: The per-chunk consumer.
        """

        def run(k: int) -> None:
            for mi, ccd, a, b in parts[k]:
                x = c[self.offsets[mi] : self.offsets[mi + 1]]
                ev = self.models[mi].evaluate(
                    x, pxyz[a:b], ccd, lay.line_guess[a:b], rate_guess=lay.rate_guess[a:b]
                )
                work(k, mi, a, b, ev)

        run_shares(len(parts), run, compute_threads(self.cfg.threads))

    def _accumulate(
        self,
        n_cc: F64,
        g_c: F64,
        d: F64,
        we: F64,
        wr: F64,
        gp: NDArray[np.intp],
        qm: int,
        slots: tuple[NDArray[np.intp], F64, int],
    ) -> None:
        """``N += sum A^T W A`` and ``g += sum A^T W r``, per run of equal patterns.

        ``slots``: ``(slot of each row, slot matrices, the model's first column)``; each
        run's block is also added to its slot's matrix (model-local columns), from which
        the redundancy numbers of the observations of fixed points are summed
        (:mod:`~planetref.adjust.redundancy`).

        Runs are contiguous (observations sorted by line), so every product works on
        views; the few observations whose window differs from their neighbours' simply
        form short runs of their own. Only a pattern's active columns enter the products
        (fixed parameters are never solved for: their rows of ``N`` stay zero): with most
        parameters fixed that is a fraction of the flops. The numpy reference of
        :func:`~planetref.adjust._numba_normal.linearize_rows`, which runs instead (with
        the residuals and weights) when numba is available and ``compiled_normal`` is set.
        """
        slot, slot_n, off = slots
        m = len(gp)
        change = (np.diff(gp) != 0) | (np.diff(slot) != 0)
        cut = np.concatenate([[0], np.flatnonzero(change) + 1, [m]])
        for a, b in itertools.pairwise(cut):
            loc, cols = self._active_columns(int(gp[a]), qm)
            if len(cols) == 0:
                continue
            da = d[a:b] if loc is None else d[a:b][:, :, loc]
            blk = np.tensordot(da, da * we[a:b, :, None], axes=([0, 1], [0, 1]))
            n_cc[np.ix_(cols, cols)] += blk
            if slot[a] >= 0:
                slot_n[slot[a]][np.ix_(cols - off, cols - off)] += blk
            # Columns within a pattern are distinct, so a fancy-index add is exact.
            g_c[cols] += np.tensordot(da, wr[a:b], axes=([0, 1], [0, 1]))

    def normal_kernels(self) -> Any:
        """The compiled normal-equation kernels, or ``None`` for the numpy references.

        :mod:`~planetref.adjust._numba_normal`; ``None`` when numba is missing or
        ``compiled_normal`` is off.
        """
        return _compiled() if self.compiled_normal else None

    def _active_columns(
        self, pattern: int, qm: int
    ) -> tuple[NDArray[np.intp] | None, NDArray[np.intp]]:
        """Local indices (None: all) and global columns of a pattern's free parameters."""
        cache = self._active_cache
        key = (pattern, qm)
        if key not in cache:
            n = int(self.act_n[pattern])
            loc = self.act_loc[pattern, :n]
            keep = loc < qm
            loc = loc[keep]
            cols = self.act_col[pattern, :n][keep]
            cache[key] = (None if np.array_equal(loc, np.arange(qm)) else loc, cols)
        return cache[key]

    def _active_tables(self) -> None:
        """Per pattern, the local indices and global columns of its non-fixed parameters.

        ``act_n`` ``(n_pat,)``, ``act_loc`` and ``act_col`` ``(n_pat, q)`` (padded).
        """
        cols = self.cols
        n_pat, q = cols.shape
        mode = np.append(self.mode, np.int8(2))  # the sink is fixed
        active = mode[cols] != 2
        self.act_n = np.count_nonzero(active, axis=1).astype(np.intp)
        self.act_loc = np.zeros((n_pat, q), np.intp)
        self.act_col = np.full((n_pat, q), self.n_params, np.intp)
        for g in range(n_pat):
            loc = np.flatnonzero(active[g])
            self.act_loc[g, : len(loc)] = loc
            self.act_col[g, : len(loc)] = cols[g, loc]
        self._active_cache.clear()


#: Shares of chunks per pass, whatever the thread count: each share sums its own
#: accumulators and the shares are added in order, so the numbers do not depend on
#: ``--threads`` (a dask worker with one thread gives the in-process result bit for bit).
SHARES = 8


def chunk_shares(
    ranges: Iterable[tuple[int, int, int, int]], chunk_size: int
) -> list[list[tuple[int, int, int, int]]]:
    """Contiguous row ranges ``(model, ccd, start, stop)`` as chunks in contiguous shares.

    Chunks of at most ``chunk_size`` rows, never across a range; :data:`SHARES` shares
    (at most one per chunk), balanced by row count; the split depends on the ranges
    only, never on the thread count.
    """
    chunks = [
        (mi, ccd, a, min(a + chunk_size, b0))
        for mi, ccd, a0, b0 in ranges
        for a in range(a0, b0, chunk_size)
    ]
    m = chunks[-1][3] if chunks else 0
    n = max(1, min(SHARES, len(chunks)))
    if n == 1:
        return [chunks]
    share = np.minimum(np.array([a for _, _, a, _ in chunks]) * n // max(m, 1), n - 1)
    return [[ch for ch, k in zip(chunks, share, strict=True) if k == j] for j in range(n)]


def run_shares(n: int, run: Callable[[int], None], threads: int) -> None:
    """``run(k)`` for ``k < n`` in ``min(threads, n)`` threads (in this one for 1).

    The compiled kernels release the GIL. The threads end with the call: nothing is
    left running for a later fork (no OpenMP or other threading runtime is started).
    """
    workers = max(1, min(threads, n))
    if workers == 1:
        for k in range(n):
            run(k)
        return
    with ThreadPoolExecutor(workers, thread_name_prefix="planetref-adjust") as ex:
        for f in [ex.submit(run, k) for k in range(n)]:
            f.result()


#: Largest key range the compiled counting sort takes (beyond it, numpy's stable sort).
_COUNTING_KEYS = 1 << 24


def group_order(key: NDArray[np.int64], line: F64) -> NDArray[np.intp]:
    """The stable order of observations by ``(group key, observed line)``.

    Compiled: a counting sort by group and line bin (bins of a power-of-two fraction
    of a line, about one observation each), then each bin's few observations by line
    (O(m) for image lines); numpy: a stable sort by line, then by
    group (the reference; the same permutation). The order does not depend on the
    order of the observations except for equal lines, so a network whose observations
    come in another order (tiles finished by workers in another order) gives the same
    sums.
    """
    if len(key) == 0:
        return np.zeros(0, np.intp)
    fn = group_kernels()
    finite = np.isfinite(line)
    if fn is not None and np.all(finite):
        lo, hi = float(line.min()), float(line.max())
        n_groups = int(key.max()) + 1
        # Bins per line: a power of two (exact scaling) giving ~2 bins per observation.
        per_line = len(key) / max(n_groups * (hi - lo + 1.0), 1.0)
        scale = 2.0 ** int(np.clip(np.ceil(np.log2(max(2.0 * per_line, 1e-300))), -20, 8))
        span = int(np.floor(hi * scale) - np.floor(lo * scale)) + 1
        n_keys = n_groups * span
        if n_keys <= max(_COUNTING_KEYS, 4 * len(key)):
            whole = np.floor(line * scale) - np.floor(lo * scale)
            bucket = key * span + whole.astype(np.int64)
            return fn.group_line_order(bucket, n_keys, np.ascontiguousarray(line))
    order = np.argsort(line, kind="stable")
    small = key[order].astype(np.uint16 if key.max(initial=0) < 2**16 else np.int64)
    return order[np.argsort(small, kind="stable")]


def group_kernels() -> Any:
    """The compiled grouping passes, or ``None`` (numpy) when numba cannot be loaded.

    The one loader of :mod:`planetref.adjust._numba_groups`: the counting sorts of the
    layout here and the variance groups' order and sums (:mod:`planetref.adjust.variance`).
    """
    return optional_module("planetref.adjust._numba_groups", "compiled grouping and sorting")


def _compiled() -> Any:
    """The compiled accumulation, or ``None`` (numpy) when numba cannot be loaded."""
    return optional_module("planetref.adjust._numba_normal", "compiled normal equations")


def _partial_factors(ev: Evaluation) -> tuple[Any, ...]:
    """``(imp, weights, src, node, tau, start, coef)`` of an evaluation's partials.

    See :func:`~planetref.adjust._numba_normal.linearize_rows`.
    """
    f = ev.factors
    if f is not None:
        basis = f.basis if f.basis is not None else _NO_BASIS
        return (f.imp, f.weights, f.src, f.node, *basis)
    return (*_plain_factors(ev.d_params), *_NO_BASIS)


def _plain_factors(d: F64) -> tuple[F64, F64, NDArray[np.intp], NDArray[np.intp]]:
    """``(imp, weights, src, node)`` of plain partials ``d (m, 2, q)``: no node factors."""
    q = d.shape[2]
    return (d, _NO_WEIGHTS, np.arange(q, dtype=np.intp), np.full(q, -1, np.intp))


_NO_WEIGHTS = np.ones((1, 1))
#: The columns of plain ground partials ``d_ground (m, 2, 3)``.
_GROUND_COLUMNS = np.arange(3, dtype=np.intp)
_NO_BASIS = (np.empty(0), np.empty(0, np.intp), np.empty((0, 0, 0)))


def quadratic(w: F64, dx: F64) -> float:
    """``sum_p dx_p^T W_p dx_p`` of per-point 3x3 weights."""
    return float(np.einsum("pi,pij,pj->", dx, w, dx))
