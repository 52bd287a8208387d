"""Tie points between the overlapping CCDs of one strip: the observation that sees jitter.

Neighbouring CCDs of a staggered focal plane share a few dozen columns of ground (the
overlap) and see it ``stagger`` lines apart. Matched there, a tie point's two image
positions differ from what a smooth attitude predicts by the attitude's change over
the stagger time (:func:`planetref.camera.jitter.overlap_transfer`).

The overlap is matched in raw image geometry, where both CCDs see it at the same scale
and orientation: for every ``step_lines`` lines a template of CCD ``a`` centred in the
overlap is searched by normalised cross-correlation within ``+-search_px`` of where the
camera predicts it in CCD ``b`` (image -> DEM -> image), and the integer peak is refined
by Gauss-Newton least squares on the template's gradients against the bicubically
resampled search window (a few hundredths of a pixel on textured ground, no pixel
locking). Ties whose offset from the prediction departs from the running median of
their neighbours are dropped (jitter varies over hundreds of lines, a blunder does
not). Every tie carries its a-priori ground point: CCD ``a``'s ray on the DEM.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from planetref.arrays import F64
from planetref.camera.jitter import stagger_lines, stagger_points

if TYPE_CHECKING:  # pragma: no cover
    from planetref.camera.base import Camera, Terrain
    from planetref.frontend.config import CcdOverlapConfig
    from planetref.raster.image import CcdImage

__all__ = [
    "OVERLAP_COLUMNS",
    "OverlapTies",
    "find_overlap_ties",
    "overlap_pairs",
    "read_overlap_ties",
    "write_overlap_ties",
]

OVERLAP_COLUMNS = (
    "point_id",
    "ccd_a",
    "ccd_b",
    "line_a",
    "sample_a",
    "line_b",
    "sample_b",
    "line_offset",
    "predicted_line_b",
    "predicted_sample_b",
    "score",
    "x_m",
    "y_m",
    "z_m",
)
"""Columns of ``<strip>/ccd_overlap_ties.csv`` (:func:`write_overlap_ties`)."""

log = logging.getLogger(__name__)


@dataclass
class OverlapTies:
    """Tie points between the overlapping CCDs of one strip (two observations each).

    Attributes:
        strip: The strip's id (both observations are of its camera).
        ccd: ``(T, 2)`` CCD names ``(a, b)``.
        line: ``(T, 2)`` raw lines in ``a`` and ``b`` (pixel centres at ``.5``).
        sample: ``(T, 2)`` raw samples.
        predicted: ``(T, 2)`` ``(line, sample)`` in ``b`` that the camera used for the
            search predicts for the point at ``(line, sample)`` of ``a``.
        xyz: ``(T, 3)`` a-priori body-fixed ground (m): ``a``'s ray on the DEM.
        score: ``(T,)`` NCC peak.
        pairs: Per pair ``"a~b"``: number of ties kept.
    """

    strip: str = ""
    ccd: NDArray[np.str_] = field(default_factory=lambda: np.zeros((0, 2), str))
    line: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    sample: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    predicted: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    xyz: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    score: F64 = field(default_factory=lambda: np.zeros(0))
    pairs: dict[str, int] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.score)

    @property
    def point_ids(self) -> list[str]:
        """Point ids ``"<strip>:ovl:<a>~<b>:<k>"``."""
        return [f"{self.strip}:ovl:{a}~{b}:{k}" for k, (a, b) in enumerate(self.ccd)]

    @property
    def line_offset(self) -> F64:
        """``line_b - line_a`` (lines): the stagger (times the line period: the time offset)."""
        return self.line[:, 1] - self.line[:, 0]

    @property
    def offset_from_prediction(self) -> F64:
        """``(T, 2)`` measured minus predicted ``(line, sample)`` in ``b`` (pixels)."""
        return np.column_stack([self.line[:, 1], self.sample[:, 1]]) - self.predicted

    def select(self, keep: NDArray[np.bool_]) -> OverlapTies:
        """The ties where ``keep`` is true (``pairs`` recounted)."""
        out = OverlapTies(
            self.strip,
            self.ccd[keep],
            self.line[keep],
            self.sample[keep],
            self.predicted[keep],
            self.xyz[keep],
            self.score[keep],
        )
        for a, b in out.ccd:
            out.pairs[f"{a}~{b}"] = out.pairs.get(f"{a}~{b}", 0) + 1
        return out


def overlap_pairs(
    camera: Camera, terrain: Terrain | float, margin_px: int
) -> list[tuple[str, str, float, float, float]]:
    """The CCD pairs whose images overlap, and where.

    CCD ``a``'s pixel centres (at its middle line) are projected into every later CCD
    ``b``; a pair overlaps where they land at least ``margin_px`` inside ``b``.

    Returns:
        ``(a, b, s0, s1, stagger_lines)``: the samples ``[s0, s1]`` of ``a`` that ``b``
        sees (with the margin) and the median ``line_b - line_a`` there.
    """
    names = list(camera.ccd_names)
    out = []
    for i, a in enumerate(names):
        n_lines, n_samples = camera.image_size(a)
        s = np.arange(0.5, n_samples, 1.0)
        ln = np.full(len(s), 0.5 * n_lines)
        for b in names[i + 1 :]:
            nb_lines, nb_samples = camera.image_size(b)
            lb, sb = stagger_lines(camera, a, b, ln, s, terrain)
            with np.errstate(invalid="ignore"):
                inside = (sb >= margin_px) & (sb <= nb_samples - margin_px)
                inside &= (lb >= 0) & (lb < nb_lines)
            if inside.sum() >= 2:
                out.append(
                    (
                        a,
                        b,
                        float(s[inside].min()),
                        float(s[inside].max()),
                        float(np.median(lb[inside] - ln[inside])),
                    )
                )
    return out


def _ncc_surface(tpl: F64, win: F64) -> F64:
    """NCC of ``tpl`` at every integer shift inside ``win`` (shape ``win - tpl + 1``)."""
    from numpy.lib.stride_tricks import sliding_window_view

    h, w = tpl.shape
    t = tpl - tpl.mean()
    tn = np.sqrt(np.sum(t * t))
    v = sliding_window_view(win, (h, w))  # (sy, sx, h, w)
    vm = v.mean(axis=(2, 3), keepdims=True)
    vc = v - vm
    num = np.einsum("ijhw,hw->ij", vc, t)
    den = np.sqrt(np.einsum("ijhw,ijhw->ij", vc, vc)) * tn
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / den, -1.0)


def _refine(tpl: F64, win: F64, y0: float, x0: float, iters: int = 4) -> tuple[float, float]:
    """Sub-pixel position of ``tpl`` in ``win`` near the integer shift ``(y0, x0)``.

    Gauss-Newton on ``sum (g * B(y + dy, x + dx) + o - T)^2`` with ``B`` resampled
    bicubically (gain ``g`` and offset ``o`` removed by normalising both sides).
    """
    from scipy.ndimage import map_coordinates, spline_filter

    h, w = tpl.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    t = (tpl - tpl.mean()) / (tpl.std() + 1e-12)
    coef = spline_filter(win, order=3, mode="nearest")  # once, not per sample call
    offsets = np.array([[0.0, 0.0], [0.5, 0.0], [-0.5, 0.0], [0.0, 0.5], [0.0, -0.5]])
    y, x = float(y0), float(x0)
    for _ in range(iters):
        base = np.array([(yy + y).ravel(), (xx + x).ravel()])
        coords = np.concatenate([base + o[:, None] for o in offsets], axis=1)
        vals = map_coordinates(coef, coords, order=3, mode="nearest", prefilter=False)
        b, yp, ym, xp, xm = vals.reshape(5, h * w)
        b = b.reshape(h, w)
        by, bx = yp - ym, xp - xm
        sd = b.std() + 1e-12
        r = ((b - b.mean()) / sd - t).ravel()
        jac = np.column_stack([by - by.mean(), bx - bx.mean()]) / sd
        n = jac.T @ jac
        if np.linalg.cond(n) > 1e8:
            break
        step = -np.linalg.solve(n, jac.T @ r)
        step = np.clip(step, -0.5, 0.5)
        y, x = y + float(step[0]), x + float(step[1])
        if np.max(np.abs(step)) < 1e-3:
            break
    return y, x


def _running_median(v: F64, half: int) -> F64:
    out = np.empty_like(v)
    for i in range(len(v)):
        out[i] = np.median(v[max(0, i - half) : i + half + 1])
    return out


def _match_pair(
    camera: Camera,
    a: str,
    b: str,
    img_a: CcdImage,
    img_b: CcdImage,
    terrain: Terrain | float,
    s_range: tuple[float, float],
    stagger: float,
    cfg: CcdOverlapConfig,
) -> tuple[F64, ...] | None:
    """Ties of one pair.

    Returns:
        ``(line_a, sample_a, line_b, sample_b, pred_line, pred_sample, xyz, score)``, or
        None when fewer than 3 templates match.
    """
    r = cfg.search_px
    hl = cfg.half_lines
    width = int(s_range[1] - s_range[0]) + 1  # samples of a that b sees
    hs = max(min(cfg.half_samples, width // 2 - r - 1), 2)
    s_c = int(np.floor(0.5 * (s_range[0] + s_range[1])))  # pixel index of the centre
    n_a, _ = camera.image_size(a)
    n_b, nb_s = camera.image_size(b)
    first = hl + r + 1 + max(0, int(np.ceil(-stagger)))
    last = n_a - hl - r - 2 - max(0, int(np.ceil(stagger)))
    if last <= first:
        return None
    rows = np.arange(first, last + 1, cfg.step_lines)
    la = rows + 0.5
    sa = np.full(len(rows), s_c + 0.5)
    pl, ps, xyz = stagger_points(camera, a, b, la, sa, terrain)
    # Column slabs of both images, read once.
    a0 = s_c - hs
    data_a, valid_a = img_a.read(0, a0, n_a, 2 * hs + 1)
    with np.errstate(invalid="ignore"):
        good_b = np.isfinite(ps)
    if not good_b.any():
        return None
    b_c = np.floor(ps[good_b]).astype(int)
    b0 = int(b_c.min()) - hs - r
    b1 = int(b_c.max()) + hs + r + 1
    data_b, valid_b = img_b.read(0, b0, n_b, b1 - b0)
    out_lb = np.full(len(rows), np.nan)
    out_sb = np.full(len(rows), np.nan)
    score = np.full(len(rows), np.nan)
    for k, row in enumerate(rows):
        if not (np.isfinite(pl[k]) and np.isfinite(ps[k])):  # NaN: missed or off b
            continue
        jl, js = int(np.floor(pl[k])), int(np.floor(ps[k]))
        if jl - hl - r < 0 or jl + hl + r >= n_b or js - hs - r < 0 or js + hs + r >= nb_s:
            continue
        tpl_v = valid_a[row - hl : row + hl + 1]
        c0 = js - hs - r - b0
        win_v = valid_b[jl - hl - r : jl + hl + r + 1, c0 : c0 + 2 * (hs + r) + 1]
        if not (tpl_v.all() and win_v.all()):
            continue
        tpl = data_a[row - hl : row + hl + 1].astype(np.float64)
        win = data_b[jl - hl - r : jl + hl + r + 1, c0 : c0 + 2 * (hs + r) + 1].astype(np.float64)
        if tpl.std() <= 0:
            continue
        surf = _ncc_surface(tpl, win)
        iy, ix = np.unravel_index(int(np.argmax(surf)), surf.shape)
        if not (0 < iy < surf.shape[0] - 1 and 0 < ix < surf.shape[1] - 1):
            continue  # the peak on the search's edge: outside the search radius
        y, x = _refine(tpl, win, float(iy), float(ix))
        if abs(y - iy) > 1.0 or abs(x - ix) > 1.0:
            continue
        out_lb[k] = jl - hl - r + y + hl + 0.5
        out_sb[k] = js - hs - r + x + hs + 0.5
        score[k] = surf[iy, ix]
    keep = np.isfinite(out_lb) & (score >= cfg.min_score)
    if keep.sum() < 3:
        return None
    la, sa, lb, sb = la[keep], sa[keep], out_lb[keep], out_sb[keep]
    pl, ps, xyz, score = pl[keep], ps[keep], xyz[keep], score[keep]
    # Blunders: far from their neighbours' running median offset from the prediction.
    good = np.ones(len(la), bool)
    for d in (lb - pl, sb - ps):
        med = _running_median(d, 5)
        dev = np.abs(d - med)
        sig = 1.4826 * np.median(dev)
        good &= ~((dev > cfg.max_deviation_px) & (dev > 4.0 * sig))
    sel = good
    return la[sel], sa[sel], lb[sel], sb[sel], pl[sel], ps[sel], xyz[sel], score[sel]


def find_overlap_ties(
    camera: Camera,
    images: dict[str, CcdImage],
    terrain: Terrain | float,
    cfg: CcdOverlapConfig,
    strip: str = "strip",
) -> OverlapTies:
    """Match tie points in the overlaps of a strip's neighbouring CCDs.

    Args:
        camera: The strip's camera (the initial one in a run: it predicts where to
            search; its smooth errors are shared by both CCDs over the stagger time).
        images: CCD name -> image.
        terrain: The reference DEM (or a height).
        cfg: :class:`~planetref.frontend.config.CcdOverlapConfig`.
        strip: The strip's id.

    Returns:
        The ties (possibly none), pair by pair, ``a`` before ``b`` in the camera's CCD
        order.
    """
    parts = []
    pairs: dict[str, int] = {}
    for a, b, s0, s1, stagger in overlap_pairs(camera, terrain, 0):
        if a not in images or b not in images:
            continue
        got = _match_pair(camera, a, b, images[a], images[b], terrain, (s0, s1), stagger, cfg)
        if got is None:
            log.info("strip %s: no CCD-overlap ties between %s and %s", strip, a, b)
            continue
        parts.append((a, b, got))
        pairs[f"{a}~{b}"] = len(got[0])
        log.info(
            "strip %s: %d CCD-overlap ties %s~%s (stagger %.1f lines)",
            strip,
            len(got[0]),
            a,
            b,
            stagger,
        )
    if not parts:
        return OverlapTies(strip=strip)
    return OverlapTies(
        strip=strip,
        ccd=np.concatenate([np.tile([a, b], (len(g[0]), 1)) for a, b, g in parts]).astype(str),
        line=np.concatenate([np.column_stack([g[0], g[2]]) for _, _, g in parts]),
        sample=np.concatenate([np.column_stack([g[1], g[3]]) for _, _, g in parts]),
        predicted=np.concatenate([np.column_stack([g[4], g[5]]) for _, _, g in parts]),
        xyz=np.concatenate([g[6] for _, _, g in parts]),
        score=np.concatenate([g[7] for _, _, g in parts]),
        pairs=pairs,
    )


def write_overlap_ties(ties: OverlapTies, path: str | os.PathLike[str]) -> Path:
    """Write the ties as CSV (:data:`OVERLAP_COLUMNS`; pixels and metres), atomically.

    ``line_offset`` is ``line_b - line_a`` (the stagger plus what the attitude did over
    it); ``predicted_*_b`` is where the camera of the search put the point in ``b``.
    """
    from planetref.runtime.atomic import write_text_atomic

    rows = [",".join(OVERLAP_COLUMNS)]
    for k, pid in enumerate(ties.point_ids):
        vals = (
            ties.line[k, 0],
            ties.sample[k, 0],
            ties.line[k, 1],
            ties.sample[k, 1],
            ties.line_offset[k],
            ties.predicted[k, 0],
            ties.predicted[k, 1],
            ties.score[k],
        )
        xyz = ",".join(f"{v:.3f}" for v in ties.xyz[k])
        rows.append(
            f"{pid},{ties.ccd[k, 0]},{ties.ccd[k, 1]},"
            + ",".join(f"{v:.4f}" for v in vals)
            + f",{xyz}"
        )
    return write_text_atomic(path, "\n".join(rows) + "\n")


def read_overlap_ties(path: str | os.PathLike[str], strip: str) -> OverlapTies:
    """Read ties written by :func:`write_overlap_ties` (``<strip>/ccd_overlap_ties.csv``).

    Raises:
        MissingFileError: No such file.
        InputError: A missing column or a bad value (naming the file).
    """
    import csv

    from planetref.errors import InputError, MissingFileError

    p = Path(path)
    if not p.is_file():
        raise MissingFileError("CCD-overlap tie file not found", path=p)
    with open(p, newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    missing = [c for c in OVERLAP_COLUMNS if rows and c not in rows[0]]
    if missing:
        raise InputError(f"missing column(s) {missing}", path=p)
    try:
        num = np.array(
            [[float(r[c]) for c in OVERLAP_COLUMNS[3:]] for r in rows], np.float64
        ).reshape(-1, len(OVERLAP_COLUMNS) - 3)
    except ValueError as exc:
        raise InputError(f"bad value: {exc}", path=p) from None
    out = OverlapTies(
        strip=strip,
        ccd=np.array([[r["ccd_a"], r["ccd_b"]] for r in rows], dtype=str).reshape(-1, 2),
        line=num[:, [0, 2]],
        sample=num[:, [1, 3]],
        predicted=num[:, 5:7],
        xyz=num[:, 8:11],
        score=num[:, 7],
    )
    for a, b in out.ccd:
        out.pairs[f"{a}~{b}"] = out.pairs.get(f"{a}~{b}", 0) + 1
    return out
