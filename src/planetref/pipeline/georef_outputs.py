"""The files of a georef run besides the report: orthoimages and figures."""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from planetref.errors import AdjustmentError, MatcherFailedError, PlanetrefError

if TYPE_CHECKING:  # pragma: no cover
    from planetref.camera.base import Camera
    from planetref.control.exports import ControlPoints
    from planetref.control.mcp import McpTable
    from planetref.control.networks import StripMcps
    from planetref.frontend.result import StripMatches, TileResult
    from planetref.frontend.tiepoints import TiePoints
    from planetref.frontend.tile_panels import PanelStore
    from planetref.pipeline.config import GeorefConfig
    from planetref.pipeline.job import StripJob
    from planetref.pipeline.rundir import RunDir
    from planetref.raster.image import CcdImage
    from planetref.report.model import FrontendSettings, StripMatching
    from planetref.scene.manifest import SceneManifest

__all__ = [
    "camera_isds",
    "campaign_points",
    "control_exports",
    "figure_jitter",
    "figure_residuals",
    "figures_matching",
    "isd_files",
    "mcp_points",
    "optional_output",
    "orthoimages",
    "part_timed",
    "timed",
    "write_camera_isds",
    "write_failed_run",
]

log = logging.getLogger("planetref.pipeline.georef")
T = TypeVar("T")


@contextlib.contextmanager
def _seconds(timing: dict[str, float], *keys: str) -> Iterator[None]:
    """Add the block's wall seconds to each of ``timing[key]``."""
    t0 = time.perf_counter()
    try:
        yield
    finally:
        dt = time.perf_counter() - t0
        for key in keys:
            timing[key] = timing.get(key, 0.0) + dt


def timed(timing: dict[str, float], part: str) -> contextlib.AbstractContextManager[None]:
    """Add the block's seconds to ``timing["outputs"]`` and to ``timing["outputs_<part>"]``."""
    return _seconds(timing, "outputs", f"outputs_{part}")


def part_timed(timing: dict[str, float], part: str) -> contextlib.AbstractContextManager[None]:
    """Add the block's seconds to ``timing["outputs_<part>"]`` only.

    For parts that run at the same time as others (their union is timed once into
    ``timing["outputs"]`` by the caller).
    """
    return _seconds(timing, f"outputs_{part}")


def orthoimages(
    job: StripJob, strip: str, camera: Camera, images: dict[str, CcdImage]
) -> list[str]:
    """Orthoimage of each CCD and their mosaic through the adjusted camera; the paths.

    One round pixel size per strip (``[ortho] gsd_m``, else the CCDs' median GSD
    rounded by :func:`~planetref.products.ortho_strip.round_gsd`); the mosaic is
    ``<strip>/ortho/mosaic.tif`` (see :mod:`planetref.products.ortho_strip`).
    """
    from planetref.camera.mapping import image_gsd_m
    from planetref.products.ortho_strip import orthorectify_strip, round_gsd

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


def optional_output(what: str, make: Callable[[], T], empty: T) -> T:
    """Make an optional output (an ISD, an ASP/ISIS file); on failure warn and go on.

    The run's results (cameras, report, orthoimages) do not depend on these files: an
    export that cannot be made (a camera the ISD sampling cannot reproduce to its
    tolerance, a full disk) costs that file only, with a warning naming it and the
    reason, on every rerun alike, never the run.

    Args:
        what: The output, for the warning ("strip strip1: CSM ISDs").
        make: Writes it and returns what the report lists.
        empty: What the report lists when it failed.
    """
    try:
        return make()
    except Exception as exc:  # any failure of the export is the export's alone
        reason = " ".join(str(exc).split()) or type(exc).__name__
        log.warning(
            "%s not written (%s: %s); the run goes on without it", what, type(exc).__name__, reason
        )
        return empty


def camera_isds(job: StripJob, strip: str, camera: Camera) -> list[str]:
    """:func:`write_camera_isds`, optional: a failure is a warning (:func:`optional_output`)."""
    return optional_output(
        f"strip {strip}: CSM ISDs", lambda: write_camera_isds(job, strip, camera), []
    )


