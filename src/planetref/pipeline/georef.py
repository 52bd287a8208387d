"""``georef``: one scene, one matcher, from raw CCD images to adjusted cameras.

Stages, per strip: tiling -> coarse-to-fine matching against the reference ortho ->
matched control points (MCPs) -> rigorous line-scan bundle adjustment -> metrics ->
outputs (adjusted cameras, RPCs, residuals, orthoimages, figures, report).

Run directory layout::

    run.json, config.json, planetref.log, report.json, report.md
    <strip>/tiles.jsonl              per-tile matching journal (resume)
    <strip>/tile_panels/*.npz        stage images of the tiles Fig. 2 draws (every tile, by
                                     this process or a worker, until it is drawn; a resume
                                     keeps them)
    <strip>/mcps.parquet, mcps.gpkg  matched control points
    <strip>/adjustment/...           adjusted cameras, RPCs, residuals, per-strip report
    <strip>/adjustment/isd/*.json    adjusted native camera as USGS CSM ISDs (one per CCD)
    <strip>/exports/*.gcp, *_cnet.csv   MCPs as an ASP GCP file, ISIS-style control network
    <strip>/ortho/<ccd>.tif          orthoimages through the adjusted camera (input type,
                                     round pixel size, overviews)
    <strip>/ortho/mosaic.tif         the strip's mosaic of all CCDs
    reference/dem_body.tif           a DEM above the areoid in body heights (parallel runs)
    figures/*.png                    matches of one tile, MCP distribution, residuals
"""

from __future__ import annotations

import contextlib
import contextvars
import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from planetref import __version__
from planetref.control.ground_sigma import reference_gsd_m
from planetref.control.networks import (
    StripMcps,
    check_points,
    joint_network,
    mcp_ground_sigmas,
    template_overlap,
    template_support_m,
)
from planetref.errors import AdjustmentError, MatcherFailedError
from planetref.frontend.matchers import (
    MatcherPair,
    build_matchers,
    matcher_options,
    matcher_recipes,
    matcher_weight_files,
)
from planetref.pipeline.config import GeorefConfig
from planetref.pipeline.georef_outputs import (
    camera_isds,
    campaign_points,
    control_exports,
    figure_residuals,
    figures_matching,
    isd_files,
    mcp_points,
    orthoimages,
    part_timed,
    timed,
    write_failed_run,
)
from planetref.pipeline.job import StripJob
from planetref.pipeline.rundir import RunDir, config_digest
from planetref.pipeline.systematic import declared_uncertainty, systematic_settings
from planetref.products.ortho_strip import GDAL_CACHE_MB
from planetref.report.blocks import (
    adjustment_block,
    check_block,
    combined_report,
    frontend_settings,
    matching_block,
    result_block,
    rmse_px,
    too_few_mcps,
)
from planetref.runtime.threads import single_threaded_blas
from planetref.scene.inputs import (
    check_body,
    check_strips,
    open_reference,
    scene_input_files,
    scene_path,
    strip_cameras,
    truth_inputs,
    truth_terrain,
    worker_dem,
)

if TYPE_CHECKING:  # pragma: no cover
    from planetref.camera.base import Camera
    from planetref.frontend.result import StripMatches
    from planetref.frontend.tasks import MatcherRecipe
    from planetref.frontend.tile_panels import PanelStore
    from planetref.matching.base import Matcher
    from planetref.raster.image import CcdImage
    from planetref.runtime.execute import Executor

__all__ = [
    "GeorefOutcome",
    "MatcherPair",
    "StripJob",
    "build_matchers",
    "matcher_options",
    "matcher_recipes",
    "matcher_weight_files",
    "run_georef",
    "scene_input_files",
]

log = logging.getLogger(__name__)


@dataclass
class GeorefOutcome:
    """What :func:`run_georef` returns.

    Attributes:
        report: The report.json content.
        run_dir: The run directory.
        files: Paths of the main outputs.
    """

    report: dict[str, Any]
    run_dir: Path
    files: dict[str, Any] = field(default_factory=dict)


