"""The files of a georef run besides the report: orthoimages and figures."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

from planetref.errors import PlanetrefError
from planetref.pipeline.rundir import RunDir

if TYPE_CHECKING:  # pragma: no cover
    from planetref.camera.base import Camera
    from planetref.control import McpTable
    from planetref.frontend.result import StripMatches, TileResult
    from planetref.pipeline.georef import StripJob
    from planetref.raster.image import CcdImage

__all__ = ["figure_residuals", "figures_matching", "orthoimages"]

log = logging.getLogger("planetref.pipeline.georef")


def orthoimages(
    job: StripJob, strip: str, camera: Camera, images: dict[str, CcdImage]
) -> list[str]:
    """Orthoimage of each CCD through the adjusted camera; the paths written."""
    from planetref.frontend.geometry import image_gsd_m
    from planetref.pipeline.orthoimage import orthorectify_ccd

    paths = []
    for ccd, image in images.items():
        gsd = job.cfg.ortho.gsd_m or image_gsd_m(camera, ccd, job.dem)
        try:
            p = orthorectify_ccd(
                image,
                camera,
                ccd,
                job.dem,
                job.ref.crs,
                job.run.file(strip, "ortho", f"{ccd}.tif"),
                gsd_m=gsd,
            )
            paths.append(str(p))
        except PlanetrefError as exc:
            log.warning("strip %s CCD %s: no orthoimage (%s)", strip, ccd, exc)
    return paths


def figures_matching(
    job: StripJob,
    matches: StripMatches,
    table: McpTable,
    sizes: dict[str, tuple[int, int]],
    images: dict[str, CcdImage],
    camera: Camera,
) -> None:
    """The MCP distribution figure and the coarse/fine matches of the richest tile."""
    from planetref.frontend.tile import match_tile
    from planetref.report.figures_matching import draw_tile_selection, figure_mcp_distribution

    strip, run = job.spec.id, job.run
    figure_mcp_distribution(
        table,
        sizes,
        run.file("figures", f"{strip}_mcp_distribution.png"),
        ccd_order=list(sizes),
        title=f"{strip}: MCPs of {matches.matcher}",
    )
    fine, coarse = job.matchers.built()

    def rematch(t: TileResult) -> TileResult:
        return match_tile(
            t.tile,
            image=images[t.tile.ccd],
            camera=camera,
            ref=job.ref,
            terrain=job.dem,
            matcher=fine,
            config=job.cfg.frontend,
            ratio=matches.plans[t.tile.ccd].ratio,
            debug=True,
            coarse_matcher=coarse,
        )

    try:  # a figure must never sink a run
        draw_tile_selection(
            matches.tiles,
            rematch,
            run.file("figures", f"{strip}_tile_matches.png"),
            title=f"{matches.matcher}, {strip}: tiles with the most, the median and the "
            "fewest verified matches (rows); coarse and fine stage (columns)",
        )
    except PlanetrefError as exc:
        log.warning("no tile-match figure for %s: %s", strip, exc)


def figure_residuals(
    run: RunDir, strip: str, result: Any, sizes: dict[str, tuple[int, int]]
) -> None:
    """The residual-vector figure of a strip after adjustment."""
    from planetref.report.georef import figure_residual_vectors

    figure_residual_vectors(
        result,
        sizes,
        run.file("figures", f"{strip}_residuals.png"),
        title=f"{strip}: residuals after adjustment (inliers)",
    )
