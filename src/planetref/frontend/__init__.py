"""The geometry-aware, coarse-to-fine matching front end.

CCD images are cut into tiles (:mod:`~planetref.frontend.tiles`); each tile is brought
to the reference geometry (:mod:`~planetref.frontend.orthorectify`) and matched coarse to
fine against the reference orthoimage (:mod:`~planetref.frontend.tile`, robust fits in
:mod:`~planetref.frontend.robust`); results (:mod:`~planetref.frontend.result`) are
journalled (:mod:`~planetref.frontend.journal`) and a strip's tiles dispatched in process
or to workers (:mod:`~planetref.frontend.strip`, :mod:`~planetref.frontend.tasks`); the
inliers become matched control points (:mod:`planetref.control.mcp`). NCP and SDU are in
:mod:`~planetref.frontend.stats`.

Importing this package loads no matcher, torch or OpenCV.
"""

from __future__ import annotations

from planetref.frontend.config import FrontendConfig
from planetref.frontend.orthorectify import downsample_tile, orthorectify
from planetref.frontend.result import StripMatches, TileResult
from planetref.frontend.stats import ncp_per_ccd, ncp_per_tile, sdu_percent
from planetref.frontend.strip import match_strip
from planetref.frontend.tasks import MatcherRecipe, TileSources
from planetref.frontend.tile import match_tile
from planetref.frontend.tiles import Tile, TilePlan, plan_tiles, tile_footprint

__all__ = [
    "FrontendConfig",
    "MatcherRecipe",
    "StripMatches",
    "Tile",
    "TilePlan",
    "TileResult",
    "TileSources",
    "downsample_tile",
    "match_strip",
    "match_tile",
    "ncp_per_ccd",
    "ncp_per_tile",
    "orthorectify",
    "plan_tiles",
    "sdu_percent",
    "tile_footprint",
]
