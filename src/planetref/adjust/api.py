"""The adjustment as one call: :func:`adjust` a :class:`~planetref.control.network.Network`.

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
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.adjust.config import AdjustConfig, validate_config
from planetref.adjust.consider import ConsiderTerms, consider_layout, estimate_key_sigma
from planetref.adjust.evaluation import (
    check_metrics,
    diagnostics,
    reprojection_blocks,
    round_summary,
)
from planetref.adjust.jitter import (
    JitterParameterization,
    dense_cameras,
    jitter_config,
    jitter_series,
    mcps_by_overlap,
    replace_cameras,
)
from planetref.adjust.models import AdjustableCamera, parameterize
from planetref.adjust.outliers import classify_inliers, robust_scale, supported
from planetref.adjust.precision import check_tile_misfit
from planetref.adjust.rays import rays, triangulate
from planetref.adjust.result import STATUSES, AdjustmentResult
from planetref.adjust.solver import BundleSolver
from planetref.adjust.variance import variance_components
from planetref.arrays import F64
from planetref.control.network import Network
from planetref.errors import AdjustmentError
from planetref.runtime.blas import single_threaded_blas
from planetref.runtime.notes import log_note
from planetref.runtime.threads import compute_threads

__all__ = ["STATUSES", "AdjustmentResult", "adjust", "rays", "triangulate"]

log = logging.getLogger("planetref.adjust")


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
        (:func:`~planetref.adjust.metrics.reprojection_metrics`) ``"before"`` (initial
        residuals of the final inliers), ``"before_all"`` (initial residuals of every
        usable observation) and ``"after"``; and ``"check"`` with the held-out
        observations' RMS/max in pixels and metres before and after.

    Raises:
        AdjustmentError: Degenerate or divergent problems, with the reason.
        InputError: Invalid configuration or cameras that cannot be adjusted.
    """
    with single_threaded_blas():
        cfg = validate_config(config if config is not None else {})
        result = _adjust(network, cfg, progress)
        if cfg.diagnostics.check_self_calibration and _self_calibrating(cfg):
            _check_self_calibration(result, network, cfg)
        if cfg.jitter.enabled:
            result = _jitter_stage(network, result, cfg, progress)
        return result


def _jitter_stage(
    network: Network,
    seed: AdjustmentResult,
    cfg: AdjustConfig,
    progress: Callable[[str], None] | None,
) -> AdjustmentResult:
    """Adjust the seed's line-scan strips again on dense attitude nodes (see jitter.py).

    The result is the dense stage's, with the seed's ``before`` metrics (the initial
    cameras'), its initial cameras, the estimated jitter per strip
    (``jitter``, summaries in ``diagnostics["jitter"]``) and the seed's headline numbers
    (``diagnostics["jitter_seed"]``).
    """
    dense = dense_cameras(seed.cameras, cfg)
    if all(dense[c] is seed.cameras[c] for c in dense):
        return seed
    # With CCD-overlap ties beside the MCPs, overlapping templates count once against
    # them (else the MCPs, biased at the frequencies their templates average, outweigh
    # the ties ~20-fold there). MCPs alone keep their weights: the prior was set
    # against those, and their covariance takes the overlap as a sandwich.
    f = float(cfg.systematic.measurement_overlap) if network.is_kind("overlap").any() else 1.0
    net = mcps_by_overlap(replace_cameras(network, dense), f)
    dcfg = jitter_config(cfg, f)

    def model(cid: str, cam: Any, c: AdjustConfig) -> AdjustableCamera:
        if cam is dense[cid] and cam is not seed.cameras[cid]:
            return JitterParameterization(
                cid, cam, c.linescan, cfg.jitter, fixed=cid in c.fixed_cameras
            )
        return parameterize(cid, cam, c)

    if progress is not None:
        progress("jitter stage: dense attitude nodes")
    res = _adjust(net, dcfg, progress, parameterizer=model)
    series = {}
    offsets = np.cumsum([0] + [len(m.x0) for m in res.models])
    for i, m in enumerate(res.models):
        if not isinstance(m, JitterParameterization):
            continue
        s = slice(offsets[i], offsets[i + 1])
        mine = res.inlier & (network.obs_camera == i)
        series[m.camera_id] = jitter_series(
            m,
            seed.cameras[m.camera_id],
            res.x[s],
            res.covariance[s, s],
            network.obs_line[mine],
            cfg.jitter,
        )
    # Never hurts: with held-out check observations, the dense solution is kept only
    # when they fit it better than the seed's (a jitter-free strip then stays as it was).
    chk_seed = (seed.metrics.get("check") or {}).get("after") or {}
    chk_dense = (res.metrics.get("check") or {}).get("after") or {}
    if (
        cfg.jitter.keep == "if_check_improves"
        and chk_seed.get("n")
        and chk_dense.get("n")
        and not chk_dense["rms_px"] < chk_seed["rms_px"]
    ):
        msg = (
            f"jitter stage not kept: the held-out check observations fit it no better "
            f"({chk_seed['rms_px']:.4g} -> {chk_dense['rms_px']:.4g} px); the node model's "
            f"solution is the result"
        )
        log.warning(msg)
        diag = dict(seed.diagnostics)
        diag["jitter"] = {cid: j.summary() | {"kept": False} for cid, j in series.items()}
        return replace(seed, diagnostics=diag, warnings=[*seed.warnings, msg])
    metrics = _with_before(res.metrics, seed.metrics)
    diag = dict(res.diagnostics)
    diag["jitter"] = {cid: j.summary() | {"kept": True} for cid, j in series.items()}
    diag["jitter_seed"] = seed.summary()
    return replace(
        res,
        network=network,
        config=cfg,
        cameras_initial=seed.cameras_initial,
        metrics=metrics,
        diagnostics=diag,
        warnings=seed.warnings + res.warnings,
        seconds=seed.seconds + res.seconds,
        jitter=series,
    )


