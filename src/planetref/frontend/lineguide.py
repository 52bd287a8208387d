"""Starting lines for projecting reference-grid points into a line-scan CCD.

Projecting a ground point into a push-broom image means finding its line: without a
starting line the camera scans the whole searchable span (a bracketing grid, then Newton),
which costs a fixed ~10 ms per call in numpy; from a good starting line the compiled
projection converges in a few chord steps per point. :class:`LineGuide` gives every
reference ``(col, row)`` such a start: the CCD's image points on a table of lines (the
whole searchable span, every ``line_spacing`` lines) and samples (from one CCD width
before the first sample to one after the last) are cast onto the DEM once, and the line
is interpolated linearly over the triangulated reference positions of the table (the
nearest table line outside it). The guide only starts the projection: the line it
converges to is the camera's exact one, whatever the guess.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator
from scipy.spatial import QhullError

from planetref.arrays import F64
from planetref.camera.base import Camera, Terrain
from planetref.camera.mapping import image_to_ref_pixel
from planetref.raster.ortho import ReferenceOrtho

__all__ = ["LineGuide"]


@dataclass(frozen=True)
class LineGuide:
    """Starting lines of reference positions, from a table of projected image points.

    Attributes:
        span: ``(line_lo, line_hi)``: the camera's searchable lines (the table's extent).
        linear: Piecewise-linear line over the table's reference ``(col, row)``.
        nearest: Line of the nearest table point (outside the table's hull).
    """

    span: tuple[float, float]
    linear: LinearNDInterpolator
    nearest: NearestNDInterpolator

    @classmethod
    def build(
        cls,
        camera: Camera,
        ccd: str,
        ref: ReferenceOrtho,
        terrain: Terrain,
        *,
        line_spacing: float = 128.0,
        n_table_samples: int = 13,
    ) -> LineGuide | None:
        """The guide of one CCD, or None for a camera without a line span (no line search).

        Args:
            camera: The camera (a line-scan camera: its ``kernel`` gives the searchable span).
            ccd: CCD name.
            ref: The reference orthoimage (its grid).
            terrain: The DEM.
            line_spacing: Table spacing along the lines (image lines).
            n_table_samples: Table points across (from ``-n_samples`` to ``2 n_samples``).
        """
        kernel = getattr(camera, "kernel", None)
        lo, hi = getattr(kernel, "line_lo", None), getattr(kernel, "line_hi", None)
        if lo is None or hi is None or not hi > lo:
            return None
        _, n_samples = camera.image_size(ccd)
        n_lines_table = max(9, int(np.ceil((hi - lo) / float(line_spacing))) + 1)
        lines = np.linspace(float(lo), float(hi), n_lines_table)
        samples = np.linspace(-float(n_samples), 2.0 * n_samples, int(n_table_samples))
        grid_l, grid_s = np.meshgrid(lines, samples, indexing="ij")
        col, row = image_to_ref_pixel(camera, ccd, grid_l.ravel(), grid_s.ravel(), ref, terrain)
        ok = np.isfinite(col) & np.isfinite(row)
        if ok.sum() < 3:
            return None
        pts = np.column_stack([col[ok], row[ok]])
        try:
            linear = LinearNDInterpolator(pts, grid_l.ravel()[ok])
        except QhullError:  # a degenerate table (collinear points): no guide
            return None
        return cls((float(lo), float(hi)), linear, NearestNDInterpolator(pts, grid_l.ravel()[ok]))

    def __call__(self, col: F64, row: F64) -> tuple[F64, NDArray[np.bool_]]:
        """Starting lines of reference ``(col, row)`` and whether each lies in the table.

        Returns:
            ``(line, inside)``: the interpolated line inside the table's hull, the
            nearest table point's line outside it.
        """
        pts = np.column_stack([np.asarray(col, np.float64), np.asarray(row, np.float64)])
        line = np.asarray(self.linear(pts), np.float64).reshape(-1)
        inside = np.isfinite(line)
        if not inside.all():
            line[~inside] = np.asarray(self.nearest(pts[~inside]), np.float64).reshape(-1)
        return line, inside
