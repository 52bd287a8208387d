"""The geometry-aware, coarse-to-fine matching front end.

CCD images are cut into tiles (:mod:`~planetref.frontend.tiles`); each tile is brought
to the reference geometry (:mod:`~planetref.frontend.orthorectify`) and matched coarse to
fine against the reference orthoimage (:mod:`~planetref.frontend.tile`, robust fits in
:mod:`~planetref.frontend.robust`); results (:mod:`~planetref.frontend.result`) are
journalled (:mod:`~planetref.frontend.journal`) and a strip's tiles dispatched in process
or to workers (:mod:`~planetref.frontend.strip`, :mod:`~planetref.frontend.tasks`); the
inliers become matched control points (:mod:`planetref.control`). NCP and SDU are in
:mod:`~planetref.frontend.stats`.

Importing this package loads no matcher, torch or OpenCV, and none of its modules: the
names below are imported on first use (so that e.g. :mod:`~planetref.frontend.stats` alone
does not pull in the orthorectification's SciPy modules; the figure process needs only it).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from planetref.frontend.config import FrontendConfig
    from planetref.frontend.orthorectify import downsample_tile, orthorectify
    from planetref.frontend.result import StripMatches, TileResult
    from planetref.frontend.stats import ncp_per_ccd, ncp_per_tile, sdu_percent
    from planetref.frontend.strip import match_strip
    from planetref.frontend.tasks import MatcherRecipe, TileSources
    from planetref.frontend.tile import match_tile
    from planetref.frontend.tiles import Tile, TilePlan, plan_tiles, tile_footprint

#: Public name -> the module that defines it.
_HOME = {
    "FrontendConfig": "config",
    "MatcherRecipe": "tasks",
    "StripMatches": "result",
    "Tile": "tiles",
    "TilePlan": "tiles",
    "TileResult": "result",
    "TileSources": "tasks",
    "downsample_tile": "orthorectify",
    "match_strip": "strip",
    "match_tile": "tile",
    "ncp_per_ccd": "stats",
    "ncp_per_tile": "stats",
    "orthorectify": "orthorectify",
    "plan_tiles": "tiles",
    "sdu_percent": "stats",
    "tile_footprint": "tiles",
}

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


def __getattr__(name: str) -> Any:
    """Import a public name (or a submodule) on first use."""
    home = _HOME.get(name)
    if home is None:
        try:
            return importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"{__name__}.{name}":
                raise
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    value = getattr(importlib.import_module(f"{__name__}.{home}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_HOME})
