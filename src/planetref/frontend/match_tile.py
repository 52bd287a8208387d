"""Coarse-to-fine matching of CCD tiles against the reference orthoimage.

For one tile (:func:`match_tile`):

1. **Footprint**: the tile's border is projected onto the reference grid through the
   initial camera and the DEM (:func:`~planetref.frontend.tiles.tile_footprint`).
2. **Coarse stage**: the tile is brought to the reference geometry on a grid coarsened by
   ``coarse_factor`` and matched against a coarsened reference window padded by the
   a-priori uncertainty. Each match's displacement (actual minus predicted reference
   position) votes for the tile's offset; the offset is the median displacement of the
   largest consistent set (a translation consensus), so a few hundred metres of initial
   error cost nothing but a wider coarse window.
3. **Fine stage**: at full reference resolution against the footprint window shifted by
   the coarse offset and padded by ``fine_pad_ref_px``. The matches are verified with
   OpenCV USAC_MAGSAC (homography or affine) at ``ransac_threshold_ref_px``, then the
   inliers must agree on the tile's displacement within ``fine_radius_ref_px``.
4. **Back to raw**: every inlier's image-side keypoint maps back to raw ``(line, sample)``
   (exactly, through the DEM and the initial camera, for orthorectified tiles), its
   reference keypoint to reference map coordinates.

The result is a :class:`TileResult` with a status (``ok``, ``too_few_inliers``,
``no_overlap``, ``no_texture``, ``error``), the offsets, counts, timings and the inlier
correspondences. It serialises to JSON (:meth:`TileResult.to_dict`), which
:func:`match_strip` uses to journal finished tiles and resume a run by tile id.

Offsets are in full-resolution reference pixels, ``(dcol, drow)`` = actual minus
predicted position of the tile's content on the reference grid.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import sys
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from os import PathLike
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from planetref.camera.base import Camera, Terrain
from planetref.errors import InputError
from planetref.frontend.config import FrontendConfig
from planetref.frontend.orthorectify import ImageSide, downsample_tile, orthorectify
from planetref.frontend.tiles import Tile, TilePlan, plan_tiles, tile_footprint
from planetref.raster.image import CcdImage
from planetref.raster.ortho import ReferenceOrtho, RefWindow

__all__ = [
    "STATUSES",
    "StageDebug",
    "StripMatches",
    "TileResult",
    "TileStatus",
    "match_strip",
    "match_tile",
    "robust_translation",
    "verify_points",
]

TileStatus = Literal["ok", "too_few_inliers", "no_overlap", "no_texture", "error"]
STATUSES: tuple[str, ...] = ("ok", "too_few_inliers", "no_overlap", "no_texture", "error")
F64 = NDArray[np.float64]
_ARRAYS = ("line", "sample", "ref_col", "ref_row", "ref_x", "ref_y", "confidence")


@dataclass
class StageDebug:
    """The images and matches of one stage, kept for figures when asked for.

    Attributes:
        stage: ``"coarse"`` or ``"fine"``.
        image0: Image side (the CCD tile in the common geometry).
        valid0: Its validity mask.
        image1: Reference window.
        valid1: Its validity mask.
        keypoints0: ``(N, 2)`` ``(x, y)`` on ``image0`` (first pixel centre at 0.5).
        keypoints1: ``(N, 2)`` on ``image1``.
        inliers: ``(N,)`` the matches the stage kept.
    """

    stage: str
    image0: NDArray[np.float32]
    valid0: NDArray[np.bool_]
    image1: NDArray[np.float32]
    valid1: NDArray[np.bool_]
    keypoints0: F64
    keypoints1: F64
    inliers: NDArray[np.bool_]


def _empty() -> F64:
    return np.empty(0, np.float64)


@dataclass
class TileResult:
    """The outcome of matching one tile.

    Attributes:
        tile: The tile.
        matcher: Matcher name.
        status: One of :data:`STATUSES`.
        message: Why, for any status but ``ok``.
        geometry: ``"orthorectify"`` or ``"downsample"``.
        search_window: The fine reference window ``(col0, row0, width, height, factor)``.
        coarse_offset_px: Coarse offset ``(dcol, drow)``, reference px; None if the coarse
            stage did not run or found no consensus.
        offset_px: Fine offset (mean displacement of the verified inliers), reference px.
        offset_mad_px: Median absolute deviation of the inlier displacements, reference px.
        n_coarse_matches: Matches of the coarse stage.
        n_coarse_inliers: Of those, consistent with the coarse offset.
        n_matches: Matches of the fine stage.
        n_inliers: Fine matches that passed USAC_MAGSAC.
        line: Raw line of each kept inlier (first pixel centre at 0.5).
        sample: Raw sample of each kept inlier.
        ref_col: Reference column of each kept inlier (full resolution).
        ref_row: Reference row.
        ref_x: Reference map x (CRS units).
        ref_y: Reference map y.
        confidence: Matcher confidence of each kept inlier.
        timings: Seconds per step (``footprint``, ``coarse_prepare``, ``coarse_match``,
            ``fine_prepare``, ``fine_match``, ``verify``, ``backmap``, ``forward``,
            ``total``).
        debug: Stage images and matches (only when asked for; never serialised).
    """

    tile: Tile
    matcher: str
    status: TileStatus
    message: str = ""
    geometry: str = "orthorectify"
    search_window: tuple[int, ...] | None = None
    coarse_offset_px: tuple[float, float] | None = None
    offset_px: tuple[float, float] | None = None
    offset_mad_px: tuple[float, float] | None = None
    n_coarse_matches: int = 0
    n_coarse_inliers: int = 0
    n_matches: int = 0
    n_inliers: int = 0
    line: F64 = field(default_factory=_empty)
    sample: F64 = field(default_factory=_empty)
    ref_col: F64 = field(default_factory=_empty)
    ref_row: F64 = field(default_factory=_empty)
    ref_x: F64 = field(default_factory=_empty)
    ref_y: F64 = field(default_factory=_empty)
    confidence: F64 = field(default_factory=_empty)
    timings: dict[str, float] = field(default_factory=dict)
    debug: list[StageDebug] = field(default_factory=list, repr=False)

    @property
    def tile_id(self) -> str:
        """The tile's id."""
        return self.tile.tile_id

    @property
    def n_points(self) -> int:
        """Number of kept correspondences (the tile's NCP when the status is ``ok``)."""
        return len(self.line)

    def to_dict(self) -> dict[str, Any]:
        """A JSON-serialisable dict (arrays as lists; ``debug`` left out)."""
        doc: dict[str, Any] = {
            "tile": self.tile.to_dict(),
            "matcher": self.matcher,
            "status": self.status,
            "message": self.message,
            "geometry": self.geometry,
            "search_window": None if self.search_window is None else list(self.search_window),
            "coarse_offset_px": _opt_pair(self.coarse_offset_px),
            "offset_px": _opt_pair(self.offset_px),
            "offset_mad_px": _opt_pair(self.offset_mad_px),
            "n_coarse_matches": self.n_coarse_matches,
            "n_coarse_inliers": self.n_coarse_inliers,
            "n_matches": self.n_matches,
            "n_inliers": self.n_inliers,
            "timings": {k: float(v) for k, v in self.timings.items()},
        }
        for name in _ARRAYS:
            doc[name] = [float(v) for v in getattr(self, name)]
        return doc

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> TileResult:
        """Inverse of :meth:`to_dict`.

        Raises:
            InputError: If a field is missing or malformed.
        """
        try:
            status = str(doc["status"])
            if status not in STATUSES:
                raise InputError(f"unknown tile status {status!r}", field="status")
            win = doc.get("search_window")
            out = cls(
                tile=Tile.from_dict(doc["tile"]),
                matcher=str(doc["matcher"]),
                status=status,  # type: ignore[arg-type]
                message=str(doc.get("message", "")),
                geometry=str(doc.get("geometry", "orthorectify")),
                search_window=None if win is None else tuple(int(v) for v in win),
                coarse_offset_px=_opt_pair(doc.get("coarse_offset_px")),
                offset_px=_opt_pair(doc.get("offset_px")),
                offset_mad_px=_opt_pair(doc.get("offset_mad_px")),
                n_coarse_matches=int(doc.get("n_coarse_matches", 0)),
                n_coarse_inliers=int(doc.get("n_coarse_inliers", 0)),
                n_matches=int(doc.get("n_matches", 0)),
                n_inliers=int(doc.get("n_inliers", 0)),
                timings={str(k): float(v) for k, v in doc.get("timings", {}).items()},
            )
            for name in _ARRAYS:
                setattr(out, name, np.asarray(doc.get(name, []), np.float64).reshape(-1))
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, InputError):
                raise
            raise InputError(f"malformed tile result ({exc!r})") from None
        if len({len(getattr(out, n)) for n in _ARRAYS}) != 1:
            raise InputError("tile result arrays differ in length")
        return out


