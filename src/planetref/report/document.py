"""A report as a list of blocks, written both as Markdown and as one self-contained HTML file.

The same blocks give ``report.md`` (figures linked by relative path) and ``report.html``
(figures embedded as base64 PNG, styles inline: no external asset, so the file can be
mailed or archived alone). :data:`DEFINITIONS` are the metric definitions every report
carries.
"""

from __future__ import annotations

import base64
import html
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from planetref.report.tables import fmt, format_markdown_table, numeric_column
from planetref.runtime.atomic import write_text_atomic

__all__ = ["DEFINITIONS", "Document", "Figure", "HtmlContents", "Table", "read_report_html"]

DEFINITIONS: list[tuple[str, str]] = [
    (
        "NCP",
        "number of correct points: the unique matched control points (MCPs) of a CCD image "
        "delivered to the adjustment, i.e. the correspondences that passed the tile's "
        "verification (coarse gate, MAGSAC++, translation consensus, back-projection, "
        "refinement when on), less those the MCP stage drops (duplicates of one image "
        "position, no DEM height; funnel stage mcp_unique). Counted before any thinning "
        "for speed. A matcher whose run failed keeps its row. Higher is better.",
    ),
    (
        "SDU",
        "spatial distribution uniformity, in percent: SDU = (1/3) * sum over s in "
        "{32, 64, 128} of 100 * (cells of an s x s grid over the image holding at least one "
        "MCP) / s^2. Higher is better.",
    ),
    (
        "residual",
        "v_i = (x_i, y_i) = projected - observed image coordinates (pixels) of MCP i after "
        "the adjustment; x = sample, y = line; over the n inlier MCPs.",
    ),
    ("RMSE", "sqrt((1/n) * sum(x_i^2 + y_i^2)) (pixels, radial). Lower is better."),
    ("RMSE x, RMSE y", "sqrt((1/n) * sum(x_i^2)) and sqrt((1/n) * sum(y_i^2)) (pixels)."),
    ("Mean", "(1/n) * sum(sqrt(x_i^2 + y_i^2)) (pixels), the mean residual length."),
    (
        "Max X / Min X, Max Y / Min Y",
        "max_i x_i, min_i x_i, max_i y_i, min_i y_i (pixels, signed).",
    ),
    (
        "OR",
        "outlier ratio = 100 * (MCPs rejected by the adjustment) / (MCPs that entered it), in "
        "percent. The front end's own rejections are in the funnel table. Lower is better.",
    ),
    (
        "Check, Check / predicted",
        "the held-out check tiles (whole tiles, never adjusted): RMS misfit of their MCPs "
        "(pixels, and metres on the ground); and the RMS over those tiles and both axes "
        "of each tile's mean misfit divided by the SD the adjustment's covariance "
        "predicts for it, ~1 when the formal precision means what it says (real data "
        "included; with one or two tiles a rough figure).",
    ),
    (
        "diff / predicted, excess",
        "(compare) matcher agreement, no truth needed: 'diff' is the RMS over the true "
        "error's image grid of the ground distance between two matchers' adjusted cameras, "
        "'predicted' what their own errors (measurements, per-tile matcher offsets) give "
        "for it; ~1 when both covariances mean what they say. 'excess' (three matchers or "
        "more) splits the pairs' excess into one error per matcher (non-negative least "
        "squares, the three-cornered hat): the ground error its covariance misses; "
        "'formal with excess' adds it to the formal precision.",
    ),
    (
        "true error",
        "(simulated scenes) RMS over a grid of image pixels of the ground distance (metres) "
        "between the terrain intersections of the same pixel through the adjusted and the "
        "true camera; 'before' uses the initial camera. Lower is better.",
    ),
    (
        "true OR",
        "(simulated scenes) true outlier ratio: 100 * (matches after RANSAC, before the "
        "consensus and the back-projection, whose true error exceeds 1, resp. 3, reference "
        "px) / (matches after RANSAC); the true error is the distance between a match's "
        "reference position and where the true camera and the true DEM put its image "
        "point on the reference grid (it includes the reference's own error). Lower is "
        "better.",
    ),
    (
        "formal",
        "(simulated scenes) the formal precision of the same ground positions: the "
        "adjustment's parameter covariance, with the declared correlated errors of the "
        "reference and of the CCD placement and the matcher's offset common to a tile, "
        "its sigma estimated from the tiles' residuals (consider parameters, "
        "docs/adjust.md), "
        "propagated to the true error's pixel grid, RMS in metres. 'true/formal' is ~1 "
        "when the reported precision means what it says (0.5-2: calibrated).",
    ),
    (
        "sigma0",
        "a-posteriori standard deviation of unit weight: sqrt(v^T P v / redundancy); "
        "before VCE it measures the a-priori weights, after it is ~1 by construction.",
    ),
]