def run_georef(
    scene: str | os.PathLike[str],
    matcher: str,
    out: str | os.PathLike[str],
    *,
    config: GeorefConfig | None = None,
    weights_dir: str | os.PathLike[str] | None = None,
    overwrite: bool = False,
    progress: bool = True,
    matchers: tuple[Matcher, Matcher] | None = None,
    executor: Executor | str | None = None,
) -> GeorefOutcome:
    """Georeference every strip of a scene with one matcher.

    Args:
        scene: ``scene.toml`` or its folder.
        matcher: Registry name of the matcher.
        out: Run directory (resumed when it holds the same run).
        config: Settings (defaults when ``None``).
        weights_dir: Folder of pretrained weights (see ``planetref matchers``).
        overwrite: Replace a different previous run in ``out``.
        progress: Show progress bars.
        matchers: Prebuilt ``(fine, coarse)`` matchers (reused across runs by ``compare``).
        executor: Where the tiles are matched: a :class:`planetref.runtime.execute.Executor`
            (left open), or a ``--scheduler`` spec (``"pool:4"``, ``"dask-local:4"``,
            ``"tcp://HOST:PORT"``; started for this run and closed after). Default: in
            this process. The results do not depend on it.

    Returns:
        The report and where things were written.

    Raises:
        PlanetrefError: Bad scene, reference or camera files, missing weights, no
            overlap, a strip without enough MCPs, a degenerate adjustment.
    """
    import rasterio

    from planetref.report.figure_jobs import FigureJobs
    from planetref.report.georef import write_georef_markdown
    from planetref.runtime.execute import Executor, make_executor
    from planetref.scene.manifest import load_manifest

    owned = executor is not None and not isinstance(executor, Executor)
    ex = make_executor(executor)
    try:
        t_start = time.perf_counter()
        cfg = config or GeorefConfig()
        scene_file = scene_path(scene)
        manifest, root = load_manifest(scene_file)
        # How far the coarse stage searches: the config's, else the scene's declared
        # a-priori uncertainty of its initial cameras (part of the run's identity).
        fe, uncertainty_source = declared_uncertainty(cfg.frontend, manifest)
        cfg = cfg.model_copy(update={"frontend": fe})
        # Inputs checked and matchers built before the run folder is claimed, so a failed
        # start (unknown matcher, missing weights, unreadable reference, camera or image, no
        # overlap) leaves nothing behind.
        input_warnings: list[str] = []  # logged once the run's log is open, and reported
        ref, dem = open_reference(manifest, root, input_warnings)
        body = manifest.body.ellipsoid()
        check_body(body, ref, "reference ortho")
        check_body(body, dem, "reference DEM", manifest.resolve(root, manifest.reference.dem))
        check_strips(manifest, root, ref, dem)
        ref_gsd = float(np.mean(ref.ground_sampling_m()))
        pair = matcher_recipes(
            matcher,
            cfg.matchers.get(matcher, {}),
            cfg.frontend,
            ref_gsd,
            weights_dir=weights_dir,
        )
        if matchers is not None:
            pair = replace(pair, instances=matchers)
        else:
            pair.built()  # fail on an unknown matcher or missing weights now
        identity = {
            "scene": str(scene_file),
            "matcher": matcher,
            "config": config_digest(cfg.identity_json()),
        }
        run = RunDir(
            out,
            "georef",
            identity,
            overwrite=overwrite,
            inputs=[scene_file, *scene_input_files(manifest, root)],
            weights=matcher_weight_files(matcher, weights_dir),
        )
        with run.logging_to_file(), contextlib.ExitStack() as stack:
            # GDAL's block cache (default 5 % of the RAM) would keep every raw block read.
            stack.enter_context(rasterio.Env(GDAL_CACHEMAX=GDAL_CACHE_MB))
            log.info(
                "georef %s with %s into %s%s",
                scene_file,
                matcher,
                run.path,
                " (resuming)" if run.resumed else "",
            )
            log.info(
                "a-priori uncertainty %g m (%s): coarse level %d",
                cfg.frontend.uncertainty_m,
                uncertainty_source,
                cfg.frontend.coarse_level(ref_gsd),
            )
            for warning in input_warnings:  # stderr, planetref.log, and report.json below
                log.warning("%s", warning)
            run.write_json(
                "config.json",
                {
                    "scene": str(scene_file),
                    "matcher": matcher,
                    "weights_dir": None if weights_dir is None else str(weights_dir),
                    "planetref_version": __version__,
                    **cfg.to_json(),
                },
            )
            truth_cams, truth_dem = truth_inputs(manifest, root)
            if ex.parallel:
                log.info("matching tiles on %s", ex.name)
            job = StripJob(
                run=run,
                manifest=manifest,
                root=root,
                ref=ref,
                dem=dem,
                matchers=pair,
                cfg=cfg,
                executor=ex,
                progress=progress,
                truth_cameras=truth_cams,
                truth_dem=truth_dem,
                timing={"matching": 0.0, "adjustment": 0.0, "outputs": 0.0},
                figures=stack.enter_context(FigureJobs()),
            )
            job.figures.start()  # matplotlib is imported there while the tiles are matched
            stack.callback(job.compile_clock.start().stop)  # compile seconds apart
            settings = frontend_settings(cfg.frontend)
            matched: dict[str, dict[str, Any]] = {}  # matching blocks, for a failed run
            try:
                if cfg.campaign.adjust_together and len(manifest.strips) > 1:
                    preps = [_strip_mcps(job.for_strip(s), matched) for s in manifest.strips]
                    with single_threaded_blas():  # RPC refits, reports, orthoimages
                        strips, campaign = _adjust_together(job, preps)
                else:
                    strips, campaign = {}, None
                    for s in manifest.strips:
                        prep = _strip_mcps(job.for_strip(s), matched)
                        with single_threaded_blas():  # RPC refits, reports, orthoimages
                            strips[s.id] = _adjust_strip(job.for_strip(s), prep)
            except (MatcherFailedError, AdjustmentError) as exc:  # the matcher ran: a result
                with timed(job.timing, "figures"):
                    job.figures.wait()
                job.timing["total"] = time.perf_counter() - t_start
                failure = write_failed_run(
                    run, exc, matcher, manifest, matched, job.timing, settings
                )
                raise failure from failure.__cause__
            with timed(job.timing, "figures"):  # the figures not drawn yet
                job.figures.wait()
            job.timing["total"] = time.perf_counter() - t_start
            report = combined_report(matcher, manifest.name, strips, job.timing, settings)
            if campaign is not None:
                report["adjustment"] = campaign.pop("adjustment")
                report["campaign"] = campaign
            if input_warnings:
                report["input_warnings"] = list(input_warnings)
            # A resumed run's step timings are what this process spent; the tiles' own
            # cost is in timing_s.matching_tiles (from the journal), so it says so.
            report["resumed"] = bool(run.resumed)
            run.write_json("report.json", report)
            write_georef_markdown(report, run.file("report.md"))
    finally:
        if owned:
            ex.close()
    files = {"report_json": str(run.path / "report.json"), "report_md": str(run.path / "report.md")}
    for sid, blk in strips.items():
        files[sid] = blk.get("files", {})
    return GeorefOutcome(report=report, run_dir=run.path, files=files)


