"""Redundancy numbers and variance component estimation (VCE) of a bundle adjustment.

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

Variance components
-------------------
Foerstner's iteration: per group ``g`` of equations, ``s_g^2 = v^T P_g v / r_g``; the
group's sigmas are multiplied by ``s_g`` and the adjustment repeated until every
``s_g`` is ~1. Groups with little redundancy keep their a-priori sigmas. Pseudo-
observations (camera priors, smoothing constraints, tie-point priors) are a choice of
datum and regularisation, not measurements: their factors are reported but never
applied.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.adjust.config import VarianceConfig
from planetref.adjust.solver import BundleSolver
from planetref.errors import AdjustmentError

__all__ = ["Redundancy", "VceResult", "redundancy", "variance_components"]

log = logging.getLogger("planetref.adjust")

#: Relative predicted cost decrease at which a re-weighted adjustment stops.
_VCE_FTOL = 1e-9
#: Most LM iterations of one re-weighted adjustment.
_VCE_MAX_LM = 8
F64 = NDArray[np.float64]
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

    @property
    def obs_order(self) -> NDArray[np.intp]:
        """Argsort of :attr:`obs`."""
        return np.argsort(self.obs)

    @property
    def total(self) -> float:
        """Sum of all redundancy numbers (the degrees of freedom)."""
        return float(self.obs_r.sum() + self.point_r.sum() + self.camera_r + self.constraint_r)


def redundancy(
    solver: BundleSolver,
    c: F64,
    xyz: F64,
    obs: NDArray[np.intp],
    xyz0: F64,
    cofactor: F64,
) -> Redundancy:
    """Redundancy numbers of every equation at a solution (plain least-squares weights).

    Args:
        solver: The solver (models, weights, priors).
        c: Adjusted global camera vector.
        xyz: Adjusted coordinates of every point, ``(P, 3)``.
        obs: The observations that took part.
        xyz0: A-priori point coordinates.
        cofactor: ``S^-1`` of the camera parameters (zero rows for fixed ones),
            ``(n_params, n_params)``.

    Returns:
        The :class:`Redundancy`.
    """
    # The solver's layout of these observations: contiguous (camera, CCD) ranges with
    # the per-observation data gathered once (the redundancy follows its order).
    lay = solver._structure(np.asarray(obs, np.intp)).lay
    obs = lay.obs
    n = len(obs)
    q = solver.q
    w = solver.obs_w0[obs]
    pt = lay.point
    unknown_pt = ~solver.point_fixed[pt]
    # Observations of fixed points need only their own G_ii, computed chunk by chunk;
    # the partials of those of unknown points are kept for the pairs below.
    t_all = np.flatnonzero(unknown_pt)
    tpos = np.full(n, -1, np.intp)
    tpos[t_all] = np.arange(len(t_all))
    a_u = np.zeros((len(t_all), 2, q))
    gpat_u = np.zeros(len(t_all), np.intp)
    b_u = np.zeros((len(t_all), 2, 3))
    v_all = np.zeros((n, 2))
    h = np.zeros((n, 2, 2))
    pxyz = lay.fixed_xyz if lay.fixed_xyz is not None else xyz[pt]
    cs = solver.cfg.chunk_size
    for mi, ccd, a0, b0 in lay.ranges:
        model = solver.models[mi]
        x = c[solver.offsets[mi] : solver.offsets[mi + 1]]
        for a in range(a0, b0, cs):
            b = min(a + cs, b0)
            ev = model.evaluate(
                x, pxyz[a:b], ccd, lay.line_guess[a:b], rate_guess=lay.rate_guess[a:b]
            )
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
    pairs = _PairG(solver, a_u, gpat_u, cofactor)
    # Observations of unknown points, sorted by point (positions into obs; ``tpos``
    # maps them into the kept partials).
    t = t_all[np.argsort(pt[t_all], kind="stable")]
    unknown, first, counts = np.unique(pt[t], return_index=True, return_counts=True)
    u = len(unknown)
    loc = np.repeat(np.arange(u), counts)
    bt = b_u[tpos[t]]
    bw = bt * w[t][:, :, None]  # W B, (m, 2, 3)
    vmat = np.einsum("mki,mkj->mij", bt, bw)
    vsum = np.zeros((u, 3, 3))
    np.add.at(vsum, loc, vmat)
    vsum += solver.point_prior_w[unknown]
    vinv = np.linalg.inv(vsum)
    cmat = np.matmul(vinv[loc], np.transpose(bw, (0, 2, 1)))  # C_k = V^-1 B^T W, (m, 3, 2)
    # Pairs (i, k) of observations of the same point, in t's order.
    cnt = counts[loc]
    pa = np.repeat(np.arange(len(t)), cnt)
    within = np.arange(len(pa)) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    pb = first[loc[pa]] + within
    tmat = np.zeros((len(t), 2, 3))
    umat = np.zeros((u, 3, 3))
    for s0 in range(0, len(pa), _PAIR_CHUNK):
        ia, ib = pa[s0 : s0 + _PAIR_CHUNK], pb[s0 : s0 + _PAIR_CHUNK]
        g = pairs(tpos[t[ia]], tpos[t[ib]])  # (k, 2, 2)
        gc = np.matmul(g, np.transpose(cmat[ib], (0, 2, 1)))  # G_ik C_k^T, (k, 2, 3)
        np.add.at(tmat, ia, gc)
        np.add.at(umat, loc[ia], np.matmul(cmat[ia], gc))
        diag = ia == ib
        h[t[ia[diag]]] = g[diag]
    btt = np.transpose(bt, (0, 2, 1))
    qjj = vinv + umat
    h[t] += (
        -np.matmul(tmat, btt)
        - np.matmul(bt, np.transpose(tmat, (0, 2, 1)))
        + np.matmul(np.matmul(bt, qjj[loc]), btt)
    )
    obs_r = 1.0 - w * np.stack([h[:, 0, 0], h[:, 1, 1]], axis=1)
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
    )


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


# ------------------------------------------------------------------ groups and VCE
@dataclass
class _Group:
    name: str
    kind: str  # "image" | "ground" | "prior"
    obs: NDArray[np.intp] = field(default_factory=lambda: np.zeros(0, np.intp))
    points: NDArray[np.intp] = field(default_factory=lambda: np.zeros(0, np.intp))
    axes: tuple[int, ...] = ()
    estimate: bool = True


def _groups(solver: BundleSolver, obs: NDArray[np.intp]) -> list[_Group]:
    """Image groups (point kind x camera/CCD) and the a-priori ground groups.

    Integer codes stand in for the kind and label strings (one string pass over the
    points, none over the observations); the groups come in the order of their names.
    """
    net = solver.net
    kinds, kind_of_pt = net.point_kind_codes
    base = max(len(cam.ccd_names) for cam in net.cameras)
    image_key = net.obs_camera[obs].astype(np.int64) * base + net.obs_ccd[obs]
    kind_obs = kind_of_pt[net.obs_point[obs]]
    labels = {}
    for key in np.flatnonzero(np.bincount(image_key)):
        cam = net.cameras[int(key) // base]
        cid = net.camera_ids[int(key) // base]
        names = cam.ccd_names
        labels[int(key)] = cid if len(names) == 1 else f"{cid}/{names[int(key) % base]}"
    out: list[_Group] = []
    for k in np.flatnonzero(np.bincount(kind_obs)):  # kinds are sorted by name
        in_kind = kind_obs == k
        for key, lab in sorted(labels.items(), key=lambda kv: kv[1]):
            sel = obs[in_kind & (image_key == key)]
            if sel.size:
                out.append(_Group(f"image {kinds[k]} {lab}", "image", obs=sel))
    pts = np.flatnonzero(np.bincount(net.obs_point[obs], minlength=net.n_points))
    weighted = pts[
        ~solver.point_fixed[pts]
        & np.any(np.isfinite(solver.point_sigma[pts]) & (solver.point_sigma[pts] > 0), axis=1)
    ]
    pk = kind_of_pt[weighted]
    local = np.asarray(net.point_sigma_local)[weighted]
    for code in np.flatnonzero(np.bincount(pk)):
        k = str(kinds[code])
        estimate = k == "mcp"
        kind_g = "ground" if estimate else "prior"
        m = pk == code
        if np.any(m & local):
            sel = weighted[m & local]
            out.append(
                _Group(
                    f"ground {k} planimetric", kind_g, points=sel, axes=(0, 1), estimate=estimate
                )
            )
            out.append(
                _Group(f"ground {k} height", kind_g, points=sel, axes=(2,), estimate=estimate)
            )
        if np.any(m & ~local):
            sel = weighted[m & ~local]
            out.append(_Group(f"ground {k}", kind_g, points=sel, axes=(0, 1, 2), estimate=estimate))
    return out


def _single_view_notes(
    solver: BundleSolver, obs: NDArray[np.intp], groups: list[_Group]
) -> dict[str, str]:
    """Groups whose split is the a-priori ratio: single-view weighted MCPs.

    A weighted MCP seen in one image only has one discrepancy (image measure against
    reference ground) shared by its image and its ground equations: only the sum of
    their variances is estimable, and the iteration keeps the a-priori ratio of the two.
    """
    net = solver.net
    pt = net.obs_point[obs]
    views = np.bincount(pt, minlength=net.n_points)
    weighted = ~solver.point_fixed & np.any(
        np.isfinite(solver.point_sigma) & (solver.point_sigma > 0), axis=1
    )
    single = weighted & (views == 1)
    out = {}
    text = (
        "single-view weighted MCPs: image and ground noise are confounded; their split "
        "is the a-priori ratio, only the sum is estimated"
    )
    for g in groups:
        pts = net.obs_point[g.obs] if g.kind == "image" else g.points
        if g.kind != "prior" and pts.size and np.mean(single[pts]) > 0.5:
            out[g.name] = text
    return out


def _image_group_of(solver: BundleSolver, groups: list[_Group]) -> NDArray[np.intp]:
    """Per network observation, the index of its image group in ``groups`` (or -1)."""
    gid = np.full(solver.net.n_obs, -1, np.intp)
    for i, g in enumerate(groups):
        if g.kind == "image":
            gid[g.obs] = i
    return gid


def _image_sums(
    groups: list[_Group], red: Redundancy, group_of: NDArray[np.intp]
) -> dict[str, tuple[float, float, int]]:
    """``(v^T P v, redundancy, equations)`` of every image group in one pass."""
    rg = group_of[red.obs]
    on = rg >= 0
    vtpv = np.bincount(
        rg[on], weights=np.sum(red.obs_w * red.obs_v**2, axis=1)[on], minlength=len(groups)
    )
    r = np.bincount(rg[on], weights=red.obs_r.sum(axis=1)[on], minlength=len(groups))
    return {
        g.name: (float(vtpv[i]), float(r[i]), 2 * len(g.obs))
        for i, g in enumerate(groups)
        if g.kind == "image"
    }


def _group_stats(
    g: _Group, red: Redundancy, image: dict[str, tuple[float, float, int]]
) -> tuple[float, float, int]:
    """``(v^T P v, redundancy, number of equations)`` of a group.

    ``image``: the sums of the image groups (:func:`_image_sums`).
    """
    if g.kind == "image":
        return image[g.name]
    order = np.argsort(red.points)
    pos = order[np.searchsorted(red.points, g.points, sorter=order)]
    ax = list(g.axes)
    v, w, r = red.point_v[pos][:, ax], red.point_w[pos][:, ax], red.point_r[pos][:, ax]
    on = w > 0
    return float(np.sum(w[on] * v[on] ** 2)), float(np.sum(r[on])), int(np.count_nonzero(on))


@dataclass
class VceResult:
    """What the variance component estimation did.

    Attributes:
        groups: Per group: name, kind, equations, redundancy, ``v^T P v``, the last
            factor ``s_g``, the cumulative scale of its sigmas and whether it was
            estimated (and if not, why).
        iterations: Re-weighting iterations (adjustments after the first).
        converged: Every estimated factor ended within the tolerance of 1.
        redundancy: The redundancy numbers at the final solution.
        stopped: Why the iteration stopped early ("" if it did not).
    """

    groups: list[dict[str, Any]]
    iterations: int
    converged: bool
    redundancy: Redundancy
    stopped: str = ""

    def dof_split(self) -> dict[str, Any]:
        """Equations and redundancy of real observations and of pseudo-observations."""
        red = self.redundancy
        real_n = 2 * len(red.obs)
        real_r = float(red.obs_r.sum())
        real_vtpv = float(np.sum(red.obs_w * red.obs_v**2))
        pseudo_n = red.camera_n + red.constraint_n
        pseudo_r = red.camera_r + red.constraint_r
        pseudo_vtpv = red.camera_vtpv + red.constraint_vtpv
        for g in self.groups:
            if g["kind"] == "ground":
                real_n += g["n_equations"]
                real_r += g["redundancy"]
                real_vtpv += g["vtpv"]
            elif g["kind"] == "prior":
                pseudo_n += g["n_equations"]
                pseudo_r += g["redundancy"]
                pseudo_vtpv += g["vtpv"]
        return {
            "n_real_equations": real_n,
            "n_pseudo_equations": pseudo_n,
            "n_camera_priors": red.camera_n,
            "n_smoothing_constraints": red.constraint_n,
            "redundancy_real": real_r,
            "redundancy_pseudo": pseudo_r,
            "vtpv_real": real_vtpv,
            "vtpv_pseudo": pseudo_vtpv,
            "sigma0_real": math.sqrt(real_vtpv / real_r) if real_r > 0 else float("nan"),
        }


def variance_components(
    solver: BundleSolver,
    c: F64,
    xyz: F64,
    obs: NDArray[np.intp],
    xyz0: F64,
    stats: dict[str, Any],
    cfg: VarianceConfig,
    progress: Callable[[str], None] | None = None,
) -> tuple[F64, F64, dict[str, Any], VceResult]:
    """Estimate the variance components by re-weighting and re-adjusting.

    Args:
        solver: The solver at the end of the outlier rounds (its loss is set linear).
        c: Camera vector of that solution.
        xyz: Point coordinates of that solution.
        obs: The inliers.
        xyz0: A-priori point coordinates.
        stats: The solver's statistics of that solution.
        cfg: VCE settings (``enabled`` False: only the redundancy and factors).
        progress: Optional progress callback.

    Returns:
        ``(c, xyz, stats, VceResult)`` of the final solution (the solver keeps the
        re-weighted sigmas).
    """
    groups = _groups(solver, obs)
    scale = {g.name: 1.0 for g in groups}
    confounded = _single_view_notes(solver, obs, groups)
    solver.loss, solver.threshold = "linear", np.inf
    iterations = 0
    converged = False
    stopped = ""
    group_of = _image_group_of(solver, groups)
    while True:
        red = redundancy(solver, c, xyz, obs, xyz0, stats["cofactor"])
        image = _image_sums(groups, red, group_of)
        table = []
        factors: dict[str, float] = {}
        for g in groups:
            vtpv, r, n_eq = _group_stats(g, red, image)
            f = math.sqrt(vtpv / r) if r > 0 else float("nan")
            why = ""
            if not g.estimate:
                why = "a-priori constraint (datum), not a measurement"
            elif not r >= cfg.min_redundancy:
                why = f"redundancy {r:.3g} < {cfg.min_redundancy:g}"
            table.append(
                {
                    "group": g.name,
                    "kind": g.kind,
                    "n_equations": n_eq,
                    "redundancy": r,
                    "vtpv": vtpv,
                    "factor": f,
                    "estimated": not why and cfg.enabled,
                    "not_estimated_because": why or (None if cfg.enabled else "VCE disabled"),
                }
            )
            if g.kind == "image":
                floor = bool(np.all(solver.obs_sigma[g.obs] <= cfg.min_sigma_px * (1 + 1e-9)))
            else:
                sig_g = solver.point_sigma[np.ix_(g.points, list(g.axes))]
                floor = bool(np.all(sig_g <= cfg.min_sigma_m * (1 + 1e-9)))
            table[-1]["at_floor"] = floor and f < 1.0
            if not why and math.isfinite(f) and f > 0 and not (floor and f < 1.0):
                factors[g.name] = f
        if not cfg.enabled:
            break
        if all(abs(f - 1.0) <= cfg.tolerance for f in factors.values()):
            converged = True
            break
        if iterations >= cfg.max_iterations:
            break
        obs_sig0 = solver.obs_sigma.copy()
        pt_sig0 = solver.point_sigma.copy()
        obs_sig, pt_sig = obs_sig0.copy(), pt_sig0.copy()
        moved = False
        for g in groups:
            f = factors.get(g.name)
            if f is None:
                continue
            f = min(max(f, 1.0 / cfg.max_step), cfg.max_step)
            if g.kind == "image":
                new = np.maximum(obs_sig[g.obs] * f, cfg.min_sigma_px)
                step = new / obs_sig[g.obs]
                obs_sig[g.obs] = new
            else:
                idx = np.ix_(g.points, list(g.axes))
                new = np.maximum(pt_sig[idx] * f, cfg.min_sigma_m)
                step = new / pt_sig[idx]
                pt_sig[idx] = new
            scale[g.name] *= float(np.exp(np.mean(np.log(step))))
            moved |= bool(np.any(np.abs(step - 1.0) > 1e-12))
        if not moved:  # every factor is held at its floor
            break
        solver.set_obs_sigma(obs_sig)
        solver.set_point_sigma(pt_sig)
        iterations += 1
        if progress is not None:
            progress(
                f"variance components {iterations}: "
                + ", ".join(f"{k} x{v:.3g}" for k, v in factors.items())
            )
        # Each re-weighting starts at the previous optimum and the weights themselves are
        # only known to ``tolerance``: a few Gauss-Newton steps to a looser cost floor
        # reach the new optimum (a full solve to ftol = 1e-12 took ~30 passes each).
        base_cfg = solver.cfg
        solver.cfg = base_cfg.model_copy(
            update={
                "ftol": max(base_cfg.ftol, _VCE_FTOL),
                "max_iterations": min(base_cfg.max_iterations, _VCE_MAX_LM),
            }
        )
        try:
            # Positive re-weighting cannot change the rank: no rank check again.
            c_new, xyz_new, _rep, _lin, stats_new = solver.run(c, xyz, obs, xyz0, check_rank=False)
        except AdjustmentError as exc:
            solver.cfg = base_cfg
            # Keep the last good solution and its weights.
            solver.set_obs_sigma(obs_sig0)
            solver.set_point_sigma(pt_sig0)
            stopped = f"stopped: the re-weighted adjustment failed ({exc})"
            log.warning("variance components %s", stopped)
            break
        solver.cfg = base_cfg
        c, xyz, stats = c_new, xyz_new, stats_new
    for row in table:
        row["sigma_scale"] = scale[row["group"]]
        row["note"] = confounded.get(row["group"], "")
    for g, row in zip(groups, table, strict=True):
        if g.kind == "image":
            sig = solver.obs_sigma[g.obs]
            row["sigma_px"] = float(np.sqrt(np.mean(sig**2)))
        else:
            sig = solver.point_sigma[np.ix_(g.points, list(g.axes))]
            row["sigma_m"] = float(np.sqrt(np.mean(sig**2)))
    return c, xyz, stats, VceResult(table, iterations, converged, red, stopped)