def _opt_pair(v: Any) -> tuple[float, float] | None:
    if v is None:
        return None
    a, b = v
    return (float(a), float(b))


# --------------------------------------------------------------------------- robust fits


def robust_translation(
    displacement: F64, radius: float, weights: F64 | None = None
) -> tuple[F64 | None, NDArray[np.bool_]]:
    """The dominant translation among displacement vectors (a translation consensus).

    Each displacement is a candidate; the one with the most displacements within
    ``radius`` wins (ties: the larger summed weight), and the offset is the median of its
    consensus set, refined once.

    Args:
        displacement: ``(N, 2)`` vectors (e.g. reference pixels).
        radius: Consensus radius, same unit.
        weights: Optional ``(N,)`` tie-breaking weights (e.g. confidences).

    Returns:
        ``(offset, inliers)``: the ``(2,)`` offset (None when there is no displacement)
        and the ``(N,)`` mask of displacements within ``radius`` of it.
    """
    d = np.asarray(displacement, np.float64).reshape(-1, 2)
    n = len(d)
    if n == 0:
        return None, np.zeros(0, bool)
    w = np.ones(n) if weights is None else np.asarray(weights, np.float64)
    # Candidates: every displacement up to 2000 (evenly strided beyond); chunked so the
    # pairwise distance matrix stays small.
    cand = np.arange(n) if n <= 2000 else np.linspace(0, n - 1, 2000).astype(np.intp)
    best, best_score = -1, (-1, -np.inf)
    r2 = radius * radius
    for a in range(0, len(cand), 256):
        c = cand[a : a + 256]
        dist2 = np.sum((d[c][:, None, :] - d[None, :, :]) ** 2, axis=-1)
        close = dist2 <= r2
        counts = close.sum(axis=1)
        wsum = (close * w[None, :]).sum(axis=1)
        for i in np.flatnonzero(counts == counts.max()):
            score = (int(counts[i]), float(wsum[i]))
            if score > best_score:
                best, best_score = int(c[i]), score
    inl = np.sum((d - d[best]) ** 2, axis=1) <= r2
    offset = np.median(d[inl], axis=0)
    inl = np.sum((d - offset) ** 2, axis=1) <= r2
    if inl.any():
        offset = np.median(d[inl], axis=0)
    return offset, inl