@dataclass
class Table:
    """A table block: header, rows, caption, and an optional CSV/LaTeX stem."""

    caption: str
    header: list[str]
    rows: list[list[Any]]


@dataclass
class Figure:
    """A figure block: a PNG and its caption."""

    path: Path
    caption: str


@dataclass
class Document:
    """A report: a title and blocks in order.

    Blocks are ``("h", level, text)``, ``("p", text)``, ``("list", items)``,
    :class:`Table` and :class:`Figure`.
    """

    title: str
    blocks: list[Any] = field(default_factory=list)

    def heading(self, text: str, level: int = 2) -> None:
        """Add a heading."""
        self.blocks.append(("h", level, text))

    def para(self, text: str) -> None:
        """Add a paragraph (Markdown ``code`` and **bold** spans)."""
        self.blocks.append(("p", text))

    def items(self, items: Sequence[str]) -> None:
        """Add a bullet list (nothing if empty)."""
        if items:
            self.blocks.append(("list", list(items)))

    def table(self, caption: str, header: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
        """Add a table."""
        self.blocks.append(Table(caption, list(header), [list(r) for r in rows]))

    def figure(self, path: str | os.PathLike[str] | None, caption: str) -> None:
        """Add a figure (nothing if the PNG does not exist)."""
        if path is not None and Path(path).is_file():
            self.blocks.append(Figure(Path(path), caption))

    # -- Markdown -------------------------------------------------------------------------
    def markdown(self, base: str | os.PathLike[str]) -> str:
        """Markdown text; figure links relative to ``base`` (the report's folder)."""
        out = [f"# {self.title}", ""]
        for b in self.blocks:
            if isinstance(b, Table):
                out += [f"**{b.caption}**", "", format_markdown_table(b.header, b.rows), ""]
            elif isinstance(b, Figure):
                rel = os.path.relpath(b.path, base).replace(os.sep, "/")
                out += [f"![{b.caption}]({rel})", "", f"*{b.caption}*", ""]
            elif b[0] == "h":
                out += ["#" * b[1] + " " + b[2], ""]
            elif b[0] == "p":
                out += [b[1], ""]
            else:
                out += [f"- {i}" for i in b[1]] + [""]
        return "\n".join(out)

    # -- HTML -----------------------------------------------------------------------------
    def html(self) -> str:
        """One self-contained HTML page (figures as base64 PNG ``data:`` URIs)."""
        e = html.escape
        body = [f"<h1>{e(self.title)}</h1>"]
        n_fig = n_tab = 0
        for b in self.blocks:
            if isinstance(b, Table):
                n_tab += 1
                numeric = [numeric_column(b.rows, i) for i in range(len(b.header))]
                head = "".join(f"<th>{e(str(h))}</th>" for h in b.header)
                rows = "".join(
                    "<tr>"
                    + "".join(
                        f'<td class="{"n" if num else "t"}">{e(fmt(v))}</td>'
                        for v, num in zip(r, numeric, strict=True)
                    )
                    + "</tr>"
                    for r in b.rows
                )
                body.append(
                    f'<table id="table-{n_tab}"><caption>{e(b.caption)}</caption>'
                    f"<thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table>"
                )
            elif isinstance(b, Figure):
                n_fig += 1
                data = base64.b64encode(b.path.read_bytes()).decode("ascii")
                body.append(
                    f'<figure id="figure-{n_fig}"><img alt="{e(b.path.name)}" '
                    f'data-file="{e(b.path.name)}" src="data:image/png;base64,{data}">'
                    f"<figcaption>{e(b.caption)}</figcaption></figure>"
                )
            elif b[0] == "h":
                body.append(f"<h{b[1]}>{e(b[2])}</h{b[1]}>")
            elif b[0] == "p":
                body.append(f"<p>{_inline(b[1])}</p>")
            else:
                body.append("<ul>" + "".join(f"<li>{_inline(i)}</li>" for i in b[1]) + "</ul>")
        return (
            '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
            f"<title>{e(self.title)}</title><style>{_CSS}</style></head><body>\n"
            + "\n".join(body)
            + "\n</body></html>\n"
        )

    def write(self, folder: str | os.PathLike[str], stem: str = "report") -> dict[str, str]:
        """Write ``<stem>.md`` and ``<stem>.html`` into ``folder``; returns their paths."""
        folder = Path(folder)
        md = write_text_atomic(folder / f"{stem}.md", self.markdown(folder))
        page = write_text_atomic(folder / f"{stem}.html", self.html())
        return {"report_md": str(md), "report_html": str(page)}


@dataclass
class HtmlContents:
    """What :func:`read_report_html` found in a report page.

    Attributes:
        figures: ``(file name, decoded bytes)`` of every ``<img>`` (``data:`` URIs only).
        external: ``src`` of images that are not embedded (a self-contained page has none).
        tables: Per ``<table>``: its caption and its rows of cell texts (header first).
    """

    figures: list[tuple[str, bytes]] = field(default_factory=list)
    external: list[str] = field(default_factory=list)
    tables: list[tuple[str, list[list[str]]]] = field(default_factory=list)


def read_report_html(path: str | os.PathLike[str]) -> HtmlContents:
    """Parse a report page: its embedded figures (base64 decoded) and its tables.

    Raises:
        InputError: An image whose ``data:`` URI is not base64 PNG.
    """
    from html.parser import HTMLParser

    from planetref.errors import InputError

    found = HtmlContents()

    class _Parser(HTMLParser):
        def __init__(self) -> None:
            super().__init__()
            self.cell: list[str] | None = None
            self.row: list[str] | None = None
            self.caption: list[str] | None = None

        def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
            a = dict(attrs)
            if tag == "img":
                src = a.get("src") or ""
                prefix = "data:image/png;base64,"
                if not src.startswith(prefix):
                    found.external.append(src)
                    return
                try:
                    data = base64.b64decode(src[len(prefix) :], validate=True)
                except ValueError as exc:
                    raise InputError(f"figure {a.get('data-file')}: bad base64", path=path) from exc
                found.figures.append((a.get("data-file") or a.get("alt") or "", data))
            elif tag == "table":
                found.tables.append(("", []))
            elif tag == "caption":
                self.caption = []
            elif tag == "tr":
                self.row = []
            elif tag in ("td", "th"):
                self.cell = []

        def handle_endtag(self, tag: str) -> None:
            if tag in ("td", "th") and self.cell is not None and self.row is not None:
                self.row.append("".join(self.cell).strip())
                self.cell = None
            elif tag == "tr" and self.row is not None and found.tables:
                found.tables[-1][1].append(self.row)
                self.row = None
            elif tag == "caption" and self.caption is not None and found.tables:
                found.tables[-1] = ("".join(self.caption).strip(), found.tables[-1][1])
                self.caption = None

        def handle_data(self, data: str) -> None:
            if self.cell is not None:
                self.cell.append(data)
            elif self.caption is not None:
                self.caption.append(data)

    _Parser().feed(Path(path).read_text(encoding="utf-8"))
    return found


def _inline(text: str) -> str:
    """Escape, then render Markdown's ``code`` and **bold** spans."""
    import re

    s = html.escape(text)
    s = re.sub(r"`([^`]+)`", r"<code>\1</code>", s)
    return re.sub(r"\*\*([^*]+)\*\*", r"<b>\1</b>", s)


_CSS = (
    "body{font-family:system-ui,sans-serif;max-width:1150px;margin:2em auto;padding:0 1em;"
    "color:#222;line-height:1.45}"
    "table{border-collapse:collapse;margin:1em 0;font-size:0.85em}"
    "caption{caption-side:top;text-align:left;font-weight:600;padding:0.3em 0}"
    "th,td{padding:0.25em 0.6em;border-bottom:1px solid #ddd}"
    "thead th{border-bottom:2px solid #444;text-align:left}"
    "td.n{text-align:right;font-variant-numeric:tabular-nums}"
    "figure{margin:1.5em 0}img{max-width:100%;border:1px solid #eee}"
    "figcaption{font-size:0.85em;color:#444}code{background:#f4f4f4;padding:0 0.2em}"
)
