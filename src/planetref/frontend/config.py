"""Typed configuration of the matching front end.

Sizes are in pixels of the full-resolution reference orthoimage ("reference pixels")
unless a name says otherwise; the tile plan converts them to CCD image pixels with the
ratio of the two ground sampling distances.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from os import PathLike
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, model_validator

from planetref.matching.refine import RefineConfig
from planetref.runtime.settings import Settings, validate_settings
from planetref.runtime.tomlfile import read_toml

__all__ = [
    "PAPER_PROTOCOL",
    "CampaignOptions",
    "CcdOverlapConfig",
    "CoarseFallback",
    "FrontendConfig",
    "GeometryMode",
    "Protocol",
    "RansacModel",
    "RefineConfig",
]

GeometryMode = Literal["orthorectify", "downsample"]
RansacModel = Literal["homography", "affine"]
Protocol = Literal["default", "paper"]
CoarseFallback = Literal["ncc", "fine"]

PAPER_PROTOCOL: dict[str, Any] = {
    # Sec. 3.2 of the seed: the CCD tile is downsampled to the reference GSD and matched
    # there (no orthorectification, no finer fine stage).
    "geometry": "downsample",
    "fine_upsample": 1,
    # OpenCV's findHomography default (3 px), as a plain RANSAC would use it: wide
    # against the adjustment's 3 x RMSE (RMSE ~1-4 CCD px = 0.1-0.4 reference px at
    # 0.5 m on 5 m), so the blunders reach the adjustment and its rule rejects them.
    "ransac_threshold_ref_px": 3.0,
    "fine_radius_ref_px": 3.0,
    # one fine pass, as the seed matched
    "fine_recentre": False,
}
"""Settings of the ``paper`` protocol (used where the configuration does not set them)."""


class CcdOverlapConfig(Settings):
    """Tie points between the overlapping CCDs of one strip (``[frontend.ccd_overlap]``).

    Neighbouring CCDs of a staggered focal plane see the ground of their overlap at
    different times (the stagger); where a tie point's two image positions differ from
    what a smooth attitude predicts, the difference is the attitude's change over that
    time: jitter (:mod:`planetref.camera.jitter` has the transfer function). The
    overlap is matched in raw image geometry: a template of the first CCD every
    ``step_lines`` lines, centred in the overlap, is searched (NCC, +-``search_px``)
    around where the initial camera predicts it in the neighbouring CCD, and the peak
    is refined to sub-pixel by least squares on the image gradients; see
    :func:`planetref.frontend.overlap.find_overlap_ties`. The ties enter the strip's
    adjustment (and a campaign's joint one) with the MCPs, as tie points observed twice
    by the strip's camera, their ground from the reference DEM with only the height
    weighted (the planimetric position under a loose 1 km sigma).

    Off by default, so a default run costs what it did: they see the attitude's change
    over the stagger time (a few milliseconds), hardly the node model's smooth attitude
    and mostly what it cannot follow; they are the observation a high-frequency
    attitude model needs. Their observations are judged by the outlier rule apart from
    the MCPs and left out of the reprojection metrics (point kind ``"overlap"``); the
    strip's report block ``ccd_overlap`` has their count, stagger and RMSE.

    Attributes:
        enabled: Match the overlaps and add the ties to the adjustment.
        step_lines: Lines between the templates along the overlap.
        half_lines: Half height of a template (lines); the template is
            ``2 * half_lines + 1`` lines.
        half_samples: Half width of a template (samples), reduced to fit the overlap
            with the search.
        search_px: Search radius around the predicted position (pixels, both axes).
        min_score: Lowest NCC peak a tie needs.
        max_deviation_px: A tie whose offset from the prediction departs from the
            running median of its neighbours' (11 templates) by more than this and by
            more than 4 of their robust sigmas is dropped as a blunder.
        sigma_px: Standard deviation of a tie's image measures (pixels): their
            matching precision (0.07-0.16 px on tiny). The ties are a variance
            component of their own: on tiny (sift, nodes every 128 lines) the true
            error was 1.81 m with the ties at 0.2, 0.5 or 1.0 px, 1.95 m without.
        height_sigma_m: A-priori sigma (m) of a tie point's height (from the reference
            DEM); its planimetric position is as good as free (1 km). The two rays of a
            tie cross at the stagger angle (~75 urad for HiRIC), so without it their
            height is undefined; a height error moves the tie by ``height * stagger
            angle``, 0.75 mm per 10 m.
    """

    enabled: bool = False
    step_lines: int = Field(8, ge=1)
    half_lines: int = Field(12, ge=2, le=128)
    half_samples: int = Field(16, ge=2, le=128)
    search_px: int = Field(3, ge=1, le=32)
    min_score: float = Field(0.7, ge=-1.0, le=1.0)
    max_deviation_px: float = Field(0.5, gt=0.0)
    sigma_px: float = Field(0.2, gt=0.0)
    height_sigma_m: float = Field(100.0, gt=0.0)


class FrontendConfig(Settings):
    """Settings of tiling, common geometry, coarse-to-fine matching and verification.

    Attributes:
        tile_size_ref_px: Side of a CCD tile, in reference pixels of the fine stage (the
            tile covers about this many reference pixels on the ground). Tiles cover
            every CCD completely; each point belongs to one tile's core.
        tile_overlap_ref_px: Overlap of neighbouring tiles, reference pixels (matches in
            the overlap are kept by the tile whose core holds them, once).
        uncertainty_m: A-priori uncertainty of the initial camera on the ground (metres);
            the coarse stage searches a window padded by this much. A run takes it from
            the scene manifest (the strips' ``initial_uncertainty_m``) when its config
            does not set it (:func:`planetref.pipeline.systematic.frontend_settings_for`).
        geometry: ``"orthorectify"`` resamples the CCD tile onto the reference grid
            through the initial camera and the DEM (removes scale, rotation and most
            relief displacement); ``"downsample"`` only averages the raw tile down to the
            reference GSD (the seed's way).
        coarse: Run the coarse stage (otherwise the fine stage searches the whole
            uncertainty window at full resolution).
        coarse_factor: Downsampling of both images in the coarse stage (the finest
            coarse level; see ``coarse_max_px``).
        coarse_max_px: Largest side of the coarse stage's window, in coarse pixels. When
            the footprint padded by the uncertainty would be larger at ``coarse_factor``,
            the coarse stage matches at a coarser level of the reference (and of the CCD
            tile, orthorectified alike), the smallest whole factor that fits
            (:meth:`coarse_level`), so the pixels it matches, and an area-based
            matcher's coarse search radius, stay bounded whatever the uncertainty. The
            default 256 leaves the coarse level of a 5 m reference at 4 up to 1.3 km
            of uncertainty (tiles of 256 reference px).
        coarse_fallback: What places the fine window of a tile whose coarse matcher finds
            no consensus (``coarse_min_matches`` within ``coarse_radius_ref_px``), or one
            around which the fine stage finds fewer than ``min_inliers`` (a consensus of
            wrong matches). ``"ncc"`` (default): the same coarse windows are searched by
            area-based NCC
            (:func:`~planetref.frontend.coarse.coarse_fallback_matcher`: NCC's own
            coarse instance, a search radius covering the uncertainty at the coarse
            level), the same for every matcher; its consensus places the fine stage as
            the matcher's own would have (after a rejected offset, when it lies beyond
            the first fine window's reach), and a tile where it finds none either fails
            (``too_few_inliers``) without a wider search. Its cost is bounded by the
            coarse window (``coarse_max_px``) whatever the uncertainty: on hiric-strip
            0.01-0.02 CPU-s per tile at 100 m and 0.20-0.62 s at 1 km, against 5-7 s for
            the whole-window search it replaced (docs/guide/pipeline.md). The
            tile's ``coarse_source`` says which search placed it. The NCC matcher
            itself has no fallback (its coarse stage is that search). ``"fine"``: the
            fine stage searches the whole uncertainty window at full resolution, and a
            second fine pass sits on its consensus (the behaviour before this option;
            its cost grows with the square of the uncertainty, and learned matchers
            spread their keypoint budget over the whole window).
        coarse_min_matches: Fewest consistent coarse matches to trust the coarse offset.
        coarse_radius_ref_px: Consensus radius of the coarse translation, reference px.
        fine_pad_ref_px: Margin of the fine reference window around the footprint
            shifted by the coarse offset, reference px. Fine matches whose displacement
            differs from the coarse offset by more than this plus
            ``coarse_radius_ref_px`` cannot be right and are dropped (funnel stage
            ``coarse_gate``).
        fine_upsample: Resolution of the fine stage, the same for every matcher: 1
            matches on the reference grid (the paper's 5 m); ``k > 1`` on a grid ``k``
            times finer (the reference resampled bicubically, the CCD image
            orthorectified at that pixel size, so the image keeps detail the reference
            grid would average away). Default 2 (2.5 m on a 5 m reference): the
            detectors find about four times the keypoints per tile (their budgets are
            their own defaults), which is where sparse matchers' density is bounded at 1.
            Thresholds, the coarse stage and the tile plan stay in reference pixels;
            the match positions and offsets are reported in reference pixels whatever
            the grid. NCC: see ``dense_spacing_ref_px``. Measured at 2 on hiric-strip,
            disk-lightglue: 5,619-6,269 correspondences per CCD (1,480-1,670 at 1); on
            the tiny demo every matcher's true error after adjustment fell. 1 is the
            cheaper choice: the fine stage costs several times more CPU at 2 (the
            README has the figures).
        fine_recentre: Run the fine stage a second time on the reference window
            resampled (bicubic) at the first pass's mean displacement, to a fraction of a
            pixel, and keep that pass's matches (the first pass's stand when the second
            finds fewer than ``min_inliers``); orthorectified tiles with a placed window
            only (in the ``downsample`` geometry the two windows differ by more than a
            shift). The same for every matcher; it doubles the fine stage's matcher
            calls. Why: the first window sits on the coarse offset rounded to whole
            reference pixels, so a displacement of a few fine pixels is left between the
            windows, of one sign along a strip; a matcher that undershoots displacement
            (XFeat: 0.06-0.23 px per px of shift, ALIKED and SIFT about 0.01;
            ``benchmarks/bench_subpixel_bias.py``) then makes an error common to the
            tiles, which the cameras absorb and no residual or covariance shows.
            Measured on hiric-strip ``moderate`` over seeds 0-2: the true error of
            XFeat-LighterGlue fell 8-26 % and of XFeat* 23-44 %, the others' moved
            within 7 % (docs/adjust.md).
        lattice_step_ref_px: Spacing of the exactly projected lattice that the
            orthorectification interpolates, reference px of the output grid.
        dense_spacing_ref_px: Grid spacing of the dense mode of area-based and
            detector-free matchers (NCC, LoFTR): one match per grid cell. It is defined
            on the reference grid whatever ``fine_upsample`` is (a cell is
            ``dense_spacing_ref_px * fine_upsample`` fine-grid pixels), so a finer fine
            stage does not multiply NCC's template count; NCC's search radius is also
            kept in reference pixels (the same ground search), and so is its template
            (``template_radius * fine_upsample`` fine-grid pixels: the same ground, with
            more detail). With the template left at 21 fine pixels (half the ground at
            2), NCC on hiric-strip lost SDU (ccd2 64.8 %); with the ground-sized one it
            gives 27-36 k per CCD, SDU 70.0-84.2 %, at 1.5x the CPU.
            Other matchers ignore it (their keypoint budgets are their own defaults; the
            front end caps nothing). On hiric-strip at ``fine_upsample = 1``, NCC gives
            about 10-13 k correspondences per CCD at 3 (SDU 57-70 %) and 27-35 k at 2
            (SDU 70-84 %).
        ransac_model: Model verified per tile with OpenCV USAC_MAGSAC.
        ransac_threshold_ref_px: Inlier threshold, reference px.
        ransac_confidence: RANSAC confidence.
        ransac_max_iters: RANSAC iteration cap.
        fine_radius_ref_px: After RANSAC, inliers whose displacement (actual minus
            predicted reference position) is farther than this from the tile's dominant
            displacement are dropped: over one tile the initial camera's error is close
            to a translation, and a model fitted to wrong matches is not.
        min_inliers: A tile with fewer fine inliers gets status ``too_few_inliers``.
        refine: Sub-pixel refinement of every verified match on the fine stage
            (:func:`planetref.matching.refine.refine_matches`), the same for every
            matcher; ``method = "none"`` (default) leaves the matcher's positions.
        max_mcps_per_tile: Thin each tile to at most this many MCPs (spread over the
            tile, highest confidence first), for speed only: NCP and SDU count the
            verified correspondences before thinning, and a thinned tile says so
            (``TileResult.thinned``). 0 (default) keeps all.
        min_valid_fraction: A tile whose image or reference window has a smaller
            fraction of valid pixels gets status ``no_overlap``.
        footprint_points_per_edge: Points per tile edge projected to the ground for the
            footprint.
        batch_tiles: Tiles matched together in this process (1: one at a time). Their
            stages advance together, and each round's matcher calls go to
            ``Matcher.match_many``: DISK, ALIKED and XFeat (with LightGlue/LighterGlue)
            then detect on up to ``2 * batch_tiles`` images per forward pass (the CCD
            sides and reference windows of one padded shape), LightGlue runs pair by pair;
            other matchers match one pair at a time. Meant for a GPU (``--device cuda``);
            the results equal tile-by-tile matching as sets of matches (keypoints 1e-3 px,
            confidences 2e-3) and it is left out of the run's and the journal's identity.
            Tiles sent to parallel workers (``--scheduler pool:N``, ``dask-local:N``, a
            dask scheduler) are matched one at a time.
        protocol: ``"default"``: planetref's front end (orthorectified tiles, a finer
            fine stage, a 1 reference px RANSAC threshold that keeps only matches far
            inside the adjustment's ``3 x RMSE``, so the adjustment's OR sees almost no
            blunder). ``"paper"``: the seed's (Sec. 3.2), so that OR can stand beside
            its 4.1-7.3 %: the settings of :data:`PAPER_PROTOCOL` wherever the
            configuration does not set them (tiles downsampled to the reference GSD,
            a 3 reference px RANSAC threshold that leaves the rejecting to the
            adjustment). The report states which protocol ran.
        ccd_overlap: Tie points between the overlapping CCDs of each strip
            (:class:`CcdOverlapConfig`; off by default).
    """

    tile_size_ref_px: int = Field(256, ge=32, le=4096)
    tile_overlap_ref_px: int = Field(16, ge=0)
    uncertainty_m: float = Field(300.0, gt=0.0)
    geometry: GeometryMode = "orthorectify"
    coarse: bool = True
    coarse_factor: int = Field(4, ge=1, le=32)
    coarse_max_px: int = Field(256, ge=32, le=4096)
    coarse_fallback: CoarseFallback = "ncc"
    coarse_min_matches: int = Field(6, ge=3)
    coarse_radius_ref_px: float = Field(6.0, gt=0.0)
    fine_pad_ref_px: int = Field(16, ge=0)
    fine_upsample: int = Field(2, ge=1, le=8)
    fine_recentre: bool = True
    lattice_step_ref_px: int = Field(8, ge=1, le=64)
    dense_spacing_ref_px: int = Field(2, ge=1, le=64)
    ransac_model: RansacModel = "homography"
    ransac_threshold_ref_px: float = Field(1.0, gt=0.0)
    ransac_confidence: float = Field(0.999, gt=0.0, lt=1.0)
    ransac_max_iters: int = Field(10000, ge=10)
    fine_radius_ref_px: float = Field(3.0, gt=0.0)
    min_inliers: int = Field(8, ge=4)
    refine: RefineConfig = RefineConfig()
    max_mcps_per_tile: int = Field(0, ge=0)
    min_valid_fraction: float = Field(0.1, ge=0.0, le=1.0)
    footprint_points_per_edge: int = Field(5, ge=2, le=64)
    batch_tiles: int = Field(1, ge=1, le=256)
    protocol: Protocol = "default"
    ccd_overlap: CcdOverlapConfig = CcdOverlapConfig()

    @model_validator(mode="before")
    @classmethod
    def _protocol(cls, values: Any) -> Any:
        # The paper protocol's settings, where the configuration leaves them open.
        if isinstance(values, Mapping) and values.get("protocol") == "paper":
            return {**PAPER_PROTOCOL, **values}
        return values

    @model_validator(mode="after")
    def _check(self) -> FrontendConfig:
        if self.tile_overlap_ref_px >= self.tile_size_ref_px:
            raise ValueError(
                f"tile_overlap_ref_px ({self.tile_overlap_ref_px}) must be "
                f"smaller than tile_size_ref_px ({self.tile_size_ref_px})"
            )
        return self

    @property
    def fine_reach_ref_px(self) -> float:
        """How far from the coarse offset a fine match can lie (reference px).

        The fine window's margin plus the coarse consensus radius.
        """
        return self.fine_pad_ref_px + self.coarse_radius_ref_px

    def coarse_level(self, ref_gsd_m: float) -> int:
        """The coarse stage's downsampling factor for this uncertainty.

        The smallest factor, at least ``coarse_factor``, at which a tile's coarse window
        (``tile_size_ref_px`` padded on each side by the uncertainty and
        ``fine_pad_ref_px``) is at most ``coarse_max_px`` coarse pixels wide. The front
        end and the coarse matcher's search radius both take it from here.

        Args:
            ref_gsd_m: Ground sampling distance of the reference (metres per pixel).

        Returns:
            The factor (reference pixels per coarse pixel).
        """
        pad = math.ceil(self.uncertainty_m / ref_gsd_m) + self.fine_pad_ref_px
        side = self.tile_size_ref_px + 2 * pad
        return max(self.coarse_factor, math.ceil(side / self.coarse_max_px))

    def identity(self) -> dict[str, Any]:
        """The settings that decide the tiles' results (``model_dump()`` less ``batch_tiles``).

        ``ccd_overlap`` decides no tile (the overlap ties are matched apart): left out.
        """
        doc = self.model_dump()
        doc.pop("batch_tiles")
        doc.pop("ccd_overlap")
        return doc

    @classmethod
    def from_mapping(
        cls, values: Mapping[str, Any], *, source: str | None = None
    ) -> FrontendConfig:
        """Validate a mapping of settings (e.g. a TOML table).

        Raises:
            InputError: Unknown keys (the message lists the valid ones) or bad values.
        """
        return validate_settings(cls, values, source=source)

    @classmethod
    def from_toml(cls, path: str | PathLike[str], table: str | None = "frontend") -> FrontendConfig:
        """Read settings from a TOML file (its ``[frontend]`` table, or the whole file).

        Raises:
            MissingFileError: No such file.
            InputError: Unreadable TOML, unknown keys or bad values.
        """
        p = Path(path)
        doc = read_toml(p, "front-end settings file")
        if table is not None and table in doc:
            doc = doc[table]
        return cls.from_mapping(doc, source=str(p))


class CampaignOptions(Settings):
    """How the strips of a scene (a campaign) are adjusted.

    With ``adjust_together`` false (the default) every strip is adjusted on its own with
    its MCPs. With it true and several strips, tie points are matched between the
    overlapping CCD images of different strips (both orthorectified onto the same
    reference-grid window through their initial cameras and the DEM), and one network
    with every strip's camera, all MCPs and the tie points is adjusted once.

    Attributes:
        adjust_together: Adjust all strips in one network tied by tie points.
        tie_sigma_m: A-priori sigma (metres, per axis) of a tie point's ground
            coordinates, taken from the reference DEM at its map position; ``None``: free
            (its XYZ are unknowns). That position comes from the *initial* cameras, so a
            sigma below their ground error (``frontend.uncertainty_m``) pulls the strips
            back towards it: on the two-strip tiny scene (107 m initial error) 5 m gave
            14 m after adjustment, 300 m or free gave 0.7 m.
        tie_sigma_px: Standard deviation of a tie point's image measures (CCD pixels).
        tie_window_ref_px: Side of the reference-grid windows an overlap is cut into
            for matching (reference pixels).
        tie_max_per_window: Most tie points kept per window (spread over it).
        tie_min_inliers: Fewest verified matches a window needs to give tie points.
        tie_min_overlap_ref_px: Smallest overlap side (reference pixels) worth matching.
    """

    adjust_together: bool = False
    tie_sigma_m: float | None = Field(None, gt=0.0)
    tie_sigma_px: float = Field(1.0, gt=0.0)
    tie_window_ref_px: int = Field(512, ge=32)
    tie_max_per_window: int = Field(100, ge=1)
    tie_min_inliers: int = Field(8, ge=4)
    tie_min_overlap_ref_px: int = Field(24, ge=8)