def verify_points(
    points0: F64,
    points1: F64,
    model: str = "homography",
    threshold: float = 1.0,
    confidence: float = 0.999,
    max_iters: int = 10000,
) -> NDArray[np.bool_]:
    """Geometric verification of point pairs with OpenCV's USAC_MAGSAC.

    A thin layer over :func:`planetref.matching.ransac.verify_matches` that centres the
    coordinates first (reference pixels of a large mosaic are big numbers) and keeps only
    the inliers whose residual under the fitted model is within ``threshold``.

    Args:
        points0: ``(N, 2)`` points in image 0.
        points1: ``(N, 2)`` points in image 1.
        model: ``"homography"`` (needs 4 matches) or ``"affine"`` (3).
        threshold: Inlier threshold in image-1 pixels.
        confidence: RANSAC confidence.
        max_iters: Iteration cap.

    Returns:
        ``(N,)`` inlier mask; all False when there are too few matches or no model.
    """
    from planetref.matching.base import Matches
    from planetref.matching.ransac import verify_matches

    p0 = np.asarray(points0, np.float64).reshape(-1, 2)
    p1 = np.asarray(points1, np.float64).reshape(-1, 2)
    n = len(p0)
    if n == 0:
        return np.zeros(0, bool)
    c0, c1 = p0.mean(axis=0), p1.mean(axis=0)
    ver = verify_matches(
        Matches(p0 - c0, p1 - c1, np.ones(n)),
        model,  # type: ignore[arg-type]
        threshold=float(threshold),
        confidence=float(confidence),
        max_iters=int(max_iters),
    )
    if ver.matrix is None:
        return np.zeros(n, bool)
    m = np.asarray(ver.matrix, np.float64)
    if m.shape == (2, 3):
        m = np.vstack([m, [0.0, 0.0, 1.0]])
    q = np.column_stack([p0 - c0, np.ones(n)]) @ m.T
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = q[:, :2] / q[:, 2:3]
    resid = np.linalg.norm(proj - (p1 - c1), axis=1)
    return ver.inliers & (resid <= threshold)


def _spread_select(line: F64, sample: F64, conf: F64, n_max: int) -> NDArray[np.intp]:
    """Up to ``n_max`` indices spread over the points' extent, best confidence first."""
    n = len(line)
    if n_max <= 0 or n <= n_max:
        return np.arange(n)
    g = max(1, int(np.ceil(np.sqrt(n_max))))

    def cell(v: F64) -> NDArray[np.intp]:
        lo, hi = float(v.min()), float(v.max())
        return np.minimum(((v - lo) / max(hi - lo, 1e-9) * g).astype(np.intp), g - 1)

    cid = cell(line) * g + cell(sample)
    order = np.lexsort((-conf, cid))
    rank = np.empty(n, np.intp)
    # Rank within the cell: round-robin over cells keeps the spread.
    sorted_cid = cid[order]
    starts = np.r_[0, np.flatnonzero(np.diff(sorted_cid)) + 1]
    run = np.arange(n) - np.repeat(starts, np.diff(np.r_[starts, n]))
    rank[order] = run
    pick = np.lexsort((-conf, rank))[:n_max]
    return np.sort(pick)


