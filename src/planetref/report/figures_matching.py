"""Figures of the matching front end, as PNG.

* :func:`figure_tile_matches`: for one tile, the image side and the reference window of
  each stage (coarse, fine) side by side, with a line per match (inliers in one colour,
  rejected matches in another).
* :func:`figure_mcp_distribution`: the MCPs over the CCD images of a strip, the images
  drawn side by side in their across-track order (one colour per CCD), each titled with
  its NCP and SDU.

Matplotlib runs on its Agg backend through a private ``Figure`` (no pyplot state, no
display needed). Files are written to a temporary name and renamed into place.
Keypoints are ``(x, y)`` in pixels of the array they lie on, first pixel centre at
``(0.5, 0.5)``; images are drawn with ``extent`` so that pixel ``(r, c)`` covers
``[c, c + 1) x [r, r + 1)`` and the points land where they belong.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.atomic import atomic_path
from planetref.errors import InputError

__all__ = ["MatchPanel", "figure_mcp_distribution", "figure_tile_matches", "panels_from_tile"]

INLIER_COLOUR = "#2ca02c"
OUTLIER_COLOUR = "#d62728"


@dataclass
class MatchPanel:
    """One image pair with its matches.

    Attributes:
        title: Panel title (e.g. ``"coarse"``).
        image0: Left image (the CCD tile in the common geometry).
        image1: Right image (the reference window).
        keypoints0: ``(N, 2)`` ``(x, y)`` on ``image0``.
        keypoints1: ``(N, 2)`` on ``image1``.
        inliers: ``(N,)`` kept matches (default: all).
        valid0: Validity of ``image0`` (invalid pixels drawn blank).
        valid1: Validity of ``image1``.
    """

    title: str
    image0: NDArray[Any]
    image1: NDArray[Any]
    keypoints0: NDArray[np.float64]
    keypoints1: NDArray[np.float64]
    inliers: NDArray[np.bool_] | None = None
    valid0: NDArray[np.bool_] | None = None
    valid1: NDArray[np.bool_] | None = None


def panels_from_tile(result: Any) -> list[MatchPanel]:
    """Panels of a :class:`~planetref.frontend.match_tile.TileResult` matched with ``debug``.

    Raises:
        InputError: If the result holds no stage images (match it with ``debug=True``).
    """
    stages = getattr(result, "debug", None) or []
    if not stages:
        raise InputError(
            f"tile {getattr(result, 'tile_id', '?')} has no stage images; "
            "match it with debug=True (or list it in debug_tiles)"
        )
    out = []
    for s in stages:
        n_in = int(np.count_nonzero(s.inliers))
        out.append(
            MatchPanel(
                f"{s.stage}: {n_in} of {len(s.inliers)} matches kept",
                s.image0,
                s.image1,
                s.keypoints0,
                s.keypoints1,
                s.inliers,
                s.valid0,
                s.valid1,
            )
        )
    return out


def _display(image: NDArray[Any], valid: NDArray[np.bool_] | None) -> NDArray[np.float64]:
    img = np.asarray(image, np.float64)
    ok = np.isfinite(img) if valid is None else (np.asarray(valid, bool) & np.isfinite(img))
    out = np.full(img.shape, np.nan)
    if ok.any():
        lo, hi = np.percentile(img[ok], [1.0, 99.0])
        out[ok] = np.clip((img[ok] - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    return out


def _save(fig: Any, path: str | PathLike[str], dpi: int) -> Path:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    return Path(path)


def figure_tile_matches(
    panels: Sequence[MatchPanel],
    path: str | PathLike[str],
    *,
    title: str = "",
    max_lines: int = 300,
    dpi: int = 110,
) -> Path:
    """Draw each stage's image pair side by side with its matches; write a PNG.

    Args:
        panels: One :class:`MatchPanel` per row (e.g. coarse, fine; see
            :func:`panels_from_tile`).
        path: Output PNG.
        title: Figure title.
        max_lines: At most this many match lines per panel (evenly subsampled).
        dpi: Resolution.

    Returns:
        The PNG path.
    """
    from matplotlib.figure import Figure
    from matplotlib.patches import ConnectionPatch

    if not panels:
        raise InputError("no panel to draw")
    fig = Figure(figsize=(10.0, 4.6 * len(panels)), layout="constrained")
    axes = fig.subplots(len(panels), 2, squeeze=False)
    cmap = _gray()
    for row, pnl in enumerate(panels):
        a0, a1 = axes[row]
        for ax, img, valid, label in (
            (a0, pnl.image0, pnl.valid0, "CCD tile"),
            (a1, pnl.image1, pnl.valid1, "reference"),
        ):
            h, w = np.shape(img)
            ax.imshow(_display(img, valid), cmap=cmap, extent=(0, w, h, 0), interpolation="nearest")
            ax.set_title(f"{label} ({w} x {h} px)", fontsize=9)
            ax.set_xlim(0, w)
            ax.set_ylim(h, 0)
            ax.tick_params(labelsize=7)
        k0 = np.asarray(pnl.keypoints0, np.float64).reshape(-1, 2)
        k1 = np.asarray(pnl.keypoints1, np.float64).reshape(-1, 2)
        inl = (
            np.ones(len(k0), bool)
            if pnl.inliers is None
            else np.asarray(pnl.inliers, bool).reshape(-1)
        )
        if len(k1) != len(k0) or len(inl) != len(k0):
            raise InputError(f"panel {pnl.title!r}: keypoint and inlier counts differ")
        idx = np.arange(len(k0))
        if len(idx) > max_lines:
            idx = idx[np.linspace(0, len(idx) - 1, max_lines).astype(int)]
        for i in idx:
            colour = INLIER_COLOUR if inl[i] else OUTLIER_COLOUR
            fig.add_artist(
                ConnectionPatch(
                    xyA=tuple(k0[i]),
                    coordsA=a0.transData,
                    xyB=tuple(k1[i]),
                    coordsB=a1.transData,
                    color=colour,
                    lw=0.6,
                    alpha=0.7,
                )
            )
        for ax, k in ((a0, k0), (a1, k1)):
            if len(k):
                ax.scatter(k[inl, 0], k[inl, 1], s=6, c=INLIER_COLOUR, linewidths=0)
                ax.scatter(k[~inl, 0], k[~inl, 1], s=6, c=OUTLIER_COLOUR, linewidths=0)
        a0.set_ylabel(pnl.title, fontsize=9)
    if title:
        fig.suptitle(title, fontsize=11)
    return _save(fig, path, dpi)


def _gray() -> Any:
    import matplotlib

    # Invalid pixels: a pale tone that no grey image takes.
    return matplotlib.colormaps["gray"].with_extremes(bad="#f4e3c8")


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
) -> Path:
    """Plot the MCPs over the CCD images of a strip, one colour per CCD; write a PNG.

    Args:
        table: MCPs (:class:`~planetref.control.McpTable` or any mapping with ``ccd``,
            ``line`` and ``sample`` columns).
        image_sizes: CCD name -> ``(n_lines, n_samples)``, in strip order (left to right
            across track) unless ``ccd_order`` says otherwise.
        path: Output PNG.
        ccd_order: CCDs left to right.
        title: Figure title.
        gap_fraction: Gap between neighbouring images, as a fraction of the mean width.
        dpi: Resolution.
        grids: SDU grid sizes (default: :data:`~planetref.frontend.stats.SDU_GRIDS`).

    Returns:
        The PNG path.
    """
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    from planetref.frontend.stats import SDU_GRIDS, sdu_percent

    order = list(ccd_order or image_sizes)
    unknown = [c for c in order if c not in image_sizes]
    if unknown or not order:
        raise InputError(f"no image size for CCDs {unknown}" if unknown else "no CCD to draw")
    ccd = np.asarray(table["ccd"]).astype(str)
    line = np.asarray(table["line"], np.float64)
    sample = np.asarray(table["sample"], np.float64)
    widths = [image_sizes[c][1] for c in order]
    heights = [image_sizes[c][0] for c in order]
    gap = gap_fraction * float(np.mean(widths))
    total_w = sum(widths) + gap * (len(order) - 1)
    max_h = max(heights)
    aspect = max_h / total_w
    fig_w = 10.0
    fig = Figure(
        figsize=(fig_w, float(np.clip(fig_w * aspect, 3.0, 14.0)) + 0.8), layout="constrained"
    )
    ax = fig.subplots()
    import matplotlib

    colours = matplotlib.colormaps["tab10"]
    x0 = 0.0
    for i, c in enumerate(order):
        nl, ns = image_sizes[c]
        colour = colours(i % 10)
        ax.add_patch(Rectangle((x0, 0), ns, nl, facecolor="#f2f2f2", edgecolor="0.3", lw=0.8))
        sel = ccd == c
        ax.scatter(x0 + sample[sel], line[sel], s=4, color=colour, linewidths=0, label=c)
        sdu = sdu_percent(line[sel], sample[sel], nl, ns, grids or SDU_GRIDS)
        ax.text(
            x0 + ns / 2,
            -0.01 * max_h,
            f"{c}\nNCP {int(sel.sum())}\nSDU {sdu:.1f}%",
            ha="center",
            va="bottom",
            fontsize=8,
        )
        x0 += ns + gap
    ax.set_xlim(-gap / 2, total_w + gap / 2)
    ax.set_ylim(max_h * 1.0, -0.12 * max_h)
    ax.set_aspect("equal" if 0.05 < aspect < 20 else "auto")
    ax.set_xlabel("sample (per CCD, images side by side)")
    ax.set_ylabel("line")
    ax.set_title(title or f"MCP distribution: {len(line)} MCPs", fontsize=10)
    return _save(fig, path, dpi)
