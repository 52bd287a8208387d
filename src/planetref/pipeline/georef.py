"""``georef``: one scene, one matcher, from raw CCD images to adjusted cameras.

Stages, per strip: tiling -> coarse-to-fine matching against the reference ortho ->
matched control points (MCPs) -> rigorous line-scan bundle adjustment -> metrics ->
outputs (adjusted cameras, RPCs, residuals, orthoimages, figures, report).

Run directory layout::

    run.json, config.json, planetref.log, report.json, report.md
    <strip>/tiles.jsonl              per-tile matching journal (resume)
    <strip>/mcps.parquet, mcps.gpkg  matched control points
    <strip>/adjustment/...           adjusted cameras, RPCs, residuals, per-strip report
    <strip>/ortho/<ccd>.tif          orthoimages through the adjusted camera
    figures/*.png                    matches of one tile, MCP distribution, residuals
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from planetref import __version__
from planetref.errors import InputError, MatchingError, PlanetrefError
from planetref.pipeline.config import GeorefConfig
from planetref.pipeline.rundir import RunDir, config_digest

__all__ = [
    "GeorefOutcome",
    "build_matchers",
    "matcher_options",
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


def build_matchers(
    name: str,
    cfg: GeorefConfig,
    ref_gsd_m: float,
    *,
    weights_dir: str | os.PathLike[str] | None = None,
) -> tuple[Any, Any]:
    """The fine-stage and coarse-stage matchers of a run.

    Area-based NCC searches a fixed radius around each template, so its coarse-stage
    instance gets a radius that covers the a-priori uncertainty at the coarse scale; the
    learned and SIFT matchers search the whole window and serve both stages.

    Returns:
        ``(fine, coarse)`` matchers.
    """
    from planetref.matching.registry import get_matcher

    fine_opts, coarse_opts = matcher_options(name, cfg, ref_gsd_m)
    fine = get_matcher(name, weights_dir=weights_dir, **fine_opts)
    if coarse_opts is None:
        return fine, fine
    return fine, get_matcher(name, weights_dir=weights_dir, **coarse_opts)


def matcher_options(
    name: str, cfg: GeorefConfig, ref_gsd_m: float
) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """The registry options of a run's fine and coarse matchers (see :func:`build_matchers`).

    Returns:
        ``(fine_options, coarse_options)``; ``coarse_options`` is None when the fine
        matcher serves both stages.
    """
    options = dict(cfg.matchers.get(name, {}))
    if name != "ncc":
        return options, None
    fe = cfg.frontend
    # NCC looks for each template around the same pixel of the other window, and the
    # front end's windows are padded: the fine stage must reach the pad plus what the
    # coarse stage leaves; the coarse stage the whole a-priori uncertainty.
    fine_radius = fe.fine_pad_ref_px + int(np.ceil(fe.coarse_radius_ref_px)) + 4
    coarse_radius = int(np.ceil(fe.uncertainty_m / (ref_gsd_m * fe.coarse_factor))) + 4
    base = {"spacing": 8, **options}
    coarse_opts = {**base, "search_radius": max(coarse_radius, int(base.get("search_radius", 0)))}
    return {"search_radius": fine_radius, **base}, coarse_opts


def _scene_path(scene: str | os.PathLike[str]) -> Path:
    p = Path(scene)
    return (p / "scene.toml" if p.is_dir() else p).resolve()


def scene_input_files(manifest: Any, root: Path) -> list[Path]:
    """Every file a scene manifest names (reference, images, cameras, truth): run inputs."""
    names = [manifest.reference.ortho, manifest.reference.dem]
    for strip in manifest.strips:
        for c in strip.ccds:
            names += [c.image, c.camera]
    if manifest.truth is not None:
        names += [manifest.truth.dem, *manifest.truth.cameras.values()]
    paths = {manifest.resolve(root, n) for n in names}
    return sorted(Path(p) for p in paths if Path(p).is_file())


def matcher_weight_files(name: str, weights_dir: str | os.PathLike[str] | None) -> list[Path]:
    """The weight files of a registered matcher that are present (their sha256 is identity)."""
    from planetref.matching.registry import MATCHERS
    from planetref.matching.weights import weights_dir as resolve_dir

    spec = MATCHERS.get(name)
    if spec is None:
        return []
    folder = resolve_dir(weights_dir)
    return [folder / w for w in spec.weights if (folder / w).is_file()]


def _open_reference(manifest: Any, root: Path) -> tuple[Any, Any]:
    from planetref.raster.dem import GridTerrain
    from planetref.raster.ortho import ReferenceOrtho

    ortho_path = manifest.resolve(root, manifest.reference.ortho)
    dem_path = manifest.resolve(root, manifest.reference.dem)
    ref = ReferenceOrtho(ortho_path, band=manifest.reference.ortho_band)
    dem = GridTerrain.from_geotiff(dem_path, band=manifest.reference.dem_band)
    return ref, dem


def _strip_cameras(manifest: Any, root: Path, strip: Any) -> tuple[Any, dict[str, Any]]:
    """The strip's camera and its CCD images, keyed by the camera's CCD names."""
    from planetref.camera.io import load_camera
    from planetref.raster.image import CcdImage

    files = {manifest.resolve(root, c.camera) for c in strip.ccds}
    if len(files) != 1:
        raise InputError(
            f"strip {strip.id}: its CCDs use {len(files)} camera files; georef "
            "adjusts a strip as one camera, so its CCDs must share one camera "
            "file (a multi-CCD native camera)"
        )
    camera = load_camera(files.pop())
    images: dict[str, Any] = {}
    for c in strip.ccds:
        cam_ccd = c.camera_ccd or c.name
        if cam_ccd not in camera.ccd_names:
            if len(camera.ccd_names) == 1:
                cam_ccd = camera.ccd_names[0]
            else:
                raise InputError(
                    f"strip {strip.id}, CCD {c.name}: the camera has no CCD "
                    f"{cam_ccd!r} (it has {list(camera.ccd_names)})"
                )
        images[cam_ccd] = _checked_image(CcdImage(manifest.resolve(root, c.image)), camera, cam_ccd)
    return camera, images


def _checked_image(image: Any, camera: Any, ccd: str) -> Any:
    """Fail early, naming the file, on a CCD image that is truncated or of the wrong size."""
    n_lines, n_samples = camera.image_size(ccd)
    shape = getattr(image, "shape", None)
    if shape is not None and tuple(shape)[:2] != (n_lines, n_samples):
        raise InputError(
            f"the image is {shape[0]} x {shape[1]} (lines x samples) but its "
            f"camera's CCD {ccd} is {n_lines} x {n_samples}",
            path=image.path,
        )
    try:
        # A truncated GeoTIFF opens fine and fails on its first missing block, so read the
        # first and last lines now rather than in the middle of a run.
        for line0 in (0, max(0, n_lines - 8)):
            image.read(line0, 0, min(8, n_lines), n_samples)
    except PlanetrefError:
        raise
    except Exception as exc:
        raise InputError(
            f"cannot read the image ({type(exc).__name__}: {exc})", path=image.path
        ) from None
    return image


MARS_SEMI_MAJOR_M = 3396190.0


def _check_body(body: Any, raster: Any, what: str, path: Any = None) -> None:
    """Refuse a reference on another body than ``body`` (e.g. an Earth CRS), in words."""
    from planetref.errors import CrsError

    crs = getattr(raster, "crs", None)
    ellipsoid = getattr(crs, "ellipsoid", None)
    a_ref = getattr(ellipsoid, "semi_major_metre", None)
    a_cam = float(body.semi_major_m)
    if a_ref is None or abs(float(a_ref) - a_cam) <= 0.01 * a_cam:
        return
    body = (
        "Mars"
        if abs(a_cam - MARS_SEMI_MAJOR_M) <= 0.01 * MARS_SEMI_MAJOR_M
        else f"the cameras' body (a = {a_cam:.0f} m)"
    )
    raise CrsError(
        f"the {what}'s CRS is not a {body} CRS ({crs.name}; ellipsoid "
        f"{ellipsoid.name}, a = {float(a_ref):.0f} m) but the cameras are on {body}",
        path=path or getattr(raster, "path", None),
    )


def _check_overlap(camera: Any, images: dict[str, Any], ref: Any, dem: Any, strip: str) -> None:
    """Refuse a strip whose footprint misses the reference ortho entirely."""
    from planetref.frontend.geometry import image_to_ref_pixel

    _check_body(camera.ellipsoid, ref, "reference ortho")
    _check_body(camera.ellipsoid, dem, "reference DEM")
    for ccd in images:
        n_lines, n_samples = camera.image_size(ccd)
        t = np.linspace(0, 1, 5)
        line = np.concatenate([t * n_lines, t * n_lines])
        sample = np.concatenate([np.zeros(5), np.full(5, n_samples)])
        col, row = image_to_ref_pixel(camera, ccd, line, sample, ref, dem)
        if np.any(np.isfinite(col)) and np.any(ref.contains_pixel(col, row)):
            return
    raise InputError(
        f"strip {strip}: its images do not overlap the reference ortho (or "
        "their rays miss the reference DEM); check the scene's reference and "
        "cameras"
    )


def _truth(manifest: Any, root: Path) -> tuple[dict[str, Any], Any]:
    from planetref.camera.io import load_camera
    from planetref.raster.dem import GridTerrain

    if manifest.truth is None:
        return {}, None
    cams = {
        sid: load_camera(manifest.resolve(root, p)) for sid, p in manifest.truth.cameras.items()
    }
    dem = GridTerrain.from_geotiff(manifest.resolve(root, manifest.truth.dem))
    return cams, dem


def run_georef(
    scene: str | os.PathLike[str],
    matcher: str,
    out: str | os.PathLike[str],
    *,
    config: GeorefConfig | None = None,
    weights_dir: str | os.PathLike[str] | None = None,
    overwrite: bool = False,
    progress: bool = True,
    matchers: tuple[Any, Any] | None = None,
    executor: Any = None,
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
        executor: Where the tiles are matched: a :class:`planetref.execute.Executor`
            (left open), or a ``--scheduler`` spec (``"pool:4"``, ``"dask-local:4"``,
            ``"tcp://HOST:PORT"``; started for this run and closed after). Default: in
            this process. The results do not depend on it.

    Returns:
        The report and where things were written.

    Raises:
        PlanetrefError: Bad scene, reference or camera files, missing weights, no
            overlap, a strip without enough MCPs, a degenerate adjustment.
    """
    from planetref.execute import Executor, make_executor

    owned = executor is not None and not isinstance(executor, Executor)
    ex = make_executor(executor)
    try:
        return _run_georef(
            scene, matcher, out, config, weights_dir, overwrite, progress, matchers, ex
        )
    finally:
        if owned:
            ex.close()


