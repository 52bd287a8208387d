"""Reports of georef and compare runs: tables (CSV, Markdown, LaTeX), report.md, report.html.

The tables (see :mod:`planetref.report.tables`) follow the seed: Table 1 (NCP and SDU per
CCD image), Table 2 (RMSE, Mean, Max/Min X/Y, OR per strip); beside them the true error
where known, the front-end funnel and the timings. The comparison's report
(:func:`write_compare_report`) is one document a reader understands alone: the scene and
its reference, the settings (and what differs per matcher), the metric definitions with
formulas, the tables, the figures and the warnings that matter.
"""

from __future__ import annotations

import json
import math
import os
import statistics
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from planetref.adjust.precision import CameraAgreement
from planetref.report.document import DEFINITIONS, Document
from planetref.report.figures_adjust import (
    OR_AXIS_TOP_PCT,
    figure_headline,
    figure_residual_vectors,
)
from planetref.report.tables import (
    ADJ_COLUMNS,
    adjustment_rows,
    format_csv,
    format_latex_table,
    format_markdown_table,
    funnel_from_journal,
    funnel_from_report,
    funnel_rows,
    matching_rows,
    timing_rows,
    truth_rows,
)
from planetref.runtime.atomic import write_text_atomic

__all__ = [
    "ADJ_COLUMNS",
    "CompareContext",
    "add_realism",
    "adjustment_rows",
    "agreement_rows",
    "excess_block",
    "figure_headline_bars",
    "figure_residual_vectors",
    "format_markdown_table",
    "matching_rows",
    "paper_departures",
    "truth_rows",
    "write_compare_report",
    "write_compare_tables",
    "write_georef_markdown",
]

_csv = format_csv


def figure_headline_bars(
    runs: Mapping[str, Mapping[str, Any]],
    path: str | os.PathLike[str],
    *,
    dpi: int = 110,
    scene: str = "",
) -> Path:
    """The headline figure (see :func:`~planetref.report.figures_adjust.figure_headline`)."""
    if not scene:
        scene = next((str(r.get("scene", "")) for r in runs.values()), "")
    return figure_headline(runs, path, scene=scene, dpi=dpi)


@dataclass
class CompareContext:
    """What a comparison report says beyond the runs' reports.

    Attributes:
        scene: Scene name.
        scene_path: The scene manifest.
        scene_facts: ``(label, value)`` lines about the scene and its reference.
        common_settings: ``(label, value)`` lines of settings every matcher shared.
        matcher_settings: Matcher -> its own settings (options that differ per matcher).
        funnels: Matcher -> front-end stage counts.
        figures: Matcher -> ``(png, caption)`` pairs.
        headline: The headline PNG.
        simulated: The scene has truth (state why its numbers are easier than reality).
        output_warnings: Matcher -> warnings written with the outputs (e.g. RPC fits).
        realism_level: The simulated scene's difficulty level when it cites sources.
        realism_sources: ``(setting, value, source)`` of every sourced realism setting.
        easier_than_real: What still makes the simulated scene easier than real data.
        agreement: Every pair of matchers' adjustments of a strip, compared with no
            truth (:class:`~planetref.adjust.precision.CameraAgreement`).
    """

    scene: str
    scene_path: str = ""
    scene_facts: list[tuple[str, str]] = field(default_factory=list)
    common_settings: list[tuple[str, str]] = field(default_factory=list)
    matcher_settings: dict[str, dict[str, Any]] = field(default_factory=dict)
    funnels: dict[str, dict[str, int]] = field(default_factory=dict)
    figures: dict[str, list[tuple[Path, str]]] = field(default_factory=dict)
    headline: Path | None = None
    simulated: bool = False
    output_warnings: dict[str, list[str]] = field(default_factory=dict)
    realism_level: str = ""
    realism_sources: list[tuple[str, str, str]] = field(default_factory=list)
    easier_than_real: list[str] = field(default_factory=list)
    agreement: list[CameraAgreement] = field(default_factory=list)


