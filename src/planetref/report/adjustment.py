"""Outputs of an adjustment: cameras, residual table, report.json/report.md, plots.

Layout of the output folder::

    report.json            headline numbers, metrics, parameters, rounds, configuration
    report.md              the same for people (the seed's Table 2 per camera and CCD)
    residuals.csv          one row per observation
    points.csv             one row per point: a-priori and adjusted XYZ, lat/lon/height,
                           sigmas, shift (metres and a-priori sigmas)
    parameters.csv         one row per parameter (initial, adjusted, sigma)
    covariance.npz         names, covariance and correlation matrices of the parameters
    config.json            the resolved configuration
    cameras/<id>.json      adjusted native line-scan cameras
    cameras/<id>.isd.json  adjusted CSM ISDs (correction stored as usgscsm parameters)
    cameras/<id>[_<ccd>]_RPC.TXT   RPCs refitted to the adjusted rigorous model
    plots/residuals_<id>[_<ccd>].png   residual vectors over each CCD image

Every file is written atomically (a temporary file in the same folder, then a rename).
Residual columns follow the seed: ``dx`` is the sample residual and ``dy`` the line
residual, both ``projected - observed`` in pixels.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from planetref.adjust.jitter import true_jitter
from planetref.adjust.metrics import geolocation_error
from planetref.adjust.network_file import safe_name
from planetref.adjust.result import AdjustmentResult
from planetref.camera.linescan import LineScanCamera
from planetref.camera.rpc.stable import fit_rpc_stable
from planetref.errors import PlanetrefError
from planetref.geometry.geodesy import xyz_to_lonlat
from planetref.report.adjustment_md import MODE_NAMES, report_md, top_correlations
from planetref.runtime.atomic import json_safe, write_bytes_atomic, write_text_atomic

__all__ = ["POINT_COLUMNS", "geolocation_metrics", "write_outputs", "write_points"]

log = logging.getLogger("planetref.adjust")
#: A refitted RPC is reported as a warning when its check RMS (pixels) exceeds both this
#: and ``RPC_WARN_FRACTION`` of the adjustment's RMSE: only then does using the RPC
#: instead of the rigorous camera add noticeably (> 12 % in quadrature) to the error.
RPC_WARN_PX = 0.1
RPC_WARN_FRACTION = 0.5


# ------------------------------------------------------------------------ metrics
def geolocation_metrics(
    result: AdjustmentResult,
    truth: Mapping[str, Any],
    *,
    terrain: Any = 0.0,
    grid: tuple[int, int] = (21, 21),
) -> dict[str, Any]:
    """Geolocation error before and after, per camera and CCD, against true cameras.

    Args:
        result: The adjustment result.
        truth: Camera id -> true camera (ids missing here are skipped).
        terrain: Height (m) or :class:`~planetref.camera.base.Terrain` of the grid points.
        grid: Image grid ``(n_lines, n_samples)``.

    Returns:
        ``{camera_id: {ccd: {"before": {...}, "after": {...}}}}`` with the fields of
        :func:`~planetref.adjust.metrics.geolocation_error` (metres and pixels, RMS and max).
    """
    out: dict[str, Any] = {}
    for cid, true_cam in truth.items():
        if cid not in result.cameras:
            continue
        per = {}
        for ccd in true_cam.ccd_names:
            per[ccd] = {
                "before": geolocation_error(
                    result.cameras_initial[cid], true_cam, ccd=ccd, terrain=terrain, grid=grid
                ),
                "after": geolocation_error(
                    result.cameras[cid], true_cam, ccd=ccd, terrain=terrain, grid=grid
                ),
            }
        out[cid] = per
    return out


# ------------------------------------------------------------------------ writing
def write_outputs(
    result: AdjustmentResult,
    out_dir: str | os.PathLike[str],
    *,
    truth: Mapping[str, Any] | None = None,
    terrain: Any = 0.0,
    rpc: bool = True,
    plots: bool = True,
    extra: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Write every output of an adjustment into a folder (see the module doc).

    Args:
        result: The adjustment result.
        out_dir: Output folder (created if needed).
        truth: Optional camera id -> true camera: adds the geolocation error before and
            after (metres and pixels) to the reports.
        terrain: Height (m) or terrain for the geolocation grid and nothing else.
        rpc: Refit and write RPCs of the adjusted cameras.
        plots: Draw the residual-vector plots.
        extra: Additional entries for report.json (e.g. the input files).

    Returns:
        ``{"report_json", "report_md", "residuals", "parameters", "covariance", "config",
        "cameras": {id: [paths]}, "plots": [paths]}``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: dict[str, Any] = {"cameras": {}, "plots": []}
    geo = geolocation_metrics(result, truth, terrain=terrain) if truth else None
    written["residuals"] = str(_write_residuals(result, out / "residuals.csv"))
    written["points"] = str(write_points(result, out / "points.csv"))
    written["parameters"] = str(_write_parameters(result, out / "parameters.csv"))
    if result.jitter:
        written["jitter"] = str(write_jitter_csv(result, out / "jitter.csv", truth))
    buf = io.BytesIO()
    np.savez_compressed(
        buf,
        names=np.array(result.parameter_names),
        covariance=result.covariance,
        correlation=result.correlation,
    )
    written["covariance"] = str(write_bytes_atomic(out / "covariance.npz", buf.getvalue()))
    written["config"] = str(
        write_text_atomic(
            out / "config.json", json.dumps(result.config.model_dump(mode="json"), indent=1) + "\n"
        )
    )
    rpc_reports: dict[str, Any] = {}
    notes: list[str] = []
    rpc_limit = max(RPC_WARN_PX, RPC_WARN_FRACTION * float(result.summary().get("rmse_px", 0.0)))
    for cid, cam in result.cameras.items():
        paths, rep = _write_camera(result, cid, cam, out / "cameras", rpc)
        written["cameras"][cid] = [str(p) for p in paths]
        if rep:
            rpc_reports[cid] = rep
            for ccd, r in rep.items():
                if "error" in r:
                    notes.append(f"camera {cid} CCD {ccd}: no RPC ({r['error']})")
                elif not r["check_rms_px"] < rpc_limit:
                    notes.append(
                        f"camera {cid} CCD {ccd}: the refitted RPC reproduces the "
                        f"adjusted camera to {r['check_rms_px']:.3g} px RMS only "
                        f"(max {r['check_max_px']:.3g} px), more than half the "
                        "adjustment's RMSE; use the rigorous camera"
                    )
    for n in notes:
        log.warning("%s", n)
    if notes:
        extra = {**(extra or {}), "output_warnings": notes}
    if plots:
        written["plots"] = [str(p) for p in _write_plots(result, out / "plots")]
    report = _report_dict(result, geo, rpc_reports, written, extra)
    written["report_json"] = str(
        write_text_atomic(
            out / "report.json", json.dumps(json_safe(report), indent=1, allow_nan=False) + "\n"
        )
    )
    written["report_md"] = str(
        write_text_atomic(out / "report.md", report_md(result, geo, rpc_reports, notes))
    )
    return written


def jitter_truth(result: AdjustmentResult, cid: str, truth: Mapping[str, Any] | None) -> Any:
    """The true jitter of strip ``cid`` relative to the seed (rad, ``(m, 3)``), or None."""
    cam = (truth or {}).get(cid)
    if not isinstance(cam, LineScanCamera) or cid not in result.jitter:
        return None
    return true_jitter(result.jitter[cid], result.cameras[cid], cam)


def write_jitter_csv(
    result: AdjustmentResult, path: Path, truth: Mapping[str, Any] | None = None
) -> Path:
    """jitter.csv: the estimated jitter per strip and node, with formal sigmas (urad).

    Columns ``camera_id, time_s, line, roll_urad, pitch_urad, yaw_urad,
    sigma_roll_urad, sigma_pitch_urad, sigma_yaw_urad`` and, with a truth, ``true_roll_urad,
    true_pitch_urad, true_yaw_urad`` (the truth's pointing relative to the seed; yaw
    empty, see :func:`~planetref.adjust.jitter.true_jitter`).
    """
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    axes = ("roll", "pitch", "yaw")
    has_truth = any(jitter_truth(result, c, truth) is not None for c in result.jitter)
    w.writerow(
        ["camera_id", "time_s", "line"]
        + [f"{a}_urad" for a in axes]
        + [f"sigma_{a}_urad" for a in axes]
        + ([f"true_{a}_urad" for a in axes] if has_truth else [])
    )
    for cid, s in result.jitter.items():
        tru = jitter_truth(result, cid, truth)
        for i in range(len(s.line)):
            row = [cid, f"{s.time_s[i]:.6f}", f"{s.line[i]:.1f}"]
            row += [f"{v * 1e6:.4f}" for v in s.angles_rad[i]]
            row += [f"{v * 1e6:.4f}" for v in s.sigma_rad[i]]
            if has_truth:
                row += (
                    ["" if not math.isfinite(v) else f"{v * 1e6:.4f}" for v in tru[i]]
                    if tru is not None
                    else ["", "", ""]
                )
            w.writerow(row)
    return write_text_atomic(path, buf.getvalue())


def _write_residuals(result: AdjustmentResult, path: Path) -> Path:
    net = result.network
    labels = [
        result.network.cameras[c].ccd_names[k]
        for c, k in zip(net.obs_camera, net.obs_ccd, strict=True)
    ]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(
        [
            "obs_id",
            "point_id",
            "point_kind",
            "camera_id",
            "ccd",
            "line",
            "sample",
            "dx_px",
            "dy_px",
            "residual_px",
            "dx_before_px",
            "dy_before_px",
            "status",
            "inlier",
        ]
    )
    r, r0 = result.residual, result.residual_initial

    def f(v: float) -> str:
        return "" if not math.isfinite(v) else f"{v:.6f}"

    for i in range(net.n_obs):
        pid = net.obs_point[i]
        w.writerow(
            [
                net.obs_ids[i],
                net.point_ids[pid],
                net.point_kind[pid],
                net.camera_ids[net.obs_camera[i]],
                labels[i],
                f"{net.obs_line[i]:.6f}",
                f"{net.obs_sample[i]:.6f}",
                f(r[i, 1]),
                f(r[i, 0]),
                f(math.hypot(r[i, 0], r[i, 1])),
                f(r0[i, 1]),
                f(r0[i, 0]),
                result.status[i],
                int(result.status[i] == "inlier"),
            ]
        )
    return write_text_atomic(path, buf.getvalue())


#: Columns of points.csv.
POINT_COLUMNS = (
    "point_id",
    "kind",
    "used",
    "apriori_x_m",
    "apriori_y_m",
    "apriori_z_m",
    "x_m",
    "y_m",
    "z_m",
    "apriori_lat_deg",
    "apriori_lon_deg",
    "apriori_height_m",
    "lat_deg",
    "lon_deg",
    "height_m",
    "sigma_frame",
    "apriori_sigma_1_m",
    "apriori_sigma_2_m",
    "apriori_sigma_3_m",
    "sigma_east_m",
    "sigma_north_m",
    "sigma_up_m",
    "shift_m",
    "shift_horizontal_m",
    "shift_up_m",
    "shift_sigma",
)


def write_points(result: AdjustmentResult, path: Path) -> Path:
    """Write points.csv: one row per point of the network.

    Columns (:data:`POINT_COLUMNS`): id, kind (``mcp``/``tie``), whether it took part;
    a-priori (for free points: triangulated) and adjusted body-fixed XYZ (m),
    planetocentric latitude, east longitude (degrees) and height above the body
    (metres), a priori and adjusted; the a-priori sigmas used in the final adjustment
    (after variance component scaling) along ``sigma_frame`` (``xyz`` or ``enu``;
    empty = free, 0 = fixed); the a-posteriori sigmas along east, north, up; the
    shift adjusted - a priori (length, horizontal, up, in metres) and its largest
    component in a-priori sigmas.
    """
    t = result.points
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(POINT_COLUMNS)

    def f(v: float, fmt: str = ".4f") -> str:
        return "" if not math.isfinite(v) else format(float(v), fmt)

    for i in range(len(t["point_id"])):
        a, x = t["xyz_apriori"][i], t["xyz"][i]
        sa = t["sigma_apriori"][i]
        w.writerow(
            [
                t["point_id"][i],
                t["kind"][i],
                int(t["used"][i]),
                *(f(v) for v in a),
                *(f(v) for v in x),
                f(t["lat_apriori"][i], ".9f"),
                f(t["lon_apriori"][i], ".9f"),
                f(t["height_apriori"][i]),
                f(t["lat"][i], ".9f"),
                f(t["lon"][i], ".9f"),
                f(t["height"][i]),
                "enu" if t["sigma_local"][i] else "xyz",
                *(f(v) for v in sa),
                *(f(v) for v in t["sigma_enu"][i]),
                f(t["shift_m"][i]),
                f(t["shift_horizontal_m"][i]),
                f(t["shift_up_m"][i]),
                f(t["shift_sigma"][i], ".3f"),
            ]
        )
    return write_text_atomic(path, buf.getvalue())


def _write_parameters(result: AdjustmentResult, path: Path) -> Path:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["name", "unit", "mode", "initial", "adjusted", "correction", "sigma"])
    for i, name in enumerate(result.parameter_names):
        w.writerow(
            [
                name,
                result.parameter_units[i],
                MODE_NAMES[int(result.parameter_mode[i])],
                repr(float(result.x0[i])),
                repr(float(result.x[i])),
                repr(float(result.x[i] - result.x0[i])),
                repr(float(result.sigma[i])),
            ]
        )
    return write_text_atomic(path, buf.getvalue())


def _height_range(result: AdjustmentResult, cid: str, cam: Any) -> tuple[float, float]:
    """Heights (m) an RPC of the camera must cover: those of its points, padded.

    The a priori coordinates are used (for MCPs the reference ground; tie points of weak
    stereo geometry can float kilometres in height in the adjustment), trimmed to the
    0.5-99.5 percentiles.
    """
    net = result.network
    ci = net.camera_ids.index(cid)
    pts = np.unique(net.obs_point[net.obs_camera == ci])
    xyz = result.point_xyz_initial[pts]
    xyz = xyz[np.all(np.isfinite(xyz), axis=1)]
    if not len(xyz):
        return -1000.0, 1000.0
    _, _, h = xyz_to_lonlat(xyz, cam.ellipsoid)
    lo, hi = (float(v) for v in np.percentile(h, [0.5, 99.5]))
    pad = max(500.0, 0.2 * (hi - lo))
    return lo - pad, hi + pad


def _write_camera(
    result: AdjustmentResult, cid: str, cam: Any, folder: Path, rpc: bool
) -> tuple[list[Path], dict[str, Any]]:
    folder.mkdir(parents=True, exist_ok=True)
    name = safe_name(cid)
    from planetref.camera.rpc.strip import write_refined_rpcs

    refined = write_refined_rpcs(cam, folder, name)
    if refined is not None:
        # RPC images: their refined RPCs (bias absorbed or refitted) are their cameras.
        model = next(m for m in result.models if m.camera_id == cid)
        bias = getattr(model, "bias_model", None)
        return refined[0], {k: {"bias_model": bias, **r} for k, r in refined[1].items()}
    paths: list[Path] = []
    if isinstance(cam, LineScanCamera):
        paths.append(cam.to_json(folder / f"{name}.json"))
    else:
        try:
            from planetref.camera.csm import CsmLineScanCamera, write_isd
        except ImportError:  # pragma: no cover
            CsmLineScanCamera = None  # type: ignore[assignment,misc]
        if CsmLineScanCamera is not None and isinstance(cam, CsmLineScanCamera):
            paths.append(write_isd(cam, folder / f"{name}.isd.json"))
    reports: dict[str, Any] = {}
    if rpc:
        from planetref.camera.rpc import RpcBody, write_rpc

        body = RpcBody(cam.ellipsoid, cam.latitude_kind)
        hr = _height_range(result, cid, cam)
        for ccd in cam.ccd_names:
            suffix = "" if len(cam.ccd_names) == 1 else f"_{safe_name(ccd)}"
            try:
                model, fit = fit_rpc_stable(
                    cam, height_range_m=hr, ccd=None if len(cam.ccd_names) == 1 else ccd
                )
            except PlanetrefError as exc:
                log.warning("camera %s CCD %s: no RPC (%s)", cid, ccd, exc)
                reports[ccd] = {"error": str(exc)}
                continue
            paths.append(write_rpc(model, folder / f"{name}{suffix}_RPC.TXT", fmt="txt", body=body))
            reports[ccd] = {
                "fit_rms_px": fit.fit_rms_px,
                "check_rms_px": fit.check_rms_px,
                "check_max_px": fit.check_max_px,
                "min_abs_denominator": fit.min_abs_denominator,
                "regularization": fit.regularization,
                "height_range_m": list(hr),
            }
    return paths, reports


def _write_plots(result: AdjustmentResult, folder: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    net = result.network
    paths = []
    for ci, cid in enumerate(net.camera_ids):
        cam = result.cameras[cid]
        for k, ccd in enumerate(cam.ccd_names):
            sel = np.flatnonzero((net.obs_camera == ci) & (net.obs_ccd == k))
            n_lines, n_samples = cam.image_size(ccd)
            r = result.residual[sel]
            ok = np.all(np.isfinite(r), axis=1)
            sel, r = sel[ok], r[ok]
            status = result.status[sel]
            length = np.hypot(r[:, 0], r[:, 1])
            ref = (
                float(np.percentile(length[status == "inlier"], 95))
                if np.any(status == "inlier")
                else (float(length.max()) if length.size else 1.0)
            )
            ref = ref if ref > 0 else 1.0
            # Arrows are exaggerated so that a 95th-percentile inlier residual is 4% of
            # the image width; gross errors are clipped to 15% of it.
            exag = 0.04 * n_samples / ref
            cap = 0.15 * n_samples
            with np.errstate(divide="ignore", invalid="ignore"):
                shrink = np.where(length * exag > cap, cap / (length * exag), 1.0)
            r = r * shrink[:, None]
            clipped = bool(np.any(shrink < 1.0))
            height = min(12.0, max(4.0, 6.0 * n_lines / max(n_samples, 1)))
            fig, ax = plt.subplots(figsize=(6.5, height))
            ax.set_xlim(0, n_samples)
            ax.set_ylim(n_lines, 0)
            for st, colour in (
                ("inlier", "tab:blue"),
                ("outlier", "tab:red"),
                ("check", "tab:green"),
                ("unusable", "0.5"),
            ):
                m = status == st
                if not np.any(m):
                    continue
                ax.quiver(
                    net.obs_sample[sel][m],
                    net.obs_line[sel][m],
                    r[m, 1] * exag,
                    r[m, 0] * exag,
                    angles="xy",
                    scale_units="xy",
                    scale=1.0,
                    color=colour,
                    width=0.003,
                    label=f"{st} ({int(m.sum())})",
                )
            label = cid if len(cam.ccd_names) == 1 else f"{cid} / {ccd}"
            met = result.metrics["cameras"][cid]
            if len(cam.ccd_names) > 1:
                met = met["ccds"][ccd]
            ax.set_title(
                f"{label}\nRMSE {met['after']['rmse_px']:.3g} px (before "
                f"{met['before']['rmse_px']:.3g}); arrows x{exag:.3g}"
                f"{', long ones clipped' if clipped else ''}",
                fontsize=9,
            )
            ax.set_xlabel("sample (px)")
            ax.set_ylabel("line (px)")
            if len(sel):
                ax.legend(loc="upper right", fontsize=7)
            fig.tight_layout()
            suffix = "" if len(cam.ccd_names) == 1 else f"_{safe_name(ccd)}"
            buf = io.BytesIO()
            fig.savefig(buf, format="png", dpi=110)
            plt.close(fig)
            paths.append(
                write_bytes_atomic(
                    folder / f"residuals_{safe_name(cid)}{suffix}.png", buf.getvalue()
                )
            )
    return paths


def _report_dict(
    result: AdjustmentResult,
    geo: dict[str, Any] | None,
    rpc: dict[str, Any],
    written: dict[str, Any],
    extra: Mapping[str, Any] | None,
) -> dict[str, Any]:
    from planetref import __version__

    params = []
    for i, name in enumerate(result.parameter_names):
        params.append(
            {
                "name": name,
                "unit": result.parameter_units[i],
                "mode": MODE_NAMES[int(result.parameter_mode[i])],
                "initial": float(result.x0[i]),
                "adjusted": float(result.x[i]),
                "correction": float(result.x[i] - result.x0[i]),
                "sigma": float(result.sigma[i]),
            }
        )
    physical = {}
    for model in result.models:
        if hasattr(model, "physical"):
            i = result.network.camera_ids.index(model.camera_id)
            lo = sum(len(m.x0) for m in result.models[:i])
            physical[model.camera_id] = model.physical(result.x[lo : lo + len(model.x0)])
    report: dict[str, Any] = {
        "planetref_version": __version__,
        "adjustment": result.summary(),
        "metrics": result.metrics,
        "parameters": params,
        "corrections_physical": physical,
        "correlations": {
            "max_abs": float(np.max(np.abs(np.triu(result.correlation, 1))))
            if result.correlation.size > 1
            else 0.0,
            "top": top_correlations(result),
        },
        "variance_components": result.variance,
        # The correlated errors in the covariance (declared, and the tiles' estimate).
        "systematic": None if result.consider is None else result.consider.summary(),
        "movement": {
            "points": result.diagnostics.get("point_shifts", {}),
            "cameras": result.diagnostics.get("camera_shifts", {}),
        },
        "correlation_check": result.diagnostics.get("correlations", {}),
        "self_calibration": result.diagnostics.get("self_calibration", []),
        "jitter": result.diagnostics.get("jitter"),
        "rounds": result.rounds,
        "warnings": result.warnings,
        "rpc_fits": rpc,
        "config": result.config.model_dump(mode="json"),
        "outputs": {k: v for k, v in written.items()},
    }
    if geo is not None:
        report["geolocation"] = geo
    if extra:
        report.update(extra)
    return report
