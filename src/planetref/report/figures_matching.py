"""Figures of the matching front end, as PNG.

* :func:`figure_tile_grid`: the seed's Fig. 2 for one matcher: several tiles chosen by a
  stated rule (:func:`select_tiles`: best, median and worst by inlier count), one row
  each, the coarse and the fine stage of the same tile side by side.
* :func:`figure_tile_matches`: the stages of one tile, one row per stage.
* :func:`figure_pair_matches`: one image pair with its matches (``planetref match
  --figure``).
* :func:`figure_mcp_distribution`: the seed's Fig. 3: the MCPs of a strip, one panel per
  CCD in that CCD's own image coordinates, in the CCD colours, with the SDU grid.

Matplotlib runs on its Agg backend through a private ``Figure`` (no pyplot state, no
display needed). Files are written to a temporary name and renamed into place.
Keypoints are ``(x, y)`` in pixels of the array they lie on, first pixel centre at
``(0.5, 0.5)``; images are drawn with ``extent`` so that pixel ``(r, c)`` covers
``[c, c + 1) x [r, r + 1)`` and the points land where they belong. Match lines are drawn
for an evenly chosen subset only (stated in the legend); every point is drawn.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.errors import InputError, PlanetrefError
from planetref.frontend.tile_panels import MatchPanel, panels_from_tile
from planetref.report.ccd_panels import ccd_panels, finish_ccd_panel
from planetref.runtime.atomic import atomic_path

__all__ = [
    "CCD_COLOURS",
    "MatchPanel",
    "TileRow",
    "ccd_colour",
    "draw_tile_selection",
    "figure_mcp_distribution",
    "figure_pair_matches",
    "figure_tile_grid",
    "figure_tile_matches",
    "mcp_distribution_sdu",
    "panels_from_tile",
    "select_tiles",
    "tile_selection_rows",
    "verified_count",
]

INLIER_COLOUR = "#1a9850"
OUTLIER_COLOUR = "#d73027"
CCD_COLOURS: tuple[str, ...] = ("#d62728", "#2ca02c", "#1f77b4", "#ff7f0e", "#9467bd")
"""CCD colours left to right across track: red, green, blue (then orange, purple)."""


def ccd_colour(index: int) -> str:
    """Colour of the ``index``-th CCD of a strip (left to right)."""
    return CCD_COLOURS[index % len(CCD_COLOURS)]


@dataclass
class TileRow:
    """One row of :func:`figure_tile_grid`: a tile's stages with a label.

    Attributes:
        label: Row label (e.g. ``"best: ccd2:r000c001, 412 inliers"``).
        panels: The tile's stages, left to right (coarse, fine).
    """

    label: str
    panels: list[MatchPanel]


def verified_count(tile: Any) -> int:
    """Correspondences a tile result verified, before any thinning for speed.

    The result's ``ncp`` when it has one, else the funnel's last stage before ``mcp``,
    else ``n_inliers`` (passed MAGSAC++), else ``n_points`` (MCPs written).
    """
    ncp = getattr(tile, "ncp", None)
    if isinstance(ncp, int | np.integer):
        return int(ncp)
    funnel = getattr(tile, "funnel", None)
    if isinstance(funnel, Mapping) and funnel:
        stages = [k for k in funnel if k != "mcp"]
        if stages:
            return int(funnel[stages[-1]])
    for attr in ("n_inliers", "n_points"):
        v = getattr(tile, attr, None)
        if v is not None:
            return int(v)
    return 0


def select_tiles(tiles: Sequence[Any], n: int = 3) -> list[tuple[str, Any]]:
    """Tiles for Fig. 2 by a stated rule: best, median and worst by verified count.

    Only tiles with status ``ok`` take part; they are ranked by :func:`verified_count`
    (not by MCPs, which a per-tile cap may equalise); ties keep plan order. With fewer
    than three such tiles the distinct ones are returned.

    Args:
        tiles: Tile results.
        n: 3 for best/median/worst, 2 for best/worst, 1 for best.

    Returns:
        ``(rule, tile)`` pairs, rule one of ``"best"``, ``"median"``, ``"worst"``.
    """
    ok = [t for t in tiles if getattr(t, "status", "ok") == "ok"]
    if not ok:
        return []
    ranked = sorted(ok, key=lambda t: -verified_count(t))
    picks = [("best", 0), ("median", (len(ranked) - 1) // 2), ("worst", len(ranked) - 1)]
    if n == 2:
        picks = [picks[0], picks[2]]
    elif n == 1:
        picks = picks[:1]
    out: list[tuple[str, Any]] = []
    seen: set[int] = set()
    for rule, i in picks:
        if i not in seen:
            seen.add(i)
            out.append((rule, ranked[i]))
    return out


def tile_selection_rows(
    tiles: Sequence[Any], panels_of: Callable[[Any], list[MatchPanel]]
) -> list[TileRow]:
    """The rows of Fig. 2: the tiles :func:`select_tiles` picks, labelled, with their stages.

    Args:
        tiles: The strip's tile results.
        panels_of: A tile result's stages as panels: kept from the matching pass (see
            :class:`~planetref.frontend.tile_panels.PanelStore`), or from matching its tile
            again with ``debug=True`` (:func:`panels_from_tile`); may raise
            :class:`~planetref.errors.PlanetrefError` (the tile is then left out).
    """
    rows = []
    for rule, t in select_tiles(tiles):
        label = f"{rule}: {t.tile_id}\n{verified_count(t)} verified"
        if getattr(t, "n_points", None) is not None:
            label += f", {int(t.n_points)} MCPs"
        try:
            rows.append(TileRow(label, panels_of(t)))
        except PlanetrefError:
            continue
    return rows


def draw_tile_selection(
    tiles: Sequence[Any],
    panels_of: Callable[[Any], list[MatchPanel]],
    path: str | PathLike[str],
    *,
    title: str = "",
) -> Path | None:
    """Fig. 2 of one matcher: draw the rows of :func:`tile_selection_rows`.

    Returns:
        The PNG path, or None if no tile could be drawn.
    """
    rows = tile_selection_rows(tiles, panels_of)
    if not rows:
        return None
    return figure_tile_grid(rows, path, title=title)


def _display(image: NDArray[Any], valid: NDArray[np.bool_] | None) -> NDArray[np.float64]:
    img = np.asarray(image, np.float64)
    ok = np.isfinite(img) if valid is None else (np.asarray(valid, bool) & np.isfinite(img))
    out = np.full(img.shape, np.nan)
    if ok.any():
        lo, hi = np.percentile(img[ok], [1.0, 99.0])
        out[ok] = np.clip((img[ok] - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    return out


def save(fig: Any, path: str | PathLike[str], dpi: int) -> Path:
    """Write ``fig`` as a PNG at ``dpi`` in one draw.

    ``Figure.savefig`` draws a figure with a layout engine twice: once without rendering
    (to run the layout), then again for the pixels. The canvas's ``print_png`` draws once,
    running the layout at the start of that draw from the same state, so the pixels are
    the same (tested against ``savefig``) for about half the drawing time.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    fig.set_dpi(dpi)
    with atomic_path(path) as tmp:
        canvas.print_png(tmp)
    return Path(path)