_TABLES = {
    "matching": "NCP and SDU (%) per CCD image (the seed's Table 1)",
    "adjustment": "Residuals after adjustment per strip (pixels; x = sample, y = line; "
    "OR in %) (the seed's Table 2)",
    "truth": "True geolocation error (RMS over an image grid), before and after",
    "funnel": "Front-end funnel: correspondences left after each stage, summed over tiles",
    "timing": "Wall-clock time per step (seconds)",
}


_SECTIONS = {
    "matching": "Matching (Table 1)",
    "adjustment": "Adjustment (Table 2)",
    "truth": "True geolocation error",
    "funnel": "Front-end funnel",
    "timing": "Timing",
}


def _tables(
    runs: Mapping[str, Mapping[str, Any]], funnels: Mapping[str, Mapping[str, int]]
) -> dict[str, tuple[list[str], list[list[Any]]]]:
    out = {"matching": matching_rows(runs), "adjustment": adjustment_rows(runs)}
    th, tr = truth_rows(runs)
    if tr:
        out["truth"] = (th, tr)
    if funnels:
        out["funnel"] = funnel_rows(funnels, {n: r["matching"]["ncp"] for n, r in runs.items()})
    out["timing"] = timing_rows(runs)
    return out


def write_compare_tables(
    runs: Mapping[str, Mapping[str, Any]],
    skipped: Mapping[str, str],
    folder: str | os.PathLike[str],
    *,
    scene: str = "",
    funnels: Mapping[str, Mapping[str, int]] | None = None,
) -> dict[str, str]:
    """Write every table as CSV (``<name>.csv``) and LaTeX booktabs (``tables/<name>.tex``).

    Returns:
        Paths by name, and ``"markdown"`` with the tables as Markdown (what ``demo``
        prints).
    """
    out = Path(folder)
    tables = _tables(runs, funnels or {})
    paths: dict[str, str] = {}
    md = [f"# Matcher comparison{': ' + scene if scene else ''}", ""]
    titles = {
        "matching": "## Matching (NCP and SDU per CCD image)",
        "adjustment": "## Adjustment (pixels; x = sample, y = line; OR = outlier ratio)",
        "truth": "## True geolocation error (RMS over an image grid)",
        "funnel": "## Front-end funnel (correspondences per stage)",
        "timing": "## Timing (s)",
    }
    for name, (h, r) in tables.items():
        paths[f"{name}_csv"] = str(write_text_atomic(out / f"{name}.csv", format_csv(h, r)))
        tex = format_latex_table(h, r, caption=_TABLES[name], label=f"tab:{name}")
        paths[f"{name}_tex"] = str(write_text_atomic(out / "tables" / f"{name}.tex", tex))
        md += [titles[name], "", format_markdown_table(h, r), ""]
    failed = _failed(runs)
    if failed:
        md += ["## Failed (ran, could not finish; rows kept above)", ""]
        md += [f"- `{k}`: {v}" for k, v in failed.items()] + [""]
    if skipped:
        md += ["## Skipped (could not run)", ""] + [f"- `{k}`: {v}" for k, v in skipped.items()]
        md += [""]
    paths["markdown"] = "\n".join(md)
    return paths


def _failed(runs: Mapping[str, Mapping[str, Any]]) -> dict[str, str]:
    """Matcher -> why its run failed, for the runs that ran but could not finish."""
    return {name: str(rep["failed"]) for name, rep in runs.items() if rep.get("failed")}


