"""The report's tables in the seed's layout, as rows, and their CSV, Markdown and LaTeX forms.

* **Table 1** (:func:`matching_rows`): NCP and SDU (%) per CCD image, one row per matcher.
* **Table 2** (:func:`adjustment_rows`): RMSE, Mean, Max X, Max Y, Min X, Min Y (pixels)
  and OR (%) per strip, one row per matcher (``x`` = sample, ``y`` = line residual); the
  per-axis RMSE follows when the report holds it.
* :func:`truth_rows`: the true geolocation error before and after (simulated scenes).
* :func:`funnel_rows`: correspondences left after each front-end stage.
* :func:`timing_rows`: seconds per step, per matcher.

A value the report does not hold is ``None`` and prints as ``-`` ("not available").
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from planetref.frontend.coarse import COARSE_FALLBACK_MATCHER
from planetref.frontend.stats import FUNNEL_STAGES as TILE_FUNNEL_STAGES

__all__ = [
    "ADJ_COLUMNS",
    "FUNNEL_STAGES",
    "adjustment_rows",
    "format_csv",
    "format_latex_table",
    "format_markdown_table",
    "funnel_from_journal",
    "funnel_from_report",
    "funnel_rows",
    "matching_rows",
    "timing_rows",
    "truth_rows",
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
"""Table 2 of the seed: header and report.json key (pixels, OR in percent)."""
EXTRA_ADJ = [("RMSE x", "rmse_x_px"), ("RMSE y", "rmse_y_px")]
"""Per-axis RMSE, shown when the report holds it."""
# A tile's stages, then the strip's MCP stage (duplicates and other drops, control/).
FUNNEL_STAGES = (*TILE_FUNNEL_STAGES, "mcp_unique")
"""Front-end stages in order (see ``TileResult.funnel``); ``mcp_unique``: the MCPs the MCP
stage delivers to the adjustment (duplicates and points without a DEM height dropped)."""


def fmt(v: Any, digits: int = 3) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "-" if not math.isfinite(v) else f"{v:.{digits}f}"
    return str(v)


def numeric_column(rows: Sequence[Sequence[Any]], i: int) -> bool:
    return all(isinstance(r[i], int | float) or r[i] is None for r in rows)


def format_markdown_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub-flavoured Markdown table (numbers right-aligned, text left-aligned)."""
    cells = [[fmt(v) for v in r] for r in rows]
    # A list, so that a table without rows (every matcher failed) has its header widths.
    widths = [max([len(str(h)), *(len(r[i]) for r in cells)]) for i, h in enumerate(header)]
    numeric = [numeric_column(rows, i) for i in range(len(header))]
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