def _match(
    job: StripJob, camera: Camera, images: dict[str, CcdImage], store: PanelStore
) -> StripMatches:
    """Match a strip's tiles, here or on the executor; their stage images go to ``store``.

    Workers write the stage images of their tiles into the store's folder themselves.
    """
    from planetref.frontend.strip import match_strip
    from planetref.frontend.tasks import TileSources

    strip, man, pair = job.spec, job.manifest, job.matchers
    if job.executor.parallel:
        sources = TileSources(
            camera=str(man.resolve(job.root, strip.ccds[0].camera)),
            images=tuple((c, str(Path(img.path).resolve())) for c, img in images.items()),
            ref=str(man.resolve(job.root, man.reference.ortho)),
            dem=str(
                worker_dem(
                    job.manifest, job.root, job.dem, job.run.file("reference", "dem_body.tif")
                )
            ),
            ref_band=man.reference.ortho_band,
            dem_band=1 if man.reference.dem_datum != "body" else man.reference.dem_band,
        )
        fine: Matcher | MatcherRecipe = pair.fine
        coarse: Matcher | MatcherRecipe | None = pair.coarse
    else:
        sources = None
        fine, coarse = pair.built()
    return match_strip(
        camera,
        images,
        job.ref,
        job.dem,
        fine,
        job.cfg.frontend,
        journal=job.run.file(strip.id, "tiles.jsonl"),
        progress=job.progress,
        coarse_matcher=coarse,
        executor=job.executor,
        sources=sources,
        debug_sink=store.add,
        panels_dir=store.folder.resolve() if job.executor.parallel else None,
    )