def _warnings(
    runs: Mapping[str, Mapping[str, Any]], more: Mapping[str, Sequence[str]] | None = None
) -> list[str]:
    """The warnings of every run (adjustment and outputs), once each, with their matcher."""
    seen: dict[str, list[str]] = {}
    for name, ws in (more or {}).items():
        for w in ws:
            seen.setdefault(w, []).append(name)
    for name, rep in runs.items():
        for sid, s in (rep.get("strips") or {}).items():
            for w in s.get("warnings") or []:
                seen.setdefault(f"{sid}: {w}" if sid not in w else w, []).append(name)
        for w in (rep.get("adjustment") or {}).get("output_warnings") or []:
            seen.setdefault(w, []).append(name)
        for t in rep["matching"].get("tiles_lost") or []:
            msg = f"tile {t.get('strip', '')} {t['tile']}: {t['status']} {t.get('message', '')}"
            seen.setdefault(msg.strip(), []).append(name)
    return [f"{w} ({', '.join(ms)})" for w, ms in seen.items()]


def _extra_adjustment(runs: Mapping[str, Mapping[str, Any]]) -> tuple[list[str], list[list[Any]]]:
    """Scalar adjustment statistics the tables above do not show (e.g. DOF, other ORs)."""
    shown = {k for _, k in ADJ_COLUMNS} | {
        "rmse_x_px",
        "rmse_y_px",
        "rmse_px_before",
        "sigma0",
        "n_total",
    }
    keys: list[str] = []
    for rep in runs.values():
        for k, v in (rep.get("adjustment") or {}).items():
            if k not in shown and k not in keys and isinstance(v, int | float | bool):
                keys.append(k)
    return ["Matcher", *keys], [
        [name] + [(rep.get("adjustment") or {}).get(k) for k in keys] for name, rep in runs.items()
    ]


def add_realism(doc: Document, context: CompareContext) -> None:
    """The simulated scene's sourced realism settings and what keeps it easier than Mars."""
    if context.realism_sources:
        doc.table(
            f"Realism settings of the `{context.realism_level}` level and the real "
            "statistic each reproduces",
            ["Setting", "Value", "Source"],
            [list(r) for r in context.realism_sources],
        )
    if context.easier_than_real:
        doc.para("What still makes this scene easier than real data:")
        doc.items(context.easier_than_real)