def _flat(image: NDArray[np.float32], valid: NDArray[np.bool_]) -> bool:
    v = image[valid]
    if v.size < 16:
        return True
    lo, hi = np.percentile(v, [0.5, 99.5])
    return not (hi - lo) > 1e-6 * max(abs(float(lo)), abs(float(hi))) + 1e-30


# --------------------------------------------------------------------------- one tile


@contextlib.contextmanager
def _timed(timings: dict[str, float], key: str) -> Iterator[None]:
    t0 = time.perf_counter()
    try:
        yield
    finally:
        timings[key] = timings.get(key, 0.0) + time.perf_counter() - t0


def _inference() -> contextlib.AbstractContextManager[Any]:
    # Only when the matcher already brought torch in: importing it here would cost
    # seconds for matchers that do not need it.
    torch = sys.modules.get("torch")
    if torch is not None:
        return torch.inference_mode()
    return contextlib.nullcontext()


def _image_side(
    stage_factor: int,
    window: RefWindow,
    *,
    image: CcdImage,
    camera: Camera,
    tile: Tile,
    ref: ReferenceOrtho,
    terrain: Terrain,
    config: FrontendConfig,
    ratio: float,
) -> ImageSide:
    if config.geometry == "orthorectify":
        # The whole image may fill the window: matches outside the tile are dropped when
        # mapped back, and the real neighbourhood beats a no-data border for matching.
        return orthorectify(
            image, camera, tile.ccd, ref, terrain, window, lattice_step=config.lattice_step_ref_px
        )
    return downsample_tile(image, tile, max(1, round(ratio * stage_factor)), camera, ref, terrain)


@dataclass
class _Stage:
    kp0: F64
    kp1: F64
    conf: F64
    predicted: F64
    actual: F64


def _match_stage(
    side: ImageSide,
    ref_img: NDArray[np.float32],
    ref_valid: NDArray[np.bool_],
    ref_window: RefWindow,
    matcher: Any,
    timings: dict[str, float],
    key: str,
) -> _Stage:
    t0 = time.perf_counter()
    with _inference():
        m = matcher.match(side.image, ref_img, side.valid, ref_valid)
    elapsed = time.perf_counter() - t0
    timings[key] = timings.get(key, 0.0) + elapsed
    fwd = getattr(matcher, "timings", {}) or {}
    timings["forward"] = timings.get("forward", 0.0) + float(fwd.get("forward", elapsed))
    kp0 = np.asarray(m.keypoints0, np.float64).reshape(-1, 2)
    kp1 = np.asarray(m.keypoints1, np.float64).reshape(-1, 2)
    conf = np.asarray(m.confidence, np.float64).reshape(-1)
    pc, pr = side.predicted_ref_pixel(kp0[:, 0], kp0[:, 1])
    ac, ar = ref_window.to_ref_pixel(kp1[:, 0], kp1[:, 1])
    return _Stage(kp0, kp1, conf, np.column_stack([pc, pr]), np.column_stack([ac, ar]))


def _valid_fraction(valid: NDArray[np.bool_]) -> float:
    return float(valid.mean()) if valid.size else 0.0


def _unmatchable(
    side: ImageSide,
    ref_img: NDArray[np.float32],
    ref_valid: NDArray[np.bool_],
    share: float,
    cfg: FrontendConfig,
) -> tuple[TileStatus, str] | None:
    """Why a stage's pair cannot be matched (status and message), or None."""
    f_img, f_ref = _valid_fraction(side.valid), _valid_fraction(ref_valid)
    if f_img < cfg.min_valid_fraction * share:
        return (
            "no_overlap",
            f"only {100 * f_img:.1f}% of the window has valid tile pixels "
            "in the reference geometry",
        )
    if f_ref < cfg.min_valid_fraction:
        return ("no_overlap", f"only {100 * f_ref:.1f}% of the reference window has data")
    if _flat(side.image, side.valid) or _flat(ref_img, ref_valid):
        return ("no_texture", "the tile or its reference window has no contrast")
    return None


def _area_share(inner: RefWindow, outer: RefWindow, cfg: FrontendConfig) -> float:
    """Share of ``outer``'s area that ``inner`` (the footprint box) covers."""
    if cfg.geometry != "orthorectify":
        return 1.0  # the image side is the raw tile itself
    a = inner.width * inner.height * inner.factor**2
    b = outer.width * outer.height * outer.factor**2
    return min(1.0, a / b) if b else 1.0


