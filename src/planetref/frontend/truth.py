"""The matcher's outliers measured against the truth of a simulated scene.

The adjustment's outlier ratio (OR) only sees what the front end lets through: with the
default 1 reference px RANSAC threshold it is ~0 whether the matcher gave 1 % or 80 %
wrong matches. On a simulated scene each match's true error can be measured instead:
the scene's true camera puts the match's raw pixel ``(line, sample)`` on the true DEM,
the reference grid gives that ground point's reference pixel, and the distance to the
match's reference position (reference px) is its true error. The *true outlier ratio*
is the share of the matches after RANSAC (before the consensus and the back-projection
remove more) whose true error exceeds 1 and 3 reference px.

The true error includes the reference's own geometric error (the simulated mosaic's
per-source offsets and warps, ``truth/reference.json``): a perfect matcher on a
reference shifted by 10 m shows 2 px at 5 m. That is what the adjustment sees too.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "TRUE_OUTLIER_PX",
    "TrueOutliers",
    "sum_true_outliers",
    "true_errors_px",
    "true_outliers",
]

TRUE_OUTLIER_PX: tuple[float, float] = (1.0, 3.0)
"""Thresholds of the true outlier ratio (reference px)."""


@dataclass(frozen=True)
class TrueOutliers:
    """True errors of the matches after RANSAC of one strip (or several, summed).

    Attributes:
        n: Matches after RANSAC whose true error could be measured.
        n_unmeasured: Matches without a raw position or whose true ray missed the DEM.
        n_over_1px: Of ``n``, true error above 1 reference px.
        n_over_3px: Of ``n``, true error above 3 reference px.
        median_px: Median true error (reference px); NaN for ``n = 0``.
    """

    n: int
    n_unmeasured: int
    n_over_1px: int
    n_over_3px: int
    median_px: float

    @property
    def pct_over_1px(self) -> float | None:
        """Percent of ``n`` above 1 reference px (None for ``n = 0``)."""
        return 100.0 * self.n_over_1px / self.n if self.n else None

    @property
    def pct_over_3px(self) -> float | None:
        """Percent of ``n`` above 3 reference px (None for ``n = 0``)."""
        return 100.0 * self.n_over_3px / self.n if self.n else None

    def to_dict(self) -> dict[str, Any]:
        """The report's ``true_outliers`` block."""
        return {
            "n": self.n,
            "n_unmeasured": self.n_unmeasured,
            "n_over_1px": self.n_over_1px,
            "n_over_3px": self.n_over_3px,
            "pct_over_1px": self.pct_over_1px,
            "pct_over_3px": self.pct_over_3px,
            "median_px": None if not np.isfinite(self.median_px) else self.median_px,
        }


def true_errors_px(
    points: np.ndarray, ccd: str, camera_true: Any, ref: Any, terrain: Any
) -> np.ndarray:
    """True errors (reference px) of matches ``(line, sample, ref_col, ref_row)`` of a CCD.

    Args:
        points: ``(N, 4)`` as :attr:`~planetref.frontend.result.TileResult.ransac_points`.
        ccd: Their CCD.
        camera_true: The scene's true camera of the strip.
        ref: The reference orthoimage (its grid).
        terrain: The true DEM.

    Returns:
        ``(N,)`` distances between each match's reference position and the true
        reference pixel of its raw pixel; NaN where either is unknown.
    """
    from planetref.camera.mapping import image_to_ref_pixel

    p = np.asarray(points, np.float64).reshape(-1, 4)
    out = np.full(len(p), np.nan)
    ok = np.all(np.isfinite(p), axis=1)
    if ok.any():
        col, row = image_to_ref_pixel(camera_true, ccd, p[ok, 0], p[ok, 1], ref, terrain)
        out[ok] = np.hypot(p[ok, 2] - col, p[ok, 3] - row)
    return out


def true_outliers(tiles: Iterable[Any], camera_true: Any, ref: Any, terrain: Any) -> TrueOutliers:
    """The true outlier ratio of a strip's tiles (every tile that reached RANSAC).

    Args:
        tiles: :class:`~planetref.frontend.result.TileResult` objects (failed tiles too:
            a matcher whose RANSAC survivors are wrong is what this measures).
        camera_true: The strip's true camera.
        ref: The reference orthoimage.
        terrain: The true DEM.
    """
    per_ccd: dict[str, list[np.ndarray]] = {}
    for t in tiles:
        pts = np.asarray(getattr(t, "ransac_points", np.empty((0, 4))), np.float64)
        if len(pts):
            per_ccd.setdefault(str(t.tile.ccd), []).append(pts.reshape(-1, 4))
    errs = [
        true_errors_px(np.concatenate(v), c, camera_true, ref, terrain) for c, v in per_ccd.items()
    ]
    e = np.concatenate(errs) if errs else np.empty(0)
    good = e[np.isfinite(e)]
    lo, hi = TRUE_OUTLIER_PX
    return TrueOutliers(
        n=int(good.size),
        n_unmeasured=int(e.size - good.size),
        n_over_1px=int(np.count_nonzero(good > lo)),
        n_over_3px=int(np.count_nonzero(good > hi)),
        median_px=float(np.median(good)) if good.size else float("nan"),
    )


def sum_true_outliers(blocks: Iterable[dict[str, Any] | None]) -> dict[str, Any] | None:
    """``true_outliers`` blocks of several strips summed (None when no strip has one)."""
    items = [b for b in blocks if b]
    if not items:
        return None
    n = sum(int(b["n"]) for b in items)
    n1 = sum(int(b["n_over_1px"]) for b in items)
    n3 = sum(int(b["n_over_3px"]) for b in items)
    with_med = [b for b in items if b.get("median_px") is not None and b["n"]]
    return {
        "n": n,
        "n_unmeasured": sum(int(b.get("n_unmeasured", 0)) for b in items),
        "n_over_1px": n1,
        "n_over_3px": n3,
        "pct_over_1px": 100.0 * n1 / n if n else None,
        "pct_over_3px": 100.0 * n3 / n if n else None,
        # The strips' medians weighted by their matches (not the pooled median).
        "median_px": (
            float(
                np.average([b["median_px"] for b in with_med], weights=[b["n"] for b in with_med])
            )
            if with_med
            else None
        ),
    }
