"""One panel per CCD, side by side, each in its own image coordinates.

The layout shared by the MCP distribution (:mod:`planetref.report.figures_matching`) and
the residual vectors (:mod:`planetref.report.figures_adjust`) figures.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["ccd_panels", "finish_ccd_panel"]


def ccd_panels(
    image_sizes: Mapping[str, tuple[int, int]], order: Sequence[str], extra_height_in: float
) -> tuple[Any, NDArray[Any], int]:
    """A figure of one panel per CCD, left to right, each in its image coordinates.

    The panels share the line axis; each is as wide as its CCD's samples.

    Args:
        image_sizes: CCD name -> ``(n_lines, n_samples)``.
        order: The CCDs to draw, left to right.
        extra_height_in: Inches added to the figure's height for the titles and legends.

    Returns:
        ``(figure, axes, max_lines)``: the axes in ``order``; the most lines of a CCD.
    """
    from matplotlib.figure import Figure

    max_h = max(image_sizes[c][0] for c in order)
    widths = [image_sizes[c][1] for c in order]
    aspect = max_h / float(np.mean(widths))
    panel_w = float(np.clip(9.0 / len(order), 2.2, 4.0))
    fig = Figure(
        figsize=(
            panel_w * len(order) + 0.6,
            float(np.clip(panel_w * aspect, 2.5, 11.0)) + extra_height_in,
        ),
        layout="constrained",
    )
    axes = np.atleast_1d(fig.subplots(1, len(order), sharey=True, width_ratios=widths))
    return fig, axes, max_h


def finish_ccd_panel(ax: Any, n_samples: int, max_lines: int) -> None:
    """Limits, labels and background of a :func:`ccd_panels` panel (pixels, lines down)."""
    ax.set_xlim(0, n_samples)
    ax.set_ylim(max_lines, 0)
    ax.set_xlabel("sample (px)", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.set_facecolor("#fafafa")