def match_tile(
    tile: Tile,
    *,
    image: CcdImage,
    camera: Camera,
    ref: ReferenceOrtho,
    terrain: Terrain,
    matcher: Any,
    config: FrontendConfig | None = None,
    ratio: float | None = None,
    debug: bool = False,
    coarse_matcher: Any = None,
) -> TileResult:
    """Match one CCD tile against the reference, coarse to fine.

    Args:
        tile: The tile (from :func:`~planetref.frontend.tiles.plan_tiles`).
        image: Reader of the tile's CCD image.
        camera: The initial camera.
        ref: The reference orthoimage.
        terrain: The reference DEM.
        matcher: Any :class:`~planetref.matching.base.Matcher`.
        config: Front-end settings (default: ``FrontendConfig()``).
        ratio: Image pixels per reference pixel (default: measured at the tile centre);
            only the ``downsample`` geometry uses it.
        debug: Keep the stage images and matches in ``result.debug`` (for figures).
        coarse_matcher: Matcher of the coarse stage (default: ``matcher``), e.g. an
            area-based matcher with a search radius as large as the uncertainty.

    Returns:
        The tile's result. Geometric failures become statuses, not exceptions.
    """
    cfg = config or FrontendConfig()
    name = str(getattr(matcher, "name", type(matcher).__name__))
    timings: dict[str, float] = {}
    t_start = time.perf_counter()
    res = TileResult(tile=tile, matcher=name, status="ok", geometry=cfg.geometry)

    def finish(status: TileStatus, message: str = "") -> TileResult:
        res.status = status
        res.message = message
        timings["total"] = time.perf_counter() - t_start
        res.timings = timings
        return res

    with _timed(timings, "footprint"):
        fp = tile_footprint(camera, tile, ref, terrain, cfg.footprint_points_per_edge)
    if fp.window is None:
        return finish("no_overlap", "no ray of the tile's border meets the DEM")
    base = fp.window
    if ratio is None and cfg.geometry == "downsample":
        from planetref.frontend.geometry import image_gsd_m

        lc, sc = tile.centre
        ratio = float(np.sqrt(fp.gsd_m[0] * fp.gsd_m[1])) / image_gsd_m(
            camera, tile.ccd, terrain, lc, sc
        )
    ratio = float(ratio or 1.0)
    pad_unc = fp.pad_px(cfg.uncertainty_m)
    rows, cols = ref.shape
    c0, r0, c1, r1 = base.padded(pad_unc).bounds_px
    if c1 <= 0 or r1 <= 0 or c0 >= cols or r0 >= rows:
        return finish("no_overlap", "the tile's search window lies outside the reference")
    side_kw = dict(
        image=image, camera=camera, tile=tile, ref=ref, terrain=terrain, config=cfg, ratio=ratio
    )

    # ---- coarse stage
    # Orthorectified tiles are resampled onto the very window of the reference they are
    # matched with, so the expected displacement between the two arrays is just the
    # initial error: area-based matchers with a bounded search work as well as the rest.
    coarse_offset: F64 | None = None
    if cfg.coarse:
        f = cfg.coarse_factor
        with _timed(timings, "coarse_prepare"):
            cwin = RefWindow.around(*base.bounds_px, pad_px=pad_unc + cfg.fine_pad_ref_px, factor=f)
            side = _image_side(f, cwin, **side_kw)
            cref, cvalid = ref.read(cwin)
        problem = _unmatchable(side, cref, cvalid, _area_share(base, cwin, cfg), cfg)
        if problem is not None:
            return finish(*problem)
        st = _match_stage(
            side, cref, cvalid, cwin, coarse_matcher or matcher, timings, "coarse_match"
        )
        res.n_coarse_matches = len(st.kp0)
        disp = st.actual - st.predicted
        ok = np.all(np.isfinite(disp), axis=1)
        offset, inl = robust_translation(disp[ok], cfg.coarse_radius_ref_px, st.conf[ok])
        full_inl = np.zeros(len(disp), bool)
        full_inl[np.flatnonzero(ok)] = inl
        res.n_coarse_inliers = int(full_inl.sum())
        if offset is not None and res.n_coarse_inliers >= cfg.coarse_min_matches:
            coarse_offset = offset
            res.coarse_offset_px = (float(offset[0]), float(offset[1]))
        if debug:
            res.debug.append(
                StageDebug("coarse", side.image, side.valid, cref, cvalid, st.kp0, st.kp1, full_inl)
            )

    # ---- fine stage
    with _timed(timings, "fine_prepare"):
        pad = cfg.fine_pad_ref_px if coarse_offset is not None else pad_unc + cfg.fine_pad_ref_px
        iwin = base.padded(pad)
        fwin = iwin if coarse_offset is None else iwin.shifted(coarse_offset[0], coarse_offset[1])
        side = _image_side(1, iwin, **side_kw)
        fref, fvalid = ref.read(fwin)
    res.search_window = fwin.to_tuple()
    problem = _unmatchable(side, fref, fvalid, _area_share(base, iwin, cfg), cfg)
    if problem is not None:
        return finish(*problem)
    st = _match_stage(side, fref, fvalid, fwin, matcher, timings, "fine_match")
    res.n_matches = len(st.kp0)
    with _timed(timings, "verify"):
        ok = np.all(np.isfinite(st.predicted), axis=1)
        src = st.predicted if cfg.geometry == "orthorectify" else st.kp0
        inl = np.zeros(len(st.kp0), bool)
        inl[ok] = verify_points(
            src[ok],
            st.actual[ok],
            cfg.ransac_model,
            cfg.ransac_threshold_ref_px,
            cfg.ransac_confidence,
            cfg.ransac_max_iters,
        )
        if inl.any():
            # True matches of one tile share (nearly) one displacement; a homography
            # fitted to wrong matches does not, whatever its residuals.
            idx = np.flatnonzero(inl)
            _, cons = robust_translation(
                (st.actual - st.predicted)[idx], cfg.fine_radius_ref_px, st.conf[idx]
            )
            inl[idx[~cons]] = False
    res.n_inliers = int(inl.sum())
    if debug:
        res.debug.append(
            StageDebug("fine", side.image, side.valid, fref, fvalid, st.kp0, st.kp1, inl)
        )
    if res.n_inliers:
        disp = (st.actual - st.predicted)[inl]
        # The mean, not the median: the inliers are verified already, and detectors that
        # report integer pixel positions make the median jump by whole pixels.
        off = np.mean(disp, axis=0)
        mad = np.median(np.abs(disp - np.median(disp, axis=0)), axis=0)
        res.offset_px = (float(off[0]), float(off[1]))
        res.offset_mad_px = (float(mad[0]), float(mad[1]))
    if res.n_inliers < cfg.min_inliers:
        coarse_note = (
            ""
            if not cfg.coarse or coarse_offset is not None
            else f" (no coarse consensus: {res.n_coarse_inliers} of {res.n_coarse_matches})"
        )
        return finish(
            "too_few_inliers",
            f"{res.n_inliers} inliers of {res.n_matches} "
            f"matches, {cfg.min_inliers} needed{coarse_note}",
        )

    with _timed(timings, "backmap"):
        idx = np.flatnonzero(inl)
        line, sample, good = side.to_raw(st.kp0[idx, 0], st.kp0[idx, 1])
        good &= tile.contains(line, sample)
        idx, line, sample = idx[good], line[good], sample[good]
        conf = st.conf[idx]
        keep = _spread_select(line, sample, conf, cfg.max_mcps_per_tile)
        idx, line, sample, conf = idx[keep], line[keep], sample[keep], conf[keep]
        ref_col, ref_row = st.actual[idx, 0], st.actual[idx, 1]
        ref_x, ref_y = ref.pixel_to_map(ref_col, ref_row)
    res.line, res.sample, res.confidence = line, sample, conf
    res.ref_col, res.ref_row = ref_col, ref_row
    res.ref_x, res.ref_y = np.asarray(ref_x, np.float64), np.asarray(ref_y, np.float64)
    if len(line) < cfg.min_inliers:
        return finish(
            "too_few_inliers",
            f"{len(line)} inliers map back into the tile, {cfg.min_inliers} needed",
        )
    return finish("ok")