def format_csv(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """CSV text (empty cell for a missing value, floats to 6 significant digits)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for r in rows:
        w.writerow(["" if v is None else (f"{v:.6g}" if isinstance(v, float) else v) for v in r])
    return buf.getvalue()


_TEX = {"&": r"\&", "%": r"\%", "_": r"\_", "#": r"\#", "$": r"\$", "{": r"\{", "}": r"\}"}


def _tex(s: str) -> str:
    return "".join(_TEX.get(ch, ch) for ch in s)


def format_latex_table(
    header: Sequence[str], rows: Sequence[Sequence[Any]], *, caption: str = "", label: str = ""
) -> str:
    r"""A LaTeX ``booktabs`` table (needs ``\\usepackage{booktabs}``)."""
    align = "".join("r" if numeric_column(rows, i) else "l" for i in range(len(header)))
    lines = [r"\begin{table}[htbp]", r"\centering"]
    if caption:
        lines.append(rf"\caption{{{_tex(caption)}}}")
    if label:
        lines.append(rf"\label{{{label}}}")
    lines += [
        rf"\begin{{tabular}}{{{align}}}",
        r"\toprule",
        " & ".join(_tex(str(h)) for h in header) + r" \\",
        r"\midrule",
    ]
    lines += [" & ".join(_tex(fmt(v)) for v in r) + r" \\" for r in rows]
    lines += [r"\bottomrule", r"\end{tabular}", r"\end{table}", ""]
    return "\n".join(lines)


def matching_rows(runs: Mapping[str, Mapping[str, Any]]) -> tuple[list[str], list[list[Any]]]:
    """Table 1: NCP and SDU per CCD image, one row per matcher.

    NCP is the unique MCPs delivered to the adjustment; a matcher whose run failed keeps
    its row (NCP and SDU as matched, usually 0, and its failed tiles). When a matcher's
    own coarse stage left tiles to NCC's coarse search (``frontend.coarse_fallback``), a
    column counts them per matcher.
    """
    ccds: list[str] = []
    for rep in runs.values():
        for c in rep["matching"]["ccds"]:
            if c not in ccds:
                ccds.append(c)
    # Tiles whose fine window NCC's coarse search placed (frontend.coarse_fallback): shown
    # only when some matcher needed it, so that it is never hidden and never noise.
    fallback = {
        n: (r["matching"].get("coarse_sources") or {}).get(COARSE_FALLBACK_MATCHER, 0)
        for n, r in runs.items()
    }
    show_fallback = any(v and n != COARSE_FALLBACK_MATCHER for n, v in fallback.items())
    header = (
        ["Matcher"]
        + [f"{c} NCP" for c in ccds]
        + [f"{c} SDU (%)" for c in ccds]
        + ["NCP", "SDU (%)", "tiles failed"]
        + (["tiles placed by NCC fallback"] if show_fallback else [])
    )
    rows = []
    for name, rep in runs.items():
        m = rep["matching"]
        per = m["ccds"]
        rows.append(
            [name]
            + [per.get(c, {}).get("ncp") for c in ccds]
            + [per.get(c, {}).get("sdu_pct") for c in ccds]
            + [m["ncp"], m["sdu_pct"], f"{m.get('tiles_failed', '-')}/{m.get('tiles_total', '-')}"]
            + ([f"{fallback[name]}/{m.get('tiles_total', '-')}"] if show_fallback else [])
        )
    return header, rows


def adjustment_rows(runs: Mapping[str, Mapping[str, Any]]) -> tuple[list[str], list[list[Any]]]:
    """Table 2: per strip, per matcher; per-axis RMSE and check points where held.

    The check columns are the RMS error of the held-out check points (image px and
    metres), shown when some report holds them, and ``Check / predicted``: the RMS over
    the held-out tiles and axes of each tile's mean misfit over the SD the covariance
    predicts for it (~1 when the formal precision means what it says; a truth-free
    anchor, rough with one or two tiles). A run that failed (its report has
    ``failed``) keeps one row per strip it reached, every value missing, and a
    ``status`` column (shown when any run failed) says so.
    """
    blocks = []
    for name, rep in runs.items():
        strips = rep.get("strips") or {"strip": {"adjustment": rep.get("adjustment")}}
        for sid, s in strips.items():
            blocks.append(
                (name, sid, s.get("adjustment") or {}, s.get("failed") or rep.get("failed"))
            )
        if not strips and rep.get("failed"):
            blocks.append((name, "-", {}, rep["failed"]))
    extra = [(h, k) for h, k in EXTRA_ADJ if any(k in a for _, _, a, _ in blocks)]
    failed = any(f for *_, f in blocks)
    # The held-out check points (whole tiles): the independent counterpart of the RMSE.
    checked = any(_check_after(a) for _, _, a, _ in blocks)
    header = (
        ["Matcher", "Strip"]
        + [h for h, _ in ADJ_COLUMNS]
        + [h for h, _ in extra]
        + (["Check (px)", "Check (m)", "Check / predicted"] if checked else [])
        + ["RMSE before", "sigma0", "n"]
        + (["status"] if failed else [])
    )
    rows = [
        [name, sid]
        + [a.get(k) for _, k in ADJ_COLUMNS + extra]
        + (
            [
                _check_after(a).get("rms_px"),
                _check_after(a).get("rms_m"),
                ((a.get("check_mcps") or {}).get("tiles") or {}).get("rms_normalised"),
            ]
            if checked
            else []
        )
        + [a.get("rmse_px_before"), a.get("sigma0"), a.get("n_total")]
        + (["failed" if f else "ok"] if failed else [])
        for name, sid, a, f in blocks
    ]
    return header, rows


def _check_after(block: Mapping[str, Any]) -> dict[str, Any]:
    """The check points' metrics after the adjustment (empty when none were held out)."""
    chk = block.get("check_mcps") or {}
    after = chk.get("after") or {}
    return dict(after) if after.get("n") else {}


def truth_rows(runs: Mapping[str, Mapping[str, Any]]) -> tuple[list[str], list[list[Any]]]:
    """True geolocation error, its formal precision, and the true outlier ratio (simulated).

    ``formal (m)`` is the adjustment's precision of the same ground positions and
    ``true/formal`` their ratio (empty for reports written before they existed);
    ``tile offset (px)`` the sigma of the matcher's offset common to a tile that the
    adjustment estimated from the tiles' residuals and took into ``formal`` (one for
    both axes; ``line/sample`` where they differ). The
    true outlier ratio (``true OR``) is the share of the matches after RANSAC whose true
    error exceeds 1 and 3 reference px (:mod:`planetref.frontend.truth`); a run that
    failed keeps its row for it.
    """
    header = [
        "Matcher",
        "before (m)",
        "after (m)",
        "after (px)",
        "max after (m)",
        "formal (m)",
        "true/formal",
        "tile offset (px)",
        "RANSAC matches",
        "true OR >1 px (%)",
        "true OR >3 px (%)",
    ]
    rows = []
    for name, rep in runs.items():
        c = rep.get("check") or {}
        t = (rep.get("matching") or {}).get("true_outliers") or {}
        if not c and not t:
            continue
        rows.append(
            [
                name,
                c.get("geoloc_rmse_m_before"),
                c.get("geoloc_rmse_m"),
                c.get("geoloc_rmse_px"),
                c.get("geoloc_max_m"),
                c.get("formal_rmse_m"),
                c.get("true_over_formal"),
                _tile_sigma(rep),
                t.get("n"),
                t.get("pct_over_1px"),
                t.get("pct_over_3px"),
            ]
        )
    return header, rows


def _tile_sigma(rep: Mapping[str, Any]) -> float | str | None:
    """The tile offsets' sigma (px) of a run's adjustment, or ``None``.

    One number, or ``"line/sample"`` where the two differ.
    """
    sysm = (rep.get("adjustment") or {}).get("systematic") or {}
    sig = sysm.get("tile_offset_sigma_px")
    if not sig:
        return None
    return float(sig[0]) if sig[0] == sig[1] else f"{sig[0]:.2f}/{sig[1]:.2f}"


def funnel_from_journal(paths: Sequence[str | Path]) -> dict[str, int]:
    """Stage counts summed over the tiles of ``tiles.jsonl`` journals.

    Uses each tile's ``funnel`` when it holds one; otherwise what every journal holds:
    the fine stage's raw matches (``raw``) and those that passed MAGSAC++ (``ransac``),
    plus the coarse stage's matches and inliers (``coarse_raw``, ``coarse_kept``).
    """
    total: dict[str, int] = {}
    for p in paths:
        p = Path(p)
        if not p.is_file():
            continue
        for text in p.read_text(encoding="utf-8").splitlines():
            try:
                res = json.loads(text).get("result") or {}
            except (json.JSONDecodeError, AttributeError):
                continue
            fun = res.get("funnel")
            if not isinstance(fun, dict):
                fun = {
                    "coarse_raw": res.get("n_coarse_matches"),
                    "coarse_kept": res.get("n_coarse_inliers"),
                    "raw": res.get("n_matches"),
                    "ransac": res.get("n_inliers"),
                }
            for k, v in fun.items():
                if isinstance(v, int | float):
                    total[k] = total.get(k, 0) + int(v)
    return total


def funnel_from_report(rep: Mapping[str, Any]) -> dict[str, int]:
    """A run's funnel from its report.json: the run's own, else its strips' summed."""
    top = rep["matching"].get("funnel")
    if isinstance(top, Mapping) and top:
        return {k: int(v) for k, v in top.items() if isinstance(v, int | float)}
    total: dict[str, int] = {}
    for s in (rep.get("strips") or {}).values():
        for k, v in ((s.get("matching") or {}).get("funnel") or {}).items():
            if isinstance(v, int | float):
                total[k] = total.get(k, 0) + int(v)
    return total


def funnel_rows(
    funnels: Mapping[str, Mapping[str, int]], ncp: Mapping[str, int]
) -> tuple[list[str], list[list[Any]]]:
    """The front-end funnel: correspondences left after each stage, per matcher.

    Args:
        funnels: Matcher -> stage counts (see :func:`funnel_from_journal`).
        ncp: Matcher -> MCPs in the report (the funnel's end).
    """
    order = ["coarse_raw", "coarse_kept", *FUNNEL_STAGES]
    present = [s for s in order if any(s in f for f in funnels.values())]
    if "mcp" not in present:
        present.append("mcp")
    header = ["Matcher", *present, "kept of raw (%)"]
    rows = []
    for name, f in funnels.items():
        vals = {**f}
        vals.setdefault("mcp", ncp.get(name))
        raw = vals.get("raw")
        end = vals.get("mcp_unique", vals.get("mcp"))
        rows.append(
            [name]
            + [vals.get(s) for s in present]
            + [100.0 * end / raw if raw and end is not None else None]
        )
    return header, rows


def timing_rows(runs: Mapping[str, Mapping[str, Any]]) -> tuple[list[str], list[list[Any]]]:
    """Wall-clock seconds per step and per tile, one row per matcher.

    ``matching_tiles`` is the seconds the tiles took when they were matched (recorded in
    the tile journal), so a resumed run, whose ``matching`` step only read the journal,
    keeps its original per-tile cost; such a run's row says ``(resumed)``.
    """
    keys: list[str] = []
    for rep in runs.values():
        for k in rep.get("timing_s") or {}:
            if k not in keys:
                keys.append(k)
    header = ["Matcher"] + [f"{k} (s)" for k in keys] + ["matching per tile (s)"]
    rows = []
    for name, rep in runs.items():
        t = rep.get("timing_s") or {}
        n = rep["matching"].get("tiles_total") or 0
        # The tiles' own recorded cost where the report has it (a resumed run keeps it),
        # else the matching step's seconds.
        m = t.get("matching_tiles", t.get("matching"))
        rows.append(
            [name + (" (resumed)" if rep.get("resumed") else "")]
            + [t.get(k) for k in keys]
            + [m / n if n and isinstance(m, int | float) else None]
        )
    return header, rows