def _with_before(after: dict[str, Any], seed: dict[str, Any]) -> dict[str, Any]:
    """``after`` with the ``before``/``before_all`` blocks of ``seed`` (same layout)."""
    out: dict[str, Any] = {}
    for key, value in after.items():
        if key in ("before", "before_all") and key in seed:
            out[key] = seed[key]
        elif isinstance(value, dict) and isinstance(seed.get(key), dict):
            out[key] = _with_before(value, seed[key])
        else:
            out[key] = value
    return out


def _self_calibrating(cfg: AdjustConfig) -> bool:
    """An optional camera-calibration block (interior, CCD placement) is adjusted."""
    ls = cfg.linescan
    return ls.interior.mode != "fixed" or ls.ccd_placement.mode != "fixed"


def _check_self_calibration(result: AdjustmentResult, network: Network, cfg: AdjustConfig) -> None:
    """Flag a self-calibration block that raises the check error.

    The adjustment is repeated with the interior and the CCD placement fixed; when the
    block lowers the inliers' RMSE but the independent check observations (held-out
    tiles) fit worse, the block fits the MCPs' own errors (a reference's offsets, a
    matcher's bias) rather than the camera: a warning says so and
    ``diagnostics["self_calibration_check"]`` holds both runs' figures.
    """
    check = result.metrics.get("check")
    if not check or not check["after"]["n"]:
        return
    ls = cfg.linescan
    fixed = cfg.model_copy(
        update={
            "linescan": ls.model_copy(
                update={
                    "interior": ls.interior.model_copy(update={"mode": "fixed"}),
                    "ccd_placement": ls.ccd_placement.model_copy(update={"mode": "fixed"}),
                }
            )
        }
    )
    try:
        base = _adjust(network, fixed, None)
    except AdjustmentError as exc:
        log.info("self-calibration check: the adjustment without it failed (%s)", exc)
        return
    rmse_on = result.metrics["all"]["after"]["rmse_px"]
    rmse_off = base.metrics["all"]["after"]["rmse_px"]
    chk_on = check["after"]["rms_px"]
    chk_off = base.metrics["check"]["after"]["rms_px"]
    # Any rise of the check error flags the block: the check points are whole tiles the
    # adjustment never saw, the only independent measure of the camera it has.
    flagged = bool(chk_on > chk_off)
    result.diagnostics["self_calibration_check"] = {
        "rmse_px": rmse_on,
        "rmse_px_without": rmse_off,
        "check_rms_px": chk_on,
        "check_rms_px_without": chk_off,
        "check_rms_m": check["after"]["rms_m"],
        "check_rms_m_without": base.metrics["check"]["after"]["rms_m"],
        "raises_check_error": flagged,
    }
    if flagged:
        msg = (
            f"self-calibration (interior {ls.interior.mode}, CCD placement "
            f"{ls.ccd_placement.mode}) raises the check error ({chk_off:.3g} -> {chk_on:.3g} px"
            f" on the held-out tiles; RMSE {rmse_off:.3g} -> {rmse_on:.3g} px): it fits the "
            f"control's own errors, not the camera; keep the interior fixed"
        )
        result.warnings.append(msg)
        log.warning(msg)