# --------------------------------------------------------------------------- a strip


@dataclass
class StripMatches:
    """Tile results of a strip (all CCDs).

    Attributes:
        matcher: Matcher name.
        config: The front-end settings.
        plans: Tile plan per CCD.
        tiles: One result per tile, in plan order.
    """

    matcher: str
    config: FrontendConfig
    plans: dict[str, TilePlan]
    tiles: list[TileResult]

    def status_counts(self) -> dict[str, int]:
        """Number of tiles per status (every status listed)."""
        out = dict.fromkeys(STATUSES, 0)
        for t in self.tiles:
            out[t.status] += 1
        return out

    def ncp_per_tile(self) -> dict[str, int]:
        """Kept correspondences of each ``ok`` tile (0 for the others)."""
        return {t.tile_id: (t.n_points if t.status == "ok" else 0) for t in self.tiles}

    def ncp_per_ccd(self) -> dict[str, int]:
        """Kept correspondences per CCD over its ``ok`` tiles."""
        out = dict.fromkeys(self.plans, 0)
        for t in self.tiles:
            if t.status == "ok":
                out[t.tile.ccd] = out.get(t.tile.ccd, 0) + t.n_points
        return out


def _config_digest(matcher: str, cfg: FrontendConfig) -> str:
    text = json.dumps({"matcher": matcher, "config": cfg.model_dump()}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _read_journal(path: Path, digest: str) -> dict[str, TileResult]:
    done: dict[str, TileResult] = {}
    if not path.exists():
        return done
    with path.open("r", encoding="utf-8") as fh:
        lines = fh.readlines()
    for i, raw in enumerate(lines):
        if not raw.strip():
            continue
        try:
            doc = json.loads(raw)
        except json.JSONDecodeError:
            if i == len(lines) - 1:
                break  # a line cut short by an interrupted run
            raise InputError(f"line {i + 1} is not JSON", path=path) from None
        if doc.get("digest") != digest:
            raise InputError(
                "the journal was written with another matcher or config "
                f"(digest {doc.get('digest')}, expected {digest}); use a new "
                "journal file",
                path=path,
            )
        res = TileResult.from_dict(doc["result"])
        done[res.tile_id] = res
    return done


def match_strip(
    camera: Camera,
    images: Mapping[str, CcdImage | str | PathLike[str]],
    ref: ReferenceOrtho | str | PathLike[str],
    terrain: Terrain | str | PathLike[str],
    matcher: Any,
    config: FrontendConfig | None = None,
    *,
    ccds: Sequence[str] | None = None,
    journal: str | PathLike[str] | None = None,
    progress: bool = True,
    raise_errors: bool = False,
    debug_tiles: Sequence[str] = (),
    coarse_matcher: Any = None,
    executor: Any = None,
    sources: Any = None,
) -> StripMatches:
    """Match every tile of every CCD image of a strip against the reference.

    Rasters are only read through windows (one tile at a time), so memory stays bounded
    by the tile size whatever the image size.

    Args:
        camera: The initial camera of the strip (all CCDs).
        images: CCD name -> image reader or path.
        ref: The reference orthoimage (reader or path).
        terrain: The reference DEM (a terrain, or a GeoTIFF path read as
            :class:`~planetref.raster.dem.GridTerrain`).
        matcher: Any :class:`~planetref.matching.base.Matcher`.
        config: Front-end settings.
        ccds: CCDs to match (default: every CCD of ``images`` that the camera knows, in
            the camera's order).
        journal: A JSON-lines file: tiles already in it are not matched again (resume),
            each new tile is appended when done.
        progress: Show a tqdm progress bar.
        raise_errors: Re-raise exceptions of a tile instead of recording status ``error``.
        debug_tiles: Tile ids whose stage images are kept (``result.debug``).
        coarse_matcher: Matcher of the coarse stage (default: ``matcher``).
        executor: A :class:`planetref.execute.Executor` for the tiles (default: in this
            process, one after another). A parallel one sends each worker only ``sources``
            and the tile; results are journalled as they arrive, and the strip's results
            are in plan order whatever the executor. ``debug_tiles`` are matched here.
        sources: A :class:`planetref.execute.TileSources` (paths and matcher spec of
            these very inputs); required by a parallel ``executor``.

    Returns:
        The strip's tile results.

    Raises:
        InputError: Unknown CCD names, a journal of another matcher/config, or a parallel
            executor without ``sources``.
    """
    from tqdm.auto import tqdm

    cfg = config or FrontendConfig()
    name = str(getattr(matcher, "name", type(matcher).__name__))
    known = tuple(camera.ccd_names)
    unknown = sorted(set(images) - set(known))
    if unknown:
        raise InputError(f"images given for unknown CCDs {unknown}; the camera has {list(known)}")
    todo_ccds = [c for c in known if c in images] if ccds is None else list(ccds)
    missing = [c for c in todo_ccds if c not in images]
    if missing:
        raise InputError(f"no image for CCDs {missing}")

    opened: list[Any] = []
    try:
        if not isinstance(ref, ReferenceOrtho):
            ref = ReferenceOrtho(ref)
            opened.append(ref)
        if isinstance(terrain, str | PathLike):
            from planetref.raster.dem import GridTerrain

            terrain = GridTerrain.from_geotiff(terrain)
        readers: dict[str, CcdImage] = {}
        for c in todo_ccds:
            src = images[c]
            if isinstance(src, CcdImage):
                readers[c] = src
            else:
                readers[c] = CcdImage(src)
                opened.append(readers[c])
            if readers[c].shape != tuple(camera.image_size(c)):
                raise InputError(
                    f"CCD {c!r}: image is {readers[c].shape} (lines, samples) "
                    f"but the camera says {tuple(camera.image_size(c))}"
                )

        plans = {c: plan_tiles(camera, c, ref, terrain, cfg) for c in todo_ccds}
        digest = _config_digest(name, cfg)
        jpath = None if journal is None else Path(journal)
        done = _read_journal(jpath, digest) if jpath is not None else {}
        all_tiles = [t for c in todo_ccds for t in plans[c].tiles]
        results: dict[str, TileResult] = {
            t.tile_id: done[t.tile_id] for t in all_tiles if t.tile_id in done
        }
        pending = [t for t in all_tiles if t.tile_id not in results]
        fh = None
        if jpath is not None:
            jpath.parent.mkdir(parents=True, exist_ok=True)
            fh = jpath.open("a", encoding="utf-8")

        def match_here(t: Tile) -> TileResult:
            try:
                return match_tile(
                    t,
                    image=readers[t.ccd],
                    camera=camera,
                    ref=ref,
                    terrain=terrain,
                    matcher=matcher,
                    config=cfg,
                    ratio=plans[t.ccd].ratio,
                    debug=t.tile_id in debug_tiles,
                    coarse_matcher=coarse_matcher,
                )
            except Exception as exc:
                if raise_errors:
                    raise
                return _error_result(t, name, cfg, exc)

        def record(r: TileResult) -> None:
            results[r.tile_id] = r
            if fh is not None:
                fh.write(json.dumps({"digest": digest, "result": r.to_dict()}) + "\n")
                fh.flush()
                os.fsync(fh.fileno())

        try:
            if executor is not None and getattr(executor, "parallel", False):
                _match_parallel(
                    executor,
                    sources,
                    pending,
                    plans,
                    cfg,
                    name,
                    match_here,
                    record,
                    raise_errors,
                    progress,
                    debug_tiles,
                    results,
                )
            else:
                bar = tqdm(
                    pending,
                    desc=f"matching ({name})",
                    unit="tile",
                    disable=None if progress else True,
                )
                for t in bar:
                    record(match_here(t))
                    bar.set_postfix(ok=sum(x.status == "ok" for x in results.values()))
        finally:
            if fh is not None:
                fh.close()
        return StripMatches(name, cfg, plans, [results[t.tile_id] for t in all_tiles])
    finally:
        for obj in opened:
            obj.close()


def _error_result(t: Tile, name: str, cfg: FrontendConfig, exc: BaseException) -> TileResult:
    return TileResult(
        tile=t,
        matcher=name,
        status="error",
        message=f"{type(exc).__name__}: {exc}",
        geometry=cfg.geometry,
    )


def _match_parallel(
    executor: Any,
    sources: Any,
    pending: list[Tile],
    plans: Mapping[str, TilePlan],
    cfg: FrontendConfig,
    name: str,
    match_here: Any,
    record: Any,
    raise_errors: bool,
    progress: bool,
    debug_tiles: Sequence[str],
    results: Mapping[str, TileResult],
) -> None:
    """The pending tiles of :func:`match_strip` on a parallel executor.

    Each result is recorded (and journalled) as it arrives; ``debug_tiles`` are matched
    here with ``match_here`` (their stage images do not travel).
    """
    from tqdm.auto import tqdm

    from planetref.execute import TileSources, run_tile_task

    if not isinstance(sources, TileSources):
        raise InputError(
            f"the {executor.name} executor needs sources= (a TileSources with "
            "the camera, image, reference and DEM paths and the matcher spec)"
        )
    lacking = sorted({t.ccd for t in pending} - {c for c, _ in sources.images})
    if lacking:
        raise InputError(f"sources= has no image path for CCDs {lacking}")
    if sources.matcher != name:
        raise InputError(f"sources= names matcher {sources.matcher!r} but the matcher is {name!r}")
    debug = set(debug_tiles)
    remote = [t for t in pending if t.tile_id not in debug]
    key = sources.key()
    config = cfg.model_dump()
    tasks = [
        {
            "sources": key,
            "tile": t.to_dict(),
            "config": config,
            "ratio": plans[t.ccd].ratio,
            "raise_errors": raise_errors,
        }
        for t in remote
    ]
    bar = tqdm(
        total=len(pending),
        desc=f"matching ({name}, {executor.name})",
        unit="tile",
        disable=None if progress else True,  # None: off when stderr is no terminal
    )
    try:
        for t in pending:
            if t.tile_id in debug:
                record(match_here(t))
                bar.update(1)
        for out in executor.map_unordered(run_tile_task, tasks):
            t = remote[out.index]
            if out.error is not None:
                if raise_errors:
                    raise out.error
                record(_error_result(t, name, cfg, out.error))
            else:
                record(TileResult.from_dict(out.result))
            bar.update(1)
            bar.set_postfix(ok=sum(x.status == "ok" for x in results.values()))
    finally:
        bar.close()
