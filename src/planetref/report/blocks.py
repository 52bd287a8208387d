"""The blocks of a georef report.json: adjustment, true geolocation error, several strips.

Each builder returns a block of the typed report (:mod:`planetref.report.model`);
:func:`combined_report` and :func:`failed_report` the whole :class:`GeorefReport`.
:func:`adjustment_block` is the one place that maps reprojection metrics
(:func:`planetref.adjust.metrics.reprojection_metrics`) to the report's ``adjustment`` block,
whether for a strip alone, a strip of a joint network, the joint network, or several
strips pooled.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from planetref import __version__
from planetref.errors import MatcherFailedError
from planetref.frontend.truth import sum_true_outliers
from planetref.report.model import (
    AdjustmentSummary,
    CheckBlock,
    FrontendSettings,
    GeorefReport,
    MatchingSummary,
    StripMatching,
    StripReport,
)

if TYPE_CHECKING:  # pragma: no cover
    from numpy.typing import NDArray

    from planetref.adjust.result import AdjustmentResult
    from planetref.camera.base import Camera
    from planetref.control.mcp import McpTable
    from planetref.frontend.config import FrontendConfig
    from planetref.frontend.result import StripMatches
    from planetref.raster.dem import GridTerrain
    from planetref.raster.ortho import ReferenceOrtho

__all__ = [
    "adjustment_block",
    "camera_view",
    "check_block",
    "combined_report",
    "failed_report",
    "frontend_settings",
    "matching_block",
    "rmse_px",
    "too_few_mcps",
]


def matching_block(
    matches: StripMatches,
    table: McpTable,
    sizes: Mapping[str, tuple[int, int]],
    truth: tuple[Camera, ReferenceOrtho, GridTerrain] | None = None,
) -> StripMatching:
    """The ``matching`` block of one strip: NCP and SDU per CCD, tiles, funnel, drops.

    NCP counts the unique MCPs delivered to the adjustment: the correspondences that
    passed a tile's verification, less those the MCP stage drops (duplicates of one CCD
    position, no DEM height, outside the reference; :func:`planetref.control.
    mcps_from_matches`). It is counted before any thinning for speed
    (``max_mcps_per_tile``), so it equals the MCPs written (``n_mcps``) unless thinning
    is on. SDU is over the MCPs written (:func:`planetref.frontend.stats.sdu_per_ccd`).

    The funnel (tile stages summed over the strip) ends with ``mcp_unique``, the MCPs
    written; its drops ``mcp_unique:<reason>`` say what the MCP stage removed, and
    ``mcp_unique:tile_failed`` the points of tiles that failed after their ``mcp`` stage.

    Args:
        matches: The strip's tile results.
        table: The MCPs written.
        sizes: ``(lines, samples)`` of each CCD image.
        truth: ``(true camera, reference ortho, true DEM)`` of a simulated scene: the
            block then has ``true_outliers``, the true outlier ratio of the matches after
            RANSAC (:func:`planetref.frontend.truth.true_outliers`).
    """
    from planetref.frontend.stats import sdu_per_ccd
    from planetref.frontend.truth import true_outliers

    statuses = matches.status_counts()
    verified = matches.ncp_per_ccd()
    offered = dict.fromkeys(sizes, 0)  # points of ok tiles handed to the MCP stage
    for t in matches.tiles:
        if t.status == "ok":
            offered[t.tile.ccd] = offered.get(t.tile.ccd, 0) + t.n_points
    ccd_col = np.asarray(table["ccd"]).astype(str) if len(table) else np.empty(0, str)
    kept = {c: int(np.count_nonzero(ccd_col == c)) for c in set(sizes) | set(offered)}
    # Without thinning verified == offered, so NCP == the MCPs written, CCD by CCD.
    ncp = {c: max(verified.get(c, 0) - (offered.get(c, 0) - kept.get(c, 0)), 0) for c in kept}
    sdu = sdu_per_ccd(table, sizes)
    lost = [
        {"tile": t.tile_id, "status": t.status, "message": t.message}
        for t in matches.tiles
        if t.status != "ok"
    ]
    funnel = matches.funnel()
    drops = matches.drops()
    counts = table.counts.to_dict() if table.counts is not None else {}
    if "mcp" in funnel:
        funnel["mcp_unique"] = len(table)
        stage_drops = {
            "tile_failed": funnel["mcp"] - sum(offered.values()),
            "duplicates": counts.get("duplicates", 0),
            "nan_dem": counts.get("nan_dem", 0),
            "outside_reference": counts.get("outside_reference", 0),
        }
        drops.update({f"mcp_unique:{k}": int(v) for k, v in stage_drops.items() if v > 0})
    block: dict[str, Any] = {
        "ccds": {c: {"ncp": int(ncp.get(c, 0)), "sdu_pct": float(sdu[c])} for c in sizes},
        "ncp": int(sum(ncp.get(c, 0) for c in sizes)),
        "n_mcps": len(table),
        "tiles_total": len(matches.tiles),
        "tiles_failed": len(matches.tiles) - statuses.get("ok", 0),
        "tiles_thinned": sum(t.thinned for t in matches.tiles),
        "tile_status": statuses,
        # Which search placed each tile's fine window (frontend.coarse_fallback): a
        # matcher whose own coarse stage needed NCC's search is not on the same terms as
        # one that placed its tiles itself, and Table 1 says so.
        "coarse_sources": dict(
            Counter(t.coarse_source for t in matches.tiles if t.coarse_source is not None)
        ),
        "tiles_lost": lost,
        "funnel": funnel,
        "drops": drops,
        "mcp_counts": counts,
    }
    if truth is not None:
        block["true_outliers"] = true_outliers(matches.tiles, *truth).to_dict()
    return StripMatching.model_validate(block)


def camera_view(result: Any, index: int) -> Any:
    """One camera's observations and residuals, just what the residual figure reads.

    Plain arrays and the CCD names only (no camera model), so the view is cheap to send
    to the figure process; works for a one-camera result and for a joint one alike.
    """
    from types import SimpleNamespace

    net = result.network
    on = np.asarray(net.obs_camera) == index
    cid = net.camera_ids[index]
    return SimpleNamespace(
        network=SimpleNamespace(
            camera_ids=[cid],
            obs_ccd=np.asarray(net.obs_ccd)[on],
            obs_line=np.asarray(net.obs_line)[on],
            obs_sample=np.asarray(net.obs_sample)[on],
        ),
        cameras={cid: SimpleNamespace(ccd_names=list(result.cameras[cid].ccd_names))},
        residual=np.asarray(result.residual)[on],
        status=np.asarray(result.status)[on],
    )


def rmse_px(res: Any) -> float | None:
    """Radial RMSE of ``(N, 2)`` residuals over the finite ones (None when there are none)."""
    r = np.asarray(res, float).reshape(-1, 2)
    r = r[np.all(np.isfinite(r), axis=1)]
    return float(np.sqrt(np.mean(np.sum(r**2, axis=1)))) if len(r) else None


def adjustment_block(
    after: dict[str, Any],
    *,
    rmse_px_before: float | None,
    sigma0: float,
    converged: bool,
    **extra: Any,
) -> AdjustmentSummary:
    """The ``adjustment`` block of report.json, from reprojection metrics after adjustment.

    The one place that maps :func:`planetref.adjust.metrics.reprojection_metrics` keys to the
    report's (a strip alone, a strip of a joint network, the joint network, several
    strips pooled). Per-axis RMSE (``rmse_x_px``, ``rmse_y_px``) is passed on when the
    metrics have it.

    Args:
        after: Metrics of the inliers after adjustment.
        rmse_px_before: RMSE before adjustment (pixels).
        sigma0: A-posteriori sigma of unit weight.
        converged: Whether the adjustment converged.
        **extra: Further entries (fields of :class:`AdjustmentSummary`).
    """
    block: dict[str, Any] = {"rmse_px_before": rmse_px_before, "rmse_px": after["rmse_px"]}
    for key in ("rmse_x_px", "rmse_y_px"):
        if key in after:
            block[key] = after[key]
    block["mean_px"] = after["mean_px"]
    for key in ("mean_x_px", "mean_y_px"):
        if key in after:
            block[key] = after[key]
    block |= {
        "max_x_px": after["max_dx_px"],
        "max_y_px": after["max_dy_px"],
        "min_x_px": after["min_dx_px"],
        "min_y_px": after["min_dy_px"],
        "outlier_ratio_pct": after["outlier_ratio_pct"],
        "n_total": after["n_total"],
        "n_inliers": after["n_inliers"],
        "sigma0": sigma0,
        "converged": converged,
    }
    return AdjustmentSummary.model_validate(block | extra)


def result_block(result: AdjustmentResult, **extra: Any) -> AdjustmentSummary:
    """The ``adjustment`` block of a whole adjustment (a strip alone or a joint network).

    Its headline metrics, variance components, check MCPs and per-CCD metrics, then
    ``extra`` (see :func:`adjustment_block`).
    """
    s = result.summary()
    return adjustment_block(
        result.metrics["all"]["after"],
        rmse_px_before=s["rmse_px_before"],
        sigma0=s["sigma0"],
        converged=s["converged"],
        **variance_block(result),
        check_mcps=result.metrics.get("check"),
        ccds={ccd: m["after"] for ccd, m in result.metrics.get("ccds", {}).items()},
        **extra,
    )


def variance_block(result: AdjustmentResult) -> dict[str, Any]:
    """sigma0 before VCE and of the real observations, dof, VCE and correlated errors.

    ``systematic``: the correlated errors taken into the covariance (consider
    parameters, :class:`~planetref.adjust.consider.ConsiderTerms`).
    """
    variance = getattr(result, "variance", None) or {}
    consider = getattr(result, "consider", None)
    return {
        "sigma0_before_vce": variance.get("sigma0_before"),
        "measurement_overlap": variance.get("measurement_overlap"),
        "sigma0_real": result.summary().get("sigma0_real"),
        "dof": variance.get("dof"),
        "variance_components": variance.get("groups"),
        "systematic": None if consider is None else consider.summary(),
    }


def check_block(
    result: AdjustmentResult, truth: dict[str, Camera], truth_dem: GridTerrain | None
) -> CheckBlock:
    """True geolocation error before and after adjustment of one strip (simulated scenes)."""
    from planetref.adjust.metrics import geolocation_error
    from planetref.adjust.precision import formal_ground_precision

    ((sid, true_cam),) = truth.items()
    before, after = [], []
    for ccd in true_cam.ccd_names:
        before.append(
            geolocation_error(result.cameras_initial[sid], true_cam, ccd=ccd, terrain=truth_dem)
        )
        after.append(geolocation_error(result.cameras[sid], true_cam, ccd=ccd, terrain=truth_dem))

    def rms(items: list[dict[str, Any]], key: str) -> float:
        vals = np.array([i[key] for i in items], float)
        return float(np.sqrt(np.mean(vals**2)))

    # The formal counterpart of the true error: the adjustment's covariance (with its
    # declared correlated errors) propagated to the same grid (calibrated: ratio 0.5-2).
    formal = formal_ground_precision(result, sid, terrain=0.0 if truth_dem is None else truth_dem)
    true_m = rms(after, "rms_m")
    return CheckBlock(
        geoloc_rmse_m_before=rms(before, "rms_m"),
        geoloc_rmse_m=true_m,
        formal_rmse_m=formal["rms_m"],
        true_over_formal=true_m / formal["rms_m"] if formal["rms_m"] > 0 else None,
        geoloc_rmse_px_before=rms(before, "rms_px"),
        geoloc_rmse_px=rms(after, "rms_px"),
        geoloc_max_m=float(max(i["max_m"] for i in after)),
        ccds={
            c: {"before": b, "after": a}
            for c, b, a in zip(true_cam.ccd_names, before, after, strict=True)
        },
    )


def combined_report(
    matcher: str,
    scene: str,
    strips: Mapping[str, StripReport],
    residuals: Mapping[str, tuple[NDArray[np.float64], NDArray[np.bool_]]],
    timing: Mapping[str, float],
    frontend: FrontendSettings | None = None,
) -> GeorefReport:
    """report.json: one strip's blocks as they are, several strips merged.

    Args:
        matcher: Matcher name.
        scene: Scene name.
        strips: Per-strip blocks.
        residuals: Per strip, its observations' ``(line, sample)`` residuals after the
            adjustment (px) and inlier flags (the pooled metrics of several strips).
        timing: Seconds per step.
        frontend: The front-end settings that decide what the matching figures mean
            (refinement, fine-stage resolution, dense spacing, thinning), stated in the
            ``matching`` block so that tables can say so.
    """
    from planetref.adjust.metrics import reprojection_metrics

    blocks = {sid: s.to_json() for sid, s in strips.items()}
    matching = _pooled_matching({sid: b["matching"] for sid, b in blocks.items()}, frontend)
    adjustment: AdjustmentSummary | None
    check: CheckBlock | None
    if len(strips) == 1:
        (only,) = strips.values()
        adjustment, check = only.adjustment, only.check
    else:
        res = np.concatenate([residuals[sid][0] for sid in strips])
        inl = np.concatenate([residuals[sid][1] for sid in strips])
        adjustment = adjustment_block(
            reprojection_metrics(res[:, 1], res[:, 0], inl),
            rmse_px_before=float(
                np.nanmean([b["adjustment"]["rmse_px_before"] for b in blocks.values()])
            ),
            sigma0=float(np.nanmean([b["adjustment"]["sigma0"] for b in blocks.values()])),
            converged=all(b["adjustment"]["converged"] for b in blocks.values()),
        )
        checks = [b["check"] for b in blocks.values() if b.get("check")]
        pooled = (
            None
            if not checks
            else {
                k: float(np.sqrt(np.mean([c[k] ** 2 for c in checks])))
                for k in (
                    "geoloc_rmse_m_before",
                    "geoloc_rmse_m",
                    "geoloc_rmse_px",
                    "formal_rmse_m",
                )
                if all(k in c for c in checks)
            }
            | {"geoloc_max_m": max(c["geoloc_max_m"] for c in checks)}
        )
        if pooled and pooled.get("formal_rmse_m"):
            pooled["true_over_formal"] = pooled["geoloc_rmse_m"] / pooled["formal_rmse_m"]
        check = None if pooled is None else CheckBlock.model_validate(pooled)
    return GeorefReport(
        matcher=matcher,
        scene=scene,
        planetref_version=__version__,
        matching=matching,
        adjustment=adjustment,
        check=check,
        timing_s=dict(timing),
        strips=dict(strips),
    )


def _pooled_matching(
    matching: Mapping[str, Mapping[str, Any]], frontend: FrontendSettings | None
) -> MatchingSummary:
    """The run's ``matching`` block: the strips' blocks (as in report.json) pooled."""
    ccds: dict[str, Any] = {}
    for sid, m in matching.items():
        for c, v in m["ccds"].items():
            ccds[c if len(matching) == 1 else f"{sid}/{c}"] = v
    block: dict[str, Any] = {
        "ccds": ccds,
        "ncp": int(sum(m["ncp"] for m in matching.values())),
        "sdu_pct": float(np.mean([v["sdu_pct"] for v in ccds.values()])) if ccds else 0.0,
        "tiles_total": sum(m["tiles_total"] for m in matching.values()),
        "tiles_failed": sum(m["tiles_failed"] for m in matching.values()),
        "tiles_thinned": sum(m.get("tiles_thinned", 0) for m in matching.values()),
        "coarse_sources": _sum_counts(m.get("coarse_sources", {}) for m in matching.values()),
        "tiles_lost": [dict(t, strip=sid) for sid, m in matching.items() for t in m["tiles_lost"]],
        "funnel": _sum_counts(m.get("funnel", {}) for m in matching.values()),
        "drops": _sum_counts(m.get("drops", {}) for m in matching.values()),
    }
    outliers = sum_true_outliers(m.get("true_outliers") for m in matching.values())
    if outliers is not None:
        block["true_outliers"] = outliers
    if frontend is not None:
        block["settings"] = frontend.to_json()
    return MatchingSummary.model_validate(block)


def frontend_settings(fe: FrontendConfig) -> FrontendSettings:
    """The front-end settings that decide what the matching figures mean (report.json)."""
    return FrontendSettings(
        refine=fe.refine.method,
        fine_upsample=fe.fine_upsample,
        dense_spacing_ref_px=fe.dense_spacing_ref_px,
        max_mcps_per_tile=fe.max_mcps_per_tile,
        protocol=fe.protocol,
    )


def too_few_mcps(
    strip_id: str, matcher: str, matching: StripMatching, min_mcps: int
) -> MatcherFailedError:
    """The error of a strip with fewer MCPs than the adjustment needs (its matching kept)."""
    status = ", ".join(f"{k} {v}" for k, v in matching.tile_status.items() if v)
    return MatcherFailedError(
        f"strip {strip_id}: only {matching.n_mcps} matched control points with matcher "
        f"{matcher} ({matching.tiles_failed}/{matching.tiles_total} tiles failed: "
        f"{status}); at least {min_mcps} are needed. See planetref.log for why tiles failed",
        matching={strip_id: matching},
    )


def failed_report(
    matcher: str,
    scene: str,
    matching: Mapping[str, StripMatching | Mapping[str, Any]],
    reason: str,
    timing: Mapping[str, float],
    frontend: FrontendSettings | None = None,
    *,
    strips_not_run: Iterable[str] = (),
) -> GeorefReport:
    """report.json of a run whose matcher ran but which could not finish.

    The ``matching`` block as in :func:`combined_report` (NCP, SDU per CCD, tiles failed,
    funnel, drops) over the strips matched; no adjustment and no true error; ``failed``
    says why. Such a run stays a row of the comparison's tables.

    Args:
        matcher: Matcher name.
        scene: Scene name.
        matching: Strip id -> its ``matching`` block (:func:`matching_block`, or its JSON).
        reason: Why the run stopped (the error's message).
        timing: Seconds per step.
        frontend: The front-end settings (see :func:`combined_report`).
        strips_not_run: Strips not matched because the run stopped before them.
    """
    blocks = {
        sid: m if isinstance(m, StripMatching) else StripMatching.model_validate(m)
        for sid, m in matching.items()
    }
    return GeorefReport(
        matcher=matcher,
        scene=scene,
        planetref_version=__version__,
        failed=reason,
        strips_not_run=list(strips_not_run),
        matching=_pooled_matching({sid: m.to_json() for sid, m in blocks.items()}, frontend),
        adjustment=None,
        check=None,
        timing_s=dict(timing),
        strips={sid: StripReport(matching=m, failed=reason) for sid, m in blocks.items()},
    )


def _sum_counts(blocks: Iterable[Mapping[str, int]]) -> dict[str, int]:
    """Counts summed key by key, keys in first-seen order."""
    out: dict[str, int] = {}
    for b in blocks:
        for k, v in b.items():
            out[k] = out.get(k, 0) + int(v)
    return out