def _adjust(
    network: Network,
    cfg: AdjustConfig,
    progress: Callable[[str], None] | None,
    *,
    parameterizer: Callable[[str, Any, AdjustConfig], AdjustableCamera] = parameterize,
) -> AdjustmentResult:
    t0 = time.perf_counter()
    net = network
    warnings: list[str] = []

    def warn(msg: str) -> None:
        warnings.append(msg)
        log.warning(msg)

    models = [
        parameterizer(cid, cam, cfg) for cid, cam in zip(net.camera_ids, net.cameras, strict=True)
    ]
    initial_cams = list(net.cameras)
    m_all = net.n_obs
    # Points whose coordinates the rays must determine: free ones, and tie points under
    # their (loose) a-priori sigma; they need min_tie_observations rays.
    sig_inf = _rows_all(np.isinf(net.point_sigma_m))
    tied = net.is_kind("tie") | net.is_kind("overlap")
    free_pt = sig_inf | (tied & ~_rows_all(net.point_sigma_m == 0))
    # CCD-overlap ties are judged by the k x RMSE rule against their own RMSE: their
    # residuals (what the attitude model leaves of the jitter, a tenth of a pixel) would
    # otherwise set a threshold that rejects most MCPs.
    own = net.is_kind("overlap")[net.obs_point]
    candidates = ~net.obs_check
    xyz0 = net.point_xyz.copy()
    finite_pt = _rows_all(np.isfinite(xyz0))
    missing = np.flatnonzero(~finite_pt)
    if missing.size:
        xyz0[missing] = triangulate(net, initial_cams, missing, candidates)
        finite_pt = _rows_all(np.isfinite(xyz0))
        lost = missing[~finite_pt[missing]]
        if lost.size:
            warn(
                f"{lost.size} free point(s) without coordinates could not be triangulated "
                f"(fewer than two rays); their observations are unusable"
            )

    solver = BundleSolver(net, models, cfg.solver, progress=progress)
    has_xyz = finite_pt[net.obs_point]
    res0 = np.full((m_all, 2), np.nan)
    valid0 = np.zeros(m_all, bool)
    # Read only from here on (the solver copies before it moves points).
    xyz_start = xyz0 if np.all(finite_pt) else np.where(np.isfinite(xyz0), xyz0, 0.0)
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
        _put_rows(res0, lin0.obs, lin0.r, lin0.valid)
        valid0[lin0.obs] = lin0.valid
        sel = np.flatnonzero(has_xyz & ~candidates)
    else:
        sel = np.flatnonzero(has_xyz)
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
    usable = _supported(usable, net.obs_point, free_pt, cfg.observations.min_tie_observations)
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
        seen = usable if len(models) == 1 else usable & (net.obs_camera == i)
        models[i], messages = model.weaken(model.coverage(net.obs_ccd[seen], net.obs_line[seen]))
        for msg in messages:
            warn(msg)
        check_geometry = getattr(models[i], "check_geometry", None)  # rank, not only counts
        if check_geometry is not None:
            check_geometry(net.obs_ccd[sel], net.obs_line[sel], net.obs_sample[sel])
    solver.set_models(models)

    # Weighted MCPs: their residuals (metrics, outlier rule) are those of the reference
    # ground point through the adjusted camera, as with fixed MCPs; the adjusted point
    # may absorb its image residual (one view) and would flatter the RMSE.
    ref_pt = net.is_kind("mcp") & ~solver.point_fixed & ~sig_inf

    def _reference(xyz_now: F64) -> F64:
        return np.where(ref_pt[:, None], xyz_start, xyz_now)

    on_ref = ref_pt[net.obs_point] if np.any(ref_pt) else np.zeros(m_all, bool)
    inlier = usable.copy()
    c = solver.x0.copy()
    xyz = xyz_start
    rigid = [getattr(m, "rigid", None) for m in solver.models]
    if cfg.solver.rigid_start and any(r is not None for r in rigid):
        # A line scanner is linearised at each observation's projected line: from a
        # start far off along track the nodes beyond the projected lines get no
        # partials and the node-wise solve is singular there and crawls. One
        # correction common to all nodes first removes the offset.
        free_models = list(solver.models)
        solver.set_models(
            [m if r is None else r() for m, r in zip(free_models, rigid, strict=True)]
        )
        _set_threshold(solver, cfg, res0, inlier, True)
        c, xyz, rep0, _, _ = solver.run(c, xyz, np.flatnonzero(inlier), xyz_start, initial=lin0)
        log.info("rigid start: %s after %d iteration(s)", rep0.reason, rep0.iterations)
        solver.set_models(free_models)
        solver.last_lambda = None
        lin0 = None  # made at the initial cameras
    residual = res0  # read only until the first round replaces it
    rounds: list[dict[str, Any]] = []
    stable = False
    stats: dict[str, Any] = {}
    last_used = inlier.copy()
    for rnd in range(cfg.outliers.max_rounds if cfg.outliers.enabled else 1):
        _set_threshold(solver, cfg, residual, inlier, rnd == 0)
        obs = np.flatnonzero(inlier)
        if progress is not None:
            progress(f"round {rnd + 1}: {obs.size} observations")
        # Handed over, not kept: the first linearisation is freed as soon as the run
        # replaces it (a million observations: ~40 MB out of the run's peak).
        initial = [lin0] if rnd == 0 else []
        lin0 = None
        c, xyz, rep, lin, stats = solver.run(
            c, xyz, obs, xyz_start, initial=initial.pop() if initial else None
        )
        last_used = inlier.copy()
        # The final linearisation holds the residuals of the observations it used; only
        # the others (rejected so far) need projecting.
        residual = np.full((m_all, 2), np.nan)
        _put_rows(residual, lin.obs, lin.r, lin.valid)
        sel = np.flatnonzero(usable & ~(inlier & ~on_ref))
        if sel.size:
            line, samp, _ = solver.project(c, _reference(xyz), sel)
            residual[sel] = np.stack([line - net.obs_line[sel], samp - net.obs_sample[sel]], 1)
        length = np.hypot(residual[:, 0], residual[:, 1])
        _, rmse = _classify(length, usable, inlier, cfg.outliers.k_rmse, own)
        rounds.append(round_summary(rnd, inlier, rmse, rep))
        if not rep.converged:
            warn(f"round {rnd + 1}: {rep.reason}")
        if not cfg.outliers.enabled:
            stable = rep.converged
            break
        new, _ = _classify(length, usable, inlier, cfg.outliers.k_rmse, own)
        new = _supported(new, net.obs_point, free_pt, cfg.observations.min_tie_observations)
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
    # sigma0 of the a-priori weights, before VCE rescales them to ~1 (what it says about
    # the stochastic model is lost once the components absorb it).
    sigma0_before = float(stats["sigma0"])
    # Variance components on the final inliers (plain least squares), then the residuals
    # of the final solution.
    c, xyz, stats, vce = variance_components(
        solver, c, xyz, np.flatnonzero(inlier), xyz_start, stats, cfg.variance, progress, lin
    )
    variance: dict[str, Any] = {
        "enabled": cfg.variance.enabled,
        "sigma0_before": sigma0_before,
        "measurement_overlap": cfg.systematic.measurement_overlap,
        "iterations": vce.iterations,
        "converged": vce.converged,
        "groups": vce.groups,
        "dof": vce.dof_split() | {"dof": int(stats["dof"]), "n_unknowns": stats["n_unknowns"]},
    }
    consider, cov_measurement = _consider(solver, cfg, net, c, xyz, inlier, xyz_start, stats)
    # What the diagnostics need of the redundancy numbers. The per-observation arrays
    # (redundancy, residuals, weights), the final linearisation and the solver's layout
    # are let go: the diagnostics and metrics below are the memory peak of the call.
    red = vce.redundancy
    used_obs, cofactor = red.obs, (red.unknown, red.point_cofactor)
    del red, lin, vce
    solver.release_layout()
    if cfg.variance.enabled:
        if not variance["converged"]:
            warn(
                f"variance components did not converge in {variance['iterations']} "
                f"iteration(s); the factors of the last one: "
                + ", ".join(
                    f"{g['group']} {g['factor']:.3g}" for g in variance["groups"] if g["estimated"]
                )
            )
        sel = np.flatnonzero(usable)
        line, samp, _ = solver.project(c, _reference(xyz), sel)
        residual[sel] = np.stack([line - net.obs_line[sel], samp - net.obs_sample[sel]], 1)
    # Observations of free points that lost their support cannot be re-tested fairly.
    code = np.ones(m_all, np.int8)  # index into STATUSES: outlier
    code[inlier] = 0
    code[~usable] = 2
    code[net.obs_check] = 3
    status = np.array(STATUSES, dtype="<U8")[code]

    # Check observations: evaluated, never used.
    chk = np.flatnonzero(net.obs_check)
    cams_after = solver.cameras(c)
    if chk.size:
        has = finite_pt[net.obs_point[chk]]
        if np.any(has):
            cs = chk[has]
            line, samp, _ = solver.project(c, xyz, cs)
            residual[cs] = np.stack([line - net.obs_line[cs], samp - net.obs_sample[cs]], 1)
    xyz_final = xyz.copy() if np.all(finite_pt) else np.where(np.isfinite(xyz0), xyz, np.nan)
    # The metrics read only the residuals: with a second thread they are summed while
    # the diagnostics run (both are compiled or numpy passes that release the GIL).
    pool = ThreadPoolExecutor(1) if compute_threads(cfg.solver.threads) > 1 else None
    pending = (
        pool.submit(reprojection_blocks, net, res0, residual, inlier, usable) if pool else None
    )
    try:
        diag = diagnostics(
            net,
            solver,
            cfg,
            (c, stats),
            (used_obs, cofactor),
            (xyz0, xyz_final),
            initial_cams,
            cams_after,
        )
        metrics = (
            pending.result()
            if pending is not None
            else reprojection_blocks(net, res0, residual, inlier, usable)
        )
    finally:
        if pool is not None:
            pool.shutdown(wait=True)
    for w in diag.pop("_warnings"):
        warn(w)
    for kind, line in diag.pop("_notes"):  # in the report's warnings; INFO in the log
        warnings.append(line)
        log_note(log, kind, line)
    points = diag.pop("_points")
    if chk.size:
        metrics["check"] = check_metrics(net, initial_cams, cams_after, chk, res0, residual, xyz0)
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
        covariance_measurement=cov_measurement,
        consider=consider,
        correlation=np.asarray(stats["correlation"]),
        point_xyz_initial=xyz0,
        point_xyz=xyz_final,
        residual_initial=res0,
        residual=residual,
        status=status,
        sigma0=float(stats["sigma0"]),
        dof=int(stats["dof"]),
        metrics=metrics,
        variance=variance,
        points=points,
        diagnostics=diag,
        rounds=rounds,
        converged=stable,
        warnings=warnings,
        seconds=time.perf_counter() - t0,
    )
    if chk.size:
        # The held-out tiles against the covariance's own prediction (no truth needed).
        anchor = check_tile_misfit(result)
        if anchor is not None:
            metrics["check"]["tiles"] = anchor
    return result