def write_camera_isds(job: StripJob, strip: str, camera: Camera) -> list[str]:
    """The adjusted native camera as one USGS CSM line-scan ISD per CCD; the paths.

    Written to ``<strip>/adjustment/isd/<strip>_<ccd>.json``; each ISD is checked against
    the native camera to 1e-3 pixel (the sampling and agreement reached are recorded in
    the ISD under ``planetref``). Other
    camera kinds (CSM, RPC) already have their own files in ``adjustment/cameras``.
    A digest of the camera and the settings (``<strip>.inputs.sha256`` next to the ISDs)
    lets a resumed run keep ISDs whose camera did not change.
    """
    from planetref.camera.csm import write_linescan_isds
    from planetref.runtime.atomic import atomic_path

    paths, stamp = isd_files(job, strip, camera)
    if stamp is None:  # not a native line-scan camera
        return []
    folder = stamp.parent
    # An adjusted strip's nodes bend its trajectory at every Lagrange window switch, so
    # 1e-3 px needs an ephemeris every 1-2 lines (hiric-strip: 1 line, 2.9e-4 px);
    # starting at 4 lines skips the coarser tries that cannot reach it.
    lps = 4.0
    digest = _isd_digest(camera, lps)
    if stamp.is_file() and stamp.read_text(encoding="utf-8").strip() == digest:
        if all(p.is_file() for p in paths):
            return [str(p) for p in paths]
    stamp.unlink(missing_ok=True)
    written = write_linescan_isds(camera, folder, strip, lines_per_sample=lps)
    with atomic_path(stamp) as tmp:
        tmp.write_text(digest + "\n", encoding="utf-8")
    return [str(p) for p in written]


def isd_files(job: StripJob, strip: str, camera: Camera) -> tuple[list[Path], Path | None]:
    """Record a strip's ISD files and digest in the run folder; ``(ISD paths, digest path)``.

    Called before :func:`camera_isds` runs in another thread, so that the run folder's
    record (not thread-safe) changes only in the calling thread. Nothing for a camera
    that is not a native line-scan camera (``([], None)``).
    """
    from planetref.camera.csm.export import isd_file_name
    from planetref.camera.linescan import LineScanCamera

    if not isinstance(camera, LineScanCamera):
        return [], None
    folder = job.run.file(strip, "adjustment", "isd")
    folder.mkdir(parents=True, exist_ok=True)
    paths = [
        job.run.file(strip, "adjustment", "isd", isd_file_name(strip, c)) for c in camera.ccd_names
    ]
    return paths, job.run.file(strip, "adjustment", "isd", f"{strip}.inputs.sha256")


def _isd_digest(camera: Camera, lines_per_sample: float) -> str:
    """SHA-256 of what a strip's ISDs are made from (the camera, the sampling, the code)."""
    import hashlib
    import json

    from planetref import __version__

    doc = {
        "camera": camera.to_dict(),  # type: ignore[attr-defined]
        "lines_per_sample": lines_per_sample,
        "tolerance_px": 1e-3,
        "version": __version__,
    }
    blob = json.dumps(doc, sort_keys=True, default=repr).encode()
    return hashlib.sha256(blob).hexdigest()


def control_exports(
    job: StripJob, name: str, points: ControlPoints, folder: tuple[str, ...]
) -> dict[str, str]:
    """MCPs (and tie points) as an ASP GCP file and an ISIS-style control network CSV.

    Optional: a failure is a warning (:func:`optional_output`) and an empty dict.

    Args:
        job: The run.
        name: File stem.
        points: A :class:`~planetref.control.exports.ControlPoints`.
        folder: Folder parts inside the run folder.
    """
    from planetref.control.exports import write_asp_gcp, write_isis_cnet_csv

    def write() -> dict[str, str]:
        body = job.manifest.body.ellipsoid()
        gcp = write_asp_gcp(points, body, job.run.file(*folder, f"{name}.gcp"))
        cnet = write_isis_cnet_csv(points, body, job.run.file(*folder, f"{name}_cnet.csv"))
        return {"asp_gcp": str(gcp), "isis_cnet_csv": str(cnet)}

    return optional_output(f"{'/'.join(folder)}: ASP GCP and ISIS control files", write, {})


def mcp_points(prep: StripMcps, cfg: GeorefConfig) -> ControlPoints:
    """A strip's MCPs for the exports."""
    from planetref.control.exports import ControlPoints

    paths = {c: str(Path(img.path).resolve()) for c, img in prep.images.items()}
    return ControlPoints.from_mcps(
        prep.mcps.table,
        paths,
        sigma_px=cfg.mcp.sigma_px,
        check=prep.mcps.check,
        prefix=f"{prep.id}:",
    )


