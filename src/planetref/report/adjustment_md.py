"""report.md of an adjustment: the seed's Table 2, the stochastic model, movements."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from planetref.adjust.result import AdjustmentResult

__all__ = ["MODE_NAMES", "report_md", "top_correlations"]

MODE_NAMES = {0: "free", 1: "weighted", 2: "fixed"}


def top_correlations(result: AdjustmentResult, n: int = 20) -> list[list[Any]]:
    """The ``n`` strongest parameter correlations as ``[name, name, r]``."""
    c = np.abs(np.triu(result.correlation, 1))
    if not c.size:
        return []
    flat = np.argsort(c, axis=None)[::-1][:n]
    out = []
    for f in flat:
        i, j = np.unravel_index(f, c.shape)
        if c[i, j] <= 0:
            break
        out.append(
            [result.parameter_names[i], result.parameter_names[j], float(result.correlation[i, j])]
        )
    return out


def _fmt(v: Any, digits: int = 4) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    if isinstance(v, int | np.integer):
        return str(int(v))
    return f"{v:.{digits}g}"


def _table2_rows(label: str, m: dict[str, Any], sigma0: float | None) -> list[str]:
    rows = []
    for when in ("before", "after"):
        s = m[when]
        rows.append(
            f"| {label} | {when} | {_fmt(s['rmse_px'])} | {_fmt(s['rmse_x_px'])} | "
            f"{_fmt(s['rmse_y_px'])} | {_fmt(s['mean_px'])} | {_fmt(s['mean_x_px'])} | "
            f"{_fmt(s['mean_y_px'])} | "
            f"{_fmt(s['max_dx_px'])} | {_fmt(s['min_dx_px'])} | "
            f"{_fmt(s['max_dy_px'])} | {_fmt(s['min_dy_px'])} | "
            f"{_fmt(s['outlier_ratio_pct'], 3)} | {s['n_inliers']}/{s['n_total']} | "
            f"{_fmt(sigma0) if when == 'after' and sigma0 is not None else '-'} |"
        )
    return rows


def _stochastic_md(result: AdjustmentResult) -> list[str]:
    """Variance components, degrees of freedom, movements, self-calibration (markdown)."""
    var = result.variance
    lines: list[str] = []
    dof = var.get("dof", {})
    if dof:
        lines += [
            "",
            "## Degrees of freedom",
            "",
            f"{dof['n_real_equations']} equations of real observations (image measures, "
            f"MCP ground coordinates) and {dof['n_pseudo_equations']} pseudo-observations "
            f"({dof['n_camera_priors']} camera priors, {dof['n_smoothing_constraints']} "
            f"smoothing constraints, the rest tie-point priors) for {dof['n_unknowns']} "
            f"unknowns: {dof['dof']} degrees of freedom, of which "
            f"{_fmt(dof['redundancy_real'])} are redundancy of the real observations and "
            f"{_fmt(dof['redundancy_pseudo'])} of the pseudo-observations (sums of "
            f"redundancy numbers). sigma0 of the real observations: "
            f"{_fmt(dof['sigma0_real'])}.",
        ]
    if var.get("groups"):
        lines += [
            "",
            f"## Variance components ({'estimated' if var['enabled'] else 'not estimated'}; "
            f"{var['iterations']} re-weighting iteration(s), converged: {var['converged']})",
            "",
            "| group | equations | redundancy | factor | sigma | estimated |",
            "|---|---|---|---|---|---|",
        ]
        for g in var["groups"]:
            sig = f"{_fmt(g['sigma_px'])} px" if "sigma_px" in g else f"{_fmt(g.get('sigma_m'))} m"
            why = "yes" if g["estimated"] else f"no: {g['not_estimated_because']}"
            if g.get("note"):
                why += f" ({g['note']})"
            lines.append(
                f"| {g['group']} | {g['n_equations']} | {_fmt(g['redundancy'])} | "
                f"{_fmt(g['factor'])} | {sig} | {why} |"
            )
    diag = result.diagnostics
    if diag.get("point_shifts"):
        lines += [
            "",
            "## Movement of the points (adjusted - a priori; all in points.csv)",
            "",
            "| kind | points | mean m | RMS m | max m | mean horizontal m | mean up m |",
            "|---|---|---|---|---|---|---|",
        ]
        for k, m in diag["point_shifts"].items():
            lines.append(
                f"| {k} | {m['n']} | {_fmt(m['mean_shift_m'])} | {_fmt(m['rms_shift_m'])} | "
                f"{_fmt(m['max_shift_m'])} | {_fmt(m['mean_horizontal_m'])} | "
                f"{_fmt(m['mean_up_m'])} |"
            )
    if diag.get("camera_shifts"):
        lines += [
            "",
            "## Movement of the camera footprints",
            "",
            "| camera | CCD | mean m | max m |",
            "|---|---|---|---|",
        ]
        for cid, per in diag["camera_shifts"].items():
            for ccd, m in per["ccds"].items():
                lines.append(f"| {cid} | {ccd} | {_fmt(m['mean_m'])} | {_fmt(m['max_m'])} |")
    if diag.get("self_calibration"):
        lines += ["", "## Self-calibration: estimability", ""]
        lines += [
            f"* {r['verdict']}; a-priori sigma {_fmt(r['sigma_prior'])}, a-posteriori "
            f"{_fmt(r['sigma'])}; correlation with the mean node height "
            f"{_fmt(r['correlation_mean_node_height'])}, multiple correlation "
            f"{_fmt(r['multiple_correlation'], 5)}; strongest: {r['correlations_text']}"
            for r in diag["self_calibration"]
        ]
    return lines


def report_md(
    result: AdjustmentResult, geo: dict[str, Any] | None, rpc: dict[str, Any], notes: list[str]
) -> str:
    """The markdown report (Table 2, checks, geolocation, stochastic model, ...)."""
    s = result.summary()
    lines = [
        "# Bundle adjustment report",
        "",
        f"RMSE {_fmt(s['rmse_px_before'])} px -> **{_fmt(s['rmse_px'])} px**; "
        f"outlier ratio {_fmt(s['outlier_ratio_pct'], 3)} % "
        f"({s['n_inliers']} of {s['n_total']} observations are inliers); "
        f"sigma0 {_fmt(s['sigma0'])}, {s['dof']} degrees of freedom; "
        f"{s['rounds']} round(s); converged: {s['converged']}.",
        "",
        "Residuals are projected - observed; dx = sample, dy = line, pixels. "
        "'before' uses the initial cameras on the same (final) inliers; the outlier "
        "ratio is that of the final k x RMSE classification. MCPs whose ground is weighted "
        "are judged by their reference ground point through the adjusted camera.",
        "",
        "## Reprojection residuals (Table 2)",
        "",
        "| camera / CCD | | RMSE | RMSE x | RMSE y | mean | mean x | mean y | max dx | min dx "
        "| max dy | min dy | OR % | inliers | sigma0 |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    lines += _table2_rows("all", result.metrics["all"], result.sigma0)
    for cid, m in result.metrics["cameras"].items():
        lines += _table2_rows(cid, m, None)
        for ccd, mc in m.get("ccds", {}).items():
            lines += _table2_rows(f"{cid} / {ccd}", mc, None)
    chk = result.metrics.get("check")
    if chk:
        lines += [
            "",
            "## Check observations (held out)",
            "",
            "| | RMS px | max px | RMS m | max m | n |",
            "|---|---|---|---|---|---|",
        ]
        for when in ("before", "after"):
            c = chk[when]
            lines.append(
                f"| {when} | {_fmt(c['rms_px'])} | {_fmt(c['max_px'])} | "
                f"{_fmt(c['rms_m'])} | {_fmt(c['max_m'])} | {c['n']} |"
            )
    if geo:
        lines += [
            "",
            "## Geolocation error against the true cameras",
            "",
            "| camera / CCD | | RMS m | max m | RMS px | max px |",
            "|---|---|---|---|---|---|",
        ]
        for cid, per in geo.items():
            for ccd, g in per.items():
                for when in ("before", "after"):
                    e = g[when]
                    lines.append(
                        f"| {cid} / {ccd} | {when} | {_fmt(e['rms_m'])} | "
                        f"{_fmt(e['max_m'])} | {_fmt(e['rms_px'])} | "
                        f"{_fmt(e['max_px'])} |"
                    )
    lines += _stochastic_md(result)
    lines += [
        "",
        "## Rounds",
        "",
        "| round | observations | RMSE px | iterations | evaluations | converged |",
        "|---|---|---|---|---|---|",
    ]
    for r in result.rounds:
        lines.append(
            f"| {r['round']} | {r['n_observations']} | {_fmt(r['rmse_px'])} | "
            f"{r['iterations']} | {r['evaluations']} | {r['converged']} |"
        )
    act = np.flatnonzero(result.parameter_mode != 2)
    lines += [
        "",
        f"## Parameters ({act.size} adjusted of {len(result.parameter_names)}; "
        f"all in parameters.csv)",
        "",
        "| parameter | unit | mode | correction | sigma |",
        "|---|---|---|---|---|",
    ]
    for i in act[:60]:
        lines.append(
            f"| {result.parameter_names[i]} | {result.parameter_units[i]} | "
            f"{MODE_NAMES[int(result.parameter_mode[i])]} | "
            f"{_fmt(result.x[i] - result.x0[i])} | {_fmt(result.sigma[i])} |"
        )
    if act.size > 60:
        lines.append(f"| ... {act.size - 60} more | | | | |")
    top = top_correlations(result, 10)
    if top:
        lines += [
            "",
            "## Strongest correlations",
            "",
            "| parameter | parameter | r |",
            "|---|---|---|",
        ]
        lines += [f"| {a} | {b} | {r:.4f} |" for a, b, r in top]
    if rpc:
        lines += [
            "",
            "## Refitted RPCs",
            "",
            "| camera | CCD | fit RMS px | check RMS px |",
            "|---|---|---|---|",
        ]
        for cid, per in rpc.items():
            for ccd, rep in per.items():
                lines.append(
                    f"| {cid} | {ccd} | {_fmt(rep.get('fit_rms_px'))} | "
                    f"{_fmt(rep.get('check_rms_px'))} |"
                )
        bias = [
            f"* {cid}: RPC image, bias model '{rep['bias_model']}' (image-space, "
            f"Grodecki & Dial 2003); refined RPC: {rep['method']}"
            for cid, per in rpc.items()
            for rep in per.values()
            if rep.get("bias_model")
        ]
        lines += ["", *bias] if bias else []
    if result.warnings or notes:
        lines += ["", "## Warnings", ""] + [f"* {w}" for w in [*result.warnings, *notes]]
    return "\n".join(lines) + "\n"