def _run_georef(
    scene: str | os.PathLike[str],
    matcher: str,
    out: str | os.PathLike[str],
    config: GeorefConfig | None,
    weights_dir: str | os.PathLike[str] | None,
    overwrite: bool,
    progress: bool,
    matchers: tuple[Any, Any] | None,
    executor: Any,
) -> GeorefOutcome:
    from planetref.simulate.manifest import load_manifest

    t_start = time.perf_counter()
    cfg = config or GeorefConfig()
    scene_path = _scene_path(scene)
    manifest, root = load_manifest(scene_path)
    # Inputs checked and matchers built before the run folder is claimed, so a failed
    # start (unknown matcher, missing weights, unreadable reference) leaves nothing behind.
    ref, dem = _open_reference(manifest, root)
    body = manifest.body.ellipsoid()
    _check_body(body, ref, "reference ortho")
    _check_body(body, dem, "reference DEM", manifest.resolve(root, manifest.reference.dem))
    ref_gsd = float(np.mean(ref.ground_sampling_m()))
    fine, coarse = matchers or build_matchers(matcher, cfg, ref_gsd, weights_dir=weights_dir)
    identity = {
        "scene": str(scene_path),
        "matcher": matcher,
        "config": config_digest(cfg.to_json()),
    }
    run = RunDir(
        out,
        "georef",
        identity,
        overwrite=overwrite,
        inputs=[scene_path, *scene_input_files(manifest, root)],
        weights=matcher_weight_files(matcher, weights_dir),
    )
    with run.logging_to_file():
        log.info(
            "georef %s with %s into %s%s",
            scene_path,
            matcher,
            run.path,
            " (resuming)" if run.resumed else "",
        )
        run.write_json(
            "config.json",
            {
                "scene": str(scene_path),
                "matcher": matcher,
                "weights_dir": None if weights_dir is None else str(weights_dir),
                "planetref_version": __version__,
                **cfg.to_json(),
            },
        )
        truth_cams, truth_dem = _truth(manifest, root)
        sources = None
        if executor.parallel:
            log.info("matching tiles on %s", executor.name)
            fine_opts, coarse_opts = matcher_options(matcher, cfg, ref_gsd)
            sources = {
                "ref": str(manifest.resolve(root, manifest.reference.ortho)),
                "ref_band": manifest.reference.ortho_band,
                "dem": str(manifest.resolve(root, manifest.reference.dem)),
                "dem_band": manifest.reference.dem_band,
                "matcher": matcher,
                "matcher_options": fine_opts,
                "coarse_options": coarse_opts,
                "weights_dir": None if weights_dir is None else str(Path(weights_dir).resolve()),
            }
        strips: dict[str, Any] = {}
        timing = {"matching": 0.0, "adjustment": 0.0, "outputs": 0.0}
        campaign = None
        if cfg.campaign.adjust_together and len(manifest.strips) > 1:
            preps = [
                _strip_mcps(
                    run,
                    manifest,
                    root,
                    strip,
                    ref,
                    dem,
                    fine,
                    coarse,
                    cfg,
                    progress,
                    timing,
                    executor=executor,
                    sources=sources,
                )
                for strip in manifest.strips
            ]
            strips, campaign = _adjust_together(
                run, preps, ref, dem, fine, cfg, truth_cams, truth_dem, timing
            )
        else:
            for strip in manifest.strips:
                strips[strip.id] = _georef_strip(
                    run,
                    manifest,
                    root,
                    strip,
                    ref,
                    dem,
                    fine,
                    coarse,
                    cfg,
                    progress,
                    truth_cams,
                    truth_dem,
                    timing,
                    executor=executor,
                    sources=sources,
                )
        timing["total"] = time.perf_counter() - t_start
        report = _combined_report(matcher, manifest.name, strips, timing)
        if campaign is not None:
            report["adjustment"] = campaign.pop("adjustment")
            report["campaign"] = campaign
        run.write_json("report.json", report)
        from planetref.report.georef import write_georef_markdown

        write_georef_markdown(report, run.file("report.md"))
    files = {"report_json": str(run.path / "report.json"), "report_md": str(run.path / "report.md")}
    for sid, s in strips.items():
        files[sid] = s.get("files", {})
    return GeorefOutcome(report=report, run_dir=run.path, files=files)


