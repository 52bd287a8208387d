"""What :func:`~planetref.adjust.api.adjust` reports besides the solution.

Reprojection metrics before/after (overall, per camera and per CCD), the held-out check
observations in pixels and metres, one line per outlier round, and the diagnostics
(point and camera movements, strong correlations, self-calibration estimability).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.adjust.config import AdjustConfig
from planetref.adjust.diagnostics import (
    camera_shifts,
    correlation_warnings,
    point_summary,
    point_table,
    self_calibration,
)
from planetref.adjust.metrics import grouped_reprojection_metrics
from planetref.adjust.rays import ground_error_m
from planetref.adjust.solver import BundleSolver, LmReport
from planetref.arrays import F64
from planetref.control.network import Network

__all__ = ["check_metrics", "diagnostics", "reprojection_blocks", "round_summary"]


def diagnostics(
    net: Network,
    solver: BundleSolver,
    cfg: AdjustConfig,
    solution: tuple[F64, dict[str, Any]],
    redundancy: tuple[NDArray[np.intp], tuple[NDArray[np.intp], F64]],
    points: tuple[F64, F64],
    cams0: list[Any],
    cams1: list[Any],
) -> dict[str, Any]:
    """Movements, strong correlations and self-calibration estimability (with warnings).

    Args:
        net: The network.
        solver: The solver of the final solution.
        cfg: The adjustment's configuration.
        solution: ``(c, stats)``: camera vector and the solver's statistics.
        redundancy: ``(obs, (unknown, cofactor))`` of the final solution's
            :class:`~planetref.adjust.redundancy.Redundancy`: the network indices of the
            observations used, those of the unknown points and their 3x3 cofactor blocks.
        points: ``(xyz0, xyz)``: a-priori and adjusted coordinates, ``(P, 3)``.
        cams0: Cameras before the adjustment.
        cams1: Cameras after it.
    """
    dc = cfg.diagnostics
    c, stats = solution
    xyz0, xyz = points
    used_obs, cof = redundancy
    table = point_table(
        net, xyz0, xyz, solver.point_sigma, solver.point_frame, cof, float(stats["sigma0"])
    )
    used = np.zeros(net.n_points, bool)
    used[net.obs_point[used_obs]] = True
    moved, w_pts, n_pts = point_summary(table, used, dc, net.point_kind_codes)
    shifts, w_cam = camera_shifts(net, cams0, cams1, xyz, dc, heights=table["height"])
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
        "_warnings": w_pts + ([] if _interpolation_only(corr_info) else w_corr) + w_cal,
        "_notes": _notes(n_pts, w_cam, corr_info, w_corr),
    }


def _interpolation_only(corr_info: dict[str, Any]) -> bool:
    """Every correlating pair of the warning is one angle of one camera at two nodes."""
    return corr_info.get("n_same_angle_node_pairs") == corr_info.get("n_other_pairs")


def _notes(
    points: list[str], cameras: list[str], corr_info: dict[str, Any], corr: list[str]
) -> list[tuple[str, str]]:
    """The diagnostics' lines that ask nothing of the user, as ``(kind, line)``.

    A footprint's movement is what the adjustment corrected (the report tables it);
    weighted points beyond ``point_shift_sigmas`` no more often than chance gives are
    the a-priori errors' tail; one attitude angle of one camera correlating between
    nodes is the interpolation's coupling. Any other correlation stays a warning.
    """
    out = [("weighted points beyond their sigmas, within chance", m) for m in points]
    out += [("camera footprints moved", m) for m in cameras]
    if _interpolation_only(corr_info):
        out += [("node attitude correlations", m) for m in corr]
    return out


def round_summary(
    rnd: int, inlier: NDArray[np.bool_], rmse: float, rep: LmReport
) -> dict[str, Any]:
    """One row of :attr:`~planetref.adjust.result.AdjustmentResult.rounds`."""
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
        "cpu_seconds": rep.cpu_seconds,
    }


def reprojection_blocks(
    net: Network,
    res0: F64,
    res: F64,
    inlier: NDArray[np.bool_],
    usable: NDArray[np.bool_],
) -> dict[str, Any]:
    """Reprojection metrics before/after, overall, per camera and per CCD.

    Args:
        net: The network.
        res0: Initial ``(line, sample)`` residuals (px), ``(M, 2)``.
        res: Final residuals (px), ``(M, 2)``.
        inlier: Final inliers.
        usable: Observations that could be used at all.

    Returns:
        ``{"all": ..., "cameras": {id: ...}, "ccds": {name: ...}}``, each with
        ``"before"``, ``"before_all"`` and ``"after"``
        (:func:`~planetref.adjust.metrics.reprojection_metrics`); check observations and
        CCD-overlap ties excluded.
    """
    # Group codes per level (-1: not in a group): 0 all adjusted observations, then
    # one per camera (when there are several), then one per CCD of multi-CCD cameras.
    # CCD-overlap ties (kind "overlap") are left out: the metrics stay those of the
    # MCPs (and campaign ties) whether or not the overlap ties are in the network.
    overlap = net.point_kind[net.obs_point] == "overlap" if "overlap" in net.point_kind else False
    adjusted = ~net.obs_check & ~overlap
    single = len(net.camera_ids) == 1
    levels = [np.where(adjusted, 0, -1)]
    n_groups = 1
    cam_code = np.full(len(net.camera_ids), -1, np.intp)
    if not single:
        cam_code[:] = np.arange(1, len(net.camera_ids) + 1)
        n_groups += len(net.camera_ids)
        levels.append(np.where(adjusted, cam_code[net.obs_camera], -1))
    ccd_base = np.zeros(len(net.camera_ids) + 1, np.intp)
    for ci, cam in enumerate(net.cameras):
        n_ccd = len(cam.ccd_names)
        ccd_base[ci + 1] = ccd_base[ci] + (n_ccd if n_ccd > 1 else 0)
    if ccd_base[-1]:
        multi = (ccd_base[1:] - ccd_base[:-1] > 0)[net.obs_camera]
        code = n_groups + ccd_base[net.obs_camera] + net.obs_ccd
        levels.append(np.where(adjusted & multi, code, -1))
        n_groups += int(ccd_base[-1])
    group = np.stack(levels)
    del levels  # (M,) codes per level: the stacked copy is what is read
    before = grouped_reprojection_metrics(res0[:, 1], res0[:, 0], inlier, group, n_groups)
    before_all = (
        [dict(d) for d in before]
        if np.array_equal(inlier, usable)
        else grouped_reprojection_metrics(res0[:, 1], res0[:, 0], usable, group, n_groups)
    )
    after = grouped_reprojection_metrics(res[:, 1], res[:, 0], inlier, group, n_groups)

    def block(g: int) -> dict[str, Any]:
        return {"before": before[g], "before_all": before_all[g], "after": after[g]}

    out: dict[str, Any] = {"all": block(0), "cameras": {}, "ccds": {}}
    for ci, cid in enumerate(net.camera_ids):
        # One camera: its block is the overall one (the same observations).
        entry = {k: dict(v) for k, v in out["all"].items()} if single else block(cam_code[ci])
        names = net.cameras[ci].ccd_names
        if len(names) > 1:
            base = n_groups - int(ccd_base[-1]) + int(ccd_base[ci])
            entry["ccds"] = {n: block(base + k) for k, n in enumerate(names)}
            for n, m in entry["ccds"].items():
                out["ccds"][n if single else f"{cid}/{n}"] = m
        out["cameras"][cid] = entry
    return out


def check_metrics(
    net: Network,
    cams0: list[Any],
    cams1: list[Any],
    chk: NDArray[np.intp],
    res0: F64,
    res1: F64,
    xyz: F64,
) -> dict[str, Any]:
    """RMS and max of the check observations in pixels and metres, before and after.

    Metres are the distance between each check observation's ray (at its point's
    height) and the point.
    """

    def stats(res: F64, cams: list[Any]) -> dict[str, float | int]:
        r = res[chk]
        length = np.hypot(r[:, 0], r[:, 1])
        ok = np.isfinite(length)
        metres = ground_error_m(net, cams, chk, xyz)
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
