"""The tile algorithm: coarse-to-fine matching of one CCD tile against the reference orthoimage.

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

   With ``fine_recentre`` (default), the fine stage runs a second time on the reference
   window resampled at the first pass's offset to a fraction of a pixel, so that the
   matcher sees (almost) no displacement between the two windows; its matches are kept.
5. **Refinement** (optional, ``refine``): every kept match is refined to sub-pixel
   precision on the fine-stage images (:func:`planetref.matching.refine.refine_matches`),
   the same way for every matcher; matches whose refinement diverges are dropped.
6. **Thinning** (optional, ``max_mcps_per_tile``), for speed only.

The result is a :class:`~planetref.frontend.result.TileResult` with a status (``ok``,
``too_few_inliers``, ``no_overlap``, ``no_texture``, ``error``), the offsets, the funnel
(how many correspondences each step kept, and why the others were dropped), timings and
the kept correspondences.

Offsets are in full-resolution reference pixels, ``(dcol, drow)`` = actual minus
predicted position of the tile's content on the reference grid.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Generator, Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from planetref.arrays import F64
from planetref.camera.base import Camera, Terrain
from planetref.frontend.batched import (
    StageAnswer,
    StageRequest,
    TileSteps,
    inference_mode,
    run_steps,
)
from planetref.frontend.coarse import COARSE_FALLBACK_MATCHER, coarse_fallback_matcher
from planetref.frontend.config import FrontendConfig
from planetref.frontend.grid import FineWindow, read_fine
from planetref.frontend.orthorectify import (
    ImageSide,
    downsample_tile,
    lattice_cache,
    orthorectify,
)
from planetref.frontend.result import StageDebug, TileResult, TileStatus
from planetref.frontend.robust import robust_translation, spread_select, verify_points
from planetref.frontend.tiles import Tile, tile_footprint
from planetref.matching.base import BaseMatcher, Matcher
from planetref.raster.image import CcdImage
from planetref.raster.ortho import ReferenceOrtho, RefWindow

__all__ = ["TileInputs", "inference_mode", "match_tile", "tile_steps"]


def _flat(image: NDArray[np.float32], valid: NDArray[np.bool_]) -> bool:
    v = image[valid]  # a copy: the percentiles may reorder it (same values)
    if v.size < 16:
        return True
    lo, hi = np.percentile(v, [0.5, 99.5], overwrite_input=True)
    return not (hi - lo) > 1e-6 * max(abs(float(lo)), abs(float(hi))) + 1e-30


# --------------------------------------------------------------------------- one tile


@contextlib.contextmanager
def _timed(timings: dict[str, float], key: str) -> Iterator[None]:
    t0 = time.perf_counter()
    try:
        yield
    finally:
        timings[key] = timings.get(key, 0.0) + time.perf_counter() - t0


@dataclass(frozen=True)
class TileInputs:
    """What a tile is matched with: the keyword arguments of :func:`match_tile`.

    The fields mean what those arguments mean (see there), with the same defaults; the
    drivers that run the steps of many tiles (:func:`tile_steps`) pass them as one value.
    """

    image: CcdImage
    camera: Camera
    ref: ReferenceOrtho
    terrain: Terrain
    matcher: Matcher
    config: FrontendConfig | None = None
    ratio: float | None = None
    debug: bool = False
    coarse_matcher: Matcher | None = None


def _image_side(
    stage_factor: float,
    window: RefWindow | FineWindow,
    tile: Tile,
    src: TileInputs,
    config: FrontendConfig,
    ratio: float,
) -> ImageSide:
    """The CCD side of a stage on ``window``'s grid (``stage_factor`` reference px per pixel)."""
    if config.geometry == "orthorectify":
        # The whole image may fill the window: matches outside the tile are dropped when
        # mapped back, and the real neighbourhood beats a no-data border for matching.
        # Both stages and all tiles of the CCD take their lattice from the nodes the
        # reader's cache keeps on the reference grid, and their raw block means from its
        # block cache: each node is projected and each raw pixel read once per worker.
        # The lattice keeps its spacing in output pixels on coarse grids (8 coarse px by
        # default: every other node of the fine stages' lattice at a coarse factor of 2)
        # and its ground spacing on the reference and finer grids. One cache per CCD
        # serves both stages: each fill of it has a fixed cost.
        cache = lattice_cache(
            src.image, src.camera, tile.ccd, src.ref, src.terrain, config.lattice_step_ref_px
        )
        return orthorectify(
            src.image,
            src.camera,
            tile.ccd,
            src.ref,
            src.terrain,
            window,  # type: ignore[arg-type]  # a FineWindow offers the same interface
            cache=cache,
            stride=max(1, round(stage_factor)),
        )
    stride = max(1, round(ratio * stage_factor))
    return downsample_tile(src.image, tile, stride, src.camera, src.ref, src.terrain)