def _georef_strip(
    run: RunDir,
    manifest: Any,
    root: Path,
    strip: Any,
    ref: Any,
    dem: Any,
    fine: Any,
    coarse: Any,
    cfg: GeorefConfig,
    progress: bool,
    truth_cams: dict[str, Any],
    truth_dem: Any,
    timing: dict[str, float],
    *,
    executor: Any = None,
    sources: dict[str, Any] | None = None,
) -> dict[str, Any]:
    prep = _strip_mcps(
        run,
        manifest,
        root,
        strip,
        ref,
        dem,
        fine,
        coarse,
        cfg,
        progress,
        timing,
        executor=executor,
        sources=sources,
    )
    return _adjust_strip(run, prep, ref, dem, cfg, truth_cams, truth_dem, timing)


@dataclass
class _StripMcps:
    """A strip after matching: its camera, images, MCPs and check flags."""

    id: str
    camera: Any
    images: dict[str, Any]
    sizes: dict[str, tuple[int, int]]
    table: Any
    check: Any
    out: dict[str, Any]


def _strip_mcps(
    run: RunDir,
    manifest: Any,
    root: Path,
    strip: Any,
    ref: Any,
    dem: Any,
    fine: Any,
    coarse: Any,
    cfg: GeorefConfig,
    progress: bool,
    timing: dict[str, float],
    *,
    executor: Any = None,
    sources: dict[str, Any] | None = None,
) -> _StripMcps:
    """Match a strip's tiles, write its MCPs and draw its check points."""
    from planetref.control import mcps_from_tiles, write_mcps
    from planetref.frontend.match_tile import match_strip
    from planetref.frontend.stats import sdu_per_ccd

    camera, images = _strip_cameras(manifest, root, strip)
    _check_overlap(camera, images, ref, dem, strip.id)
    sizes = {c: camera.image_size(c) for c in images}
    out: dict[str, Any] = {"files": {}}

    t0 = time.perf_counter()
    tile_sources = None
    if sources is not None:
        from planetref.execute import TileSources

        tile_sources = TileSources(
            camera=str(manifest.resolve(root, strip.ccds[0].camera)),
            images=tuple((c, str(Path(img.path).resolve())) for c, img in images.items()),
            **sources,
        )
    matches = match_strip(
        camera,
        images,
        ref,
        dem,
        fine,
        cfg.frontend,
        journal=run.file(strip.id, "tiles.jsonl"),
        progress=progress,
        coarse_matcher=coarse,
        executor=executor,
        sources=tile_sources,
    )
    table = mcps_from_tiles(matches, ref=ref, dem=dem)
    timing["matching"] += time.perf_counter() - t0
    log.info(
        "strip %s: %d tiles matched with %s in %.0f s (%s): %d MCPs",
        strip.id,
        len(matches.tiles),
        matches.matcher,
        time.perf_counter() - t0,
        ", ".join(f"{k} {v}" for k, v in matches.status_counts().items()),
        len(table),
    )
    written = write_mcps(table, run.file(strip.id, "mcps.parquet"))
    out["files"]["mcps"] = [
        str(p) for p in (written if isinstance(written, list | tuple) else [written])
    ]
    statuses = matches.status_counts()
    lost = [
        {"tile": t.tile_id, "status": t.status, "message": t.message}
        for t in matches.tiles
        if t.status != "ok"
    ]
    for item in lost:
        log.warning(
            "strip %s tile %s: %s %s", strip.id, item["tile"], item["status"], item["message"]
        )
    ncp = {c: int(np.count_nonzero(np.asarray(table["ccd"]).astype(str) == c)) for c in images}
    sdu = sdu_per_ccd(table, sizes)
    out["matching"] = {
        "ccds": {c: {"ncp": ncp[c], "sdu_pct": float(sdu[c])} for c in images},
        "ncp": len(table),
        "tiles_total": len(matches.tiles),
        "tiles_failed": len(matches.tiles) - statuses.get("ok", 0),
        "tile_status": statuses,
        "tiles_lost": lost,
        "mcp_counts": table.counts.to_dict() if table.counts is not None else {},
    }
    _figures_matching(
        run, strip.id, matches, table, sizes, images, camera, ref, dem, fine, coarse, cfg
    )
    n = len(table)
    if n < cfg.mcp.min_mcps:
        raise MatchingError(
            f"strip {strip.id}: only {n} matched control points with matcher "
            f"{matches.matcher} ({statuses}); at least {cfg.mcp.min_mcps} are needed. "
            "See planetref.log for why tiles failed"
        )
    rng = np.random.default_rng(cfg.mcp.seed)
    check = np.zeros(n, bool)
    n_check = round(cfg.mcp.check_fraction * n)
    if n_check and n - n_check >= cfg.mcp.min_mcps:
        check[rng.choice(n, n_check, replace=False)] = True
    return _StripMcps(strip.id, camera, images, sizes, table, check, out)


