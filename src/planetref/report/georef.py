"""Reports of georef and compare runs: Markdown, CSV and JSON tables, and figures.

The two tables of the seed:

* **Matching** — NCP and SDU (%) per CCD image, one row per matcher.
* **Adjustment** — RMSE, Mean, Max X, Max Y, Min X, Min Y (pixels) and OR (%) per strip,
  one row per matcher; ``x`` is the sample residual, ``y`` the line residual.

Where truth is known a third table gives the true geolocation error before and after.
Figures are written with matplotlib's Agg canvas through a temporary file.
"""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from planetref.atomic import write_text_atomic
from planetref.report.figures_matching import _save

__all__ = [
    "adjustment_rows",
    "figure_headline_bars",
    "figure_residual_vectors",
    "format_markdown_table",
    "matching_rows",
    "write_compare_tables",
    "write_georef_markdown",
]

ADJ_COLUMNS = [
    ("RMSE", "rmse_px"),
    ("Mean", "mean_px"),
    ("Max X", "max_x_px"),
    ("Max Y", "max_y_px"),
    ("Min X", "min_x_px"),
    ("Min Y", "min_y_px"),
    ("OR (%)", "outlier_ratio_pct"),
]


def _fmt(v: Any, digits: int = 3) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "-" if not math.isfinite(v) else f"{v:.{digits}f}"
    return str(v)


