"""Tile tasks that the executors of :mod:`planetref.runtime.execute` run in worker processes.

A task carries only descriptions, never arrays or matcher instances: the strip's file
paths (:class:`TileSources`), the matchers as typed recipes (:class:`MatcherRecipe`: a
registry name and its options), the tile and the front-end settings. Each worker opens
the rasters, the camera and the DEM and builds the matchers once, and caches them
(:func:`_worker_context`) for every later tile of the same strip.
"""

from __future__ import annotations

import functools
import json
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from planetref.camera.base import Camera
from planetref.frontend.config import FrontendConfig
from planetref.frontend.result import TileResult, error_result
from planetref.frontend.tile import match_tile
from planetref.frontend.tiles import Tile
from planetref.matching.base import Matcher
from planetref.raster.dem import GridTerrain
from planetref.raster.image import CcdImage
from planetref.raster.ortho import ReferenceOrtho

__all__ = ["MatcherRecipe", "TileSources", "TileTask", "open_worker_dem", "run_tile_task"]


@dataclass(frozen=True)
class MatcherRecipe:
    """How to build a matcher: its registry name and constructor options.

    (The registry's own entry type is :class:`planetref.matching.base.MatcherSpec`; a
    recipe is one configured use of it.)

    Attributes:
        name: Registry name (``planetref matchers``).
        options: Keyword options of the constructor.
        weights_dir: Folder of pretrained weights (learned matchers).
        device: Torch device of a learned matcher (the run's ``--device``, resolved);
            classical matchers run on the CPU whatever it says.
    """

    name: str
    options: Mapping[str, Any] = field(default_factory=dict)
    weights_dir: str | None = None
    device: str = "cpu"

    def build(self) -> Matcher:
        """The matcher (learned weights load lazily, on the first match).

        Raises:
            InputError: Unknown name or option.
            WeightsError: Missing weights.
        """
        from planetref.matching.registry import MATCHERS, get_matcher

        spec = MATCHERS.get(self.name)
        options = dict(self.options)
        # A ``device`` among a matcher's own options ([matchers.NAME]) is that matcher's.
        device = options.pop("device", self.device if spec is not None and spec.weights else "cpu")
        return get_matcher(self.name, weights_dir=self.weights_dir, device=device, **options)

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly form."""
        return {
            "name": self.name,
            "options": dict(self.options),
            "weights_dir": self.weights_dir,
            "device": self.device,
        }

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> MatcherRecipe:
        """Inverse of :meth:`to_dict`."""
        return cls(
            str(doc["name"]),
            dict(doc.get("options") or {}),
            doc.get("weights_dir"),
            str(doc.get("device") or "cpu"),
        )


@dataclass(frozen=True)
class TileSources:
    """Where a worker finds the files of a strip's tiles (paths only).

    Attributes:
        camera: Camera file of the strip (all its CCDs).
        images: ``(ccd, path)`` of each CCD image, CCD names as the camera knows them.
        ref: Reference orthoimage path.
        dem: Reference DEM (GeoTIFF) path.
        ref_band: Band of the reference orthoimage.
        dem_band: Band of the DEM.
    """

    camera: str
    images: tuple[tuple[str, str], ...]
    ref: str
    dem: str
    ref_band: int = 1
    dem_band: int = 1

    def key(self) -> str:
        """A canonical JSON text of the sources (part of the worker cache key)."""
        doc = {
            "camera": self.camera,
            "images": [list(p) for p in self.images],
            "ref": self.ref,
            "dem": self.dem,
            "ref_band": self.ref_band,
            "dem_band": self.dem_band,
        }
        return json.dumps(doc, sort_keys=True, default=str)


@dataclass(frozen=True)
class TileTask:
    """One tile to match in a worker (small and picklable).

    Attributes:
        sources: :meth:`TileSources.key` of the strip.
        fine: The fine-stage matcher.
        coarse: The coarse-stage matcher; None: ``fine`` serves both stages.
        tile: The tile.
        config: The front-end settings.
        ratio: Image pixels per reference pixel of the tile's CCD (the plan's).
        raise_errors: Re-raise an exception of the matching instead of status ``error``.
        panels: A folder where the worker writes the tile's stage images for figures
            (:func:`planetref.frontend.tile_panels.save_panels`), or None.
    """

    sources: str
    fine: MatcherRecipe
    coarse: MatcherRecipe | None
    tile: Tile
    config: FrontendConfig
    ratio: float | None = None
    raise_errors: bool = False
    panels: str | None = None


@dataclass
class _WorkerContext:
    camera: Camera
    images: dict[str, CcdImage]
    ref: ReferenceOrtho
    dem: GridTerrain
    fine: Matcher
    coarse: Matcher


def _matchers_key(fine: MatcherRecipe, coarse: MatcherRecipe | None) -> str:
    doc = {"fine": fine.to_dict(), "coarse": None if coarse is None else coarse.to_dict()}
    return json.dumps(doc, sort_keys=True, default=str)


def open_worker_dem(path: str, band: int) -> GridTerrain:
    """The reference DEM in a worker, without the warning about filled holes.

    The run opened the same file before it dispatched any tile and said then which holes
    it filled (once per run); every worker process filling them again is no news.
    """
    from planetref.raster.dem_holes import DemHoleWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DemHoleWarning)
        return GridTerrain.from_geotiff(path, band=band)


@functools.lru_cache(maxsize=4)
def _worker_context(sources: str, matchers: str) -> _WorkerContext:
    """Open a strip's rasters, camera and DEM and build its matchers, once per process."""
    from planetref.camera.io import load_camera

    doc = json.loads(sources)
    recipes = json.loads(matchers)
    fine = MatcherRecipe.from_dict(recipes["fine"]).build()
    coarse = (
        fine if recipes["coarse"] is None else MatcherRecipe.from_dict(recipes["coarse"]).build()
    )
    return _WorkerContext(
        camera=load_camera(doc["camera"]),
        images={ccd: CcdImage(path) for ccd, path in doc["images"]},
        ref=ReferenceOrtho(doc["ref"], band=int(doc["ref_band"])),
        dem=open_worker_dem(doc["dem"], int(doc["dem_band"])),
        fine=fine,
        coarse=coarse,
    )