def _adjust_strip(
    run: RunDir,
    prep: _StripMcps,
    ref: Any,
    dem: Any,
    cfg: GeorefConfig,
    truth_cams: dict[str, Any],
    truth_dem: Any,
    timing: dict[str, float],
) -> dict[str, Any]:
    """Adjust one strip on its own with its MCPs and write its outputs."""
    from planetref.adjust.api import adjust
    from planetref.adjust.problem import Network
    from planetref.adjust.report import write_outputs

    strip, camera, images, sizes = prep, prep.camera, prep.images, prep.sizes
    table, check, out = prep.table, prep.check, prep.out
    network = Network.mcps(
        camera,
        line=table["line"],
        sample=table["sample"],
        xyz=table.xyz(),
        ccd=np.asarray(table["ccd"]).astype(str),
        camera_id=strip.id,
        sigma_px=cfg.mcp.sigma_px,
        check=check,
        **_mcp_ground_sigmas(table),
    )
    t0 = time.perf_counter()
    result = adjust(network, cfg.adjust)
    timing["adjustment"] += time.perf_counter() - t0
    t0 = time.perf_counter()
    truth = {strip.id: truth_cams[strip.id]} if strip.id in truth_cams else None
    adj_files = write_outputs(
        result,
        run.file(strip.id, "adjustment"),
        truth=truth,
        terrain=truth_dem if truth_dem is not None else dem,
    )
    out["files"]["adjustment"] = adj_files
    out["adjustment"] = _adjustment_block(result)
    out["check"] = _check_block(result, truth, truth_dem, camera) if truth else None
    out["warnings"] = list(result.warnings)
    if cfg.ortho.enabled:
        out["files"]["ortho"] = _orthoimages(
            run, strip.id, result.cameras[strip.id], images, dem, ref, cfg
        )
    _figure_residuals(run, strip.id, result, sizes)
    timing["outputs"] += time.perf_counter() - t0
    out["_residuals"] = (result.residual, result.inlier)
    return out