def _strip_mcps(job: StripJob, matched: dict[str, dict[str, Any]]) -> StripMcps:
    """Match a strip's tiles, write its MCPs, draw its check points; ``matched`` += block."""
    from planetref.control.mcp import mcps_from_tiles, write_mcps
    from planetref.frontend.tile_panels import PanelStore
    from planetref.report.figures_matching import select_tiles

    strip, cfg = job.spec, job.cfg
    camera, images = strip_cameras(job.manifest, job.root, strip)  # checked by check_strips
    sizes = {c: camera.image_size(c) for c in images}
    out: dict[str, Any] = {"files": {}}

    t0, c0 = job.clock()
    # Fig. 2's tiles, kept in the run folder as they are matched (a resumed run finds them).
    store = PanelStore(persistent=job.run.path / strip.id / "tile_panels")
    matches = _match(job, camera, images, store)
    table = mcps_from_tiles(matches, ref=job.ref, dem=job.dem)
    job.charge("matching", t0, c0)
    # What the tiles took when they were matched, as their journal records it: a resumed
    # run keeps the original cost instead of the seconds it spent reading the journal.
    job.timing["matching_tiles"] = job.timing.get("matching_tiles", 0.0) + sum(
        float(t.timings.get("total", 0.0)) for t in matches.tiles
    )
    log.info(
        "strip %s: %d tiles matched with %s in %.0f s (%s): %d MCPs",
        strip.id,
        len(matches.tiles),
        matches.matcher,
        time.perf_counter() - t0,
        ", ".join(f"{k} {v}" for k, v in matches.status_counts().items()),
        len(table),
    )
    written = write_mcps(table, job.run.file(strip.id, "mcps.parquet"))
    out["files"]["mcps"] = [
        str(p) for p in (written if isinstance(written, list | tuple) else [written])
    ]
    cam = job.truth_cameras.get(strip.id)  # the true DEM read for it, then let go
    truth = None if cam is None else (cam, job.ref, truth_terrain(job.truth_dem, job.dem))
    out["matching"] = matched[strip.id] = matching_block(matches, table, sizes, truth)
    del truth  # the true DEM is not held through the figures
    for item in out["matching"]["tiles_lost"]:
        log.warning(
            "strip %s tile %s: %s %s", strip.id, item["tile"], item["status"], item["message"]
        )
    with single_threaded_blas(), timed(job.timing, "figures"), store:  # figures are outputs
        figures_matching(job, matches, table, sizes, images, camera, store)
        store.keep_only(t.tile_id for _, t in select_tiles(matches.tiles))
    n = len(table)
    if n < cfg.mcp.min_mcps:
        raise too_few_mcps(strip.id, matches.matcher, out["matching"], cfg.mcp.min_mcps)
    check = check_points(
        table["tile_id"],
        table["ccd"],
        cfg.mcp.check_fraction,
        cfg.mcp.min_mcps,
        cfg.mcp.seed,
        cfg.mcp.check_blocks,
    )
    return StripMcps(strip.id, camera, images, sizes, table, check, out)