def write_compare_report(
    runs: Mapping[str, Mapping[str, Any]],
    skipped: Mapping[str, str],
    folder: str | os.PathLike[str],
    context: CompareContext,
) -> dict[str, str]:
    """Write the tables (CSV, LaTeX), ``report.md`` and the self-contained ``report.html``.

    Returns:
        Paths by name, and ``"markdown"`` with the tables as Markdown.
    """
    folder = Path(folder)
    paths = write_compare_tables(
        runs, skipped, folder, scene=context.scene, funnels=context.funnels
    )
    tables = _tables(runs, context.funnels)
    doc = Document(f"Matcher comparison: {context.scene}")
    doc.para(
        f"Matchers compared: {', '.join(f'`{n}`' for n in runs) or 'none'}. Every matcher ran "
        "on the same scene with the same initial cameras, front-end and adjustment settings; "
        "only the matcher (and the options listed under Settings) differs."
    )
    doc.heading("Scene and reference")
    doc.items([f"**{k}**: {v}" for k, v in context.scene_facts] or [f"scene `{context.scene}`"])
    if context.simulated:
        doc.para(
            "This is a **simulated** scene: the truth is known, so the true error can be "
            "measured. It is easier than real data: the images and the reference are "
            "rendered from one synthetic terrain by the same simulator, and changes between "
            "image and reference (illumination, season, surface) are only those the "
            "simulation config (`truth/config.toml`) puts in. The camera that made the "
            "images is not the adjustment's model: it adds what that model cannot "
            "represent (its `truth_mismatch` and `jitter` settings: CCD placement, "
            "lens distortion, line-rate error and attitude and position oscillations), "
            "so the true error after the adjustment has a floor the matcher cannot remove."
        )
        add_realism(doc, context)
    doc.heading("Settings")
    doc.items([f"**{k}**: {v}" for k, v in context.common_settings])
    if context.matcher_settings:
        keys = sorted({k for s in context.matcher_settings.values() for k in s})
        doc.table(
            "Settings that differ per matcher (options passed to the matcher; '-' = its defaults)",
            ["Matcher", *keys],
            [[n] + [_short(s.get(k)) for k in keys] for n, s in context.matcher_settings.items()],
        )
    doc.heading("Metric definitions")
    doc.items([f"**{k}**: {v}" for k, v in DEFINITIONS])
    doc.heading("Headline")
    doc.figure(
        context.headline,
        "Headline metrics per matcher. Hatched: before the adjustment; coloured: after; "
        "dashes: per-CCD values; whisker: maximum true error. Each panel says which "
        "direction is better. Linear axes from 0; a hatched bar cut at the top of its "
        "panel carries its value after an upward arrow; the outlier ratio's axis runs "
        f"to at least {OR_AXIS_TOP_PCT:g} %.",
    )
    for name, (h, r) in tables.items():
        doc.heading(_SECTIONS[name])
        doc.table(_TABLES[name], _timing_header(h) if name == "timing" else h, r)
    if "funnel" not in tables:
        doc.para("Front-end funnel: not available (no tile journal).")
    if context.agreement:
        doc.heading("Matcher agreement (no truth needed)")
        doc.para(
            "Each pair of matchers adjusted the same strip on the same reference, DEM and "
            "initial cameras: their errors from the reference and the CCD placement are "
            "shared, their own (measurement noise, the per-tile matcher offsets) are not. "
            "'diff' is the RMS over the true error's image grid of the ground distance "
            "between the two adjusted cameras; 'predicted' what the two adjustments' own "
            "covariances give for it. diff / predicted is ~1 when both say what they "
            "know; a matcher well above 1 against every other carries an error its own "
            "residuals and covariance do not show (e.g. one common to all its tiles). "
            "This is the comparison's anchor on real data, where no truth is known. With "
            "three matchers or more, each pair's excess (diff squared minus predicted "
            "squared) is split into one error per matcher (non-negative least squares, the "
            "'three-cornered hat'): 'excess' is the ground error the matcher's own "
            "covariance misses, and 'formal with excess' its formal precision with it "
            "added. The split takes the matchers' unmodelled errors as independent."
        )
        mh, mr = agreement_rows(context.agreement, runs)
        doc.table("Agreement per matcher (median over its pairs)", mh, mr)
        doc.table(
            "Agreement of each pair of matchers",
            ["Strip", "Matchers", "diff (m)", "predicted (m)", "diff / predicted"],
            [
                [
                    a.camera_id,
                    " / ".join(a.matchers),
                    _f3(a.diff_m),
                    _f3(a.predicted_m),
                    _f2(a.ratio),
                ]
                for a in context.agreement
            ],
        )
    eh, er = _extra_adjustment(runs)
    if len(eh) > 1:
        doc.heading("Further adjustment statistics")
        doc.table("Further adjustment statistics (as in report.json)", eh, er)
    doc.para(
        "CSV of every table: `matching.csv`, `adjustment.csv`, `truth.csv`, `funnel.csv`, "
        "`timing.csv`; LaTeX (booktabs): `tables/*.tex`."
    )
    doc.heading("Figures")
    for name, figs in context.figures.items():
        if figs:
            doc.heading(name, 3)
        for png, caption in figs:
            doc.figure(png, caption)
    doc.heading("Warnings")
    warns = _warnings(runs, context.output_warnings)
    doc.items(warns)
    if not warns:
        doc.para("None.")
    failed = _failed(runs)
    if failed:
        doc.heading("Failed matchers")
        doc.para(
            "These matchers ran (their rows stay in the tables: NCP, SDU, failed tiles, "
            "funnel) but their runs could not finish:"
        )
        doc.items([f"`{k}`: {v}" for k, v in failed.items()])
    if skipped:
        doc.heading("Skipped matchers")
        doc.para("These matchers could not run:")
        doc.items([f"`{k}`: {v}" for k, v in skipped.items()])
    written = doc.write(folder)
    paths.update(written)
    return paths