@dataclass
class _Stage:
    kp0: F64
    kp1: F64
    conf: F64
    predicted: F64
    actual: F64

    def offset(self, keep: NDArray[np.bool_]) -> F64:
        """The mean displacement (actual minus predicted, reference px) of ``keep``."""
        return np.asarray(np.mean((self.actual - self.predicted)[keep], axis=0), np.float64)


def _match_stage(
    side: ImageSide,
    ref_img: NDArray[np.float32],
    ref_valid: NDArray[np.bool_],
    ref_window: RefWindow | FineWindow,
    matcher: Matcher,
    timings: dict[str, float],
    key: str,
) -> Generator[StageRequest, StageAnswer, _Stage]:
    got = yield StageRequest(matcher, side.image, side.valid, ref_img, ref_valid)
    timings[key] = timings.get(key, 0.0) + got.seconds
    timings["forward"] = timings.get("forward", 0.0) + got.forward
    m = got.matches
    kp0 = np.asarray(m.keypoints0, np.float64).reshape(-1, 2)
    kp1 = np.asarray(m.keypoints1, np.float64).reshape(-1, 2)
    conf = np.asarray(m.confidence, np.float64).reshape(-1)
    pc, pr = side.predicted_ref_pixel(kp0[:, 0], kp0[:, 1])
    ac, ar = ref_window.to_ref_pixel(kp1[:, 0], kp1[:, 1])
    return _Stage(kp0, kp1, conf, np.column_stack([pc, pr]), np.column_stack([ac, ar]))


def _coarse_consensus(st: _Stage, cfg: FrontendConfig) -> tuple[F64 | None, NDArray[np.bool_]]:
    """A coarse stage's offset (None below ``coarse_min_matches``) and its inlier mask."""
    disp = st.actual - st.predicted
    ok = np.all(np.isfinite(disp), axis=1)
    offset, inl = robust_translation(disp[ok], cfg.coarse_radius_ref_px, st.conf[ok])
    full_inl = np.zeros(len(disp), bool)
    full_inl[np.flatnonzero(ok)] = inl
    if offset is None or int(full_inl.sum()) < cfg.coarse_min_matches:
        return None, full_inl
    return offset, full_inl