def _adjust_strip(job: StripJob, prep: StripMcps) -> dict[str, Any]:
    """Adjust one strip on its own with its MCPs and write its outputs."""
    from planetref.adjust.api import adjust
    from planetref.control.network import Network
    from planetref.report.adjustment import write_outputs

    cfg, run, table, out = job.cfg, job.run, prep.table, prep.out
    network = Network.mcps(
        prep.camera,
        line=table["line"],
        sample=table["sample"],
        xyz=table.xyz(),
        ccd=np.asarray(table["ccd"]).astype(str),
        camera_id=prep.id,
        sigma_px=cfg.mcp.sigma_px,
        check=prep.check,
        **mcp_ground_sigmas(table),
    )
    adjust_cfg, declared = systematic_settings(
        cfg.adjust,
        job.manifest,
        [prep.id],
        reference_gsd_m(job.ref),
        mcp_overlap(job, [table]),
    )
    t0, c0 = job.clock()
    result = adjust(network, adjust_cfg)
    job.charge("adjustment", t0, c0)
    t0, c0 = job.clock()
    truth = {prep.id: job.truth_cameras[prep.id]} if prep.id in job.truth_cameras else None
    camera = result.cameras[prep.id]
    # Adjusted cameras, RPC refits, residuals and reports first (beside the orthoimages
    # they raised the peak memory by ~180 MB on hiric-strip, for ~1.6 CPU-s of overlap).
    with part_timed(job.timing, "adjustment_files"):
        dem = truth_terrain(job.truth_dem, job.dem)
        out["files"]["adjustment"] = write_outputs(
            result,
            run.file(prep.id, "adjustment"),
            truth=truth,
            terrain=dem,
            plots=False,  # figures/<strip>_residuals.png draws the same residual vectors
        )
        out["adjustment"] = result_block(result, systematic_source=declared)
        out["check"] = check_block(result, truth, dem) if truth else None
    del dem  # a truth DEM is not held through the orthoimages (the run's memory peak)
    out["warnings"] = list(result.warnings)

    def isds() -> list[str]:
        with part_timed(job.timing, "isd"):
            return camera_isds(job, prep.id, camera)

    # The CSM ISDs in one thread beside the orthoimages (single-threaded BLAS; the
    # orthoimages' kernels release the GIL). Their files are recorded in the run folder
    # here, and the thread runs in this context (its atomic writes are watched).
    isd_files(job, prep.id, camera)
    with ThreadPoolExecutor(1, thread_name_prefix="isd") as pool:
        isd = pool.submit(contextvars.copy_context().run, isds)
        with part_timed(job.timing, "exports"):
            out["files"]["exports"] = control_exports(
                job, f"{prep.id}_mcps", mcp_points(prep, cfg), (prep.id, "exports")
            )
        with part_timed(job.timing, "figures"):  # drawn while the orthoimages are written
            figure_residuals(job, prep.id, result, prep.sizes)
        if cfg.ortho.enabled:
            with part_timed(job.timing, "orthoimages"):
                out["files"]["ortho"] = orthoimages(job, prep.id, camera, prep.images)
        out["files"]["isd"] = isd.result()
    job.charge("outputs", t0, c0)
    out["_residuals"] = (result.residual, result.inlier)
    return out


def mcp_overlap(job: StripJob, tables: list[Any]) -> float:
    """Mean number of MCPs per independent measurement (:func:`template_overlap`)."""
    fine = job.matchers.fine
    support = template_support_m(
        fine.name, fine.options, job.cfg.frontend.fine_upsample, reference_gsd_m(job.ref)
    )
    if support is None:
        return 1.0
    x = np.concatenate([np.asarray(t["ref_x"], float) for t in tables])
    y = np.concatenate([np.asarray(t["ref_y"], float) for t in tables])
    return template_overlap(x, y, support)