def _mcp_ground_sigmas(table: Any) -> dict[str, Any]:
    """MCP ground points weighted by their a-priori sigmas (east, north, up) if known."""
    cols = getattr(table, "columns", {})
    if "sigma_ground_xy_m" not in cols or "sigma_ground_h_m" not in cols:
        return {}
    xy = np.asarray(cols["sigma_ground_xy_m"], float)
    h = np.asarray(cols["sigma_ground_h_m"], float)
    return {"ground_sigma_m": np.column_stack([xy, xy, h]), "ground_sigma_local": True}


def _adjust_together(
    run: RunDir,
    preps: list[_StripMcps],
    ref: Any,
    dem: Any,
    fine: Any,
    cfg: GeorefConfig,
    truth_cams: dict[str, Any],
    truth_dem: Any,
    timing: dict[str, float],
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
    from planetref.adjust.problem import Network
    from planetref.adjust.report import write_outputs
    from planetref.pipeline.campaign import find_tie_points

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
    ties = find_tie_points(
        {p.id: (p.camera, p.images) for p in preps}, ref, dem, fine, cfg.frontend, opts
    )
    timing["tie_points"] = time.perf_counter() - t0
    log.info("campaign: %d tie points between %d strips", len(ties), len(preps))
    cams = {p.id: p.camera for p in preps}
    obs_cam: list[str] = []
    obs_pt: list[str] = []
    obs_ccd: list[str] = []
    line: list[Any] = []
    sample: list[Any] = []
    sig_px: list[Any] = []
    check: list[Any] = []
    xyz: dict[str, Any] = {}
    sig_m: dict[str, Any] = {}
    kind: dict[str, str] = {}
    local: dict[str, bool] = {}
    for p in preps:
        t = p.table
        pts = [f"{p.id}:mcp{i}" for i in range(len(t))]
        pxyz = t.xyz()
        gs = _mcp_ground_sigmas(t).get("ground_sigma_m")
        for i, pid in enumerate(pts):
            xyz[pid], kind[pid] = pxyz[i], "mcp"
            sig_m[pid] = 0.0 if gs is None else gs[i]
            local[pid] = gs is not None
        obs_cam += [p.id] * len(t)
        obs_pt += pts
        obs_ccd += list(np.asarray(t["ccd"]).astype(str))
        line.append(np.asarray(t["line"], float))
        sample.append(np.asarray(t["sample"], float))
        sig_px.append(np.full(len(t), cfg.mcp.sigma_px))
        check.append(p.check)
    tie_sigma = np.inf if opts.tie_sigma_m is None else float(opts.tie_sigma_m)
    for i, pid in enumerate(ties.point_ids):
        xyz[pid], sig_m[pid], kind[pid] = ties.xyz[i], tie_sigma, "tie"
        for k in range(2):
            obs_cam.append(str(ties.strip[i, k]))
            obs_pt.append(pid)
            obs_ccd.append(str(ties.ccd[i, k]))
        line.append(ties.line[i])
        sample.append(ties.sample[i])
        sig_px.append(np.full(2, opts.tie_sigma_px))
        check.append(np.zeros(2, bool))
    network = Network.from_records(
        cams,
        obs_camera=obs_cam,
        obs_point=obs_pt,
        line=np.concatenate(line),
        sample=np.concatenate(sample),
        point_xyz=xyz,
        point_sigma_m=sig_m,
        point_kind=kind,
        obs_ccd=obs_ccd,
        sigma_px=np.concatenate(sig_px),
        check=np.concatenate(check),
        point_sigma_local=local,
    )
    t0 = time.perf_counter()
    result = adjust(network, cfg.adjust)
    timing["adjustment"] += time.perf_counter() - t0
    t0 = time.perf_counter()
    truth = {sid: truth_cams[sid] for sid in cams if sid in truth_cams} or None
    joint_files = write_outputs(
        result,
        run.file("campaign", "adjustment"),
        truth=truth,
        terrain=truth_dem if truth_dem is not None else dem,
    )
    strips: dict[str, dict[str, Any]] = {}
    is_tie = np.asarray(network.point_kind)[network.obs_point] == "tie"
    for ci, p in enumerate(preps):
        out = p.out
        out["files"]["adjustment"] = joint_files
        cm = result.metrics["cameras"][p.id]
        on = network.obs_camera == ci
        after = cm["after"]
        out["adjustment"] = {
            "rmse_px_before": cm["before"]["rmse_px"],
            "rmse_px": after["rmse_px"],
            "rmse_x_px": after["rmse_x_px"],
            "rmse_y_px": after["rmse_y_px"],
            "mean_px": after["mean_px"],
            "max_x_px": after["max_dx_px"],
            "max_y_px": after["max_dy_px"],
            "min_x_px": after["min_dx_px"],
            "min_y_px": after["min_dy_px"],
            "outlier_ratio_pct": after["outlier_ratio_pct"],
            "n_total": after["n_total"],
            "n_inliers": after["n_inliers"],
            "sigma0": result.sigma0,
            "converged": result.converged,
            "n_tie_observations": int(np.count_nonzero(on & is_tie)),
            "ccds": {c: m["after"] for c, m in cm.get("ccds", {}).items()},
        }
        one = {p.id: truth_cams[p.id]} if p.id in truth_cams else None
        out["check"] = _check_block(result, one, truth_dem, p.camera) if one else None
        out["warnings"] = list(result.warnings)
        if cfg.ortho.enabled:
            out["files"]["ortho"] = _orthoimages(
                run, p.id, result.cameras[p.id], p.images, dem, ref, cfg
            )
        out["_residuals"] = (result.residual[on], result.inlier[on])
        _figure_residuals(run, p.id, _camera_view(result, ci), p.sizes)
        strips[p.id] = out
    timing["outputs"] += time.perf_counter() - t0
    campaign = {
        "adjust_together": True,
        "n_tie_points": len(ties),
        "n_tie_observations": 2 * len(ties),
        "tie_points_per_strip_pair": ties.per_strip_pair(),
        "tie_points_per_image_pair": dict(ties.pairs),
        "tie_sigma_m": opts.tie_sigma_m,
        "adjustment": _adjustment_block(result)
        | {
            "n_tie_points": len(ties),
            "tie_rmse_px": None
            if not len(ties)
            else _rmse(result.residual[is_tie & result.inlier]),
            "tie_rmse_px_before": None if not len(ties) else _rmse(result.residual_initial[is_tie]),
        },
        "files": {k: v for k, v in joint_files.items() if k != "cameras"},
    }
    return strips, campaign


def _camera_view(result: Any, index: int) -> Any:
    """The observations of one camera of a joint result, as the residual figure reads it."""
    from types import SimpleNamespace

    net = result.network
    on = net.obs_camera == index
    cid = net.camera_ids[index]
    sub = SimpleNamespace(
        camera_ids=(cid,),
        obs_ccd=net.obs_ccd[on],
        obs_line=net.obs_line[on],
        obs_sample=net.obs_sample[on],
    )
    return SimpleNamespace(
        network=sub,
        cameras={cid: result.cameras[cid]},
        residual=result.residual[on],
        status=result.status[on],
    )


def _rmse(res: Any) -> float | None:
    r = np.asarray(res, float).reshape(-1, 2)
    r = r[np.all(np.isfinite(r), axis=1)]
    return float(np.sqrt(np.mean(np.sum(r**2, axis=1)))) if len(r) else None


def _adjustment_block(result: Any) -> dict[str, Any]:
    s = result.summary()
    after = result.metrics["all"]["after"]
    return {
        "rmse_px_before": s["rmse_px_before"],
        "rmse_px": s["rmse_px"],
        "rmse_x_px": after["rmse_x_px"],
        "rmse_y_px": after["rmse_y_px"],
        "mean_px": after["mean_px"],
        "mean_x_px": after["mean_x_px"],
        "mean_y_px": after["mean_y_px"],
        "max_x_px": after["max_dx_px"],
        "max_y_px": after["max_dy_px"],
        "min_x_px": after["min_dx_px"],
        "min_y_px": after["min_dy_px"],
        "outlier_ratio_pct": after["outlier_ratio_pct"],
        "n_total": after["n_total"],
        "n_inliers": after["n_inliers"],
        "sigma0": s["sigma0"],
        "sigma0_real": s.get("sigma0_real"),
        "dof": result.variance.get("dof"),
        "variance_components": result.variance.get("groups"),
        "converged": s["converged"],
        "check_mcps": result.metrics.get("check"),
        "ccds": {ccd: m["after"] for ccd, m in result.metrics.get("ccds", {}).items()},
    }


def _check_block(result: Any, truth: dict[str, Any], truth_dem: Any, camera: Any) -> dict[str, Any]:
    from planetref.metrics import geolocation_error

    ((sid, true_cam),) = truth.items()
    before, after = [], []
    for ccd in true_cam.ccd_names:
        before.append(
            geolocation_error(result.cameras_initial[sid], true_cam, ccd=ccd, terrain=truth_dem)
        )
        after.append(geolocation_error(result.cameras[sid], true_cam, ccd=ccd, terrain=truth_dem))

    def rms(items: list[dict[str, Any]], key: str) -> float:
        vals = np.array([i[key] for i in items], float)
        return float(np.sqrt(np.mean(vals**2)))

    return {
        "geoloc_rmse_m_before": rms(before, "rms_m"),
        "geoloc_rmse_m": rms(after, "rms_m"),
        "geoloc_rmse_px_before": rms(before, "rms_px"),
        "geoloc_rmse_px": rms(after, "rms_px"),
        "geoloc_max_m": float(max(i["max_m"] for i in after)),
        "ccds": {
            c: {"before": b, "after": a}
            for c, b, a in zip(true_cam.ccd_names, before, after, strict=True)
        },
    }


def _orthoimages(
    run: RunDir,
    strip: str,
    camera: Any,
    images: dict[str, Any],
    dem: Any,
    ref: Any,
    cfg: GeorefConfig,
) -> list[str]:
    from planetref.frontend.geometry import image_gsd_m
    from planetref.pipeline.orthoimage import orthorectify_ccd

    paths = []
    for ccd, image in images.items():
        gsd = cfg.ortho.gsd_m or image_gsd_m(camera, ccd, dem)
        try:
            p = orthorectify_ccd(
                image, camera, ccd, dem, ref.crs, run.file(strip, "ortho", f"{ccd}.tif"), gsd_m=gsd
            )
            paths.append(str(p))
        except PlanetrefError as exc:
            log.warning("strip %s CCD %s: no orthoimage (%s)", strip, ccd, exc)
    return paths


def _figures_matching(
    run: RunDir,
    strip: str,
    matches: Any,
    table: Any,
    sizes: dict[str, tuple[int, int]],
    images: dict[str, Any],
    camera: Any,
    ref: Any,
    dem: Any,
    fine: Any,
    coarse: Any,
    cfg: GeorefConfig,
) -> None:
    from planetref.frontend.match_tile import match_tile
    from planetref.report.figures_matching import draw_tile_selection, figure_mcp_distribution

    figure_mcp_distribution(
        table,
        sizes,
        run.file("figures", f"{strip}_mcp_distribution.png"),
        ccd_order=list(sizes),
        title=f"{strip}: MCPs of {matches.matcher}",
    )

    def rematch(t: Any) -> Any:
        return match_tile(
            t.tile,
            image=images[t.tile.ccd],
            camera=camera,
            ref=ref,
            terrain=dem,
            matcher=fine,
            config=cfg.frontend,
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


def _figure_residuals(
    run: RunDir, strip: str, result: Any, sizes: dict[str, tuple[int, int]]
) -> None:
    from planetref.report.georef import figure_residual_vectors

    figure_residual_vectors(
        result,
        sizes,
        run.file("figures", f"{strip}_residuals.png"),
        title=f"{strip}: residuals after adjustment (inliers)",
    )


def _combined_report(
    matcher: str, scene: str, strips: dict[str, dict[str, Any]], timing: dict[str, float]
) -> dict[str, Any]:
    """report.json: one strip's blocks as they are, several strips merged."""
    from planetref.metrics import reprojection_metrics

    ccds: dict[str, Any] = {}
    for sid, s in strips.items():
        for c, v in s["matching"]["ccds"].items():
            ccds[c if len(strips) == 1 else f"{sid}/{c}"] = v
    ncp = sum(s["matching"]["ncp"] for s in strips.values())
    sdu = float(np.mean([v["sdu_pct"] for v in ccds.values()])) if ccds else 0.0
    matching = {
        "ccds": ccds,
        "ncp": ncp,
        "sdu_pct": sdu,
        "tiles_total": sum(s["matching"]["tiles_total"] for s in strips.values()),
        "tiles_failed": sum(s["matching"]["tiles_failed"] for s in strips.values()),
        "tiles_lost": [
            dict(t, strip=sid) for sid, s in strips.items() for t in s["matching"]["tiles_lost"]
        ],
    }
    if len(strips) == 1:
        (only,) = strips.values()
        adjustment = dict(only["adjustment"])
        check = only["check"]
    else:
        res = np.concatenate([s["_residuals"][0] for s in strips.values()])
        inl = np.concatenate([s["_residuals"][1] for s in strips.values()])
        m = reprojection_metrics(res[:, 1], res[:, 0], inl)
        adjustment = {
            "rmse_px": m["rmse_px"],
            "mean_px": m["mean_px"],
            "max_x_px": m["max_dx_px"],
            "max_y_px": m["max_dy_px"],
            "min_x_px": m["min_dx_px"],
            "min_y_px": m["min_dy_px"],
            "outlier_ratio_pct": m["outlier_ratio_pct"],
            "n_total": m["n_total"],
            "n_inliers": m["n_inliers"],
            "rmse_px_before": float(
                np.nanmean([s["adjustment"]["rmse_px_before"] for s in strips.values()])
            ),
            "sigma0": float(np.nanmean([s["adjustment"]["sigma0"] for s in strips.values()])),
            "converged": all(s["adjustment"]["converged"] for s in strips.values()),
        }
        checks = [s["check"] for s in strips.values() if s["check"]]
        check = (
            None
            if not checks
            else {
                k: float(np.sqrt(np.mean([c[k] ** 2 for c in checks])))
                for k in ("geoloc_rmse_m_before", "geoloc_rmse_m", "geoloc_rmse_px")
            }
            | {"geoloc_max_m": max(c["geoloc_max_m"] for c in checks)}
        )
    strips_out = {
        sid: {k: v for k, v in s.items() if not k.startswith("_") and k != "files"}
        for sid, s in strips.items()
    }
    return {
        "matcher": matcher,
        "scene": scene,
        "planetref_version": __version__,
        "matching": matching,
        "adjustment": adjustment,
        "check": check,
        "timing_s": timing,
        "strips": strips_out,
    }
