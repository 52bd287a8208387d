"""Rank check and a-posteriori statistics (sigma0, covariance, correlations) of a solution.

:class:`StatisticsMixin` is mixed into :class:`~planetref.adjust.solver.BundleSolver`:
after convergence ``sigma0 = sqrt(v^T P v / dof)``, camera covariance ``sigma0^2 S^-1``
with ``S`` the undamped reduced matrix, correlations. A rank-deficient reduced system
raises :class:`~planetref.errors.AdjustmentError` naming the parameters that the
observations do not determine.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from planetref.adjust.consider import ConsiderLayout, ConsiderSensitivity
from planetref.adjust.linearization import quadratic
from planetref.adjust.schur import Iterate
from planetref.arrays import F64, expand_ranges
from planetref.control.network import enu_rotation
from planetref.errors import AdjustmentError

if TYPE_CHECKING:
    from planetref.adjust.config import SolverConfig
    from planetref.adjust.linearization import Linearization
    from planetref.adjust.schur import Structure
    from planetref.control.network import PointMatrices

__all__ = ["StatisticsMixin"]


class StatisticsMixin:
    """Rank check and statistics of a :class:`~planetref.adjust.solver.BundleSolver`.

    Uses the solver's ``n_params``, ``active``, ``prior_w``, ``con_a``, ``con_n``, ``con_w``,
    ``names``, ``cfg``, ``point_prior_w``, ``point_prior_axis_w``, ``_reduced`` and
    ``_prior_cost``.
    """

    # The host's state and methods used here, set by BundleSolver and SchurMixin (a
    # typed contract; annotations only, nothing is defined at run time).
    cfg: SolverConfig
    n_params: int
    names: list[str]
    active: NDArray[np.intp]
    prior_w: F64
    con_a: F64
    con_w: F64
    con_n: F64 | None
    point_prior_w: PointMatrices
    point_prior_axis_w: PointMatrices
    _reduced: Callable[[Iterate, float], tuple[F64, F64, F64, list[tuple[F64, F64, F64]]]]
    _prior_cost: Callable[[F64], float]
    cols: NDArray[np.intp]
    _structure: Callable[..., Structure]
    _linearize: Callable[..., Linearization]

    def _check_rank(self, at: Iterate, when: str) -> None:
        lin = at.lin
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
        con_n, self.con_n = self.con_n, None  # the constraints are checked apart (below)
        try:
            s_mat, _, _, _ = self._reduced(at, 0.0)
        finally:
            self.con_n = con_n
        sa = s_mat[np.ix_(act, act)]
        # Scaled by the diagonal before the point elimination: a parameter that the
        # points absorb entirely (a datum defect) shows up as a (near-)zero eigenvalue.
        d = np.sqrt(full_diag)
        z = np.eye(act.size)
        if con_n is not None:
            # The constraints (e.g. smoothed weak nodes, sigma 1e-7 rad) are as good as
            # exact, and their weights dwarf the observations': checked as weights they
            # make any determined direction look singular next to them. Checked as exact:
            # the observations must determine every direction the constraints leave free
            # (their null space; each basis vector mixes only parameters that the
            # constraints tie together, so the diagonal scaling keeps its meaning).
            d = np.sqrt(np.diag(lin.n_cc)[: self.n_params][act] + self.prior_w[act])
            a_act = self.con_a[:, act]
            a_act = a_act[np.any(a_act != 0.0, axis=1)]
            if len(a_act):
                _, r_f, perm = scipy.linalg.qr(a_act, mode="economic", pivoting=True)
                tol = abs(r_f[0, 0]) * max(a_act.shape) * np.finfo(float).eps
                rank = int(np.sum(np.abs(np.diag(r_f)) > tol))
                n_free = act.size - rank
                basis = np.zeros((act.size, n_free))
                basis[perm[:rank]] = -scipy.linalg.solve_triangular(
                    r_f[:rank, :rank], r_f[:rank, rank:]
                )
                basis[perm[rank:]] = np.eye(n_free)
                z = basis / np.linalg.norm(basis, axis=0)
            sa = z.T @ sa @ z
            d = np.sqrt(np.maximum((z * z).T @ (d * d), 0.0))
            d = np.where(d > 0, d, 1.0)  # directions no observation touches: zero rows
        sh = sa / d[:, None] / d[None, :]
        ev, vec = np.linalg.eigh(0.5 * (sh + sh.T))
        rcond = max(ev[0], 0.0) / ev[-1] if ev[-1] > 0 else 0.0
        if not rcond > self.cfg.min_rcond:
            weights = np.abs(z @ vec[:, 0])
            weights /= max(float(np.linalg.norm(weights)), 1e-300)
            top = np.argsort(weights)[::-1][:6]
            names = [f"{self.names[act[i]]} ({weights[i]:.2f})" for i in top if weights[i] > 0.05]
            raise AdjustmentError(
                f"the reduced normal matrix is singular (reciprocal condition "
                f"{rcond:.2g} < {self.cfg.min_rcond:g}, {when} cameras): the observations do "
                f"not determine a combination of {', '.join(names)}; fix or weight these "
                f"parameters (e.g. a datum: a fixed camera or control points)"
            )

    def _statistics(self, at: Iterate, s_mat: F64 | None = None) -> dict[str, object]:
        """sigma0, covariance and correlations at ``at``.

        ``s_mat``: the undamped reduced matrix at ``at`` when the caller has it (the LM
        loop's last one), else it is formed here.
        """
        lin, _, c, xyz, xyz0, unknown = at
        p = self.n_params
        if s_mat is None:
            s_mat, _, _, _ = self._reduced(at, 0.0)
        act = self.active
        # v^T P v with the final (robust) weights, plus the pseudo-observations.
        vtpv = float(np.sum(lin.weight * np.where(lin.valid[:, None], lin.r, 0.0) ** 2))
        vtpv += 2.0 * self._prior_cost(c)
        n_prior = int(np.count_nonzero(self.prior_w)) + len(self.con_w)
        if len(unknown):
            dx = xyz[unknown] - xyz0[unknown]
            vtpv += quadratic(self.point_prior_w[unknown], dx)
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
                self._check_rank(at, "adjusted")
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

    def consider_sensitivity(
        self,
        c: F64,
        xyz: F64,
        obs: NDArray[np.intp],
        xyz0: F64,
        cofactor: F64,
        layout: ConsiderLayout,
        response: str | None = None,
    ) -> ConsiderSensitivity:
        """Sensitivity of the adjusted parameters to consider parameters, ``(p, K)``.

        The consider parameters ``z`` (:class:`~planetref.adjust.consider.ConsiderLayout`,
        ``K`` columns): per reference patch an offset (east, north; metres) of the
        a-priori coordinates of its weighted points, then per key of each observation
        key kind (a camera's CCD, a matching tile) an offset (line, sample; pixels) of its
        observations. A linear estimator moves by ``dc = S^-1 d(rhs)/dz z``; the columns
        are that derivative, from one linearisation and point elimination at the solution
        (the point blocks ``V^-1`` of the elimination turn each point's share into its
        camera terms).

        With ``response`` (a key kind, e.g. ``"tile"``) it also gives what the variance
        of those keys' offsets is estimated from: per column ``t`` of that kind the
        weighted sum of its observations' residuals ``u_t = D_t^T P v``, and the
        response ``M = D_T^T P R D`` of those sums to every consider parameter (``R`` the
        residual operator, cameras and points adjusted), ``M = L - H_T^T S^-1 H`` with
        ``L = D_T^T P D - b_T^T V^-1 b`` (the point eliminations' share, point by point)
        and ``H = d(rhs)/dz``. Under ``Cov(e) = sigma0^2 P^-1 + sum sigma_j^2 D_j D_j^T``,
        ``E[u^T u] = sigma0^2 tr(M_TT) + sum_j sigma_j^2 |M_Tj|^2``
        (:func:`~planetref.adjust.consider.estimate_key_sigma`).

        Only observations of unknown (weighted or free) points take part: an offset of a
        fixed point's coordinates or of its observation is not propagated.

        Args:
            c: Adjusted parameter vector.
            xyz: Adjusted point coordinates, ``(P, 3)``.
            obs: The observations of the solution (its inliers).
            xyz0: A-priori point coordinates, ``(P, 3)``.
            cofactor: ``S^-1`` over the active parameters (zero elsewhere), ``(p, p)``.
            layout: The consider parameters.
            response: The key kind whose residual sums and response are wanted, or
                ``None``.
        """
        p = self.n_params
        k_tot = layout.n_columns
        n_patches = layout.n_patches
        point_patch = layout.point_patch
        st = self._structure(obs)
        self._unknown_ids = st.unknown
        lin = self._linearize(c, xyz, st.lay, st.tie_pos, st.n_tie, st.unknown, xyz0)
        _, _, _, blocks = self._reduced(Iterate(lin, st.chunks, c, xyz, xyz0, st.unknown), 0.0)
        rows = np.flatnonzero(st.tie_pos >= 0)
        tie_obs = np.empty(st.n_tie, np.intp)
        tie_obs[st.tie_pos[rows]] = lin.obs[rows]
        h = np.zeros((p + 1) * k_tot)
        resp = None if response is None else layout.columns(response)
        n_resp = 0 if resp is None else resp.stop - resp.start
        lmat = np.zeros((n_resp, k_tot))
        sums = np.zeros(n_resp)
        for ch, (vinv, _, _) in zip(st.chunks, blocks, strict=True):
            a = lin.a_t[ch.obs]
            we = lin.weight_t[ch.obs]
            wb = lin.b_t[ch.obs] * we[:, :, None]
            # y = A^T W B per observation, (m, q, 3).
            y = a[:, 0, :, None] * wb[:, 0, None, :] + a[:, 1, :, None] * wb[:, 1, None, :]
            gcols = self.cols[lin.gpat_t[ch.obs]]
            gpts = st.unknown[ch.pts]
            # The columns each observation's offsets (and each point's prior) enter, with
            # their b = B^T P D vectors: what the point-local terms of M are made of.
            ent_pt: list[NDArray[np.intp]] = []
            ent_col: list[NDArray[np.intp]] = []
            ent_vec: list[F64] = []

            patch = point_patch[gpts]
            if n_patches and np.any(patch >= 0):
                en = enu_rotation(xyz0[gpts])[:, :2, :]  # (n, 2, 3): east, north rows
                bp = self.point_prior_w[gpts] @ np.transpose(en, (0, 2, 1))  # (n, 3, 2)
                t = vinv @ bp
                contrib = -np.matmul(y, t[ch.pt])  # (m, q, 2)
                pp = patch[ch.pt]
                for k in range(2):
                    _scatter(h, gcols, k_tot, 2 * pp + k, contrib[:, :, k], pp >= 0)
                    if n_resp:
                        on = np.flatnonzero(patch >= 0)
                        ent_pt.append(on)
                        ent_col.append(2 * patch[on] + k)
                        ent_vec.append(bp[on, :, k])
            keys = [(kk, obs_key[tie_obs[ch.obs]], base) for kk, obs_key, base in layout.keys()]
            for _, key, base in keys:
                _key_columns(h, k_tot, key, base, (a, we, wb, y, gcols), vinv, ch)
                if n_resp:
                    on = np.flatnonzero(key >= 0)
                    for k in range(2):
                        ent_pt.append(ch.pt[on])
                        ent_col.append(base + 2 * key[on] + k)
                        ent_vec.append(wb[on, k, :])
            if n_resp and resp is not None:
                _response_terms(lmat, sums, resp, vinv, ent_pt, ent_col, ent_vec, keys, we, ch, lin)
        g_mat = cofactor @ h.reshape(p + 1, k_tot)[:p]
        response_mat = None
        if resp is not None:
            h_t = h.reshape(p + 1, k_tot)[:p, resp]
            response_mat = lmat - h_t.T @ g_mat
        return ConsiderSensitivity(g_mat, response_mat, sums if resp is not None else None)


def _response_terms(
    lmat: F64,
    sums: F64,
    resp: slice,
    vinv: F64,
    ent_pt: list[NDArray[np.intp]],
    ent_col: list[NDArray[np.intp]],
    ent_vec: list[F64],
    keys: list[tuple[str, NDArray[np.intp], int]],
    we: F64,
    ch: Any,
    lin: Any,
) -> None:
    """Add one chunk's share of ``L`` and of the residual sums (see ``consider_sensitivity``).

    ``L[t, j] = D_t^T P D_j - b_t^T V^-1 b_j`` over the rows ``t`` of ``resp``: the first
    term where an observation carries both columns (same axis), the second point by point
    over the pairs of its columns.
    """
    pts = np.concatenate(ent_pt)
    cols = np.concatenate(ent_col)
    vecs = np.concatenate(ent_vec)
    # b per (point, column): an observation-key column of a point seen twice in a key
    # sums both observations' vectors.
    uid, inv = np.unique(pts.astype(np.int64) * lmat.shape[1] + cols, return_inverse=True)
    inv = inv.ravel()
    b = np.zeros((len(uid), 3))
    np.add.at(b, inv, vecs)
    upt = (uid // lmat.shape[1]).astype(np.intp)
    ucol = (uid % lmat.shape[1]).astype(np.intp)
    vb = np.matmul(vinv[upt], b[:, :, None])[:, :, 0]
    # Pairs (first in resp, second any) of the same point: entries are sorted by point.
    first = np.flatnonzero((ucol >= resp.start) & (ucol < resp.stop))
    starts = np.searchsorted(upt, upt)  # first entry of each entry's point
    ends = np.searchsorted(upt, upt, side="right")
    owner, ib = expand_ranges(starts[first], ends[first] - starts[first])
    ia = first[owner]
    val = np.einsum("ij,ij->i", b[ia], vb[ib])
    np.add.at(lmat, (ucol[ia] - resp.start, ucol[ib]), -val)
    # D_t^T P D_j: the observations' weights where they carry both columns.
    kind_key = [key for _, key, base in keys if base == resp.start]
    if not kind_key:
        return
    rkey = kind_key[0]
    on = rkey >= 0
    if not np.any(on):
        return
    r = lin.r_t[ch.obs]
    for k in range(2):
        row = 2 * rkey[on] + k
        for _, key, base in keys:
            has = key[on] >= 0
            np.add.at(lmat, (row[has], base + 2 * key[on][has] + k), we[on, k][has])
        np.add.at(sums, row, we[on, k] * r[on, k])


def _key_columns(
    h: F64,
    k_tot: int,
    key: NDArray[np.intp],
    base: int,
    rows: tuple[F64, F64, F64, F64, NDArray[np.intp]],
    vinv: F64,
    ch: Any,
) -> None:
    """Add one chunk's ``d(rhs)/dz`` of one observation-key kind to ``h`` (flat, ``K`` wide).

    Per (point, key) entry ``E`` of the chunk and axis ``k``: ``b_E = sum B^T w`` over the
    point's observations in that key; every observation ``i`` of the point carries
    ``[key_i = g] a_ik w_ik - y_i V^-1 b_E`` in column ``base + 2 g + k`` (a tie point seen
    in another key too carries its share there). All keys at once: one pass per chunk
    whatever the number of keys (a loop over 300 tiles made the consider terms 7 times
    the adjustment's cost on 50 k MCPs).

    Args:
        h: ``d(rhs)/dz``, ``(p + 1) * K`` flat, added to.
        k_tot: ``K``.
        key: Key per chunk observation (-1: none).
        base: The kind's first column.
        rows: ``(a, we, wb, y, gcols)`` of the chunk's observations (camera partials,
            weights, ``W B``, ``A^T W B`` and the parameter columns).
        vinv: The chunk's point blocks ``V^-1``, ``(n, 3, 3)``.
        ch: The chunk (its ``pt`` and ``starts``).
    """
    a, we, wb, y, gcols = rows
    on = np.flatnonzero(key >= 0)
    if not on.size:
        return
    n_key = int(key[on].max()) + 1
    uid, e_of = np.unique(ch.pt[on].astype(np.int64) * n_key + key[on], return_inverse=True)
    e_of = e_of.ravel()
    e_pt = (uid // n_key).astype(np.intp)
    e_key = (uid % n_key).astype(np.intp)
    b = np.zeros((len(uid), 2, 3))
    np.add.at(b, e_of, wb[on])
    vb = np.matmul(vinv[e_pt][:, None], b[:, :, :, None])[..., 0]  # (E, 2, 3)
    # Pairs (observation of the entry's point, entry): the chunk's observations are
    # grouped by point (ch.starts).
    starts = np.asarray(ch.starts, np.intp)
    stops = np.append(starts[1:], len(key))
    ent, obs = expand_ranges(starts[e_pt], stops[e_pt] - starts[e_pt])
    obs_entry = np.full(len(key), -1, np.intp)
    obs_entry[on] = e_of
    own = obs_entry[obs] == ent
    for k in range(2):
        contrib = -np.matmul(y[obs], vb[ent, k, :, None])[:, :, 0]
        contrib[own] += a[obs[own], k, :] * we[obs[own], k, None]
        col = base + 2 * e_key[ent] + k
        idx = gcols[obs] * k_tot + col[:, None]
        h += np.bincount(idx.ravel(), contrib.ravel(), minlength=h.size)


def _scatter(
    h: F64,
    gcols: NDArray[np.intp],
    k_tot: int,
    col: NDArray[np.intp],
    contrib: F64,
    on: NDArray[np.bool_],
) -> None:
    """``h[gcols[i, j], col[i]] += contrib[i, j]`` for the rows ``on`` (``h`` flat)."""
    idx = gcols[on] * k_tot + col[on, None]
    h += np.bincount(idx.ravel(), contrib[on].ravel(), minlength=h.size)
