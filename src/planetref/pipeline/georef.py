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
    McpSet,
    StripMcps,
    joint_network,
    template_overlap,
    template_support_m,
    with_overlap_ties,
)
from planetref.errors import AdjustmentError, MatcherFailedError
from planetref.frontend.matchers import (
    MatcherPair,
    build_matchers,
    matcher_options,
    matcher_recipes,
    matcher_weight_files,
)
from planetref.pipeline.artefacts import StripOutcome, StripProducts, solve_or_reload
from planetref.pipeline.config import GeorefConfig
from planetref.pipeline.georef_outputs import (
    camera_isds,
    campaign_points,
    control_exports,
    figure_jitter,
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
from planetref.report.model import (
    AdjustmentSummary,
    CampaignBlock,
    CcdOverlapBlock,
    CcdOverlapPair,
    GeorefReport,
    StripMatching,
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
    from planetref.adjust.config import AdjustConfig
    from planetref.adjust.result import AdjustmentResult
    from planetref.camera.base import Camera
    from planetref.control.network import Network
    from planetref.frontend.overlap import OverlapTies
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
        report: The report.json content (``typed.to_json()``).
        run_dir: The run directory.
        files: Paths of the main outputs.
        typed: The report as its typed model.
    """

    report: dict[str, Any]
    run_dir: Path
    files: dict[str, Any] = field(default_factory=dict)
    typed: GeorefReport | None = None


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
    device: str = "cpu",
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
        device: Torch device of the learned matchers (``"cpu"``, ``"cuda"``, ``"cuda:1"``;
            resolved, not ``"auto"``), passed to them when they are built. Part of the
            run's identity when it is not the CPU.

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
            device=device,
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
        if device != "cpu":  # a CPU run's identity stays what it was
            identity["device"] = device
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
                    **({} if device == "cpu" else {"device": device}),
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
            matched: dict[str, StripMatching] = {}  # matching blocks, for a failed run
            mcp_files: dict[str, list[str]] = {}
            strips: dict[str, StripOutcome]
            campaign: CampaignBlock | None
            try:
                if cfg.campaign.adjust_together and len(manifest.strips) > 1:
                    preps = [
                        _strip_mcps(job.for_strip(s), matched, mcp_files) for s in manifest.strips
                    ]
                    with single_threaded_blas():  # RPC refits, reports, orthoimages
                        strips, campaign, joint = _adjust_together(job, preps, matched, mcp_files)
                else:
                    strips, campaign, joint = {}, None, None
                    for s in manifest.strips:
                        prep = _strip_mcps(job.for_strip(s), matched, mcp_files)
                        with single_threaded_blas():  # RPC refits, reports, orthoimages
                            strips[s.id] = _adjust_strip(
                                job.for_strip(s), prep, matched[s.id], mcp_files[s.id]
                            )
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
            typed = combined_report(
                matcher,
                manifest.name,
                {sid: o.report for sid, o in strips.items()},
                {sid: (o.residual, o.inlier) for sid, o in strips.items()},
                job.timing,
                settings,
            )
            if campaign is not None and joint is not None:
                typed.adjustment = joint
                typed.campaign = campaign
            if input_warnings:
                typed.input_warnings = list(input_warnings)
            # A resumed run's step timings are what this process spent; the tiles' own
            # cost is in timing_s.matching_tiles (from the journal), so it says so.
            typed.resumed = bool(run.resumed)
            report = typed.to_json()
            run.write_json("report.json", report)
            write_georef_markdown(report, run.file("report.md"))
    finally:
        if owned:
            ex.close()
    files: dict[str, Any] = {
        "report_json": str(run.path / "report.json"),
        "report_md": str(run.path / "report.md"),
    }
    for sid, o in strips.items():
        files[sid] = o.products.to_dict()
    return GeorefOutcome(report=report, run_dir=run.path, files=files, typed=typed)


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


def _strip_mcps(
    job: StripJob, matched: dict[str, StripMatching], mcp_files: dict[str, list[str]]
) -> StripMcps:
    """Match a strip's tiles, write its MCPs, draw its check points.

    Its ``matching`` block goes to ``matched`` and the MCP files to ``mcp_files``.
    """
    from planetref.control.mcp import mcps_from_tiles, write_mcps
    from planetref.frontend.tile_panels import PanelStore
    from planetref.report.figures_matching import select_tiles

    strip, cfg = job.spec, job.cfg
    camera, images = strip_cameras(job.manifest, job.root, strip)  # checked by check_strips
    sizes = {c: camera.image_size(c) for c in images}

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
    mcp_files[strip.id] = [
        str(p) for p in (written if isinstance(written, list | tuple) else [written])
    ]
    cam = job.truth_cameras.get(strip.id)  # the true DEM read for it, then let go
    truth = None if cam is None else (cam, job.ref, truth_terrain(job.truth_dem, job.dem))
    matching = matched[strip.id] = matching_block(matches, table, sizes, truth)
    del truth  # the true DEM is not held through the figures
    for item in matching.tiles_lost:
        log.warning("strip %s tile %s: %s %s", strip.id, item.tile, item.status, item.message)
    with single_threaded_blas(), timed(job.timing, "figures"), store:  # figures are outputs
        figures_matching(job, matches, table, sizes, images, camera, store)
        store.keep_only(t.tile_id for _, t in select_tiles(matches.tiles))
    n = len(table)
    if n < cfg.mcp.min_mcps:
        raise too_few_mcps(strip.id, matches.matcher, matching, cfg.mcp.min_mcps)
    mcps = McpSet.held_out(strip.id, table, cfg.mcp)
    overlap = _overlap_ties(job, camera, images) if cfg.frontend.ccd_overlap.enabled else None
    return StripMcps(strip.id, camera, images, sizes, mcps, overlap)


def _overlap_ties(job: StripJob, camera: Camera, images: dict[str, CcdImage]) -> OverlapTies:
    """The strip's CCD-overlap tie points (``[frontend.ccd_overlap]``), written to CSV."""
    from planetref.frontend.overlap import find_overlap_ties, write_overlap_ties

    strip, ovl = job.spec, job.cfg.frontend.ccd_overlap
    t0, c0 = job.clock()
    ties = find_overlap_ties(camera, images, job.dem, ovl, strip.id)
    job.charge("ccd_overlap", t0, c0)
    write_overlap_ties(ties, _overlap_file(job, strip.id))
    log.info("strip %s: %d CCD-overlap tie points", strip.id, len(ties))
    return ties


def _overlap_file(job: StripJob, strip: str) -> Path:
    """Where a strip's CCD-overlap ties are written (``<strip>/ccd_overlap_ties.csv``)."""
    return job.run.file(strip, "ccd_overlap_ties.csv")


def _overlap_block(
    job: StripJob,
    camera: Camera,
    ties: OverlapTies,
    network: Network,
    result: AdjustmentResult,
    strip: str | None = None,
) -> CcdOverlapBlock:
    """The report block of a strip's CCD-overlap ties: staggers, gains and RMSE."""
    from planetref.camera.jitter import overlap_transfer

    period = _line_period_s(camera)
    pairs: dict[str, CcdOverlapPair] = {}
    for pair, n in ties.pairs.items():
        a, b = pair.split("~")
        on = (ties.ccd[:, 0] == a) & (ties.ccd[:, 1] == b)
        lines = float(np.median(ties.line_offset[on]))
        dt = None if period is None else abs(lines) * period
        pairs[pair] = CcdOverlapPair(
            n_ties=n,
            stagger_lines=lines,
            stagger_s=dt,
            # The gain |2 sin(pi f dt)| reaches 1 at 1 / (6 dt): below it the overlap
            # sees less than the jitter itself.
            unit_gain_hz=None if not dt else 1.0 / (6.0 * dt),
            gain_at_10hz=None if not dt else float(overlap_transfer(10.0, dt)),
        )
    return CcdOverlapBlock(
        n_ties=len(ties),
        pairs=pairs,
        sigma_px=job.cfg.frontend.ccd_overlap.sigma_px,
        **overlap_rmse(network, result, strip),
    )


def _line_period_s(camera: Camera) -> float | None:
    """The camera's line period at its middle line (s), when it has a time model."""
    rates = getattr(camera, "line_rates", None)
    if rates is None:
        return None
    n_lines, _ = camera.image_size(camera.ccd_names[0])
    return float(np.asarray(rates.period(0.5 * n_lines)).ravel()[0])


def _adjust_strip(
    job: StripJob, prep: StripMcps, matching: StripMatching, mcp_files: list[str]
) -> StripOutcome:
    """Adjust one strip on its own with its MCPs and write its outputs.

    The adjustment is reloaded from the run folder when its inputs did not change
    (:func:`~planetref.pipeline.artefacts.solve_or_reload`).
    """
    from planetref.adjust.api import adjust
    from planetref.report.adjustment import write_outputs
    from planetref.report.model import StripReport

    cfg, run = job.cfg, job.run
    network = prep.mcps.network(prep.camera, cfg.mcp.sigma_px)
    if prep.overlap is not None:
        network = with_overlap_ties(network, prep.overlap, cfg.frontend.ccd_overlap)
    adjust_cfg, declared = _adjust_settings(job, [prep.id], [prep.mcps])
    t0, c0 = job.clock()
    result, _ = solve_or_reload(run, (prep.id, "adjustment"), network, adjust_cfg, adjust)
    job.charge("adjustment", t0, c0)
    t0, c0 = job.clock()
    truth = {prep.id: job.truth_cameras[prep.id]} if prep.id in job.truth_cameras else None
    camera = result.cameras[prep.id]
    products = StripProducts(mcps=mcp_files)
    if prep.overlap is not None:
        products.ccd_overlap = str(_overlap_file(job, prep.id))
    # Adjusted cameras, RPC refits, residuals and reports first (beside the orthoimages
    # they raised the peak memory by ~180 MB on hiric-strip, for ~1.6 CPU-s of overlap).
    with part_timed(job.timing, "adjustment_files"):
        dem = truth_terrain(job.truth_dem, job.dem)
        products.adjustment = write_outputs(
            result,
            run.file(prep.id, "adjustment"),
            truth=truth,
            terrain=dem,
            plots=False,  # figures/<strip>_residuals.png draws the same residual vectors
        )
        report = StripReport(
            matching=matching,
            adjustment=result_block(result, systematic_source=declared),
            check=check_block(result, truth, dem) if truth else None,
        )
        if prep.overlap is not None:
            report.ccd_overlap = _overlap_block(job, prep.camera, prep.overlap, network, result)
    del dem  # a truth DEM is not held through the orthoimages (the run's memory peak)
    report.warnings = list(result.warnings)

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
            products.exports = control_exports(
                job, f"{prep.id}_mcps", mcp_points(prep, cfg), (prep.id, "exports")
            )
        with part_timed(job.timing, "figures"):  # drawn while the orthoimages are written
            figure_residuals(job, prep.id, result, prep.sizes)
            figure_jitter(job, prep.id, result, truth)
        if cfg.ortho.enabled:
            with part_timed(job.timing, "orthoimages"):
                products.ortho = orthoimages(job, prep.id, camera, prep.images)
        products.isd = isd.result()
    job.charge("outputs", t0, c0)
    return StripOutcome(report, products, result.residual, result.inlier)


def overlap_rmse(
    network: Network, result: AdjustmentResult, strip: str | None = None
) -> dict[str, Any]:
    """RMSE (px) of a strip's CCD-overlap tie observations before and after adjustment."""
    pid = np.asarray(network.point_ids)[network.obs_point]
    on = np.char.find(pid.astype(str), ":ovl:") >= 0
    if strip is not None:
        on &= np.char.startswith(pid.astype(str), f"{strip}:ovl:")
    if not on.any():
        return {"rmse_px_before": None, "rmse_px": None}
    return {
        "rmse_px_before": rmse_px(result.residual_initial[on]),
        "rmse_px": rmse_px(result.residual[on & result.inlier]),
        "n_inlier_observations": int(np.count_nonzero(on & result.inlier)),
    }


def _adjust_settings(
    job: StripJob, strip_ids: list[str], mcps: list[McpSet]
) -> tuple[AdjustConfig, dict[str, Any]]:
    """The adjustment's settings for these strips' MCPs, and their systematic sources.

    The sources are :func:`~planetref.pipeline.systematic.systematic_settings`'s. The
    fine matcher's template (:func:`template_support_m`) decides both the MCPs' mean
    number per independent measurement (:func:`template_overlap`, 1 for sparse
    matchers) and, when the jitter stage is on and ``mcp_support_m`` unset, the
    template the jitter's resolution limit is bounded by.
    """
    fine, gsd = job.matchers.fine, reference_gsd_m(job.ref)
    support = template_support_m(fine.name, fine.options, job.cfg.frontend.fine_upsample, gsd)
    overlap = 1.0
    if support is not None:
        x = np.concatenate([np.asarray(m.table["ref_x"], float) for m in mcps])
        y = np.concatenate([np.asarray(m.table["ref_y"], float) for m in mcps])
        overlap = template_overlap(x, y, support)
    adjust_cfg, declared = systematic_settings(
        job.cfg.adjust, job.manifest, strip_ids, gsd, overlap
    )
    jit = adjust_cfg.jitter
    if jit.enabled and jit.mcp_support_m is None and support is not None:
        jit = jit.model_copy(update={"mcp_support_m": support})
        adjust_cfg = adjust_cfg.model_copy(update={"jitter": jit})
    return adjust_cfg, declared


def _adjust_together(
    job: StripJob,
    preps: list[StripMcps],
    matched: dict[str, StripMatching],
    mcp_files: dict[str, list[str]],
) -> tuple[dict[str, StripOutcome], CampaignBlock, AdjustmentSummary]:
    """Adjust every strip in one network: all MCPs plus tie points between strips.

    The joint adjustment's outputs (every camera, residuals, parameters) go to
    ``campaign/adjustment``; each strip keeps its own blocks (metrics of its
    observations, true geolocation error, orthoimages) computed from the joint result.

    Returns:
        ``(strips, campaign, adjustment)``: each strip's outcome (as :func:`_adjust_strip`
        returns), the ``campaign`` block of report.json and the joint adjustment's
        ``adjustment`` block (the run's).
    """
    from planetref.adjust.api import adjust
    from planetref.frontend.tiepoints import find_tie_points
    from planetref.report.adjustment import write_outputs
    from planetref.report.model import StripReport

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
    for p in preps:
        if p.overlap is not None:
            network = with_overlap_ties(network, p.overlap, cfg.frontend.ccd_overlap)
    adjust_cfg, declared = _adjust_settings(job, [p.id for p in preps], [p.mcps for p in preps])
    t0, c0 = job.clock()
    result, _ = solve_or_reload(run, ("campaign", "adjustment"), network, adjust_cfg, adjust)
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
    strips: dict[str, StripOutcome] = {}
    is_tie = np.asarray(network.point_kind)[network.obs_point] == "tie"
    for ci, p in enumerate(preps):
        products = StripProducts(mcps=mcp_files[p.id], adjustment=joint_files)
        cm = result.metrics["cameras"][p.id]
        on = network.obs_camera == ci
        report = StripReport(
            matching=matched[p.id],
            adjustment=adjustment_block(
                cm["after"],
                rmse_px_before=cm["before"]["rmse_px"],
                sigma0=result.sigma0,
                converged=result.converged,
                n_tie_observations=int(np.count_nonzero(on & is_tie)),
                ccds={c: m["after"] for c, m in cm.get("ccds", {}).items()},
            ),
            check=checks.get(p.id),
            warnings=list(result.warnings),
        )
        if p.overlap is not None:
            report.ccd_overlap = _overlap_block(
                job, p.camera, p.overlap, network, result, strip=p.id
            )
            products.ccd_overlap = str(_overlap_file(job, p.id))
        products.isd = camera_isds(job, p.id, result.cameras[p.id])
        figure_residuals(job, p.id, result, p.sizes, ci)
        figure_jitter(job, p.id, result, truth)
        if cfg.ortho.enabled:
            products.ortho = orthoimages(job, p.id, result.cameras[p.id], p.images)
        strips[p.id] = StripOutcome(report, products, result.residual[on], result.inlier[on])
    exports = campaign_points(preps, ties, cfg)
    joint_exports = control_exports(job, "campaign", exports, ("campaign", "exports"))
    job.charge("outputs", t0, c0)
    campaign = CampaignBlock(
        adjust_together=True,
        n_tie_points=len(ties),
        n_tie_observations=2 * len(ties),
        tie_points_per_strip_pair=ties.per_strip_pair(),
        tie_points_per_image_pair=dict(ties.pairs),
        tie_sigma_m=opts.tie_sigma_m,
        files={
            **{k: v for k, v in joint_files.items() if k != "cameras"},
            "exports": joint_exports,
        },
    )
    joint = result_block(
        result,
        systematic_source=declared,
        n_tie_points=len(ties),
        tie_rmse_px=None if not len(ties) else rmse_px(result.residual[is_tie & result.inlier]),
        tie_rmse_px_before=None if not len(ties) else rmse_px(result.residual_initial[is_tie]),
    )
    return strips, campaign, joint