def _consider(
    solver: BundleSolver,
    cfg: AdjustConfig,
    net: Network,
    c: F64,
    xyz: F64,
    inlier: NDArray[np.bool_],
    xyz0: F64,
    stats: dict[str, Any],
) -> tuple[ConsiderTerms | None, F64]:
    """Take the declared correlated errors into ``stats``' covariance (consider parameters).

    Returns:
        ``(terms, covariance of the measurements alone)``; ``terms`` is ``None`` when no
        correlated error is declared (the covariance is then unchanged).
    """
    cov_meas = np.asarray(stats["covariance"])
    f = cfg.systematic.measurement_overlap
    if f != 1.0:
        # Observations sharing their pixels (dense templates) are fewer independent
        # ones: their errors' covariance is f times the independent one's. The
        # estimator's (sandwich) covariance is S^-1 (f S_obs + P) S^-1 with S = S_obs + P
        # (P: the camera priors and constraints, independent pseudo-observations), i.e.
        # f Q - (f - 1) Q P Q: parameters known from their priors alone keep their sigma.
        q = np.asarray(stats["cofactor"])
        prior = np.diag(solver.prior_w)
        if solver.con_n is not None:
            prior = prior + solver.con_n
        cov_meas = float(stats["sigma0"]) ** 2 * (f * q - (f - 1.0) * (q @ prior @ q))
    weighted_mcp = (
        net.is_kind("mcp") & ~solver.point_fixed & ~_rows_all(np.isinf(net.point_sigma_m))
    )
    estimated = []
    for m in solver.models:
        mode = np.asarray(m.mode)
        estimated.append(any("ccd[" in n and mode[i] != 2 for i, n in enumerate(m.names)))
    layout = consider_layout(net, cfg.systematic, weighted_mcp, estimated, used=inlier)
    if not layout.names:
        if cfg.systematic.measurement_overlap != 1.0:
            _set_covariance(stats, cov_meas)
        return None, cov_meas
    estimate = cfg.systematic.tile_offset_sigma_px == "estimate" and bool(
        layout.columns("tile").stop
    )
    sens = solver.consider_sensitivity(
        c,
        xyz,
        np.flatnonzero(inlier),
        xyz0,
        np.asarray(stats["cofactor"]),
        layout,
        response="tile" if estimate else None,
    )
    if np.any(solver.point_fixed[net.obs_point[inlier]]):
        log.warning(
            "the declared CCD and tile offsets act on the observations of weighted and free "
            "points only: those of fixed points do not enter the covariance's correlated part"
        )
    sigma = layout.sigma
    tile = None
    if estimate:
        # Overlapping templates' errors add up within a tile like f independent ones
        # each (the measurements' covariance is scaled by f alike, above).
        tile = estimate_key_sigma(
            sens,
            layout,
            "tile",
            float(stats["sigma0"]) * math.sqrt(f),
            per_axis=cfg.systematic.tile_offset_axes == "per-axis",
        )
        cols = layout.columns("tile")
        sigma = sigma.copy()
        sigma[cols.start : cols.stop : 2] = tile.sigma_px[0]
        sigma[cols.start + 1 : cols.stop : 2] = tile.sigma_px[1]
        log.info(
            "tile offsets: sigma %.3g px (line), %.3g px (sample) from %d tiles",
            tile.sigma_px[0],
            tile.sigma_px[1],
            tile.n_tiles,
        )
    terms = ConsiderTerms(
        names=layout.names,
        units=layout.units,
        sigma=sigma,
        sensitivity=sens.g,
        ccd=layout.ccd,
        patch_m=cfg.systematic.patch_m,
        n_patches=layout.n_patches,
        kinds=layout.kinds,
        tile=tile,
        point_patch=layout.point_patch,
    )
    _set_covariance(stats, cov_meas + terms.covariance)
    return terms, cov_meas


