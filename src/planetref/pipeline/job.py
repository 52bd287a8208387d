"""The georeferencing job of one strip: everything its stages need, as one typed value."""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

from planetref.runtime.optional import CompileClock

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
        compile_clock: numba's compile seconds in this process (reported apart).
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
    compile_clock: CompileClock = field(default_factory=CompileClock)
    strip: StripSpec | None = None

    def clock(self) -> tuple[float, float]:
        """``(wall seconds, compile seconds)`` now, the start of a timed step."""
        return time.perf_counter(), self.compile_clock.seconds()

    def charge(self, key: str, t0: float, c0: float) -> None:
        """Add the seconds since :meth:`clock` to ``timing[key]``, less numba's compiling.

        The one-off compile of the kernels (tens of seconds on a fresh install) goes to
        ``timing["compile"]`` instead of the step that first called them.
        """
        compiled = self.compile_clock.seconds() - c0
        self.timing[key] = self.timing.get(key, 0.0) + time.perf_counter() - t0 - compiled
        if compiled > 0:
            self.timing["compile"] = self.timing.get("compile", 0.0) + compiled

    def for_strip(self, strip: StripSpec) -> StripJob:
        """This job for one strip."""
        return replace(self, strip=strip)

    @property
    def spec(self) -> StripSpec:
        """The strip (a job made by :meth:`for_strip`)."""
        if self.strip is None:
            raise RuntimeError("a run-wide StripJob has no strip")
        return self.strip