def _f3(v: float) -> str:
    return f"{v:.3f}" if math.isfinite(v) else "-"


def _f2(v: float) -> str:
    return f"{v:.2f}" if math.isfinite(v) else "-"


def excess_block(report: Mapping[str, Any], excess_m: float) -> dict[str, float | None]:
    """A run's excess error beside its formal precision: ``runs.<matcher>.agreement``.

    Args:
        report: The run's report.json content (its ``check`` block).
        excess_m: Its excess error (:func:`~planetref.adjust.precision.excess_error`).

    Returns:
        ``{"excess_m", "formal_with_excess_m", "true_over_formal_with_excess"}``: the
        formal precision with the excess added in quadrature, and on a simulated scene
        the true error over it (``None`` where the report lacks a figure).
    """
    chk = report.get("check") or {}
    formal = chk.get("formal_rmse_m")
    both = None if formal is None else math.hypot(float(formal), excess_m)
    true = chk.get("geoloc_rmse_m")
    return {
        "excess_m": excess_m,
        "formal_with_excess_m": both,
        "true_over_formal_with_excess": None if true is None or not both else float(true) / both,
    }


def agreement_rows(
    pairs: Sequence[CameraAgreement], runs: Mapping[str, Mapping[str, Any]]
) -> tuple[list[str], list[list[str]]]:
    """Per matcher: its pairs' diff / predicted (median, largest) and its excess error.

    The excess (:func:`~planetref.adjust.precision.excess_error`, three matchers or more)
    is the ground error its covariance misses, read from each run's ``agreement`` block
    (:func:`excess_block`, which ``compare`` writes); "formal with excess" adds it to the
    run's formal precision, and on a simulated scene the true error is set beside both.
    """
    ratios: dict[str, list[float]] = {}
    for a in pairs:
        for name in a.matchers:
            ratios.setdefault(name, []).append(a.ratio)
    truth = any((runs.get(n) or {}).get("check", {}).get("geoloc_rmse_m") for n in ratios)
    header = ["Matcher", "pairs", "median diff / predicted", "largest", "excess (m)"]
    header += ["formal (m)", "formal with excess (m)"]
    if truth:
        header += ["true / formal", "true / formal with excess"]
    rows = []
    for name, r in ratios.items():
        run = runs.get(name) or {}
        chk = run.get("check") or {}
        agr = run.get("agreement") or {}
        formal = chk.get("formal_rmse_m")
        row = [name, str(len(r)), _f2(statistics.median(r)), _f2(max(r))]
        row += [
            _opt(agr.get("excess_m"), _f3),
            _opt(formal, _f3),
            _opt(agr.get("formal_with_excess_m"), _f3),
        ]
        if truth:
            true = chk.get("geoloc_rmse_m")
            row += [
                _opt(None if true is None or not formal else true / formal, _f2),
                _opt(agr.get("true_over_formal_with_excess"), _f2),
            ]
        rows.append(row)
    return header, rows


def _opt(v: float | None, fmt: Callable[[float], str]) -> str:
    return "-" if v is None else fmt(float(v))


def _timing_header(header: list[str]) -> list[str]:
    """The timing table's header as the report shows it: words that wrap.

    ``outputs_adjustment_files (s)`` is one unbreakable word; eleven of them made the
    table wider than the page. The caption gives the unit (seconds); the CSV keeps the
    full names.
    """
    return [h.removesuffix(" (s)").replace("_", " ") for h in header]


def _short(v: Any) -> Any:
    if v is None or isinstance(v, int | float):
        return v
    s = str(v)
    return s if len(s) <= 60 else s[:57] + "..."