def format_markdown_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub-flavoured Markdown table (numbers right-aligned, text left-aligned)."""
    cells = [[_fmt(v) for v in r] for r in rows]
    widths = [max(len(str(h)), *(len(r[i]) for r in cells)) for i, h in enumerate(header)]
    numeric = [
        all(isinstance(r[i], int | float) or r[i] is None for r in rows) for i in range(len(header))
    ]
    out = [
        "| " + " | ".join(str(h).ljust(w) for h, w in zip(header, widths, strict=True)) + " |",
        "|"
        + "|".join(
            "-" * (w + 1) + (":" if num else "-") for w, num in zip(widths, numeric, strict=True)
        )
        + "|",
    ]
    for r in cells:
        out.append(
            "| "
            + " | ".join(
                c.rjust(w) if num else c.ljust(w)
                for c, w, num in zip(r, widths, numeric, strict=True)
            )
            + " |"
        )
    return "\n".join(out)


def matching_rows(runs: Mapping[str, Mapping[str, Any]]) -> tuple[list[str], list[list[Any]]]:
    """Header and rows of the matching table (NCP and SDU per CCD image, per matcher)."""
    ccds: list[str] = []
    for rep in runs.values():
        for c in rep["matching"]["ccds"]:
            if c not in ccds:
                ccds.append(c)
    header = (
        ["Matcher"]
        + [f"{c} NCP" for c in ccds]
        + [f"{c} SDU (%)" for c in ccds]
        + ["NCP", "SDU (%)", "tiles failed"]
    )
    rows = []
    for name, rep in runs.items():
        m = rep["matching"]
        per = m["ccds"]
        rows.append(
            [name]
            + [per.get(c, {}).get("ncp") for c in ccds]
            + [per.get(c, {}).get("sdu_pct") for c in ccds]
            + [m["ncp"], m["sdu_pct"], f"{m['tiles_failed']}/{m['tiles_total']}"]
        )
    return header, rows


def adjustment_rows(runs: Mapping[str, Mapping[str, Any]]) -> tuple[list[str], list[list[Any]]]:
    """Header and rows of the adjustment table (per strip, per matcher)."""
    header = ["Matcher", "Strip"] + [h for h, _ in ADJ_COLUMNS] + ["RMSE before", "sigma0"]
    rows = []
    for name, rep in runs.items():
        strips = rep.get("strips") or {"strip": {"adjustment": rep["adjustment"]}}
        for sid, s in strips.items():
            a = s["adjustment"]
            rows.append(
                [name, sid]
                + [a.get(k) for _, k in ADJ_COLUMNS]
                + [a.get("rmse_px_before"), a.get("sigma0")]
            )
    return header, rows


def truth_rows(runs: Mapping[str, Mapping[str, Any]]) -> tuple[list[str], list[list[Any]]]:
    """Header and rows of the true geolocation error (where truth is known)."""
    header = ["Matcher", "before (m)", "after (m)", "after (px)", "max after (m)"]
    rows = [
        [
            name,
            c["geoloc_rmse_m_before"],
            c["geoloc_rmse_m"],
            c["geoloc_rmse_px"],
            c["geoloc_max_m"],
        ]
        for name, rep in runs.items()
        if (c := rep.get("check"))
    ]
    return header, rows


def _csv(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for r in rows:
        w.writerow(["" if v is None else (f"{v:.6g}" if isinstance(v, float) else v) for v in r])
    return buf.getvalue()


def write_compare_tables(
    runs: Mapping[str, Mapping[str, Any]],
    skipped: Mapping[str, str],
    folder: str | os.PathLike[str],
    *,
    scene: str = "",
) -> dict[str, str]:
    """Write the tables as Markdown (``report.md``) and CSV files.

    Returns:
        Paths by name, and ``"markdown"`` with the Markdown text itself.
    """
    out = Path(folder)
    mh, mr = matching_rows(runs)
    ah, ar = adjustment_rows(runs)
    th, tr = truth_rows(runs)
    paths = {
        "matching_csv": str(write_text_atomic(out / "matching.csv", _csv(mh, mr))),
        "adjustment_csv": str(write_text_atomic(out / "adjustment.csv", _csv(ah, ar))),
    }
    md = [
        f"# Matcher comparison{': ' + scene if scene else ''}",
        "",
        "## Matching (NCP and SDU per CCD image)",
        "",
        format_markdown_table(mh, mr),
        "",
        "## Adjustment (pixels; x = sample, y = line; OR = outlier ratio)",
        "",
        format_markdown_table(ah, ar),
        "",
    ]
    if tr:
        paths["truth_csv"] = str(write_text_atomic(out / "truth.csv", _csv(th, tr)))
        md += [
            "## True geolocation error (RMS over an image grid)",
            "",
            format_markdown_table(th, tr),
            "",
        ]
    if skipped:
        md += ["## Skipped", ""] + [f"- `{k}`: {v}" for k, v in skipped.items()] + [""]
    text = "\n".join(md)
    paths["report_md"] = str(write_text_atomic(out / "report.md", text))
    paths["markdown"] = text
    return paths


def write_georef_markdown(report: Mapping[str, Any], path: str | os.PathLike[str]) -> Path:
    """report.md of one georef run."""
    runs = {report["matcher"]: report}
    mh, mr = matching_rows(runs)
    ah, ar = adjustment_rows(runs)
    lines = [
        f"# georef: {report['scene']} with {report['matcher']}",
        "",
        "## Matching",
        "",
        format_markdown_table(mh, mr),
        "",
        "## Adjustment (pixels)",
        "",
        format_markdown_table(ah, ar),
        "",
    ]
    th, tr = truth_rows(runs)
    if tr:
        lines += ["## True geolocation error", "", format_markdown_table(th, tr), ""]
    lost = report["matching"].get("tiles_lost") or []
    if lost:
        lines += (
            ["## Tiles without MCPs", ""]
            + [
                f"- {t.get('strip', '')} {t['tile']}: {t['status']} {t.get('message', '')}"
                for t in lost
            ]
            + [""]
        )
    t = report.get("timing_s", {})
    lines += ["## Timing (s)", "", format_markdown_table(list(t), [list(t.values())]), ""]
    return write_text_atomic(path, "\n".join(lines))


def figure_residual_vectors(
    result: Any,
    image_sizes: Mapping[str, tuple[int, int]],
    path: str | os.PathLike[str],
    *,
    title: str = "",
    scale: float | None = None,
    dpi: int = 110,
) -> Path:
    """Residual vectors of the inlier observations over the CCD images side by side.

    Args:
        result: An :class:`~planetref.adjust.api.AdjustmentResult` of one camera.
        image_sizes: CCD name -> ``(n_lines, n_samples)``, left to right.
        path: Output PNG.
        title: Figure title.
        scale: Image pixels drawn per pixel of residual (default: so that the 95th
            percentile residual is drawn 4 % of the mean CCD width long).
        dpi: Resolution.
    """
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    net = result.network
    cam = result.cameras[net.camera_ids[0]]
    names = np.array([cam.ccd_names[k] for k in net.obs_ccd])
    r = result.residual
    inl = result.status == "inlier"
    order = list(image_sizes)
    widths = [image_sizes[c][1] for c in order]
    gap = 0.08 * float(np.mean(widths))
    max_h = max(image_sizes[c][0] for c in order)
    total_w = sum(widths) + gap * (len(order) - 1)
    length = np.hypot(r[inl, 0], r[inl, 1]) if inl.any() else np.array([1.0])
    p95 = float(np.nanpercentile(length, 95)) if length.size else 1.0
    scale = scale or 0.04 * float(np.mean(widths)) / max(p95, 1e-6)
    fig = Figure(
        figsize=(10.0, float(np.clip(10.0 * max_h / total_w, 3.0, 14.0)) + 0.8),
        layout="constrained",
    )
    ax = fig.subplots()
    x0 = 0.0
    for c in order:
        nl, ns = image_sizes[c]
        ax.add_patch(Rectangle((x0, 0), ns, nl, facecolor="#f7f7f7", edgecolor="0.3", lw=0.8))
        sel = inl & (names == c)
        if sel.any():
            ax.quiver(
                x0 + net.obs_sample[sel],
                net.obs_line[sel],
                r[sel, 1] * scale,
                r[sel, 0] * scale,
                angles="xy",
                scale_units="xy",
                scale=1.0,
                width=0.0015,
                color="tab:red",
            )
        ax.text(x0 + ns / 2, -0.01 * max_h, c, ha="center", va="bottom", fontsize=8)
        x0 += ns + gap
    ax.set_xlim(-gap / 2, total_w + gap / 2)
    ax.set_ylim(max_h, -0.08 * max_h)
    ax.set_aspect("equal" if 0.05 < max_h / total_w < 20 else "auto")
    ax.set_xlabel("sample")
    ax.set_ylabel("line")
    ax.set_title((title or "residuals") + f"  (arrows x{scale:.0f})", fontsize=10)
    return _save(fig, path, dpi)


def figure_headline_bars(
    runs: Mapping[str, Mapping[str, Any]], path: str | os.PathLike[str], *, dpi: int = 110
) -> Path:
    """Bar chart of the headline metrics per matcher: NCP, SDU, RMSE, OR, true error."""
    from matplotlib.figure import Figure

    names = list(runs)
    panels = [
        ("NCP", lambda r: r["matching"]["ncp"]),
        ("SDU (%)", lambda r: r["matching"]["sdu_pct"]),
        ("RMSE (px)", lambda r: r["adjustment"]["rmse_px"]),
        ("OR (%)", lambda r: r["adjustment"]["outlier_ratio_pct"]),
    ]
    if any(r.get("check") for r in runs.values()):
        panels.append(
            (
                "true error after (m)",
                lambda r: (r.get("check") or {}).get("geoloc_rmse_m", float("nan")),
            )
        )
    fig = Figure(figsize=(3.0 * len(panels), 3.4), layout="constrained")
    axes = fig.subplots(1, len(panels))
    import matplotlib

    colours = [matplotlib.colormaps["tab10"](i % 10) for i in range(len(names))]
    for ax, (label, get) in zip(np.atleast_1d(axes), panels, strict=True):
        vals = []
        for n in names:
            try:
                v = float(get(runs[n]))
            except (KeyError, TypeError):
                v = float("nan")
            vals.append(v)
        ax.bar(range(len(names)), np.nan_to_num(vals), color=colours)
        ax.set_xticks(range(len(names)), names, rotation=45, ha="right", fontsize=8)
        ax.set_title(label, fontsize=9)
    return _save(fig, path, dpi)