def _adjust_together(
    job: StripJob, preps: list[StripMcps]
) -> tuple[dict[str, dict[str, Any]], dict[str, Any]]:
    """Adjust every strip in one network: all MCPs plus tie points between strips.

    The joint adjustment's outputs (every camera, residuals, parameters) go to
    ``campaign/adjustment``; each strip keeps its own blocks (metrics of its
    observations, true geolocation error, orthoimages) computed from the joint result.

    Returns:
        ``(strips, campaign)``: the per-strip blocks (as :func:`_adjust_strip` returns)
        and the ``campaign`` block of report.json (its ``adjustment`` entry is the joint
        adjustment's).
    """
    from planetref.adjust.api import adjust
    from planetref.frontend.tiepoints import find_tie_points
    from planetref.report.adjustment import write_outputs

    cfg, run, timing = job.cfg, job.run, job.timing
    opts = cfg.campaign
    if opts.tie_sigma_m is not None and opts.tie_sigma_m < cfg.frontend.uncertainty_m:
        log.warning(
            "campaign.tie_sigma_m = %g m is below the initial cameras' uncertainty "
            "(%g m) that the tie points' a-priori ground comes from: it will pull "
            "the strips towards their initial error",
            opts.tie_sigma_m,
            cfg.frontend.uncertainty_m,
        )
    t0 = time.perf_counter()
    fine, _ = job.matchers.built()
    ties = find_tie_points(
        {p.id: (p.camera, p.images) for p in preps}, job.ref, job.dem, fine, cfg.frontend, opts
    )
    timing["tie_points"] = time.perf_counter() - t0
    log.info("campaign: %d tie points between %d strips", len(ties), len(preps))
    network = joint_network(preps, ties, cfg.mcp, cfg.campaign)
    adjust_cfg, declared = systematic_settings(
        cfg.adjust,
        job.manifest,
        [p.id for p in preps],
        reference_gsd_m(job.ref),
        mcp_overlap(job, [p.table for p in preps]),
    )
    t0, c0 = job.clock()
    result = adjust(network, adjust_cfg)
    job.charge("adjustment", t0, c0)
    t0, c0 = job.clock()
    cams = {p.id: p.camera for p in preps}
    truth = {sid: job.truth_cameras[sid] for sid in cams if sid in job.truth_cameras} or None
    dem = truth_terrain(job.truth_dem, job.dem)
    joint_files = write_outputs(
        result,
        run.file("campaign", "adjustment"),
        truth=truth,
        terrain=dem,
        plots=False,  # figures/<strip>_residuals.png draws the same residual vectors
    )
    checks = {
        sid: check_block(result, {sid: job.truth_cameras[sid]}, dem)
        for sid in cams
        if sid in job.truth_cameras
    }
    del dem  # a truth DEM is not held through the orthoimages (the run's memory peak)
    strips: dict[str, dict[str, Any]] = {}
    is_tie = np.asarray(network.point_kind)[network.obs_point] == "tie"
    for ci, p in enumerate(preps):
        out = p.out
        out["files"]["adjustment"] = joint_files
        cm = result.metrics["cameras"][p.id]
        on = network.obs_camera == ci
        out["adjustment"] = adjustment_block(
            cm["after"],
            rmse_px_before=cm["before"]["rmse_px"],
            sigma0=result.sigma0,
            converged=result.converged,
            n_tie_observations=int(np.count_nonzero(on & is_tie)),
            ccds={c: m["after"] for c, m in cm.get("ccds", {}).items()},
        )
        out["check"] = checks.get(p.id)
        out["warnings"] = list(result.warnings)
        out["files"]["isd"] = camera_isds(job, p.id, result.cameras[p.id])
        figure_residuals(job, p.id, result, p.sizes, ci)
        if cfg.ortho.enabled:
            out["files"]["ortho"] = orthoimages(job, p.id, result.cameras[p.id], p.images)
        out["_residuals"] = (result.residual[on], result.inlier[on])
        strips[p.id] = out
    exports = campaign_points(preps, ties, cfg)
    joint_exports = control_exports(job, "campaign", exports, ("campaign", "exports"))
    job.charge("outputs", t0, c0)
    campaign = {
        "adjust_together": True,
        "n_tie_points": len(ties),
        "n_tie_observations": 2 * len(ties),
        "tie_points_per_strip_pair": ties.per_strip_pair(),
        "tie_points_per_image_pair": dict(ties.pairs),
        "tie_sigma_m": opts.tie_sigma_m,
        "adjustment": result_block(
            result,
            systematic_source=declared,
            n_tie_points=len(ties),
            tie_rmse_px=None if not len(ties) else rmse_px(result.residual[is_tie & result.inlier]),
            tie_rmse_px_before=None if not len(ties) else rmse_px(result.residual_initial[is_tie]),
        ),
        "files": {
            **{k: v for k, v in joint_files.items() if k != "cameras"},
            "exports": joint_exports,
        },
    }
    return strips, campaign