def paper_departures(config: Mapping[str, Any]) -> list[str]:
    """Where a run's settings (``config.json``'s content) depart from the seed paper's."""
    adj = config.get("adjust") or {}
    interior = ((adj.get("linescan") or {}).get("interior") or {}).get("mode", "fixed")
    mcp = config.get("mcp") or {}
    out = []
    if interior == "fixed":
        out.append(
            "interior orientation (x_p, y_p, f) fixed, where the seed paper estimates it per "
            "strip: estimated from MCPs it absorbs the reference's own errors (docs/adjust.md)"
        )
    if mcp.get("check_blocks", "tiles") == "tiles" and mcp.get("check_fraction", 0.1):
        out.append(
            f"check points: whole tiles holding >= {100 * mcp.get('check_fraction', 0.1):.0f} % "
            "of the MCPs are held out of the adjustment (independent of the adjusted MCPs)"
        )
    out.append(
        "the covariance includes the declared correlated errors of the reference and of the "
        "CCD placement, and a matcher offset common to each tile with a sigma estimated "
        "from the tiles' residuals (consider parameters; formal vs true error in the truth "
        "table)"
    )
    return out


def write_georef_markdown(report: Mapping[str, Any], path: str | os.PathLike[str]) -> Path:
    """report.md of one georef run, and beside it a self-contained report.html.

    Tables 1 and 2, the true error, the funnel (from the run's tile journals), the
    timings, lost tiles, warnings, the definitions and the run's figures
    (``figures/*.png`` next to ``path``).
    """
    path = Path(path)
    folder = path.parent
    runs = {report["matcher"]: report}
    journals = [folder / sid / "tiles.jsonl" for sid in report.get("strips") or {}]
    funnel = funnel_from_report(report) or funnel_from_journal(journals)
    doc = Document(f"georef: {report['scene']} with {report['matcher']}")
    if report.get("failed"):
        doc.para(f"**The run failed**: {report['failed']}")
    protocol = ((report.get("matching") or {}).get("settings") or {}).get("protocol")
    if protocol:
        doc.para(f"Front-end protocol: `{protocol}`.")
    for name, (h, r) in _tables(runs, {report["matcher"]: funnel} if funnel else {}).items():
        doc.heading(_SECTIONS[name])
        doc.table(_TABLES[name], h, r)
    try:
        config = json.loads((folder / "config.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        config = None
    if config is not None:
        doc.heading("Settings that depart from the seed paper")
        doc.items(paper_departures(config))
    lost = report["matching"].get("tiles_lost") or []
    if lost:
        doc.heading("Tiles without MCPs")
        doc.items(
            [
                f"{t.get('strip', '')} {t['tile']}: {t['status']} {t.get('message', '')}"
                for t in lost
            ]
        )
    more: list[str] = []
    for sid in report.get("strips") or {}:
        try:
            adj = json.loads((folder / sid / "adjustment" / "report.json").read_text())
        except (OSError, ValueError):
            continue
        more += adj.get("output_warnings") or []
    warns = _warnings(runs, {report["matcher"]: more})
    if warns:
        doc.heading("Warnings")
        doc.items(warns)
    doc.heading("Figures")
    for kind, caption in _RUN_FIGURES.items():
        for png in sorted((folder / "figures").glob(f"*_{kind}.png")):
            doc.figure(png, f"{png.stem[: -len(kind) - 1]}: {caption}")
    doc.heading("Metric definitions")
    doc.items([f"**{k}**: {v}" for k, v in DEFINITIONS])
    write_text_atomic(path.with_suffix(".html"), doc.html())
    return write_text_atomic(path, doc.markdown(folder))


_RUN_FIGURES = {
    "tile_matches": "matches of the tiles with the most, the median and the fewest verified "
    "matches, coarse and fine stage side by side (green: kept, red: rejected)",
    "mcp_distribution": "MCP distribution per CCD in image coordinates with the SDU grid",
    "residuals": "residual vectors after the adjustment per CCD (black: check points)",
    "jitter": "jitter stage: estimated roll, pitch, yaw (dense attitude nodes minus the node "
    "model) with 2 sigma, and their amplitude spectra; dashed: the truth's pointing relative "
    "to the node model; red: the resolution limit",
}