def _set_covariance(stats: dict[str, Any], cov: F64) -> None:
    """Replace ``stats``' covariance and the sigmas and correlations read from it."""
    sig = np.sqrt(np.maximum(np.diag(cov), 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        corr = cov / sig[:, None] / sig[None, :]
    corr[~np.isfinite(corr)] = 0.0
    stats["covariance"], stats["sigma"], stats["correlation"] = cov, sig, corr


def _put_rows(dst: F64, rows: NDArray[np.intp], src: F64, valid: NDArray[np.bool_]) -> None:
    """``dst[rows] = src`` (NaN where not ``valid``) for ``(n, 2)`` float64 rows.

    Each row moves as one 16-byte element (a complex view): a one-dimensional scatter,
    about twice as fast as numpy's row scatter, the same bits.
    """
    val = src if np.all(valid) else np.where(valid[:, None], src, np.nan)
    flat = np.ascontiguousarray(val, np.float64).view(np.complex128).reshape(-1)
    dst.view(np.complex128).reshape(-1)[rows] = flat


def _rows_all(flags: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Rows of ``(n, 3)`` flags that are all true (faster than ``np.all(axis=1)``)."""
    return flags[:, 0] & flags[:, 1] & flags[:, 2]


def _supported(
    inlier: NDArray[np.bool_], obs_point: NDArray[np.intp], free_pt: NDArray[np.bool_], min_obs: int
) -> NDArray[np.bool_]:
    """:func:`~planetref.adjust.outliers.supported` (a copy of ``inlier`` without free points)."""
    if not np.any(free_pt):
        return inlier.copy()
    return supported(inlier, obs_point, free_pt, min_obs)


def _classify(
    length: F64,
    usable: NDArray[np.bool_],
    inlier: NDArray[np.bool_],
    k_rmse: float,
    own: NDArray[np.bool_],
) -> tuple[NDArray[np.bool_], float]:
    """:func:`classify_inliers`, the observations flagged ``own`` against their own RMSE.

    Returns:
        The new inliers, and the RMSE of the other observations (the pooled one when
        none is flagged).
    """
    if not own.any():
        return classify_inliers(length, usable, inlier, k_rmse)
    new, rmse = classify_inliers(length, usable & ~own, inlier & ~own, k_rmse)
    new_own, _ = classify_inliers(length, usable & own, inlier & own, k_rmse)
    return new | new_own, rmse


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