def _gray() -> Any:
    import matplotlib

    # Invalid pixels: a pale tone that no grey image takes.
    return matplotlib.colormaps["gray"].with_extremes(bad="#f4e3c8")


def _show(ax: Any, img: NDArray[Any], valid: NDArray[np.bool_] | None, label: str) -> None:
    h, w = np.shape(img)
    # Display only (the extent keeps pixel units): a panel is at most ~550 px wide at the
    # figures' dpi, so more than 700 px of image would only cost drawing time.
    step = max(1, int(np.ceil(max(h, w) / 700)))
    shown = _display(
        np.asarray(img)[::step, ::step], None if valid is None else valid[::step, ::step]
    )
    ax.imshow(shown, cmap=_gray(), extent=(0, w, h, 0), interpolation="nearest")
    ax.set_title(f"{label} ({w} x {h} px)", fontsize=8)
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.tick_params(labelsize=6)


def _pair(
    fig: Any,
    a0: Any,
    a1: Any,
    pnl: MatchPanel,
    max_lines: int,
    labels: tuple[str, str] = ("CCD tile", "reference"),
) -> tuple[int, int, int]:
    """Draw one pair; returns (inliers, rejected, lines drawn)."""
    from matplotlib.patches import ConnectionPatch

    _show(a0, pnl.image0, pnl.valid0, labels[0])
    _show(a1, pnl.image1, pnl.valid1, labels[1])
    k0 = np.asarray(pnl.keypoints0, np.float64).reshape(-1, 2)
    k1 = np.asarray(pnl.keypoints1, np.float64).reshape(-1, 2)
    inl = np.ones(len(k0), bool) if pnl.inliers is None else np.asarray(pnl.inliers, bool).ravel()
    if len(k1) != len(k0) or len(inl) != len(k0):
        raise InputError(f"panel {pnl.title!r}: keypoint and inlier counts differ")
    # Lines: an even subset of the inliers, and of the rejected (at most a third of them).
    drawn = 0
    for sel, colour, cap in (
        (np.flatnonzero(inl), INLIER_COLOUR, max_lines),
        (np.flatnonzero(~inl), OUTLIER_COLOUR, max(max_lines // 3, 1)),
    ):
        if len(sel) > cap:
            sel = sel[np.linspace(0, len(sel) - 1, cap).astype(int)]
        for i in sel:
            fig.add_artist(
                ConnectionPatch(
                    xyA=tuple(k0[i]),
                    coordsA=a0.transData,
                    xyB=tuple(k1[i]),
                    coordsB=a1.transData,
                    color=colour,
                    lw=0.6,
                    alpha=0.6,
                )
            )
        drawn += len(sel)
    for ax, k in ((a0, k0), (a1, k1)):
        if len(k):
            ax.scatter(k[~inl, 0], k[~inl, 1], s=9, marker="x", c=OUTLIER_COLOUR, linewidths=0.8)
            ax.scatter(
                k[inl, 0], k[inl, 1], s=10, facecolors="none", edgecolors=INLIER_COLOUR, lw=0.8
            )
    return int(inl.sum()), int((~inl).sum()), drawn


def _legend(fig: Any, max_lines: int) -> None:
    from matplotlib.lines import Line2D

    handles = [
        Line2D([], [], color=INLIER_COLOUR, marker="o", mfc="none", lw=0.8, label="kept (inlier)"),
        Line2D([], [], color=OUTLIER_COLOUR, marker="x", lw=0.8, label="rejected"),
    ]
    fig.legend(
        handles=handles,
        loc="outside lower center",
        ncol=2,
        fontsize=8,
        frameon=False,
        title=f"lines: at most {max_lines} kept and {max(max_lines // 3, 1)} rejected "
        "per pair (evenly chosen); every point is marked; axes in pixels",
        title_fontsize=7,
    )


def figure_tile_grid(
    rows: Sequence[TileRow],
    path: str | PathLike[str],
    *,
    title: str = "",
    max_lines: int = 40,
    dpi: int = 90,
) -> Path:
    """Several tiles, one row each, their stages side by side (coarse | fine); write a PNG.

    Each stage takes two axes (the CCD tile in the common geometry, then the reference
    window), so a row reads: coarse tile, coarse reference, fine tile, fine reference.

    Args:
        rows: One :class:`TileRow` per tile.
        path: Output PNG.
        title: Figure title.
        max_lines: Match lines drawn per pair for the kept matches.
        dpi: Resolution.
    """
    from matplotlib.figure import Figure

    if not rows or not all(r.panels for r in rows):
        raise InputError("no tile to draw")
    n_st = max(len(r.panels) for r in rows)
    fig = Figure(figsize=(3.2 * 2 * n_st, 3.3 * len(rows) + 1.0), layout="constrained")
    axes = fig.subplots(len(rows), 2 * n_st, squeeze=False)
    for r, row in enumerate(rows):
        for s in range(n_st):
            a0, a1 = axes[r][2 * s], axes[r][2 * s + 1]
            if s >= len(row.panels):
                a0.set_axis_off()
                a1.set_axis_off()
                continue
            pnl = row.panels[s]
            n_in, n_out, _ = _pair(
                fig, a0, a1, pnl, max_lines, (f"{pnl.title}: CCD tile", f"{pnl.title}: reference")
            )
            a0.set_xlabel(f"{n_in} kept, {n_out} rejected", fontsize=7)
        axes[r][0].set_ylabel(row.label, fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    _legend(fig, max_lines)
    return save(fig, path, dpi)


def figure_tile_matches(
    panels: Sequence[MatchPanel],
    path: str | PathLike[str],
    *,
    title: str = "",
    max_lines: int = 60,
    dpi: int = 110,
) -> Path:
    """Draw each stage's image pair side by side with its matches; write a PNG.

    Args:
        panels: One :class:`MatchPanel` per row (e.g. coarse, fine; see
            :func:`panels_from_tile`).
        path: Output PNG.
        title: Figure title.
        max_lines: At most this many match lines of kept matches per panel (evenly
            subsampled; a third as many for the rejected).
        dpi: Resolution.

    Returns:
        The PNG path.
    """
    from matplotlib.figure import Figure

    if not panels:
        raise InputError("no panel to draw")
    fig = Figure(figsize=(10.0, 4.6 * len(panels) + 0.6), layout="constrained")
    axes = fig.subplots(len(panels), 2, squeeze=False)
    for row, pnl in enumerate(panels):
        n_in, n_out, _ = _pair(fig, axes[row][0], axes[row][1], pnl, max_lines)
        axes[row][0].set_ylabel(f"{pnl.title}: {n_in} kept, {n_out} rejected", fontsize=9)
    if title:
        fig.suptitle(title, fontsize=11)
    _legend(fig, max_lines)
    return save(fig, path, dpi)


def figure_pair_matches(
    path: str | PathLike[str],
    image0: NDArray[Any],
    valid0: NDArray[np.bool_] | None,
    image1: NDArray[Any],
    valid1: NDArray[np.bool_] | None,
    k0: NDArray[np.float64],
    k1: NDArray[np.float64],
    title: str,
    max_lines: int = 80,
    *,
    inliers: NDArray[np.bool_] | None = None,
    labels: tuple[str, str] = ("image 0", "image 1"),
    dpi: int = 100,
) -> Path:
    """One image pair with its matches (``planetref match --figure``); write a PNG.

    Axes are in pixels of each image; at most ``max_lines`` lines are drawn (evenly
    chosen) and every match is marked; the legend gives the counts.

    Args:
        path: Output PNG.
        image0: Left image.
        valid0: Its validity (None: finite pixels).
        image1: Right image.
        valid1: Its validity.
        k0: ``(N, 2)`` ``(x, y)`` on ``image0``.
        k1: ``(N, 2)`` on ``image1``.
        title: Figure title.
        max_lines: Lines drawn for the kept matches.
        inliers: ``(N,)`` kept matches (default: all).
        labels: Titles of the two images.
        dpi: Resolution.
    """
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12.0, 6.8), layout="constrained")
    a0, a1 = fig.subplots(1, 2)
    n_in, n_out, _ = _pair(
        fig,
        a0,
        a1,
        MatchPanel(title, image0, image1, k0, k1, inliers, valid0, valid1),
        max_lines,
        labels,
    )
    for ax in (a0, a1):
        ax.set_xlabel("x = sample (px)", fontsize=8)
    a0.set_ylabel("y = line (px)", fontsize=8)
    fig.suptitle(f"{title}: {n_in} matches kept" + (f", {n_out} rejected" if n_out else ""))
    _legend(fig, max_lines)
    return save(fig, path, dpi)


def figure_mcp_distribution(
    table: Any,
    image_sizes: Mapping[str, tuple[int, int]],
    path: str | PathLike[str],
    *,
    ccd_order: Sequence[str] | None = None,
    title: str = "",
    gap_fraction: float = 0.08,
    dpi: int = 110,
    grids: Sequence[int] | None = None,
    sdu: Mapping[str, float] | None = None,
) -> Path:
    """The seed's Fig. 3: MCPs of a strip, one panel per CCD in its image coordinates.

    Each panel shows one CCD image (samples across, lines down, in pixels) with its MCPs
    in the CCD's colour (:data:`CCD_COLOURS`), the coarsest SDU grid drawn over it and
    its occupied cells shaded; the title gives NCP and SDU (all grids).

    Args:
        table: MCPs (:class:`~planetref.control.mcp.McpTable` or any mapping with ``ccd``,
            ``line`` and ``sample`` columns).
        image_sizes: CCD name -> ``(n_lines, n_samples)``, in strip order (left to right
            across track) unless ``ccd_order`` says otherwise.
        path: Output PNG.
        ccd_order: CCDs left to right.
        title: Figure title.
        gap_fraction: Kept for compatibility (panels are separate now).
        dpi: Resolution.
        grids: SDU grid sizes (default: :data:`~planetref.frontend.stats.SDU_GRIDS`).
        sdu: Each CCD's SDU over ``grids`` (:func:`mcp_distribution_sdu`), when the caller
            has it (the figure process then needs no front-end module); else computed.

    Returns:
        The PNG path.
    """
    del gap_fraction
    order = list(ccd_order or image_sizes)
    unknown = [c for c in order if c not in image_sizes]
    if unknown or not order:
        raise InputError(f"no image size for CCDs {unknown}" if unknown else "no CCD to draw")
    if grids is None or sdu is None or set(order) - set(sdu):
        grids, sdu = mcp_distribution_sdu(table, image_sizes, grids)
    gs = tuple(grids)
    ccd = np.asarray(table["ccd"]).astype(str)
    line = np.asarray(table["line"], np.float64)
    sample = np.asarray(table["sample"], np.float64)
    fig, axes, max_h = ccd_panels(image_sizes, order, 1.2)
    g = min(gs)
    for i, (ax, c) in enumerate(zip(axes, order, strict=True)):
        nl, ns = image_sizes[c]
        sel = ccd == c
        colour = ccd_colour(i)
        ln, sm = line[sel], sample[sel]
        inside = (ln >= 0) & (ln < nl) & (sm >= 0) & (sm < ns)
        occ = np.zeros((g, g), bool)
        r = np.minimum((ln[inside] * g / nl).astype(int), g - 1)
        cc = np.minimum((sm[inside] * g / ns).astype(int), g - 1)
        occ[r, cc] = True
        ax.imshow(
            np.where(occ, 1.0, np.nan),
            extent=(0, ns, nl, 0),
            cmap=_single(colour),
            vmin=0,
            vmax=1,
            alpha=0.18,
            interpolation="nearest",
            aspect="auto",
        )
        # The SDU grid: one line collection per direction across the whole panel (as
        # axhline/axvline would draw them, which cost one artist each in the layout).
        k = np.arange(g + 1)
        grid = {"colors": "0.85", "lw": 0.3, "zorder": 0, "capstyle": "projecting"}
        ax.hlines(k * nl / g, 0, 1, transform=ax.get_yaxis_transform(which="grid"), **grid)
        ax.vlines(k * ns / g, 0, 1, transform=ax.get_xaxis_transform(which="grid"), **grid)
        ax.scatter(sm, ln, s=5, color=colour, linewidths=0, zorder=3)
        ax.set_title(f"{c}\nNCP {int(sel.sum())}, SDU {sdu[c]:.1f} %", fontsize=9, color=colour)
        finish_ccd_panel(ax, ns, max_h)
    axes[0].set_ylabel("line (px)", fontsize=8)
    fig.suptitle(
        (title or f"MCP distribution: {len(line)} MCPs")
        + f"\ngrid: {g} x {g} SDU cells (occupied shaded); SDU = mean over grids {list(gs)}",
        fontsize=9,
    )
    return save(fig, path, dpi)


def mcp_distribution_sdu(
    table: Any, image_sizes: Mapping[str, tuple[int, int]], grids: Sequence[int] | None = None
) -> tuple[tuple[int, ...], dict[str, float]]:
    """The grids and each CCD's SDU that :func:`figure_mcp_distribution` prints.

    Args:
        table: MCPs (``ccd``, ``line`` and ``sample`` columns).
        image_sizes: CCD name -> ``(n_lines, n_samples)``.
        grids: SDU grid sizes (default: :data:`~planetref.frontend.stats.SDU_GRIDS`).
    """
    from planetref.frontend.stats import SDU_GRIDS, sdu_percent

    gs = tuple(int(g) for g in (grids or SDU_GRIDS))
    ccd = np.asarray(table["ccd"]).astype(str)
    line = np.asarray(table["line"], np.float64)
    sample = np.asarray(table["sample"], np.float64)
    out = {}
    for c, (nl, ns) in image_sizes.items():
        sel = ccd == c
        out[c] = float(sdu_percent(line[sel], sample[sel], nl, ns, gs))
    return gs, out


def _single(colour: str) -> Any:
    from matplotlib.colors import ListedColormap

    return ListedColormap([colour]).with_extremes(bad=(0, 0, 0, 0))