def _verify_fine(
    st: _Stage,
    coarse_offset: F64 | None,
    cfg: FrontendConfig,
    res: TileResult,
    timings: dict[str, float],
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """The fine stage's verification (funnel stages ``raw`` to ``consensus``).

    Returns:
        ``(inliers, ransac_inliers)``: the matches that passed the translation consensus,
        and those that passed USAC_MAGSAC.
    """
    res.n_matches = len(st.kp0)
    res.record("raw", res.n_matches)
    with _timed(timings, "verify"):
        # Gate: a predicted position, and (after a coarse consensus) a displacement that
        # the fine window around the coarse offset can hold at all.
        ok = np.all(np.isfinite(st.predicted), axis=1)
        gate = {"no_prediction": int(np.count_nonzero(~ok))}
        if coarse_offset is not None:
            with np.errstate(invalid="ignore"):
                far = np.any(
                    np.abs(st.actual - st.predicted - coarse_offset) > cfg.fine_reach_ref_px,
                    axis=1,
                )
            gate["outside_window"] = int(np.count_nonzero(ok & far))
            ok &= ~far
        res.record("coarse_gate", int(ok.sum()), gate)
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
        res.record("ransac", int(inl.sum()), {"outlier": int(ok.sum() - inl.sum())})
        ransac_inl = inl.copy()
        n_ransac = int(inl.sum())
        if inl.any():
            # True matches of one tile share (nearly) one displacement; a homography
            # fitted to wrong matches does not, whatever its residuals.
            idx = np.flatnonzero(inl)
            _, cons = robust_translation(
                (st.actual - st.predicted)[idx], cfg.fine_radius_ref_px, st.conf[idx]
            )
            inl[idx[~cons]] = False
        res.record("consensus", int(inl.sum()), {"off_translation": n_ransac - int(inl.sum())})
    return inl, ransac_inl


def _same_search(coarse: Matcher, fallback: Matcher) -> bool:
    """Whether the coarse matcher already searched as far as the fallback would.

    True for NCC's own coarse stage (the fallback is NCC's coarse instance; the run's
    may carry the user's options, and a radius at least the fallback's).
    """
    if type(coarse) is not type(fallback):
        return False
    opt = type(fallback).search_option if isinstance(fallback, BaseMatcher) else None
    if opt is None:
        return True
    reach = getattr(fallback, opt, 0)
    offset = getattr(coarse, "initial_offset", (0.0, 0.0))
    return bool(getattr(coarse, opt, 0) >= reach and tuple(offset) == (0.0, 0.0))


def _place(res: TileResult, offset: F64, source: str) -> None:
    """Record the offset that places the fine window, and which search gave it."""
    res.coarse_offset_px = (float(offset[0]), float(offset[1]))
    res.coarse_source = source


def _name(matcher: Matcher) -> str:
    return str(getattr(matcher, "name", type(matcher).__name__))


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


def _refine(
    cfg: FrontendConfig,
    side: ImageSide,
    fref: NDArray[np.float32],
    fvalid: NDArray[np.bool_],
    kp0: F64,
    kp1: F64,
) -> tuple[F64, F64, NDArray[np.bool_], dict[str, int]]:
    """Sub-pixel refinement of the fine-stage matches (reference side moves).

    Returns:
        ``(kp1, sigma_px, ok, drop_reasons)``.
    """
    from planetref.matching.refine import refine_matches

    rr = refine_matches(side.image, fref, kp0, kp1, cfg.refine, valid0=side.valid, valid1=fvalid)
    reasons: dict[str, int] = {}
    for r in np.asarray(rr.reason)[~np.asarray(rr.ok, bool)]:
        reasons[str(r) or "dropped"] = reasons.get(str(r) or "dropped", 0) + 1
    return (
        np.asarray(rr.points1, np.float64).reshape(-1, 2),
        np.asarray(rr.sigma_px, np.float64).reshape(-1),
        np.asarray(rr.ok, bool).reshape(-1),
        reasons,
    )


def match_tile(
    tile: Tile,
    *,
    image: CcdImage,
    camera: Camera,
    ref: ReferenceOrtho,
    terrain: Terrain,
    matcher: Matcher,
    config: FrontendConfig | None = None,
    ratio: float | None = None,
    debug: bool = False,
    coarse_matcher: Matcher | None = None,
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
    return run_steps(
        tile_steps(
            tile,
            TileInputs(
                image=image,
                camera=camera,
                ref=ref,
                terrain=terrain,
                matcher=matcher,
                config=config,
                ratio=ratio,
                debug=debug,
                coarse_matcher=coarse_matcher,
            ),
        )
    )


def tile_steps(tile: Tile, inputs: TileInputs) -> TileSteps:
    """The steps of :func:`match_tile`: a generator of its matcher calls.

    It yields a :class:`StageRequest` per stage (coarse, fine, a second fine pass), takes
    the :class:`StageAnswer` sent back, and returns the tile's result, so that a driver can
    make the calls of several tiles together (:mod:`planetref.frontend.batched`).

    Args:
        tile: The tile (from :func:`~planetref.frontend.tiles.plan_tiles`).
        inputs: What it is matched with (see :func:`match_tile`).
    """
    camera, ref, terrain = inputs.camera, inputs.ref, inputs.terrain
    matcher, ratio, debug = inputs.matcher, inputs.ratio, inputs.debug
    cfg = inputs.config or FrontendConfig()
    name = _name(matcher)
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
        from planetref.camera.mapping import image_gsd_m

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

    # ---- coarse stage
    # Orthorectified tiles are resampled onto the very window of the reference they are
    # matched with, so the expected displacement between the two arrays is just the
    # initial error: area-based matchers with a bounded search work as well as the rest.
    coarse_offset: F64 | None = None
    pending: Matcher | None = None  # the NCC search of the coarse windows, still untried
    if cfg.coarse:
        # The coarse level adapts to the uncertainty (a bounded window; see
        # FrontendConfig.coarse_level): from the reference's nominal GSD, as the coarse
        # matcher's search radius is (frontend.matchers.matcher_options).
        gsd = float(np.mean(ref.ground_sampling_m()))
        f = cfg.coarse_level(gsd)
        with _timed(timings, "coarse_prepare"):
            cwin = RefWindow.around(*base.bounds_px, pad_px=pad_unc + cfg.fine_pad_ref_px, factor=f)
            cside = _image_side(f, cwin, tile, inputs, cfg, ratio)
            cref, cvalid = ref.read(cwin)
        problem = _unmatchable(cside, cref, cvalid, _area_share(base, cwin, cfg), cfg)
        if problem is not None:
            return finish(*problem)
        coarse = inputs.coarse_matcher or matcher
        st = yield from _match_stage(cside, cref, cvalid, cwin, coarse, timings, "coarse_match")
        res.n_coarse_matches = len(st.kp0)
        coarse_offset, full_inl = _coarse_consensus(st, cfg)
        res.n_coarse_inliers = int(full_inl.sum())
        if coarse_offset is not None:
            _place(res, coarse_offset, "matcher")
        if debug:
            res.debug.append(
                StageDebug(
                    "coarse", cside.image, cside.valid, cref, cvalid, st.kp0, st.kp1, full_inl
                )
            )
        fallback = coarse_fallback_matcher(cfg, gsd)
        if fallback is not None and not _same_search(coarse, fallback):
            pending = fallback
        if coarse_offset is None and cfg.coarse_fallback == "ncc":
            # The front end's own bounded search of the same coarse windows (the same for
            # every matcher); when it finds nothing either, no wider search follows.
            n_fb = ""
            if pending is not None:
                fb = yield from _match_stage(
                    cside, cref, cvalid, cwin, pending, timings, "coarse_fallback"
                )
                pending = None
                coarse_offset, fb_inl = _coarse_consensus(fb, cfg)
                n_fb = f", NCC {int(fb_inl.sum())} of {len(fb.kp0)}"
                if coarse_offset is not None:
                    _place(res, coarse_offset, COARSE_FALLBACK_MATCHER)
            if coarse_offset is None:
                return finish(
                    "too_few_inliers",
                    f"no coarse consensus: {res.n_coarse_inliers} of {res.n_coarse_matches}"
                    f"{n_fb}, {cfg.coarse_min_matches} needed",
                )

    # ---- fine stage
    # The fine stage checks the coarse offset: when it finds too few inliers around the
    # coarse matcher's offset (a consensus of a few wrong matches: XFeat on 20 m coarse
    # pixels agreed on a 2 km error in 1 of 12 hiric-strip tiles at 1 km), the NCC search
    # of the coarse windows (``coarse_fallback = "ncc"``) gives a second offset, and the
    # fine stage runs once more around it when it lies beyond the first window's reach.
    # With ``coarse_fallback = "fine"``, when the coarse stage ran but found no consensus,
    # the fine stage searches the whole a-priori uncertainty; matchers whose precision
    # falls with the displacement (XFeat*'s head is ~1 px only within ~2 px of its cell)
    # then give loose matches that a 1-px RANSAC mostly rejects. The first fine pass's
    # consensus offset then places the window of a second pass, as a coarse offset would
    # have (the same for every matcher).
    attempt = 0
    while True:
        attempt += 1
        res.funnel, res.drops = {}, {}
        up = cfg.fine_upsample
        with _timed(timings, "fine_prepare"):
            pad = (
                cfg.fine_pad_ref_px if coarse_offset is not None else pad_unc + cfg.fine_pad_ref_px
            )
            iwin = base.padded(pad)
            fwin = (
                iwin if coarse_offset is None else iwin.shifted(coarse_offset[0], coarse_offset[1])
            )
            fwin_img = FineWindow(iwin, up) if up > 1 else iwin
            side = _image_side(1.0 / up, fwin_img, tile, inputs, cfg, ratio)
            fine_ref = FineWindow(fwin, up)
            fref, fvalid = read_fine(ref, fine_ref)
        res.search_window = fwin.to_tuple()
        problem = _unmatchable(side, fref, fvalid, _area_share(base, iwin, cfg), cfg)
        if problem is not None and pending is None:
            return finish(*problem)
        if problem is None:
            st = yield from _match_stage(
                side, fref, fvalid, fine_ref, matcher, timings, "fine_match"
            )
            inl, ransac_inl = _verify_fine(st, coarse_offset, cfg, res, timings)
            found = int(inl.sum()) >= cfg.min_inliers
            if coarse_offset is None:
                # coarse_fallback = "fine": this pass searched the whole window; its
                # consensus places a second pass
                if attempt == 1 and cfg.coarse and found:
                    coarse_offset = st.offset(inl)
                    _place(res, coarse_offset, "fine")
                    continue
                break
            if found:
                break
        if pending is not None and coarse_offset is not None:
            fb = yield from _match_stage(
                cside, cref, cvalid, cwin, pending, timings, "coarse_fallback"
            )
            pending = None
            offset, _ = _coarse_consensus(fb, cfg)
            if offset is not None and np.any(
                np.abs(offset - coarse_offset) > cfg.fine_reach_ref_px
            ):
                coarse_offset = offset
                _place(res, offset, COARSE_FALLBACK_MATCHER)
                continue
        if problem is not None:
            return finish(*problem)
        break
    if (
        cfg.fine_recentre
        and cfg.geometry == "orthorectify"
        and coarse_offset is not None
        and int(inl.sum()) >= cfg.min_inliers
    ):
        # The fine window sat on the coarse offset rounded to whole reference pixels, so
        # a displacement of up to a few fine pixels was left between the two windows, of
        # one sign along a strip (the coarse errors are smooth). Matchers that undershoot
        # such a displacement (XFeat: 0.06-0.23 px per px, benchmarks/
        # bench_subpixel_bias.py) then share an error over the tiles that the cameras
        # absorb and no residual shows. A second pass on the reference resampled at the
        # first pass's offset, to a fraction of a pixel, leaves only the first pass's
        # error as displacement: the same for every matcher. (A bias a matcher has at no
        # displacement at all stays; the comparison's excess error shows it.)
        shift = st.offset(inl)
        first = (st, inl, ransac_inl, fref, fvalid, fine_ref, res.funnel, res.drops, res.n_matches)
        with _timed(timings, "fine_prepare"):
            fine_ref = FineWindow.at(iwin, float(shift[0]), float(shift[1]), up)
            fref, fvalid = read_fine(ref, fine_ref)
        res.funnel, res.drops = {}, {}
        st = yield from _match_stage(side, fref, fvalid, fine_ref, matcher, timings, "fine_match")
        inl, ransac_inl = _verify_fine(st, shift, cfg, res, timings)
        if int(inl.sum()) >= cfg.min_inliers:
            res.fine_shift_px = (float(shift[0]), float(shift[1]))
            res.search_window = fine_ref.base.to_tuple()
        else:  # keep the first pass (its result stands on its own)
            st, inl, ransac_inl, fref, fvalid, fine_ref, res.funnel, res.drops, res.n_matches = (
                first
            )
    with _timed(timings, "backmap"):
        # Every match RANSAC kept, before the consensus and the back-projection, with its
        # raw and reference position: on a simulated scene their true errors measure the
        # matcher's outliers (planetref.frontend.truth), whatever the later stages keep.
        ridx = np.flatnonzero(ransac_inl)
        rl, rs, rgood = side.to_raw(st.kp0[ridx, 0], st.kp0[ridx, 1])
        rc, rr = fine_ref.to_ref_pixel(st.kp1[ridx, 0], st.kp1[ridx, 1])
        # Rounded to 1e-3 px as the journal keeps them, so a resumed run measures the same.
        points = np.column_stack(
            [np.where(rgood, rl, np.nan), np.where(rgood, rs, np.nan), rc, rr]
        ).astype(np.float64)
        res.ransac_points = np.asarray(np.round(points, 3), np.float64)
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
        inside = good & tile.contains(line, sample)
        # The tile's verification is judged on all its inliers; of those, it keeps the
        # ones in its core (its neighbour keeps the rest of the overlap).
        n_inside = int(inside.sum())
        owned = inside & tile.owns(line, sample)
        res.record(
            "backprojection",
            int(owned.sum()),
            {
                "no_raw_position": int(np.count_nonzero(~good)),
                "outside_tile": int(np.count_nonzero(good & ~inside)),
                "neighbour_tile": int(np.count_nonzero(inside & ~owned)),
            },
        )
        idx, line, sample = idx[owned], line[owned], sample[owned]
    kp1 = st.kp1[idx]
    sigma = np.full(len(idx), np.nan)
    if cfg.refine.method != "none" and len(idx):
        with _timed(timings, "refine"):
            kp1, sigma, rok, reasons = _refine(cfg, side, fref, fvalid, st.kp0[idx], kp1)
            idx, line, sample, kp1, sigma = idx[rok], line[rok], sample[rok], kp1[rok], sigma[rok]
        res.record("refine", len(idx), reasons)
    conf = st.conf[idx]
    keep = spread_select(line, sample, conf, cfg.max_mcps_per_tile)
    n_verified = len(idx)
    res.thinned = len(keep) < n_verified
    idx, line, sample, conf = idx[keep], line[keep], sample[keep], conf[keep]
    kp1, sigma = kp1[keep], sigma[keep]
    res.record("mcp", len(idx), {"thinned": n_verified - len(idx)})
    ref_col, ref_row = fine_ref.to_ref_pixel(kp1[:, 0], kp1[:, 1])
    ref_x, ref_y = ref.pixel_to_map(ref_col, ref_row)
    res.line, res.sample, res.confidence, res.sigma_px = line, sample, conf, sigma
    res.ref_col, res.ref_row = np.asarray(ref_col, np.float64), np.asarray(ref_row, np.float64)
    res.ref_x, res.ref_y = np.asarray(ref_x, np.float64), np.asarray(ref_y, np.float64)
    if n_inside < cfg.min_inliers:
        return finish(
            "too_few_inliers",
            f"{n_inside} inliers map back into the tile, {cfg.min_inliers} needed",
        )
    return finish("ok")
