"""The adjustment as one call: :func:`adjust` a :class:`~planetref.adjust.problem.Network`.

Steps: parameterise every camera, triangulate free points without coordinates, drop
observations that cannot be projected or whose free point has too few rays, check that
every parameter group is observed, then alternate Levenberg-Marquardt and the ``k x
RMSE`` outlier rule until the inlier set is stable, and compute the metrics before and
after.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.adjust._blas import single_threaded_blas
from planetref.adjust.config import AdjustConfig, validate_config
from planetref.adjust.diagnostics import (
    camera_shifts,
    correlation_warnings,
    point_summary,
    point_table,
    self_calibration,
)
from planetref.adjust.models import AdjustableCamera, parameterize
from planetref.adjust.outliers import classify_inliers, robust_scale, supported
from planetref.adjust.problem import Network
from planetref.adjust.solver import BundleSolver, LmReport
from planetref.adjust.variance import VceResult, variance_components
from planetref.errors import AdjustmentError
from planetref.geometry.geodesy import ray_ellipsoid_intersection, xyz_to_lonlat
from planetref.metrics import reprojection_metrics

__all__ = ["AdjustmentResult", "adjust", "rays", "triangulate"]

log = logging.getLogger("planetref.adjust")
F64 = NDArray[np.float64]

#: Observation status codes of :attr:`AdjustmentResult.status`.
STATUSES = ("inlier", "outlier", "unusable", "check")


@dataclass(frozen=True, eq=False)
class AdjustmentResult:
    """Everything an adjustment produced.

    Attributes:
        network: The input network.
        config: The configuration used.
        models: The cameras' parameterisations (names, units, modes).
        cameras_initial: Camera id -> initial camera.
        cameras: Camera id -> adjusted camera.
        parameter_names: ``"camera_id:name"`` per global parameter.
        parameter_units: Unit per parameter.
        parameter_mode: ``0`` free, ``1`` weighted, ``2`` fixed, per parameter.
        x0: Initial parameter values.
        x: Adjusted parameter values.
        sigma: A-posteriori standard deviations (0 for fixed parameters).
        covariance: A-posteriori covariance of the parameters, ``(n, n)``.
        correlation: Correlation matrix, ``(n, n)``.
        point_xyz_initial: Initial point coordinates (after triangulation), ``(P, 3)``.
        point_xyz: Adjusted point coordinates, ``(P, 3)``.
        residual_initial: ``(line, sample)`` residuals (px) with the initial cameras and
            points, ``(M, 2)``, NaN where not projectable.
        residual: Residuals after the adjustment, ``(M, 2)``.
        status: Per observation ``inlier``, ``outlier``, ``unusable`` or ``check``.
        sigma0: A-posteriori standard deviation of unit weight.
        dof: Degrees of freedom (redundancy).
        metrics: Reprojection metrics before/after, overall, per camera and per CCD,
            and of the check observations (see :func:`adjust`).
        variance: Variance components per observation group, their iterations, and the
            degrees of freedom split into real observations (image measures, MCP
            ground coordinates) and pseudo-observations (camera priors, smoothing
            constraints, tie-point priors).
        points: Per point columns (a-priori and adjusted coordinates, sigmas, shifts;
            see :func:`~planetref.adjust.diagnostics.point_table`).
        diagnostics: Point and camera movements, strong correlations and the
            estimability of the self-calibration parameters.
        rounds: Per outlier round: inliers, RMSE, LM iterations, cost.
        converged: The last LM run converged and the inlier set is stable.
        warnings: Messages about auto-weighted groups, unusable points, instability.
        seconds: Wall time of the adjustment.
    """

    network: Network
    config: AdjustConfig
    models: list[AdjustableCamera]
    cameras_initial: dict[str, Any]
    cameras: dict[str, Any]
    parameter_names: list[str]
    parameter_units: list[str]
    parameter_mode: NDArray[np.int8]
    x0: F64
    x: F64
    sigma: F64
    covariance: F64
    correlation: F64
    point_xyz_initial: F64
    point_xyz: F64
    residual_initial: F64
    residual: F64
    status: NDArray[np.str_]
    sigma0: float
    dof: int
    metrics: dict[str, Any]
    variance: dict[str, Any] = field(default_factory=dict)
    points: dict[str, Any] = field(default_factory=dict)
    diagnostics: dict[str, Any] = field(default_factory=dict)
    rounds: list[dict[str, Any]] = field(default_factory=list)
    converged: bool = False
    warnings: list[str] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def inlier(self) -> NDArray[np.bool_]:
        """True for inlier observations."""
        return self.status == "inlier"

    def summary(self) -> dict[str, Any]:
        """The headline numbers (the ``adjustment`` block of report.json)."""
        after = self.metrics["all"]["after"]
        before = self.metrics["all"]["before"]
        dof = self.variance.get("dof", {})
        return {
            "rmse_px_before": before["rmse_px"],
            "rmse_x_px": after["rmse_x_px"],
            "rmse_y_px": after["rmse_y_px"],
            "rmse_px_before_all": self.metrics["all"]["before_all"]["rmse_px"],
            "rmse_px": after["rmse_px"],
            "mean_px_before": before["mean_px"],
            "mean_px": after["mean_px"],
            "outlier_ratio_pct": after["outlier_ratio_pct"],
            "n_total": after["n_total"],
            "n_inliers": after["n_inliers"],
            "n_unusable": int(np.count_nonzero(self.status == "unusable")),
            "n_check": int(np.count_nonzero(self.status == "check")),
            "sigma0": self.sigma0,
            "sigma0_real": dof.get("sigma0_real"),
            "dof": self.dof,
            "redundancy_real": dof.get("redundancy_real"),
            "redundancy_pseudo": dof.get("redundancy_pseudo"),
            "n_pseudo_equations": dof.get("n_pseudo_equations"),
            "rounds": len(self.rounds),
            "converged": self.converged,
            "seconds": self.seconds,
        }


# ------------------------------------------------------------------ geometry helpers
def rays(
    camera: Any,
    line: F64,
    sample: F64,
    ccd: str | None,
    heights: tuple[float, float] = (-10_000.0, 10_000.0),
) -> tuple[F64, F64]:
    """Body-fixed rays of image points of any camera, from two terrain intersections.

    Returns:
        ``(point, unit direction)`` per image point, ``(m, 3)`` each (NaN if a ray misses).
    """
    lo = camera.image_to_ground(line, sample, heights[0], ccd=ccd, on_miss="nan")
    hi = camera.image_to_ground(line, sample, heights[1], ccd=ccd, on_miss="nan")
    d = lo - hi
    with np.errstate(invalid="ignore", divide="ignore"):
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
    return hi, d


def triangulate(
    network: Network, cameras: list[Any], points: NDArray[np.intp], obs_mask: NDArray[np.bool_]
) -> F64:
    """Least-squares intersection of the rays of each point's observations.

    Args:
        network: The network.
        cameras: Cameras, in the network's order.
        points: Indices of the points to triangulate.
        obs_mask: Observations that may be used.

    Returns:
        ``(len(points), 3)`` XYZ in metres; NaN for points with fewer than two rays or
        parallel rays.
    """
    out = np.full((len(points), 3), np.nan)
    if not len(points):
        return out
    pmap = np.full(network.n_points, -1, np.intp)
    pmap[points] = np.arange(len(points))
    use = obs_mask & (pmap[network.obs_point] >= 0)
    a = np.zeros((len(points), 3, 3))
    b = np.zeros((len(points), 3))
    n = np.zeros(len(points), np.intp)
    for ci, cam in enumerate(cameras):
        for k, name in enumerate(cam.ccd_names):
            sel = np.flatnonzero(use & (network.obs_camera == ci) & (network.obs_ccd == k))
            if not sel.size:
                continue
            o, d = rays(cam, network.obs_line[sel], network.obs_sample[sel], name)
            ok = np.all(np.isfinite(o), axis=1) & np.all(np.isfinite(d), axis=1)
            o, d, sel = o[ok], d[ok], sel[ok]
            proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
            idx = pmap[network.obs_point[sel]]
            np.add.at(a, idx, proj)
            np.add.at(b, idx, np.einsum("mij,mj->mi", proj, o))
            np.add.at(n, idx, 1)
    good = n >= 2
    if np.any(good):
        det = np.linalg.det(a[good])
        scale = np.einsum("pii->p", a[good]) ** 3
        solvable = np.abs(det) > 1e-12 * scale
        gi = np.flatnonzero(good)[solvable]
        out[gi] = np.linalg.solve(a[gi], b[gi][..., None])[..., 0]
    return out


def _ground_error_m(network: Network, cameras: list[Any], obs: NDArray[np.intp], xyz: F64) -> F64:
    """Metres between each observation's ray at its point's height and the point."""
    out = np.full(len(obs), np.nan)
    for ci, cam in enumerate(cameras):
        for k, name in enumerate(cam.ccd_names):
            m = (network.obs_camera[obs] == ci) & (network.obs_ccd[obs] == k)
            sel = np.flatnonzero(m)
            if not sel.size:
                continue
            o = obs[sel]
            p = xyz[network.obs_point[o]]
            _, _, h = xyz_to_lonlat(p, cam.ellipsoid)
            origin, d = rays(cam, network.obs_line[o], network.obs_sample[o], name)
            s = ray_ellipsoid_intersection(origin, d, cam.ellipsoid, h)
            # The ray origin lies at +10 km, so the intersection is along +d.
            hit = origin + s[:, None] * d
            out[sel] = np.linalg.norm(hit - p, axis=1)
    return out


# ------------------------------------------------------------------------- adjust
def adjust(
    network: Network,
    config: AdjustConfig | dict[str, Any] | None = None,
    *,
    progress: Callable[[str], None] | None = None,
) -> AdjustmentResult:
    """Adjust the cameras (and unknown points) of a network.

    Args:
        network: Cameras, points and observations.
        config: An :class:`AdjustConfig`, a mapping validated into one, or ``None`` for
            the defaults.
        progress: Optional callback receiving one line per LM iteration and round.

    Returns:
        The :class:`AdjustmentResult`. ``metrics`` holds, for ``"all"``, each camera
        (``"cameras"``) and each of its CCDs (``"cameras"[id]["ccds"]``, also flat in
        ``"ccds"``, keyed by CCD name for one camera and ``"id/ccd"`` otherwise), the
        reprojection metrics
        (:func:`~planetref.metrics.reprojection_metrics`) ``"before"`` (initial
        residuals of the final inliers), ``"before_all"`` (initial residuals of every
        usable observation) and ``"after"``; and ``"check"`` with the held-out
        observations' RMS/max in pixels and metres before and after.

    Raises:
        AdjustmentError: Degenerate or divergent problems, with the reason.
        InputError: Invalid configuration or cameras that cannot be adjusted.
    """
    with single_threaded_blas():
        return _adjust(network, config, progress)


def _adjust(
    network: Network,
    config: AdjustConfig | dict[str, Any] | None,
    progress: Callable[[str], None] | None,
) -> AdjustmentResult:
    t0 = time.perf_counter()
    cfg = validate_config(config if config is not None else {})
    net = network
    warnings: list[str] = []

    def warn(msg: str) -> None:
        warnings.append(msg)
        log.warning(msg)

    models = [
        parameterize(cid, cam, cfg) for cid, cam in zip(net.camera_ids, net.cameras, strict=True)
    ]
    initial_cams = list(net.cameras)
    m_all = net.n_obs
    # Points whose coordinates the rays must determine: free ones, and tie points under
    # their (loose) a-priori sigma; they need min_tie_observations rays.
    free_pt = np.all(np.isinf(net.point_sigma_m), axis=1) | (
        (np.asarray(net.point_kind) == "tie") & ~np.all(net.point_sigma_m == 0, axis=1)
    )
    candidates = ~net.obs_check
    xyz0 = net.point_xyz.copy()
    missing = np.flatnonzero(~np.all(np.isfinite(xyz0), axis=1))
    if missing.size:
        xyz0[missing] = triangulate(net, initial_cams, missing, candidates)
        lost = missing[~np.all(np.isfinite(xyz0[missing]), axis=1)]
        if lost.size:
            warn(
                f"{lost.size} free point(s) without coordinates could not be triangulated "
                f"(fewer than two rays); their observations are unusable"
            )

    solver = BundleSolver(net, models, cfg.solver, progress=progress)
    has_xyz = np.all(np.isfinite(xyz0[net.obs_point]), axis=1)
    res0 = np.full((m_all, 2), np.nan)
    valid0 = np.zeros(m_all, bool)
    sel = np.flatnonzero(has_xyz)
    xyz_start = np.where(np.isfinite(xyz0), xyz0, 0.0)
    # With plain least squares in the first round, the initial residuals come from a
    # full linearisation of the candidates that the first LM run reuses when they all
    # turn out usable (one pass fewer); with a robust loss the weights need the
    # residuals first, so project only. Check observations are projected separately.
    linear_first = cfg.solver.loss == "linear"
    lin0 = None
    cand = np.flatnonzero(has_xyz & candidates)
    if cand.size and linear_first:
        solver.loss, solver.threshold = "linear", np.inf
        lin0 = solver.linearize(solver.x0, xyz_start, cand, xyz_start)
        res0[lin0.obs] = np.where(lin0.valid[:, None], lin0.r, np.nan)
        valid0[lin0.obs] = lin0.valid
        sel = np.flatnonzero(has_xyz & ~candidates)
    if sel.size:
        line0, samp0, v0 = solver.project(solver.x0, xyz_start, sel)
        res0[sel] = np.stack([line0 - net.obs_line[sel], samp0 - net.obs_sample[sel]], 1)
        valid0[sel] = v0
    usable = candidates & valid0
    n_bad = int(np.count_nonzero(candidates & ~valid0))
    if n_bad:
        warn(
            f"{n_bad} observation(s) cannot be projected with the initial cameras; "
            f"they are unusable"
        )
    before_support = usable.copy()
    usable = supported(usable, net.obs_point, free_pt, cfg.observations.min_tie_observations)
    n_weak = int(np.count_nonzero(before_support & ~usable))
    if n_weak:
        warn(
            f"{n_weak} observation(s) of free points seen fewer than "
            f"{cfg.observations.min_tie_observations} times are unusable"
        )
    if not np.any(usable):
        raise AdjustmentError(
            "no usable observations: none can be projected with the initial cameras"
        )

    # Every parameter group must be observed (or be weighted, if so configured).
    for i, model in enumerate(models):
        sel = usable & (net.obs_camera == i)
        issues = model.coverage(net.obs_ccd[sel], net.obs_line[sel])
        for msg in model.weaken(issues):
            warn(msg)
    solver.refresh_modes()

    # Weighted MCPs: their residuals (metrics, outlier rule) are those of the reference
    # ground point through the adjusted camera, as with fixed MCPs; the adjusted point
    # may absorb its image residual (one view) and would flatter the RMSE.
    ref_pt = (
        (np.asarray(net.point_kind) == "mcp")
        & ~solver.point_fixed
        & ~np.all(np.isinf(net.point_sigma_m), axis=1)
    )

    def _reference(xyz_now: F64) -> F64:
        return np.where(ref_pt[:, None], xyz_start, xyz_now)

    on_ref = ref_pt[net.obs_point]
    inlier = usable.copy()
    c = solver.x0.copy()
    xyz = xyz_start
    residual = res0.copy()
    rounds: list[dict[str, Any]] = []
    stable = False
    stats: dict[str, Any] = {}
    last_used = inlier.copy()
    for rnd in range(cfg.outliers.max_rounds if cfg.outliers.enabled else 1):
        _set_threshold(solver, cfg, residual, inlier, rnd == 0)
        obs = np.flatnonzero(inlier)
        if progress is not None:
            progress(f"round {rnd + 1}: {obs.size} observations")
        c, xyz, rep, lin, stats = solver.run(
            c, xyz, obs, xyz_start, initial=lin0 if rnd == 0 else None
        )
        lin0 = None
        last_used = inlier.copy()
        # The final linearisation holds the residuals of the observations it used; only
        # the others (rejected so far) need projecting.
        residual = np.full((m_all, 2), np.nan)
        residual[lin.obs] = np.where(lin.valid[:, None], lin.r, np.nan)
        sel = np.flatnonzero(usable & ~(inlier & ~on_ref))
        if sel.size:
            line, samp, _ = solver.project(c, _reference(xyz), sel)
            residual[sel] = np.stack([line - net.obs_line[sel], samp - net.obs_sample[sel]], 1)
        length = np.hypot(residual[:, 0], residual[:, 1])
        _, rmse = classify_inliers(length, usable, inlier, cfg.outliers.k_rmse)
        rounds.append(_round_summary(rnd, inlier, rmse, rep))
        if not rep.converged:
            warn(f"round {rnd + 1}: {rep.reason}")
        if not cfg.outliers.enabled:
            stable = rep.converged
            break
        new, _ = classify_inliers(length, usable, inlier, cfg.outliers.k_rmse)
        new = supported(new, net.obs_point, free_pt, cfg.observations.min_tie_observations)
        if np.array_equal(new, inlier):
            stable = rep.converged
            break
        changed = int(np.count_nonzero(new != inlier))
        log.info("round %d: RMSE %.4g px, %d observation(s) change status", rnd + 1, rmse, changed)
        if not np.any(new):
            raise AdjustmentError(
                f"the {cfg.outliers.k_rmse} x RMSE rule rejected every observation"
            )
        inlier = new
    else:
        warn(
            f"the inlier set did not stabilise in {cfg.outliers.max_rounds} rounds; the "
            f"result is that of the last round"
        )
    inlier = last_used
    # Variance components on the final inliers (plain least squares), then the residuals
    # of the final solution.
    c, xyz, stats, vce = variance_components(
        solver, c, xyz, np.flatnonzero(inlier), xyz_start, stats, cfg.variance, progress
    )
    if cfg.variance.enabled:
        if not vce.converged:
            warn(
                f"variance components did not converge in {vce.iterations} iteration(s); "
                f"the factors of the last one: "
                + ", ".join(f"{g['group']} {g['factor']:.3g}" for g in vce.groups if g["estimated"])
            )
        sel = np.flatnonzero(usable)
        line, samp, _ = solver.project(c, _reference(xyz), sel)
        residual[sel] = np.stack([line - net.obs_line[sel], samp - net.obs_sample[sel]], 1)
    # Observations of free points that lost their support cannot be re-tested fairly.
    status = np.full(m_all, "outlier", dtype="<U8")
    status[inlier] = "inlier"
    status[~usable] = "unusable"
    status[net.obs_check] = "check"

    # Check observations: evaluated, never used.
    chk = np.flatnonzero(net.obs_check)
    cams_after = solver.cameras(c)
    if chk.size:
        has = np.all(np.isfinite(xyz0[net.obs_point[chk]]), axis=1)
        if np.any(has):
            cs = chk[has]
            line, samp, _ = solver.project(c, xyz, cs)
            residual[cs] = np.stack([line - net.obs_line[cs], samp - net.obs_sample[cs]], 1)
    xyz_final = np.where(np.isfinite(xyz0), xyz, np.nan)
    diag = _diagnostics(
        net, solver, cfg, (c, stats), vce, (xyz0, xyz_final), initial_cams, cams_after
    )
    for w in diag.pop("_warnings"):
        warn(w)
    points = diag.pop("_points")
    metrics = _metrics(net, res0, residual, status, inlier, usable)
    if chk.size:
        metrics["check"] = _check_metrics(net, initial_cams, cams_after, chk, res0, residual, xyz0)
    result = AdjustmentResult(
        network=net,
        config=cfg,
        models=models,
        cameras_initial=dict(zip(net.camera_ids, initial_cams, strict=True)),
        cameras=dict(zip(net.camera_ids, cams_after, strict=True)),
        parameter_names=list(solver.names),
        parameter_units=list(solver.units),
        parameter_mode=solver.mode.copy(),
        x0=solver.x0.copy(),
        x=c,
        sigma=np.asarray(stats["sigma"]),
        covariance=np.asarray(stats["covariance"]),
        correlation=np.asarray(stats["correlation"]),
        point_xyz_initial=xyz0,
        point_xyz=xyz_final,
        residual_initial=res0,
        residual=residual,
        status=status,
        sigma0=float(stats["sigma0"]),
        dof=int(stats["dof"]),
        metrics=metrics,
        variance={
            "enabled": cfg.variance.enabled,
            "iterations": vce.iterations,
            "converged": vce.converged,
            "groups": vce.groups,
            "dof": vce.dof_split() | {"dof": int(stats["dof"]), "n_unknowns": stats["n_unknowns"]},
        },
        points=points,
        diagnostics=diag,
        rounds=rounds,
        converged=stable,
        warnings=warnings,
        seconds=time.perf_counter() - t0,
    )
    return result


def _diagnostics(
    net: Network,
    solver: BundleSolver,
    cfg: AdjustConfig,
    solution: tuple[F64, dict[str, Any]],
    vce: VceResult,
    points: tuple[F64, F64],
    cams0: list[Any],
    cams1: list[Any],
) -> dict[str, Any]:
    """Movements, strong correlations and self-calibration estimability (with warnings)."""
    dc = cfg.diagnostics
    c, stats = solution
    xyz0, xyz = points
    red = vce.redundancy
    cof = {int(j): red.point_cofactor[k] for k, j in enumerate(red.unknown)}
    table = point_table(
        net, xyz0, xyz, solver.point_sigma, solver.point_frame, cof, float(stats["sigma0"])
    )
    used = np.zeros(net.n_points, bool)
    used[net.obs_point[red.obs]] = True
    moved, w_pts = point_summary(table, used, dc)
    shifts, w_cam = camera_shifts(net, cams0, cams1, xyz, dc)
    corr_info, w_corr = correlation_warnings(solver.names, stats["correlation"], dc)
    calib, w_cal = self_calibration(
        solver.names, solver.mode, solver.sigma, solver.x0, c, stats["covariance"], dc
    )
    return {
        "point_shifts": moved,
        "camera_shifts": shifts,
        "correlations": corr_info,
        "self_calibration": calib,
        "_points": table | {"used": used},
        "_warnings": w_pts + w_cam + w_corr + w_cal,
    }


def _set_threshold(
    solver: BundleSolver, cfg: AdjustConfig, residual: F64, inlier: NDArray[np.bool_], first: bool
) -> None:
    """Robust-loss threshold (normalised units) for the next LM run."""
    sc = cfg.solver
    if sc.loss == "linear" or (sc.loss_rounds == "first" and not first):
        solver.loss = "linear"
        solver.threshold = np.inf
        return
    solver.loss = sc.loss
    net = solver.net
    if sc.loss_scale_px is not None:
        sig = np.sqrt(np.mean(net.obs_sigma_px**2, axis=1))
        solver.threshold = sc.loss_threshold * sc.loss_scale_px / sig
        return
    s = np.sqrt(np.sum(residual[inlier] ** 2 * solver.obs_w0[inlier], axis=1))
    scale = robust_scale(s)
    solver.threshold = sc.loss_threshold * (scale if math.isfinite(scale) else 1.0)


def _round_summary(
    rnd: int, inlier: NDArray[np.bool_], rmse: float, rep: LmReport
) -> dict[str, Any]:
    return {
        "round": rnd + 1,
        "n_observations": int(np.count_nonzero(inlier)),
        "rmse_px": rmse,
        "iterations": rep.iterations,
        "evaluations": rep.evaluations,
        "cost_initial": rep.cost_initial,
        "cost_final": rep.cost_final,
        "converged": rep.converged,
        "reason": rep.reason,
        "seconds": rep.seconds,
    }


def _metrics(
    net: Network,
    res0: F64,
    res: F64,
    status: NDArray[np.str_],
    inlier: NDArray[np.bool_],
    usable: NDArray[np.bool_],
) -> dict[str, Any]:
    adjusted = ~net.obs_check

    def block(sel: NDArray[np.bool_]) -> dict[str, Any]:
        idx = np.flatnonzero(sel & adjusted)
        return {
            "before": reprojection_metrics(res0[idx, 1], res0[idx, 0], inlier[idx]),
            "before_all": reprojection_metrics(res0[idx, 1], res0[idx, 0], usable[idx]),
            "after": reprojection_metrics(res[idx, 1], res[idx, 0], inlier[idx]),
        }

    out: dict[str, Any] = {"all": block(np.ones(net.n_obs, bool)), "cameras": {}, "ccds": {}}
    single = len(net.camera_ids) == 1
    for ci, cid in enumerate(net.camera_ids):
        on = net.obs_camera == ci
        entry = block(on)
        names = net.cameras[ci].ccd_names
        if len(names) > 1:
            entry["ccds"] = {n: block(on & (net.obs_ccd == k)) for k, n in enumerate(names)}
            for n, m in entry["ccds"].items():
                out["ccds"][n if single else f"{cid}/{n}"] = m
        out["cameras"][cid] = entry
    return out


def _check_metrics(
    net: Network,
    cams0: list[Any],
    cams1: list[Any],
    chk: NDArray[np.intp],
    res0: F64,
    res1: F64,
    xyz: F64,
) -> dict[str, Any]:
    def stats(res: F64, cams: list[Any]) -> dict[str, float | int]:
        r = res[chk]
        length = np.hypot(r[:, 0], r[:, 1])
        ok = np.isfinite(length)
        metres = _ground_error_m(net, cams, chk, xyz)
        okm = np.isfinite(metres)
        nan = float("nan")
        return {
            "rms_px": float(np.sqrt(np.mean(length[ok] ** 2))) if ok.any() else nan,
            "max_px": float(np.max(length[ok])) if ok.any() else nan,
            "rms_m": float(np.sqrt(np.mean(metres[okm] ** 2))) if okm.any() else nan,
            "max_m": float(np.max(metres[okm])) if okm.any() else nan,
            "n": int(np.count_nonzero(ok)),
        }

    return {"before": stats(res0, cams0), "after": stats(res1, cams1)}
