"""Schur complement of the point unknowns: reduced camera system and back-substitution.

Point unknowns are eliminated per point (3x3 blocks, vectorised over chunks of complete
points); the reduced camera system (at most a few hundred unknowns) is Jacobi-scaled
and solved densely by Cholesky; points are back-substituted. :class:`SchurMixin` is
mixed into :class:`~planetref.adjust.solver.BundleSolver`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from planetref.adjust.linearization import Layout, Linearization
from planetref.arrays import F64, expand_ranges
from planetref.errors import AdjustmentError
from planetref.runtime.optional import optional_module

if TYPE_CHECKING:
    from planetref.adjust.config import SolverConfig
    from planetref.control.network import Network, PointMatrices

__all__ = ["SchurMixin"]


@dataclass
class _TieChunk:
    """Observations of a contiguous range of unknown points (complete points)."""

    obs: NDArray[np.intp]  # positions in the linearisation's tie arrays
    pt: NDArray[np.intp]  # local point index (0..n_pts-1) per observation
    pts: NDArray[np.intp]  # global unknown-point indices of the chunk
    pair_a: NDArray[np.intp]  # observation pairs within points (chunk-local)
    pair_b: NDArray[np.intp]
    starts: NDArray[np.intp]  # first observation of each point (chunk-local)


class Iterate(NamedTuple):
    """An LM iterate and its linearisation.

    What the reduced system, the rank check and the statistics read; unpacks as
    ``(lin, chunks, c, xyz, xyz0, unknown)``.
    """

    lin: Linearization  # the linearisation at (c, xyz)
    chunks: list[_TieChunk]  # the observations of unknown points, by point
    c: F64  # global camera vector
    xyz: F64  # every network point, (P, 3)
    xyz0: F64  # a-priori coordinates, (P, 3)
    unknown: NDArray[np.intp]  # network indices of the unknown points


@dataclass
class Structure:
    lay: Layout
    unknown: NDArray[np.intp]  # network indices of the points whose XYZ are unknowns
    tie_pos: NDArray[np.intp]  # per layout row: row in the tie arrays, or -1
    chunks: list[_TieChunk]
    n_tie: int


class SchurMixin:
    """Reduced normal equations of a :class:`~planetref.adjust.solver.BundleSolver`.

    Uses the solver's ``net``, ``n_params``, ``cols``, ``cfg``, ``active``, ``prior_w``,
    ``x0``, ``con_n``, ``point_prior_w`` and ``_unknown_ids``.
    """

    # The host's state used here, set by BundleSolver (a typed contract; annotations
    # only, nothing is defined at run time).
    net: Network
    cfg: SolverConfig
    n_params: int
    cols: NDArray[np.intp]
    active: NDArray[np.intp]
    prior_w: F64
    x0: F64
    con_n: F64 | None
    point_prior_w: PointMatrices
    _unknown_ids: NDArray[np.intp]

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
                    pa, pb = expand_ranges(first, cnt)
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

    def _reduced(self, at: Iterate, lam: float) -> tuple[F64, F64, F64, list[tuple[F64, F64, F64]]]:
        """Reduced camera system ``(S, rhs, D_c)`` and per-chunk point blocks at ``at``."""
        lin, chunks, c, xyz, xyz0, unknown = at
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
        if chunks and _compiled() is not None:
            return self._reduced_compiled(at, lam, s_mat, rhs, d_c)
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

    def _reduced_compiled(
        self, at: Iterate, lam: float, s_mat: F64, rhs: F64, d_c: F64
    ) -> tuple[F64, F64, F64, list[tuple[F64, F64, F64]]]:
        """:meth:`_reduced`'s point elimination by the compiled kernel (same maths).

        One loop over the points: each point's 3x3 block is factored in registers and
        only the active columns of its observations' patterns are updated; the terms of
        points seen once (MCPs) are summed per pattern in dense blocks first (up to
        :data:`_POOL_ELEMENTS`). ``S`` leaves exactly symmetric.
        """
        lin, chunks, _, xyz, xyz0, unknown = at
        p = self.n_params
        n_u = len(unknown)
        starts = _point_starts(chunks, len(lin.a_t))
        pw = self.point_prior_w[unknown]
        prior_g = np.einsum("pij,pj->pi", pw, xyz[unknown] - xyz0[unknown])
        vinv, bx, dx = np.empty((n_u, 3, 3)), np.empty((n_u, 3)), np.empty((n_u, 3))
        bad = _compiled().eliminate_points(
            lin.a_t,
            lin.b_t,
            lin.weight_t,
            lin.r_t,
            lin.gpat_t,
            self.cols,
            starts,
            np.ascontiguousarray(pw),
            prior_g,
            float(lam),
            p,
            s_mat,
            rhs,
            vinv,
            bx,
            dx,
            _POOL_ELEMENTS,
        )
        if bad >= 0:
            raise AdjustmentError(
                f"point {self.net.point_ids[unknown[bad]]!r}: its coordinates are not "
                f"determined by its observations (rays parallel or too few); give it an "
                f"a-priori sigma or remove it"
            )
        blocks = [(vinv[ch.pts], bx[ch.pts], dx[ch.pts]) for ch in chunks]
        return s_mat[:p, :p], rhs[:p], d_c, blocks

    def _back_substitute(
        self,
        lin: Linearization,
        chunks: list[_TieChunk],
        blocks: list[tuple[F64, F64, F64]],
        delta_c: F64,
        n_unknown: int,
    ) -> tuple[F64, F64, F64]:
        """Point steps ``dX = V^-1 (b_x - W^T dc)`` and their gradient/diagonal terms.

        Compiled (:func:`~planetref.adjust._numba_schur.back_substitute`) when numba is
        there; the numpy loop below is its reference.
        """
        dc_pad = np.concatenate([delta_c, [0.0]])
        k = _compiled()
        if k is not None and chunks:
            pts = np.concatenate([ch.pts for ch in chunks])
            starts = _point_starts(chunks, len(lin.a_t))
            vinv = np.concatenate([b[0] for b in blocks])
            bx = np.concatenate([b[1] for b in blocks])
            step = np.empty((len(pts), 3))
            k.back_substitute(
                lin.a_t,
                lin.b_t,
                lin.weight_t,
                lin.gpat_t,
                self.cols,
                starts,
                vinv,
                bx,
                dc_pad,
                step,
            )
            dx = np.zeros((n_unknown, 3))
            bx_all = np.zeros((n_unknown, 3))
            dd_all = np.zeros((n_unknown, 3))
            dx[pts], bx_all[pts] = step, bx
            dd_all[pts] = np.concatenate([b[2] for b in blocks])
            return dx, bx_all, dd_all
        dx = np.zeros((n_unknown, 3))
        bx_all = np.zeros((n_unknown, 3))
        dd_all = np.zeros((n_unknown, 3))
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


def _point_starts(chunks: list[_TieChunk], n_rows: int) -> NDArray[np.intp]:
    """First tie row of each unknown point, in chunk order, then ``n_rows``.

    The compiled kernels' layout: the chunks' rows are contiguous, point after point.
    """
    starts = [ch.obs[0] + ch.starts for ch in chunks] + [[n_rows]]
    return np.concatenate(starts).astype(np.intp)


def _first_singular(v: F64) -> int:
    for i in range(len(v)):
        try:
            np.linalg.cholesky(v[i])
        except np.linalg.LinAlgError:
            return i
    return 0


#: Most float64 elements (patterns x q x q, 8 MB) of the compiled elimination's
#: per-pattern blocks of one-observation terms; beyond it they go straight into S.
_POOL_ELEMENTS = 1 << 20


def _compiled() -> Any:
    """The compiled point elimination, or ``None`` (numpy) when numba cannot be loaded."""
    return optional_module("planetref.adjust._numba_schur", "compiled point elimination")
