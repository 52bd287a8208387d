"""The outcome of matching one tile (:class:`TileResult`) and of a strip (:class:`StripMatches`).

A tile result holds a status, the offsets, the per-stage counts (the *funnel*: how many
correspondences each stage of the tile algorithm kept, and why the others were dropped),
timings and the kept correspondences. It serialises to one JSON object
(:meth:`TileResult.to_dict`), which the journal (:mod:`planetref.frontend.journal`) and
the parallel executors (:mod:`planetref.frontend.tasks`) carry.

Offsets are in full-resolution reference pixels, ``(dcol, drow)`` = actual minus
predicted position of the tile's content on the reference grid.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from planetref.arrays import F64
from planetref.errors import InputError
from planetref.frontend.config import FrontendConfig
from planetref.frontend.stats import FUNNEL_STAGES
from planetref.frontend.tiles import Tile, TilePlan

__all__ = [
    "FUNNEL_STAGES",
    "STATUSES",
    "StageDebug",
    "StripMatches",
    "TileResult",
    "TileStatus",
]

TileStatus = Literal["ok", "too_few_inliers", "no_overlap", "no_texture", "error"]
STATUSES: tuple[str, ...] = ("ok", "too_few_inliers", "no_overlap", "no_texture", "error")


_ARRAYS = ("line", "sample", "ref_col", "ref_row", "ref_x", "ref_y", "confidence", "sigma_px")


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
        coarse_offset_px: Offset ``(dcol, drow)`` that placed the fine window, reference
            px: the coarse stage's, or, when it found no consensus, that of a first fine
            pass over the whole uncertainty (the funnel is the second pass's); None if
            the coarse stage did not run or neither found a consensus.
        coarse_source: What placed the fine window: ``"matcher"`` (the coarse
            matcher's consensus), ``"ncc"`` (the front end's NCC search after the coarse
            matcher found none; ``frontend.coarse_fallback``), ``"fine"`` (a first fine
            pass over the whole uncertainty), None (nothing did).
        fine_shift_px: The offset ``(dcol, drow)``, reference px, at which the reference
            window of a second fine pass was resampled (the first pass's mean
            displacement; ``FrontendConfig.fine_recentre``); the funnel, offsets and
            matches are that pass's. None when no second pass ran or it found too few
            inliers (then the first pass's stand).
        offset_px: Fine offset (mean displacement of the verified inliers), reference px.
        offset_mad_px: Median absolute deviation of the inlier displacements, reference px.
        n_coarse_matches: Matches of the coarse stage.
        n_coarse_inliers: Of those, consistent with the coarse offset.
        n_matches: Matches of the fine stage (``funnel["raw"]``).
        n_inliers: Fine matches that passed USAC_MAGSAC and the translation consensus
            (``funnel["consensus"]``).
        funnel: Correspondences left after each stage, keys in the order of
            :data:`FUNNEL_STAGES` (a stage that did not run is missing): ``raw``
            (fine-stage matcher output), ``coarse_gate`` (displacement within the fine
            window around the coarse offset, and a predicted reference position),
            ``ransac``, ``consensus``, ``backprojection`` (maps back into the tile's own
            core through the DEM), ``refine`` (sub-pixel refinement kept it), ``mcp``
            (written; below the previous stage only when ``thinned``). A tile that
            failed keeps the counts it reached.
        drops: Why correspondences were dropped: ``"<stage>:<reason>"`` -> count.
        thinned: True when ``max_mcps_per_tile`` removed verified correspondences (an
            option for speed; metrics count the verified ones, see :attr:`ncp`).
        line: Raw line of each kept correspondence (first pixel centre at 0.5).
        sample: Raw sample of each kept correspondence.
        ref_col: Reference column of each kept correspondence (full resolution).
        ref_row: Reference row.
        ref_x: Reference map x (CRS units).
        ref_y: Reference map y.
        confidence: Matcher confidence of each kept correspondence.
        sigma_px: A-posteriori precision of the refined reference position (pixels of
            the fine-stage grid, i.e. reference pixels divided by ``fine_upsample``);
            NaN where no refinement ran.
        ransac_points: ``(N, 4)`` ``(line, sample, ref_col, ref_row)`` of every fine match
            that passed RANSAC, before the consensus and the back-projection (raw
            position NaN where it has none), for the true outlier ratio on simulated
            scenes (:mod:`planetref.frontend.truth`); empty when RANSAC did not run.
        timings: Seconds per step (``footprint``, ``coarse_prepare``, ``coarse_match``,
            ``coarse_fallback``, ``fine_prepare``, ``fine_match``, ``verify``,
            ``backmap``, ``refine``, ``forward``, ``total``).
        debug: Stage images and matches (only when asked for; never serialised).
    """

    tile: Tile
    matcher: str
    status: TileStatus
    message: str = ""
    geometry: str = "orthorectify"
    search_window: tuple[int, ...] | None = None
    coarse_offset_px: tuple[float, float] | None = None
    coarse_source: str | None = None
    fine_shift_px: tuple[float, float] | None = None
    offset_px: tuple[float, float] | None = None
    offset_mad_px: tuple[float, float] | None = None
    n_coarse_matches: int = 0
    n_coarse_inliers: int = 0
    n_matches: int = 0
    n_inliers: int = 0
    funnel: dict[str, int] = field(default_factory=dict)
    drops: dict[str, int] = field(default_factory=dict)
    thinned: bool = False
    line: F64 = field(default_factory=_empty)
    sample: F64 = field(default_factory=_empty)
    ref_col: F64 = field(default_factory=_empty)
    ref_row: F64 = field(default_factory=_empty)
    ref_x: F64 = field(default_factory=_empty)
    ref_y: F64 = field(default_factory=_empty)
    confidence: F64 = field(default_factory=_empty)
    sigma_px: F64 = field(default_factory=_empty)
    ransac_points: F64 = field(default_factory=lambda: np.empty((0, 4), np.float64))
    timings: dict[str, float] = field(default_factory=dict)
    debug: list[StageDebug] = field(default_factory=list, repr=False)

    @property
    def tile_id(self) -> str:
        """The tile's id."""
        return self.tile.tile_id

    @property
    def n_points(self) -> int:
        """Number of kept correspondences (MCPs written for the tile)."""
        return len(self.line)

    @property
    def ncp(self) -> int:
        """Correspondences that passed the tile's verification, before any thinning.

        The last funnel stage before ``mcp`` (``refine`` when it ran, else
        ``backprojection``); 0 for a tile that did not end ``ok``.
        """
        if self.status != "ok":
            return 0
        for stage in ("refine", "backprojection"):
            if stage in self.funnel:
                return int(self.funnel[stage])
        return self.n_points

    def record(self, stage: str, count: int, drops: Mapping[str, int] | None = None) -> None:
        """Record a funnel stage's count and the reasons of its drops (non-zero only)."""
        self.funnel[stage] = int(count)
        for reason, n in (drops or {}).items():
            if n:
                key = f"{stage}:{reason}"
                self.drops[key] = self.drops.get(key, 0) + int(n)

    def to_dict(self) -> dict[str, Any]:
        """A JSON-serialisable dict (arrays as lists; NaN as null; ``debug`` left out)."""
        doc: dict[str, Any] = {
            "tile": self.tile.to_dict(),
            "matcher": self.matcher,
            "status": self.status,
            "message": self.message,
            "geometry": self.geometry,
            "search_window": None if self.search_window is None else list(self.search_window),
            "coarse_offset_px": _opt_pair(self.coarse_offset_px),
            "coarse_source": self.coarse_source,
            "fine_shift_px": _opt_pair(self.fine_shift_px),
            "offset_px": _opt_pair(self.offset_px),
            "offset_mad_px": _opt_pair(self.offset_mad_px),
            "n_coarse_matches": self.n_coarse_matches,
            "n_coarse_inliers": self.n_coarse_inliers,
            "n_matches": self.n_matches,
            "n_inliers": self.n_inliers,
            "funnel": {k: int(v) for k, v in self.funnel.items()},
            "drops": {k: int(v) for k, v in self.drops.items()},
            "thinned": bool(self.thinned),
            "timings": {k: float(v) for k, v in self.timings.items()},
        }
        for name in _ARRAYS:
            doc[name] = [float(v) if np.isfinite(v) else None for v in self._array(name)]
        if len(self.ransac_points):
            # Rounded to 1e-3 px (far below any true error it serves), columns as lists.
            doc["ransac_points"] = [
                [round(float(v), 3) if np.isfinite(v) else None for v in col]
                for col in np.asarray(self.ransac_points, np.float64).T
            ]
        return doc

    def _array(self, name: str) -> F64:
        a = getattr(self, name)
        if name == "sigma_px" and len(a) != len(self.line):
            return np.full(len(self.line), np.nan)
        return a

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> TileResult:
        """Inverse of :meth:`to_dict` (documents without funnel or sigmas are accepted).

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
                coarse_source=None
                if doc.get("coarse_source") is None
                else str(doc["coarse_source"]),
                fine_shift_px=_opt_pair(doc.get("fine_shift_px")),
                offset_px=_opt_pair(doc.get("offset_px")),
                offset_mad_px=_opt_pair(doc.get("offset_mad_px")),
                n_coarse_matches=int(doc.get("n_coarse_matches", 0)),
                n_coarse_inliers=int(doc.get("n_coarse_inliers", 0)),
                n_matches=int(doc.get("n_matches", 0)),
                n_inliers=int(doc.get("n_inliers", 0)),
                funnel={str(k): int(v) for k, v in doc.get("funnel", {}).items()},
                drops={str(k): int(v) for k, v in doc.get("drops", {}).items()},
                thinned=bool(doc.get("thinned", False)),
                timings={str(k): float(v) for k, v in doc.get("timings", {}).items()},
            )
            rp = doc.get("ransac_points")
            if rp:
                out.ransac_points = np.array(
                    [[np.nan if v is None else v for v in col] for col in rp], np.float64
                ).T.reshape(-1, 4)
            for name in _ARRAYS:
                values = doc.get(name)
                if values is None and name == "sigma_px":
                    values = [None] * len(doc.get("line", []))
                arr = np.array([np.nan if v is None else v for v in values or []], np.float64)
                setattr(out, name, arr.reshape(-1))
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


def error_result(tile: Tile, matcher: str, geometry: str, exc: BaseException) -> TileResult:
    """The result of a tile whose matching raised ``exc`` (status ``error``)."""
    return TileResult(
        tile=tile,
        matcher=matcher,
        status="error",
        message=f"{type(exc).__name__}: {exc}",
        geometry=geometry,
    )


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
        """NCP of each tile (:attr:`TileResult.ncp`: verified, before any thinning)."""
        return {t.tile_id: t.ncp for t in self.tiles}

    def ncp_per_ccd(self) -> dict[str, int]:
        """NCP per CCD over its tiles (verified, before any thinning)."""
        out = dict.fromkeys(self.plans, 0)
        for t in self.tiles:
            out[t.tile.ccd] = out.get(t.tile.ccd, 0) + t.ncp
        return out

    def funnel(self) -> dict[str, int]:
        """The funnel summed over the strip's tiles (stages in order)."""
        out: dict[str, int] = {}
        for stage in FUNNEL_STAGES:
            vals = [t.funnel[stage] for t in self.tiles if stage in t.funnel]
            if vals:
                out[stage] = int(sum(vals))
        return out

    def drops(self) -> dict[str, int]:
        """The reasons of the drops summed over the strip's tiles."""
        out: dict[str, int] = {}
        for t in self.tiles:
            for k, v in t.drops.items():
                out[k] = out.get(k, 0) + int(v)
        return dict(sorted(out.items()))
