"""Redundancy numbers of the equations of a bundle-adjustment solution.

Redundancy numbers
------------------
For every equation ``i`` (an image measure's line or sample, an a-priori coordinate of
a weighted point, a camera prior, a smoothing constraint) the redundancy number is
``r_i = 1 - p_i (J Q J^T)_ii`` with ``p_i`` its weight and ``Q = N^-1`` the cofactor
matrix of all unknowns; ``sum r_i`` is the degrees of freedom. ``Q`` is never formed:
with the camera block ``Q_cc = S^-1`` (the reduced matrix) and the point blocks
``V_j`` (3x3), an observation ``i`` of a point ``j`` has

    J_i Q J_i^T = G_ii - T_i B_i^T - B_i T_i^T + B_i (V_j^-1 + U_j) B_i^T

with ``G_ik = A_i S^-1 A_k^T`` over the pairs of observations of the same point,
``C_k = V_j^-1 B_k^T W_k``, ``T_i = sum_k G_ik C_k^T`` and ``U_j = sum_kl C_k G_kl C_l^T``;
the point's cofactor block is ``Q_jj = V_j^-1 + U_j``. (``A``: camera partials,
``B``: ground partials, ``W``: weights.)

Observations of fixed points need only ``G_ii`` (compiled, :mod:`planetref.adjust.
_numba_normal`, with :class:`_PairG` as the numpy reference); the pairs of observations of
unknown points go through :class:`_PairG`. The variance components built on these
numbers are in :mod:`planetref.adjust.variance`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from planetref.adjust.linearization import Layout, Linearization
from planetref.adjust.solver import BundleSolver
from planetref.arrays import F64, expand_ranges

if TYPE_CHECKING:
    from planetref.adjust.models import Evaluation

__all__ = ["Redundancy", "group_sum", "redundancy"]

_PAIR_CHUNK = 65536


@dataclass
class Redundancy:
    """Redundancy numbers of the equations of one solution.

    Attributes:
        obs: Network indices of the image observations, ``(n,)``.
        obs_r: Redundancy numbers of their (line, sample) equations, ``(n, 2)``.
        obs_v: Their residuals (px), ``(n, 2)``.
        obs_w: Their weights (1/px^2), ``(n, 2)``.
        points: Network indices of the weighted unknown points, ``(k,)``.
        point_r: Redundancy numbers of their a-priori coordinates, in each point's sigma
            frame, ``(k, 3)`` (0 on axes without a prior).
        point_v: Their residuals (adjusted - a priori, metres, sigma frame), ``(k, 3)``.
        point_w: Their weights (1/m^2), ``(k, 3)``.
        unknown: Network indices of every unknown point, ``(u,)``.
        point_cofactor: Cofactor blocks of the unknown points (XYZ, m^2), ``(u, 3, 3)``.
        camera_r: Redundancy of the camera priors (sum).
        camera_vtpv: Their ``v^T P v``.
        camera_n: Their number of equations.
        constraint_r: Redundancy of the smoothing constraints (sum).
        constraint_vtpv: Their ``v^T P v``.
        constraint_n: Their number of equations.
        slot_obs: One network observation of each slot (point kind, camera, CCD) whose
            observations of fixed points are summed in :attr:`slot_r`, ``(s,)``.
        slot_r: The sums of their redundancy numbers (their rows of :attr:`obs_r` are
            0), ``(s,)``; empty when every observation has its own numbers.
        own: The rows of :attr:`obs_r` that may be non-zero, ascending (``None``: every
            row); the others are summed in :attr:`slot_r`.
        slot: Per row, its slot (index into :attr:`slot_obs`; ``-1`` for the rows in
            :attr:`own`), or ``None`` without slot sums.
    """

    obs: NDArray[np.intp]
    obs_r: F64
    obs_v: F64
    obs_w: F64
    points: NDArray[np.intp]
    point_r: F64
    point_v: F64
    point_w: F64
    unknown: NDArray[np.intp]
    point_cofactor: F64
    camera_r: float
    camera_vtpv: float
    camera_n: int
    constraint_r: float
    constraint_vtpv: float
    constraint_n: int
    slot_obs: NDArray[np.intp]
    slot_r: F64
    own: NDArray[np.intp] | None = None
    slot: NDArray[np.intp] | None = None

    @property
    def obs_order(self) -> NDArray[np.intp]:
        """Argsort of :attr:`obs`."""
        return np.argsort(self.obs)

    @property
    def total(self) -> float:
        """Sum of all redundancy numbers (the degrees of freedom)."""
        return float(self.image_total + self.point_r.sum() + self.camera_r + self.constraint_r)

    @property
    def image_total(self) -> float:
        """Sum of the redundancy numbers of the image equations."""
        return float(self.obs_r.sum() + self.slot_r.sum())

    def row_groups(self, group_of: NDArray[np.intp]) -> NDArray[np.intp]:
        """``group_of[obs]``: the group of each row (``group_of`` per network observation).

        With slot sums, the rows of a slot take its group (a slot lies in one group) and
        only the other rows are looked up, sparing a random gather over every row.
        """
        if self.slot is None or self.own is None:
            return group_of[self.obs]
        sg = np.append(group_of[self.slot_obs], -1)  # slot -1 -> -1
        rg = sg[self.slot]
        rg[self.own] = group_of[self.obs[self.own]]
        return rg

    def image_sums(self, group_of: NDArray[np.intp], n_groups: int) -> F64:
        """Redundancy of the image equations per group, ``(n_groups,)``.

        ``group_of``: per network observation its group (``-1``: none). A slot lies in
        one group (groups never split a point kind, camera or CCD).
        """
        # Row sums of obs_r, column by column (rows that are 0 by construction add
        # nothing and are skipped).
        if self.own is None:
            r = group_sum(group_of[self.obs], self.obs_r[:, 0] + self.obs_r[:, 1], n_groups)
        else:
            o = self.own
            r = group_sum(group_of[self.obs[o]], self.obs_r[o, 0] + self.obs_r[o, 1], n_groups)
        if len(self.slot_r):
            sg = group_of[self.slot_obs]
            r += np.bincount(sg[sg >= 0], weights=self.slot_r[sg >= 0], minlength=n_groups)
        return r


def group_sum(group: NDArray[np.intp], weights: F64, n_groups: int) -> F64:
    """Sums of ``weights`` per group (``group < 0``: none), ``np.bincount`` order."""
    on = group >= 0
    if not np.all(on):
        group, weights = group[on], weights[on]
    # Float even without any row (bincount then returns integers).
    return np.bincount(group, weights=weights, minlength=n_groups).astype(np.float64, copy=False)


def redundancy(
    solver: BundleSolver,
    c: F64,
    xyz: F64,
    obs: NDArray[np.intp],
    xyz0: F64,
    cofactor: F64,
    lin: Linearization | None = None,
) -> Redundancy:
    """Redundancy numbers of every equation at a solution (plain least-squares weights).

    With ``lin``, the solver's linearisation at exactly this solution (plain
    least-squares loss, the current weights), nothing is evaluated again: the
    observations of fixed points are summed per slot (point kind, camera, CCD) as
    ``r_s = n_s - tr(Q N_s)`` from the slot matrices ``N_s`` that the linearisation
    accumulated (:attr:`Redundancy.slot_r`; their per-observation numbers stay 0), and
    the observations of unknown points take their partials from the linearisation's
    tie arrays. Without it (or when ``lin`` does not qualify), the models are
    evaluated again and every observation gets its own numbers (the reference).

    Args:
        solver: The solver (models, weights, priors).
        c: Adjusted global camera vector.
        xyz: Adjusted coordinates of every point, ``(P, 3)``.
        obs: The observations that took part.
        xyz0: A-priori point coordinates.
        cofactor: ``S^-1`` of the camera parameters (zero rows for fixed ones),
            ``(n_params, n_params)``.
        lin: The final linearisation of ``obs`` at ``(c, xyz)``, or ``None``.

    Returns:
        The :class:`Redundancy`.
    """
    # The solver's layout of these observations: contiguous (camera, CCD) ranges with
    # the per-observation data gathered once (the redundancy follows its order).
    st = solver._structure(np.asarray(obs, np.intp), guesses=False)
    lay = st.lay
    w = lay.w0  # solver.obs_w0[lay.obs] (a new weight makes a new layout)
    h: F64 | None
    if lin is not None and _reusable(solver, lin, lay):  # (``_reusable`` checks too)
        all_valid = bool(np.all(lin.valid))
        v_all = lin.r if all_valid else np.where(lin.valid[:, None], lin.r, 0.0)
        h = None  # only the observations of unknown points have their own numbers
        tpos, a_u, gpat_u, b_u = st.tie_pos, lin.a_t, lin.gpat_t, lin.b_t
        slot_r = _slot_redundancy(solver, lin, lay, cofactor)
    else:
        solver.refresh_guesses(lay)
        v_all, h, tpos, a_u, gpat_u, b_u = _evaluate(solver, c, xyz, lay, cofactor)
        slot_r = np.zeros(0)
    eqs = (v_all, h, w, slot_r)
    return _finish(solver, (c, xyz, xyz0), lay, cofactor, eqs, (tpos, a_u, gpat_u, b_u))


def _reusable(solver: BundleSolver, lin: Linearization | None, lay: Layout) -> bool:
    """Whether a linearisation can stand in for a fresh evaluation (see :func:`redundancy`)."""
    if (
        lin is None
        or lin.loss != "linear"
        or len(lin.slot_n) != len(lay.slot_obs)
        or not np.array_equal(lin.obs, lay.obs)
    ):
        return False
    # Every observation of a fixed point needs a slot (the layout gives each one, unless
    # the slot matrices would be too large: then there are none).
    if not len(lay.slot_obs) and np.any(solver.point_fixed[lay.point]):
        return False
    if np.all(lin.valid):
        return np.array_equal(lin.weight, lay.w0)
    return np.array_equal(lin.weight, np.where(lin.valid[:, None], lay.w0, 0.0))


def _slot_redundancy(solver: BundleSolver, lin: Linearization, lay: Layout, cofactor: F64) -> F64:
    """``r_s = n_s - tr(Q N_s)`` per slot (its equations less their cofactor trace)."""
    on = lay.slot >= 0
    n_eq = 2.0 * np.bincount(lay.slot[on], minlength=len(lay.slot_obs))
    out = np.empty(len(lay.slot_obs))
    # One model per camera, in the network's order.
    for s_i, mi in enumerate(solver.net.obs_camera[lay.slot_obs]):
        a, b = int(solver.offsets[mi]), int(solver.offsets[mi + 1])
        out[s_i] = n_eq[s_i] - float(np.sum(cofactor[a:b, a:b] * lin.slot_n[s_i, : b - a, : b - a]))
    return out


def _evaluate(
    solver: BundleSolver, c: F64, xyz: F64, lay: Layout, cofactor: F64
) -> tuple[F64, F64, NDArray[np.intp], F64, NDArray[np.intp], F64]:
    """The reference: evaluate the models again over the layout.

    Returns ``(v, h, tpos, a_u, gpat_u, b_u)``: residuals ``(n, 2)``, ``A_i Q A_i^T`` of
    the observations of fixed points ``(n, 2, 2)``, and for those of unknown points their
    rows in the kept partials (``-1`` elsewhere), camera partials, patterns and ground
    partials.
    """
    n = len(lay.obs)
    q = solver.q
    unknown_pt = ~solver.point_fixed[lay.point]
    # Observations of fixed points need only their own G_ii, computed chunk by chunk;
    # the partials of those of unknown points are kept for the pairs.
    t_all = np.flatnonzero(unknown_pt)
    tpos = np.full(n, -1, np.intp)
    tpos[t_all] = np.arange(len(t_all))
    a_u = np.zeros((len(t_all), 2, q))
    gpat_u = np.zeros(len(t_all), np.intp)
    b_u = np.zeros((len(t_all), 2, 3))
    v_all = np.zeros((n, 2))
    h = np.zeros((n, 2, 2))
    pxyz = lay.fixed_xyz if lay.fixed_xyz is not None else xyz[lay.point]

    def work(_k: int, mi: int, a: int, b: int, ev: Evaluation) -> None:
        ok = ev.valid
        every = bool(np.all(ok))
        d = ev.d_params if every else np.where(ok[:, None, None], ev.d_params, 0.0)
        gp = ev.pattern + solver.pat_offsets[mi]
        np.subtract(ev.line, lay.line[a:b], out=v_all[a:b, 0])
        np.subtract(ev.sample, lay.sample[a:b], out=v_all[a:b, 1])
        if not every:
            v_all[a:b][~ok] = 0.0
        fixed = ~unknown_pt[a:b]
        if np.all(fixed):
            h[a:b] = _diag_cofactor(solver, d, gp, cofactor)
        elif np.any(fixed):
            fx = np.flatnonzero(fixed)
            h[a + fx] = _diag_cofactor(solver, d[fx], gp[fx], cofactor)
        tu = tpos[a:b]
        is_u = tu >= 0
        if np.any(is_u):
            a_u[tu[is_u], :, : d.shape[2]] = d[is_u]
            gpat_u[tu[is_u]] = gp[is_u]
            b_u[tu[is_u]] = np.where(ok[is_u, None, None], ev.d_ground[is_u], 0.0)

    solver.map_chunks(lay, solver.chunk_parts(lay), c, pxyz, work)
    return v_all, h, tpos, a_u, gpat_u, b_u


def _finish(
    solver: BundleSolver,
    sol: tuple[F64, F64, F64],
    lay: Layout,
    cofactor: F64,
    eqs: tuple[F64, F64 | None, F64, F64],
    kept: tuple[NDArray[np.intp], F64, NDArray[np.intp], F64],
) -> Redundancy:
    """The pairs of observations of unknown points, the point and camera priors.

    ``sol``: ``(c, xyz, xyz0)``; ``eqs``: ``(v, h, w, slot_r)`` of the image equations
    (``slot_r`` empty: every observation has its own ``h``; ``h`` ``None``: the
    observations of fixed points are summed in ``slot_r``, their rows of ``obs_r`` are
    0); ``kept``: ``(tpos, a_u, gpat_u, b_u)`` (see :func:`_evaluate`).
    """
    c, xyz, xyz0 = sol
    v_all, h, w, slot_r = eqs
    obs = lay.obs
    pt = lay.point
    t_all = np.flatnonzero(~solver.point_fixed[pt])
    # Observations of unknown points, sorted by point (positions into obs; ``tpos``
    # maps them into the kept partials).
    t = t_all[np.argsort(pt[t_all], kind="stable")]
    unknown, first, counts = np.unique(pt[t], return_index=True, return_counts=True)
    hd, qjj = _tie_cofactors(solver, kept, w[t], t, (unknown, first, counts), cofactor)
    if h is None:
        obs_r = np.zeros((len(obs), 2))
    else:
        obs_r = 1.0 - w * np.stack([h[:, 0, 0], h[:, 1, 1]], axis=1)
    obs_r[t] = 1.0 - w[t] * hd
    # With slot sums (``h`` None) the rows of the observations of fixed points stay 0:
    # they are summed per slot instead.
    # Priors of weighted points, in their sigma frames.
    pw_axis = solver.point_prior_axis_w[unknown]
    has = np.any(pw_axis > 0, axis=1)
    rot = solver.point_frame[unknown[has]]
    q_frame = np.matmul(np.matmul(rot, qjj[has]), np.transpose(rot, (0, 2, 1)))
    wp = pw_axis[has]
    point_r = np.where(wp > 0, 1.0 - wp * np.einsum("pii->pi", q_frame), 0.0)
    dx = xyz[unknown[has]] - xyz0[unknown[has]]
    point_v = np.einsum("pij,pj->pi", rot, dx)
    # Camera priors and smoothing constraints.
    dc = c - solver.x0
    diag_q = np.diag(cofactor)
    prior = solver.prior_w > 0
    camera_r = float(np.sum(1.0 - solver.prior_w[prior] * diag_q[prior]))
    camera_vtpv = float(np.sum(solver.prior_w * dc * dc))
    con_r = con_vtpv = 0.0
    if len(solver.con_w):
        aq = solver.con_a @ cofactor
        con_r = float(np.sum(1.0 - solver.con_w * np.einsum("ij,ij->i", aq, solver.con_a)))
        con_vtpv = float(np.sum(solver.con_w * (solver.con_a @ dc) ** 2))
    return Redundancy(
        obs=obs,
        obs_r=obs_r,
        obs_v=v_all,
        obs_w=w,
        points=unknown[has],
        point_r=point_r,
        point_v=point_v,
        point_w=wp,
        unknown=unknown,
        point_cofactor=qjj,
        camera_r=camera_r,
        camera_vtpv=camera_vtpv,
        camera_n=int(np.count_nonzero(prior)),
        constraint_r=con_r,
        constraint_vtpv=con_vtpv,
        constraint_n=len(solver.con_w),
        slot_obs=lay.slot_obs if len(slot_r) else np.zeros(0, np.intp),
        slot_r=slot_r,
        own=t_all if h is None else None,
        slot=lay.slot if len(slot_r) else None,
    )


def _tie_cofactors(
    solver: BundleSolver,
    kept: tuple[NDArray[np.intp], F64, NDArray[np.intp], F64],
    w_t: F64,
    t: NDArray[np.intp],
    points: tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]],
    cofactor: F64,
) -> tuple[F64, F64]:
    """``diag(J_i Q J_i^T)`` of the observations of unknown points and the points' ``Q_XX``.

    Compiled (:func:`~planetref.adjust._numba_normal.point_redundancy`) when the solver's
    normal kernels are; the numpy loop over pairs of observations below is its reference.

    Args:
        solver: The solver.
        kept: ``(tpos, a_u, gpat_u, b_u)`` (see :func:`_evaluate`).
        w_t: Plain weights of the observations ``t``, ``(n, 2)``.
        t: The observations of unknown points (layout positions), sorted by point.
        points: ``(unknown, first, counts)``: the points of ``t`` (network indices),
            their first position in ``t`` and their number of observations.
        cofactor: ``S^-1`` of the camera parameters.

    Returns:
        ``(h, qjj)``: ``(n, 2)`` in ``t``'s order and ``(n_u, 3, 3)``.
    """
    tpos, a_u, gpat_u, b_u = kept
    unknown, first, counts = points
    u = len(unknown)
    fn = solver.normal_kernels()
    if fn is not None:
        h = np.empty((len(t), 2))
        qjj = np.empty((u, 3, 3))
        fn.point_redundancy(
            a_u,
            b_u,
            gpat_u,
            np.ascontiguousarray(w_t),
            tpos[t],
            np.append(first, len(t)).astype(np.intp),
            np.ascontiguousarray(solver.point_prior_w[unknown]),
            np.ascontiguousarray(cofactor),
            (solver.act_n, solver.act_loc, solver.act_col),
            h,
            qjj,
        )
        return h, qjj
    pairs = _PairG(solver, a_u, gpat_u, cofactor)
    loc = np.repeat(np.arange(u), counts)
    bt = b_u[tpos[t]]
    bw = bt * w_t[:, :, None]  # W B, (m, 2, 3)
    vmat = np.einsum("mki,mkj->mij", bt, bw)
    vsum = np.zeros((u, 3, 3))
    np.add.at(vsum, loc, vmat)
    vsum += solver.point_prior_w[unknown]
    vinv = np.linalg.inv(vsum)
    cmat = np.matmul(vinv[loc], np.transpose(bw, (0, 2, 1)))  # C_k = V^-1 B^T W, (m, 3, 2)
    # Pairs (i, k) of observations of the same point, in t's order.
    pa, pb = expand_ranges(first[loc], counts[loc])
    tmat = np.zeros((len(t), 2, 3))
    umat = np.zeros((u, 3, 3))
    ht = np.zeros((len(t), 2, 2))  # J_i Q J_i^T of the observations of unknown points
    for s0 in range(0, len(pa), _PAIR_CHUNK):
        ia, ib = pa[s0 : s0 + _PAIR_CHUNK], pb[s0 : s0 + _PAIR_CHUNK]
        g = pairs(tpos[t[ia]], tpos[t[ib]])  # (k, 2, 2)
        gc = np.matmul(g, np.transpose(cmat[ib], (0, 2, 1)))  # G_ik C_k^T, (k, 2, 3)
        np.add.at(tmat, ia, gc)
        np.add.at(umat, loc[ia], np.matmul(cmat[ia], gc))
        diag = ia == ib
        ht[ia[diag]] = g[diag]
    btt = np.transpose(bt, (0, 2, 1))
    qjj = vinv + umat
    ht += (
        -np.matmul(tmat, btt)
        - np.matmul(bt, np.transpose(tmat, (0, 2, 1)))
        + np.matmul(np.matmul(bt, qjj[loc]), btt)
    )
    return np.stack([ht[:, 0, 0], ht[:, 1, 1]], axis=1), qjj


def _diag_cofactor(solver: BundleSolver, d: F64, gp: NDArray[np.intp], cofactor: F64) -> F64:
    """``A_i Q A_i^T`` of each observation, ``(m, 2, 2)``: compiled, or :class:`_PairG`."""
    fn = solver.normal_kernels()
    if fn is None:
        idx = np.arange(len(gp))
        return _PairG(solver, d, gp, cofactor)(idx, idx)
    out = np.empty((len(gp), 2, 2))
    fn.diag_cofactor(d, gp, cofactor, solver.act_n, solver.act_loc, solver.act_col, out)
    return out


class _PairG:
    """``G_ik = A_i Q A_k^T`` for pairs of observations, grouped by their patterns.

    Only a pattern's active columns enter (fixed parameters have zero cofactors), and
    each pair of patterns takes one sub-matrix of ``Q``: no ``(n, q, q)`` gather.
    """

    def __init__(self, solver: BundleSolver, a: F64, gpat: NDArray[np.intp], q: F64) -> None:
        self.solver, self.a, self.gpat, self.q = solver, a, gpat, q
        self.n_pat = len(solver.cols)

    def __call__(self, i: NDArray[np.intp], k: NDArray[np.intp]) -> F64:
        out = np.zeros((len(i), 2, 2))
        if not len(i):
            return out
        gi, gk = self.gpat[i], self.gpat[k]
        key = gi.astype(np.int64) * self.n_pat + gk
        order = np.argsort(key, kind="stable")
        cut = np.flatnonzero(np.diff(key[order])) + 1
        qw = self.a.shape[2]
        for seg in np.split(order, cut):
            loc_i, ci = self.solver._active_columns(int(gi[seg[0]]), qw)
            loc_k, ck = self.solver._active_columns(int(gk[seg[0]]), qw)
            if not (len(ci) and len(ck)):
                continue
            ai = self.a[i[seg]] if loc_i is None else self.a[i[seg]][:, :, loc_i]
            ak = self.a[k[seg]] if loc_k is None else self.a[k[seg]][:, :, loc_k]
            # One GEMM for the whole group, then the row-wise products with A_k.
            aq = (ai.reshape(-1, len(ci)) @ self.q[np.ix_(ci, ck)]).reshape(len(seg), 2, -1)
            out[seg] = np.einsum("mrb,msb->mrs", aq, ak)
        return out