def campaign_points(preps: list[StripMcps], ties: TiePoints, cfg: GeorefConfig) -> ControlPoints:
    """Every strip's MCPs and the tie points between strips, for the exports."""
    from planetref.control.exports import ControlPoints

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
    store: PanelStore | None = None,
) -> None:
    """The MCP distribution figure and the coarse/fine matches of three tiles (Fig. 2).

    Both are drawn by ``job.figures`` (a child process). Fig. 2's tiles come from
    ``store`` (kept during matching, by this process or by the parallel workers); a tile
    not in it (a resumed run's journal tile without its file, or a worker that could not
    write it) is matched again here.
    """
    from planetref.frontend.tile import match_tile
    from planetref.report.figures_matching import (
        MatchPanel,
        figure_mcp_distribution,
        figure_tile_grid,
        mcp_distribution_sdu,
        panels_from_tile,
        tile_selection_rows,
    )

    strip, run = job.spec.id, job.run
    columns = {k: np.asarray(table[k]) for k in ("ccd", "line", "sample")}
    grids, sdu = mcp_distribution_sdu(columns, sizes)  # here, where the front end is loaded
    job.figures.submit(
        f"{strip}_mcp_distribution",
        figure_mcp_distribution,
        columns,
        sizes,
        run.file("figures", f"{strip}_mcp_distribution.png"),
        ccd_order=list(sizes),
        title=f"{strip}: MCPs of {matches.matcher}",
        grids=grids,
        sdu=sdu,
    )

    def panels_of(t: TileResult) -> list[MatchPanel]:
        kept = None if store is None else store.panels(t.tile_id)
        if kept is not None:
            return kept
        fine, coarse = job.matchers.built()
        return panels_from_tile(
            match_tile(
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
        )

    rows = tile_selection_rows(matches.tiles, panels_of)
    if not rows:
        log.warning("no tile-match figure for %s: no tile to draw", strip)
        return
    job.figures.submit(
        f"{strip}_tile_matches",
        figure_tile_grid,
        rows,
        run.file("figures", f"{strip}_tile_matches.png"),
        title=f"{matches.matcher}, {strip}: tiles with the most, the median and the "
        "fewest verified matches (rows); coarse and fine stage (columns)",
    )


def figure_jitter(job: StripJob, strip: str, result: Any, truth: dict[str, Any] | None) -> None:
    """figures/<strip>_jitter.png: the jitter stage's estimate (and the truth's), if any."""
    series = result.jitter.get(strip)
    if series is None:
        return
    from planetref.report.adjustment import jitter_truth
    from planetref.report.figures_adjust import figure_jitter as draw

    tru = jitter_truth(result, strip, truth)
    job.figures.submit(
        f"{strip}_jitter",
        draw,
        series.time_s,
        series.angles_rad * 1e6,
        series.sigma_rad * 1e6,
        job.run.file("figures", f"{strip}_jitter.png"),
        truth_urad=None if tru is None else tru * 1e6,
        limit_hz=series.resolution.limit_hz,
        title=f"{strip}: estimated jitter (dense nodes minus the node model)"
        + (" and the truth" if tru is not None else ""),
    )


def figure_residuals(
    job: StripJob, strip: str, result: Any, sizes: dict[str, tuple[int, int]], index: int = 0
) -> None:
    """The residual-vector figure of camera ``index`` of a result (drawn by ``job.figures``).

    Only what the figure reads of the result travels to the figure process
    (:func:`~planetref.report.blocks.camera_view`).
    """
    from planetref.report.blocks import camera_view
    from planetref.report.georef import figure_residual_vectors

    job.figures.submit(
        f"{strip}_residuals",
        figure_residual_vectors,
        camera_view(result, index),
        dict(sizes),
        job.run.file("figures", f"{strip}_residuals.png"),
        title=f"{strip}: residuals after adjustment (inliers)",
    )


def write_failed_run(
    run: RunDir,
    exc: MatcherFailedError | AdjustmentError,
    matcher: str,
    manifest: SceneManifest,
    matched: Mapping[str, StripMatching],
    timing: Mapping[str, float],
    settings: FrontendSettings,
) -> MatcherFailedError:
    """report.json and report.md of a run whose matcher ran but failed.

    Returns:
        The error to raise: ``exc`` itself, or for a degenerate adjustment a
        :class:`MatcherFailedError` saying so; its ``report`` is the report written.

    Args:
        run: The run directory.
        exc: The failure (a MatcherFailedError's ``matching`` holds the failing strip's
            block; an adjustment's failure concerns the strips matched).
        matcher: Matcher name.
        manifest: The scene.
        matched: Strip id -> matching block of the strips matched before.
        timing: Seconds per step.
        settings: The front-end settings (:func:`frontend_settings`).
    """
    from planetref.report.blocks import failed_report
    from planetref.report.georef import write_georef_markdown

    if isinstance(exc, AdjustmentError):
        failure = MatcherFailedError(f"adjustment failed: {exc}")
        failure.__cause__ = exc
    else:
        failure = exc
    got = {**matched, **failure.matching}
    failure.report = failed_report(
        matcher,
        manifest.name,
        got,
        str(failure),
        timing,
        settings,
        strips_not_run=[s.id for s in manifest.strips if s.id not in got],
    ).to_json()
    run.write_json("report.json", failure.report)
    write_georef_markdown(failure.report, run.file("report.md"))
    return failure
