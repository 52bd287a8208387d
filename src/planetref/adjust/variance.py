"""Variance component estimation (VCE) of a bundle adjustment.

The redundancy numbers it rests on are computed in :mod:`planetref.adjust.redundancy`.

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
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

from planetref.adjust.config import VarianceConfig
from planetref.adjust.linearization import Linearization, group_kernels
from planetref.adjust.redundancy import Redundancy, group_sum, redundancy
from planetref.adjust.solver import BundleSolver
from planetref.arrays import F64
from planetref.errors import AdjustmentError

__all__ = ["Redundancy", "VceResult", "redundancy", "variance_components"]

log = logging.getLogger("planetref.adjust")

#: Relative predicted cost decrease at which a re-weighted adjustment stops.
_VCE_FTOL = 1e-9
#: Most LM iterations of one re-weighted adjustment.
_VCE_MAX_LM = 8


# ------------------------------------------------------------------ groups and VCE
@dataclass
class _Group:
    name: str
    kind: str  # "image" | "ground" | "prior"
    obs: NDArray[np.intp] = field(default_factory=lambda: np.zeros(0, np.intp))
    points: NDArray[np.intp] = field(default_factory=lambda: np.zeros(0, np.intp))
    axes: tuple[int, ...] = ()
    estimate: bool = True
    mcp: bool = False  # MCPs' measures (VarianceConfig.mcp_weight_share applies)


def _groups(solver: BundleSolver, obs: NDArray[np.intp]) -> list[_Group]:
    """Image groups (point kind x camera/CCD) and the a-priori ground groups.

    Integer codes stand in for the kind and label strings (one string pass over the
    points, none over the observations); the groups come in the order of their names.
    """
    net = solver.net
    kinds, kind_of_pt = net.point_kind_codes
    base = max(len(cam.ccd_names) for cam in net.cameras)
    n_keys = len(net.cameras) * base
    # One stable sort by (kind, camera, CCD) gives every image group its observations
    # in the order of ``obs``, as a mask per group would.
    fn = group_kernels()
    args = (obs, net.obs_camera, net.obs_ccd, net.obs_point, kind_of_pt, base, n_keys, len(kinds))
    order, bounds = _group_order_numpy(*args) if fn is None else fn.group_order(*args)
    counts = np.diff(bounds).reshape(len(kinds), n_keys)
    labels: dict[int, str] = {}
    for key in map(int, np.flatnonzero(counts.sum(axis=0))):
        cam = net.cameras[key // base]
        cid = net.camera_ids[key // base]
        names = cam.ccd_names
        labels[key] = cid if len(names) == 1 else f"{cid}/{names[key % base]}"
    out: list[_Group] = []
    for ki in np.flatnonzero(counts.sum(axis=1)):  # kinds are sorted by name
        for key in sorted(labels, key=lambda key: labels[key]):
            cc = int(ki) * n_keys + key
            sel = obs[order[bounds[cc] : bounds[cc + 1]]]
            if sel.size:
                out.append(
                    _Group(
                        f"image {kinds[ki]} {labels[key]}",
                        "image",
                        obs=sel,
                        mcp=str(kinds[ki]) == "mcp",
                    )
                )
    if not np.any(~solver.point_fixed):  # no unknown point: no ground group
        return out
    pts = np.flatnonzero(np.bincount(net.obs_point[obs], minlength=net.n_points))
    unknown = pts[~solver.point_fixed[pts]]
    weighted = unknown[_has_prior(solver.point_sigma[unknown])]
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
                    f"ground {k} planimetric",
                    kind_g,
                    points=sel,
                    axes=(0, 1),
                    estimate=estimate,
                    mcp=estimate,
                )
            )
            out.append(
                _Group(
                    f"ground {k} height",
                    kind_g,
                    points=sel,
                    axes=(2,),
                    estimate=estimate,
                    mcp=estimate,
                )
            )
        if np.any(m & ~local):
            sel = weighted[m & ~local]
            out.append(
                _Group(
                    f"ground {k}",
                    kind_g,
                    points=sel,
                    axes=(0, 1, 2),
                    estimate=estimate,
                    mcp=estimate,
                )
            )
    return out


def _group_order_numpy(
    obs: NDArray[np.intp],
    obs_camera: NDArray[np.intp],
    obs_ccd: NDArray[np.intp],
    obs_point: NDArray[np.intp],
    kind_of_pt: NDArray[np.intp],
    base: int,
    n_keys: int,
    n_kinds: int,
) -> tuple[NDArray[np.intp], NDArray[np.int64]]:
    """The reference of :func:`planetref.adjust._numba_groups.group_order`."""
    code = (
        kind_of_pt[obs_point[obs]].astype(np.int64) * n_keys
        + obs_camera[obs].astype(np.int64) * base
        + obs_ccd[obs]
    )
    n_code = n_kinds * n_keys
    order = np.argsort(code, kind="stable")
    bounds = np.concatenate([[0], np.cumsum(np.bincount(code, minlength=n_code))])
    return order, bounds


def _group_vtpv_numpy(group: NDArray[np.intp], w: F64, v: F64, n_groups: int) -> F64:
    """The reference of :func:`planetref.adjust._numba_groups.group_vtpv`."""
    return group_sum(group, w[:, 0] * v[:, 0] ** 2 + w[:, 1] * v[:, 1] ** 2, n_groups)


def _has_prior(sigma: F64) -> NDArray[np.bool_]:
    """Rows of ``(n, 3)`` sigmas with a finite positive sigma on some axis."""
    ok = np.isfinite(sigma) & (sigma > 0)
    return ok[:, 0] | ok[:, 1] | ok[:, 2]


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
    # Weighted points (unknown, with a finite positive sigma) seen once.
    once = np.flatnonzero(~solver.point_fixed & (views == 1))
    once = once[_has_prior(solver.point_sigma[once])]
    out: dict[str, str] = {}
    if not once.size:
        return out
    single = np.zeros(net.n_points, bool)
    single[once] = True
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
    # Per observation w_l v_l^2 + w_s v_s^2 (the row sums of w v^2), summed per group.
    fn = group_kernels()
    args = (red.row_groups(group_of), red.obs_w, red.obs_v, len(groups))
    vtpv = _group_vtpv_numpy(*args) if fn is None else fn.group_vtpv(*args)
    r = red.image_sums(group_of, len(groups))
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


def _image_at_floor(
    solver: BundleSolver, group_of: NDArray[np.intp], n_groups: int, min_sigma_px: float
) -> NDArray[np.bool_]:
    """Per group: every sigma of its observations is at the floor (``min_sigma_px``)."""
    sig = solver.obs_sigma
    thr = min_sigma_px * (1 + 1e-9)
    above = ~((sig[:, 0] <= thr) & (sig[:, 1] <= thr)) & (group_of >= 0)
    return np.bincount(group_of[above], minlength=n_groups) == 0


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
        real_r = red.image_total
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
    lin: Linearization | None = None,
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
        lin: The solver's final linearisation of ``obs`` at ``(c, xyz)`` (spares the
            redundancy numbers a pass over the observations; see
            :func:`~planetref.adjust.redundancy.redundancy`).

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
    capped = False  # the last re-weighted adjustment stopped at _VCE_MAX_LM unconverged
    while True:
        red = redundancy(solver, c, xyz, obs, xyz0, _cofactor(stats), lin)
        image = _image_sums(groups, red, group_of)
        table: list[dict[str, Any]] = []
        factors: dict[str, float] = {}
        img_floor = _image_at_floor(solver, group_of, len(groups), cfg.min_sigma_px)
        for i, g in enumerate(groups):
            vtpv, r, n_eq = _group_stats(g, red, image)
            share = cfg.mcp_weight_share if g.mcp else 1.0
            f = math.sqrt(vtpv / (share * r)) if r > 0 else float("nan")
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
                floor = bool(img_floor[i])
            else:
                sig_g = solver.point_sigma[np.ix_(g.points, np.asarray(g.axes, np.intp))]
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
            f_g = factors.get(g.name)
            if f_g is None:
                continue
            f = min(max(f_g, 1.0 / cfg.max_step), cfg.max_step)
            if g.kind == "image":
                new = np.maximum(obs_sig[g.obs] * f, cfg.min_sigma_px)
                step = new / obs_sig[g.obs]
                obs_sig[g.obs] = new
            else:
                idx = np.ix_(g.points, np.asarray(g.axes, np.intp))
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
            c_new, xyz_new, _rep, lin_new, stats_new = solver.run(
                c, xyz, obs, xyz0, check_rank=False
            )
        except AdjustmentError as exc:
            solver.cfg = base_cfg
            # Keep the last good solution and its weights.
            solver.set_obs_sigma(obs_sig0)
            solver.set_point_sigma(pt_sig0)
            stopped = f"stopped: the re-weighted adjustment failed ({exc})"
            log.warning("variance components %s", stopped)
            break
        solver.cfg = base_cfg
        c, xyz, stats, lin = c_new, xyz_new, stats_new, lin_new
        capped = not _rep.converged
    if capped and not stopped:
        # The re-weighted adjustments stop after a few steps (the weights are only known
        # to ``tolerance``), but the solution handed back must be the optimum of the
        # final weights: finish it with the solver's own limits, then take its
        # redundancy numbers (the factors above stay those that ended the iteration).
        c, xyz, _rep, lin, stats = solver.run(c, xyz, obs, xyz0, check_rank=False)
        red = redundancy(solver, c, xyz, obs, xyz0, _cofactor(stats), lin)
    for row in table:
        row["sigma_scale"] = scale[row["group"]]
        row["note"] = confounded.get(row["group"], "")
    for g, row in zip(groups, table, strict=True):
        if g.kind == "image":
            sig = solver.obs_sigma[g.obs]
            row["sigma_px"] = float(np.sqrt(np.mean(sig**2)))
        else:
            sig = solver.point_sigma[np.ix_(g.points, np.asarray(g.axes, np.intp))]
            row["sigma_m"] = float(np.sqrt(np.mean(sig**2)))
    return c, xyz, stats, VceResult(table, iterations, converged, red, stopped)


def _cofactor(stats: dict[str, object]) -> F64:
    """The camera cofactor ``S^-1`` of the solver's statistics, ``(n_params, n_params)``.

    The statistics are a plain mapping of mixed values (see the solver's ``run``); this
    names the type of the one entry read here.
    """
    return cast(F64, stats["cofactor"])