def run_tile_task(task: TileTask) -> dict[str, Any]:
    """Match one tile in a worker (the task function given to every executor).

    Returns:
        The tile's :meth:`~planetref.frontend.result.TileResult.to_dict`. An exception of
        the matching itself becomes status ``error`` (as in process) unless
        ``raise_errors``; failing to open the inputs raises (and the executor retries).
        With ``task.panels`` the stage images are written there first (a failed write
        only costs the figure a second match of the tile).
    """
    ctx = _worker_context(task.sources, _matchers_key(task.fine, task.coarse))
    try:
        res: TileResult = match_tile(
            task.tile,
            image=ctx.images[task.tile.ccd],
            camera=ctx.camera,
            ref=ctx.ref,
            terrain=ctx.dem,
            matcher=ctx.fine,
            config=task.config,
            ratio=task.ratio,
            coarse_matcher=ctx.coarse,
            debug=task.panels is not None,
        )
    except Exception as exc:
        if task.raise_errors:
            raise
        name = str(getattr(ctx.fine, "name", type(ctx.fine).__name__))
        res = error_result(task.tile, name, task.config.geometry, exc)
    if task.panels is not None and res.debug:
        from planetref.errors import PlanetrefError
        from planetref.frontend.tile_panels import save_panels

        try:
            save_panels(task.panels, res, pending=True)  # the parent adopts it
        except (OSError, PlanetrefError):
            pass  # the figure matches this tile again
        res.debug = []
    return res.to_dict()
