"""The files of a georef run besides the report: orthoimages and figures."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

import numpy as np

from planetref.errors import PlanetrefError
from planetref.pipeline.rundir import RunDir

if TYPE_CHECKING:  # pragma: no cover
    from planetref.camera.base import Camera
    from planetref.control import McpTable
    from planetref.frontend.result import StripMatches, TileResult
    from planetref.pipeline.georef import StripJob
    from planetref.raster.image import CcdImage

__all__ = [
    "camera_isds",
    "campaign_points",
    "control_exports",
    "figure_residuals",
    "figures_matching",
    "mcp_points",
    "orthoimages",
]

log = logging.getLogger("planetref.pipeline.georef")


def orthoimages(
    job: StripJob, strip: str, camera: Camera, images: dict[str, CcdImage]
) -> list[str]:
    """Orthoimage of each CCD and their mosaic through the adjusted camera; the paths.

    One round pixel size per strip (``[ortho] gsd_m``, else the CCDs' median GSD
    rounded by :func:`~planetref.pipeline.ortho_strip.round_gsd`); the mosaic is
    ``<strip>/ortho/mosaic.tif`` (see :mod:`planetref.pipeline.ortho_strip`).
    """
    from planetref.frontend.geometry import image_gsd_m
    from planetref.pipeline.ortho_strip import orthorectify_strip, round_gsd

    gsd = job.cfg.ortho.gsd_m or round_gsd(
        float(np.median([image_gsd_m(camera, ccd, job.dem) for ccd in images]))
    )
    paths = {ccd: job.run.file(strip, "ortho", f"{ccd}.tif") for ccd in images}
    mosaic = job.run.file(strip, "ortho", "mosaic.tif") if len(images) > 1 else None
    try:
        res = orthorectify_strip(
            images, camera, job.dem, job.ref.crs, paths, gsd_m=gsd, mosaic=mosaic
        )
    except PlanetrefError as exc:
        log.warning("strip %s: no orthoimages (%s)", strip, exc)
        return []
    missing = sorted(set(images) - set(res.ccds))
    if missing:
        log.warning("strip %s CCDs %s: no orthoimage (footprint misses the DEM)", strip, missing)
    return [str(p) for p in res.ccds.values()] + ([str(res.mosaic)] if res.mosaic else [])


def camera_isds(job: StripJob, strip: str, camera: Camera) -> list[str]:
    """The adjusted native camera as one USGS CSM line-scan ISD per CCD; the paths.

    Written to ``<strip>/adjustment/isd/<strip>_<ccd>.json``; each ISD is checked against
    the native camera to 1e-3 pixel (the sampling and agreement reached are recorded in
    the ISD under ``planetref``). Other
    camera kinds (CSM, RPC) already have their own files in ``adjustment/cameras``.
    """
    from planetref.camera.csm import write_linescan_isds
    from planetref.camera.linescan import LineScanCamera

    if not isinstance(camera, LineScanCamera):
        return []
    folder = job.run.file(strip, "adjustment", "isd")
    folder.mkdir(parents=True, exist_ok=True)
    # An adjusted strip's nodes bend its trajectory at every Lagrange window switch, so
    # 1e-3 px needs an ephemeris every 1-2 lines (hiric-strip: 1 line, 2.9e-4 px);
    # starting at 4 lines skips the coarser tries that cannot reach it.
    return [str(p) for p in write_linescan_isds(camera, folder, strip, lines_per_sample=4.0)]


def control_exports(
    job: StripJob, name: str, points: Any, folder: tuple[str, ...]
) -> dict[str, str]:
    """MCPs (and tie points) as an ASP GCP file and an ISIS-style control network CSV.

    Args:
        job: The run.
        name: File stem.
        points: A :class:`~planetref.report.control_exports.ControlPoints`.
        folder: Folder parts inside the run folder.
    """
    from planetref.report.control_exports import write_asp_gcp, write_isis_cnet_csv

    body = job.manifest.body.ellipsoid()
    gcp = write_asp_gcp(points, body, job.run.file(*folder, f"{name}.gcp"))
    cnet = write_isis_cnet_csv(points, body, job.run.file(*folder, f"{name}_cnet.csv"))
    return {"asp_gcp": str(gcp), "isis_cnet_csv": str(cnet)}


def mcp_points(prep: Any, cfg: Any) -> Any:
    """A strip's MCPs (a :class:`~planetref.pipeline.networks.StripMcps`) for the exports."""
    from pathlib import Path

    from planetref.report.control_exports import ControlPoints

    paths = {c: str(Path(img.path).resolve()) for c, img in prep.images.items()}
    return ControlPoints.from_mcps(
        prep.table, paths, sigma_px=cfg.mcp.sigma_px, check=prep.check, prefix=f"{prep.id}:"
    )


def campaign_points(preps: list[Any], ties: Any, cfg: Any) -> Any:
    """Every strip's MCPs and the tie points between strips, for the exports."""
    from pathlib import Path

    from planetref.report.control_exports import ControlPoints

    paths = {(p.id, c): str(Path(img.path).resolve()) for p in preps for c, img in p.images.items()}
    parts = [mcp_points(p, cfg) for p in preps]
    if len(ties):
        opts = cfg.campaign
        parts.append(
            ControlPoints.from_ties(
                ties, paths, sigma_m=opts.tie_sigma_m, sigma_px=opts.tie_sigma_px
            )
        )
    return ControlPoints.concatenate(parts)


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
