"""The georeferencing job of one strip: everything its stages need, as one typed value."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # pragma: no cover
    from planetref.camera.base import Camera
    from planetref.frontend.matchers import MatcherPair
    from planetref.pipeline.config import GeorefConfig
    from planetref.pipeline.rundir import RunDir
    from planetref.raster.dem import GridTerrain
    from planetref.raster.ortho import ReferenceOrtho
    from planetref.report.figure_jobs import FigureJobs
    from planetref.runtime.execute import Executor
    from planetref.scene.inputs import TruthDem
    from planetref.scene.manifest import SceneManifest, StripSpec

__all__ = ["StripJob"]


@dataclass(frozen=True)
class StripJob:
    """Everything the georeferencing of one strip needs (one typed value, not 13 arguments).

    Attributes:
        run: The run directory.
        manifest: The scene manifest.
        root: Folder the manifest's relative paths start from.
        ref: The reference orthoimage.
        dem: The reference DEM.
        matchers: The run's matchers.
        cfg: The run's settings.
        executor: Where tiles are matched.
        progress: Show progress bars.
        truth_cameras: True camera per strip id (simulated scenes), else empty.
        truth_dem: True DEM (simulated scenes, read when used), else None.
        timing: Seconds per step, summed over the strips (updated in place).
        figures: Draws the figures in a child process while the run goes on.
        strip: The strip (None in the run-wide template that :meth:`for_strip` copies).
    """

    run: RunDir
    manifest: SceneManifest
    root: Path
    ref: ReferenceOrtho
    dem: GridTerrain
    matchers: MatcherPair
    cfg: GeorefConfig
    executor: Executor
    progress: bool
    truth_cameras: dict[str, Camera]
    truth_dem: TruthDem | None
    timing: dict[str, float]
    figures: FigureJobs
    strip: StripSpec | None = None

    def for_strip(self, strip: StripSpec) -> StripJob:
        """This job for one strip."""
        return replace(self, strip=strip)

    @property
    def spec(self) -> StripSpec:
        """The strip (a job made by :meth:`for_strip`)."""
        if self.strip is None:
            raise RuntimeError("a run-wide StripJob has no strip")
        return self.strip
