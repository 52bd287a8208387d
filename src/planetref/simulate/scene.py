"""Simulate a complete scene and write its directory (atomically).

Layout of a scene directory (all paths in ``scene.toml`` are relative to it)::

    scene.toml                      the manifest (docs/scene-manifest.md)
    reference/ortho.tif             CTX-like ortho, reference CRS, 8-bit
    reference/dem.tif               MOLA-like DEM, reference CRS, float32 metres
    strips/<id>/<ccd>.tif           CCD images (no georeference), 16- or 8-bit
    strips/<id>/camera.json         initial camera of the strip (all CCDs, native JSON)
    strips/<id>/<ccd>.RPB           RPC fitted to the initial camera (optional)
    truth/<id>.camera.json          true camera of each strip
    truth/dem.tif                   full-resolution truth DEM (local equirectangular)
    truth/checkpoints.csv           random true pixel <-> ground correspondences
    truth/craters.csv               the crater population
    truth/reference.json            mosaic sources, seams, MOLA-like tracks, areoid
    truth/change.json               new craters, dust-devil tracks, dune shift
    truth/errors.json               measured initial errors, self-checks, facts
    truth/config.toml               the full configuration (re-runnable)
    preview.png                     optional overview figure

The scene is built in a temporary sibling folder and renamed into place at the end, so
an interrupted run never leaves a half-written scene behind.

Random streams: one independent generator per component, see
:mod:`planetref.simulate.streams`.
"""

from __future__ import annotations

import csv
import json
import math
import os
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from planetref.errors import InputError
from planetref.simulate.config import SimulationConfig
from planetref.simulate.streams import seed_sequence, stream

if TYPE_CHECKING:
    from planetref.simulate.grid import MapGrid

__all__ = ["SceneModel", "SceneResult", "build_scene_model", "simulate_scene", "stream"]

COARSE_FACTOR = 32
"""Regional-relief grid spacing, in truth DEM cells."""


@dataclass
class SceneResult:
    """What :func:`simulate_scene` made.

    Attributes:
        root: The scene directory.
        manifest_path: Its ``scene.toml``.
        errors: Measured initial errors and self-checks per strip (as in
            ``truth/errors.json``).
        timings_s: Wall-clock seconds per stage (not written to the scene).
    """

    root: Path
    manifest_path: Path
    errors: dict[str, Any]
    timings_s: dict[str, float] = field(default_factory=dict)


def _check_target(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise InputError("exists and is not a directory", path=out)
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise InputError(
            "directory exists and is not empty (use --overwrite to replace it)", path=out
        )


def _commit(tmp: Path, out: Path) -> None:
    """Move the finished scene into place (replacing an existing one)."""
    if out.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
        os.replace(out, old / "scene")
        os.replace(tmp, out)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, out)


def _relief_above_reference_dem(
    sm: SceneModel, ref_dem: NDArray[np.floating], dem_grid: MapGrid, ref: Any, local: Any
) -> Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]]:
    """Truth height (reference epoch) minus reference DEM height at reference-CRS points.

    What an off-nadir source orthorectified on the reference DEM displaces (metres; 0
    where the DEM has no value). With a declared areoid, the DEM's heights are brought
    back above the sphere first, as a user of the mosaic would have.
    """
    from scipy.ndimage import map_coordinates

    from planetref.simulate.reference import areoid_height

    t = sm.terrain
    height = t.height if t.height_reference is None else t.height_reference
    base = np.asarray(ref_dem, dtype=np.float64)
    mola = sm.cfg.reference.mola
    if mola.areoid:
        xx, yy = np.meshgrid(dem_grid.x_centres(), dem_grid.y_centres())
        base = base + areoid_height(xx, yy, mola)
    base = np.where(np.isfinite(base), base, np.nan)

    def relief(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        lon, lat = ref.map_to_lonlat(x, y)
        tx, ty = local.lonlat_to_map(lon, lat)
        r, c = sm.grid.to_index(tx, ty)
        h = map_coordinates(height, [r, c], order=1, mode="nearest")
        rr, cc = dem_grid.to_index(x, y)
        hc = map_coordinates(base, [rr, cc], order=1, mode="nearest")
        dh = h - hc
        return np.where(np.isfinite(dh), dh, 0.0)

    return relief


def simulate_scene(
    config: SimulationConfig,
    out_dir: str | os.PathLike[str],
    *,
    overwrite: bool = False,
    preview: bool = False,
    progress: bool = False,
    log: Callable[[str], None] | None = None,
) -> SceneResult:
    """Simulate a scene and write it to ``out_dir``.

    Args:
        config: The simulation config (its ``seed`` decides every random draw).
        out_dir: Target directory; it must not exist or be empty unless ``overwrite``.
        overwrite: Replace an existing non-empty directory.
        preview: Also write ``preview.png``.
        progress: Show tqdm progress bars on stderr.
        log: Called with one-line status messages.

    Returns:
        The result (paths, measured errors, timings).

    Raises:
        InputError: If ``out_dir`` is a file, or a non-empty directory without
            ``overwrite``.
        GeometryError: If the truth DEM does not cover a ray (margins too small).
    """
    out = Path(out_dir).resolve()
    _check_target(out, overwrite)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    try:
        result = _build(
            config, tmp, preview=preview, progress=progress, log=log or (lambda _m: None)
        )
        _commit(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    result.root = out
    result.manifest_path = out / "scene.toml"
    return result


def _footprint_bounds(
    cameras: list[Any], projection: Any, heights: tuple[float, float]
) -> tuple[float, float, float, float]:
    """Map box of the image borders of all cameras at two heights."""
    xs, ys = [], []
    for cam in cameras:
        for c in cam.ccds:
            n = 33
            t_l = np.linspace(0.0, c.n_lines, n)
            t_s = np.linspace(0.0, c.n_samples, n)
            lines = np.concatenate([t_l, t_l, np.zeros(n), np.full(n, float(c.n_lines))])
            samples = np.concatenate([np.zeros(n), np.full(n, float(c.n_samples)), t_s, t_s])
            for h in heights:
                xyz = cam.image_to_ground(lines, samples, h, ccd=c.name)
                x, y, _ = projection.xyz_to_map(xyz)
                xs.append(x)
                ys.append(y)
    x, y = np.concatenate(xs), np.concatenate(ys)
    return float(x.min()), float(y.min()), float(x.max()), float(y.max())


def _write_csv(path: Path, rows: list[dict[str, Any]], columns: list[str]) -> None:
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(columns)
        for r in rows:
            w.writerow(
                [
                    repr(float(r[k])) if isinstance(r[k], float | np.floating) else r[k]
                    for k in columns
                ]
            )


@dataclass
class SceneModel:
    """Everything of a scene before it is rendered: cameras, grids, truth terrain.

    Attributes:
        cfg: The config.
        strips: Cameras of each strip (:class:`~planetref.simulate.orbit.StripCameras`).
        local_wkt: WKT of the truth grid's local equirectangular CRS.
        local: That CRS as a :class:`~planetref.raster.dem.MapProjection`.
        ref: The reference CRS.
        grid: Truth DEM grid.
        coarse_grid: Regional-relief grid (covers the reference DEM).
        dem_grid: Reference DEM grid (reference CRS).
        ortho_grid: Reference ortho grid (reference CRS, true positions).
        terrain: The truth terrain.
        dem: The truth DEM as a terrain.
        enu: Rows east, north, up at the site centre (the shading frame).
        tiles: Sub-DEM texture tiles.
        change: What changed between the reference and the image epochs.
    """

    cfg: SimulationConfig
    strips: list[Any]
    local_wkt: str
    local: Any
    ref: Any
    grid: Any
    coarse_grid: Any
    dem_grid: Any
    ortho_grid: Any
    terrain: Any
    dem: Any
    enu: np.ndarray
    tiles: Any
    change: Any = None

    def radiance_model(
        self, which: str, *, sun_override: Any = None, haze_override: float | None = None
    ) -> Any:
        """The radiance model of the ``"target"`` (line-scan) or ``"reference"`` images.

        It holds the shading fields (about 10 bytes per truth DEM cell); drop it when done.

        Args:
            which: ``"target"`` or ``"reference"`` (the reference epoch's ground).
            sun_override: Another sun (a mosaic source's).
            haze_override: Another haze level.
        """
        from planetref.simulate.photometry import RadianceModel, ShadingFields, cast_shadow

        phot = self.cfg.photometry
        t = self.terrain
        height = t.height
        if which == "target":
            sun, albedo, haze = phot.target_sun, t.albedo, phot.target_haze
        elif which == "reference":
            sun, albedo, haze = phot.reference_sun, t.albedo_reference, phot.reference_haze
            if t.height_reference is not None:
                height = t.height_reference
        else:
            raise InputError(f"unknown radiance model {which!r}; use 'target' or 'reference'")
        if sun_override is not None:
            sun = sun_override
        if haze_override is not None:
            haze = haze_override
        shadow = cast_shadow(height, self.grid.res, sun)
        fields = ShadingFields(self.grid, height, albedo, t.texture_amplitude, shadow)
        return RadianceModel(fields, self.tiles, sun, phot, self.cfg.albedo, haze)


def build_scene_model(cfg: SimulationConfig) -> SceneModel:
    """Build the cameras, grids and truth terrain of a scene (nothing is written).

    Args:
        cfg: The config.

    Returns:
        The scene model.
    """
    from planetref.raster.dem import GridTerrain, MapProjection
    from planetref.simulate.change import apply_surface_change
    from planetref.simulate.grid import MapGrid, enu_basis, local_crs_wkt
    from planetref.simulate.orbit import build_strip_cameras
    from planetref.simulate.photometry import TextureTiles
    from planetref.simulate.reference import box_in_crs
    from planetref.simulate.terrain import generate_terrain

    seed = cfg.seed
    strips = [
        build_strip_cameras(cfg, s, stream(seed, "strip", i), stream(seed, "mismatch", i))
        for i, s in enumerate(cfg.strips)
    ]
    t = cfg.terrain
    local_wkt = local_crs_wkt(cfg.site.lat_deg, cfg.site.lon_deg)
    local = MapProjection(local_wkt)
    ref = MapProjection(cfg.reference.crs)
    h_env = 4.0 * t.regional.rms_m + t.ridges.height_m + 0.3 * t.craters.d_max_m + 50.0
    cams = [s.truth for s in strips] + [s.initial for s in strips]
    xmin, ymin, xmax, ymax = _footprint_bounds(cams, local, (-h_env, h_env))
    m = cfg.site.margin_m
    res = t.dem_gsd_m
    coarse_res = COARSE_FACTOR * res
    grid = MapGrid.covering(xmin - m, ymin - m, xmax + m, ymax + m, res, align=coarse_res)
    pad = cfg.reference.dem_pad_m
    gb = grid.bounds
    rb = box_in_crs((gb[0] - pad, gb[1] - pad, gb[2] + pad, gb[3] + pad), local, ref)
    dem_grid = MapGrid.covering(*rb, cfg.reference.dem_pixel_m)
    sigma_m = cfg.reference.dem_smoothing_px * cfg.reference.dem_pixel_m
    cpad = 4 * coarse_res + 3.0 * sigma_m + cfg.reference.dem_pixel_m
    cb = box_in_crs(dem_grid.bounds, ref, local)
    coarse_grid = MapGrid.covering(
        cb[0] - cpad, cb[1] - cpad, cb[2] + cpad, cb[3] + cpad, coarse_res, align=coarse_res
    )
    inner = 2 * res + 2 * cfg.reference.ortho_gsd_m
    ob = box_in_crs((gb[0] + inner, gb[1] + inner, gb[2] - inner, gb[3] - inner), local, ref)
    g = cfg.reference.ortho_gsd_m
    ox0, ox1 = math.ceil(ob[0] / g) * g, math.floor(ob[2] / g) * g
    oy1, oy0 = math.ceil(ob[1] / g) * g, math.floor(ob[3] / g) * g
    ortho_grid = MapGrid(ox0, oy0, g, round((oy0 - oy1) / g), round((ox1 - ox0) / g))
    streams = {
        k: stream(seed, k)
        for k in ("regional", "fractal", "plains", "dunes", "craters", "ridges", "albedo")
    }
    terrain = generate_terrain(cfg, grid, coarse_grid, streams)
    change = apply_surface_change(cfg, terrain, stream(seed, "change"))
    dem = GridTerrain(terrain.height, grid.transform, local_wkt)
    tiles = TextureTiles(cfg.albedo, res, stream(seed, "texture"))
    return SceneModel(
        cfg=cfg,
        strips=strips,
        local_wkt=local_wkt,
        local=local,
        ref=ref,
        grid=grid,
        coarse_grid=coarse_grid,
        dem_grid=dem_grid,
        ortho_grid=ortho_grid,
        terrain=terrain,
        dem=dem,
        enu=enu_basis(cfg.site.lat_deg, cfg.site.lon_deg),
        tiles=tiles,
        change=change,
    )


def _build(
    cfg: SimulationConfig, root: Path, *, preview: bool, progress: bool, log: Callable[[str], None]
) -> SceneResult:
    from tqdm import tqdm

    from planetref.scene.manifest import (
        CcdSpec,
        ReferenceSpec,
        SceneManifest,
        StripSpec,
        TruthSpec,
        write_manifest,
    )
    from planetref.simulate.measure import (
        checkpoints,
        measure_consistency,
        measure_initial_errors,
    )
    from planetref.simulate.mosaic import draw_mosaic, reference_accuracy, sources_to_dict
    from planetref.simulate.reference import (
        areoid_raster,
        finish_ortho,
        ortho_radiance,
        reference_dem,
        write_raster,
    )
    from planetref.simulate.render import render_ccd

    timings: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        timings[name] = now - clock
        clock = now

    seed = cfg.seed
    for sub in ("reference", "strips", "truth"):
        (root / sub).mkdir()
    sm = build_scene_model(cfg)
    strips, grid, terrain, dem, enu = sm.strips, sm.grid, sm.terrain, sm.dem, sm.enu
    ortho_grid, dem_grid, local, ref = sm.ortho_grid, sm.dem_grid, sm.local, sm.ref
    res = grid.res
    log(
        f"truth DEM {grid.rows} x {grid.cols} at {res} m, ortho {ortho_grid.rows} x "
        f"{ortho_grid.cols} at {ortho_grid.res} m, reference DEM {dem_grid.rows} x "
        f"{dem_grid.cols}, {len(terrain.craters)} craters"
    )
    lap("terrain")

    # Line-scan images ---------------------------------------------------------------
    model = sm.radiance_model("target")
    lap("shading")
    total_lines = sum(c.n_lines for s in strips for c in s.truth.ccds)
    render_stats: dict[str, dict[str, dict[str, float]]] = {}
    strip_specs = []
    with tqdm(
        total=total_lines,
        unit="line",
        desc="rendering",
        disable=None if progress else True,
        leave=False,
    ) as bar:
        for i, s in enumerate(strips):
            sdir = root / "strips" / s.strip.id
            sdir.mkdir()
            render_stats[s.strip.id] = {}
            ccd_specs = []
            for k, c in enumerate(s.truth.ccds):
                img = sdir / f"{c.name}.tif"
                render_stats[s.strip.id][c.name] = render_ccd(
                    s.truth,
                    c.name,
                    dem,
                    model,
                    enu,
                    cfg.sensor,
                    img,
                    chunk_pixels=cfg.render.chunk_pixels,
                    noise_seed=seed_sequence(seed, "ccd_noise", i, k),
                    progress=bar.update,
                    processes=cfg.render.processes or (os.cpu_count() or 1),
                )
                ccd_specs.append((c.name, img))
            s.initial.to_json(sdir / "camera.json")
            specs = []
            for name, img in ccd_specs:
                rpc_rel = None
                if cfg.render.write_rpc:
                    from planetref.camera.rpc import MARS_BODY, write_rpc
                    from planetref.camera.rpc.stable import fit_rpc_stable

                    # Through the regularisation ladder: a long strip's initial camera
                    # is not exactly rational, and the plain fit may put a denominator
                    # pole near the image. A well-behaved fit stops at the first rung
                    # (the plain fit's own setting): the same RPC bit for bit.
                    rpc, rep = fit_rpc_stable(
                        s.initial,
                        ccd=name,
                        height_range_m=(dem.min_height_m - 100.0, dem.max_height_m + 100.0),
                    )
                    render_stats[s.strip.id][name]["rpc_check_max_px"] = rep.check_max_px
                    write_rpc(rpc, sdir / f"{name}.RPB", body=MARS_BODY)
                    rpc_rel = f"strips/{s.strip.id}/{name}.RPB"
                specs.append(
                    CcdSpec(
                        name=name,
                        image=img.relative_to(root).as_posix(),
                        camera=f"strips/{s.strip.id}/camera.json",
                        camera_ccd=name,
                        rpc=rpc_rel,
                    )
                )
            # The calibration's accuracy as an instrument team would state it: the RMS
            # of the CCD placement errors the truth is drawn with (not the drawn ones).
            strip_specs.append(
                StripSpec(
                    id=s.strip.id,
                    ccds=tuple(specs),
                    ccd_accuracy_px=cfg.truth_mismatch.ccd_offset_px,
                    # The navigation's stated bound, where the config declares one.
                    initial_uncertainty_m=cfg.initial_errors.declared_uncertainty_m,
                )
            )
            s.truth.to_json(root / "truth" / f"{s.strip.id}.camera.json")
    del model
    lap("render")

    # Reference ortho and DEM ---------------------------------------------------------
    # The DEM first: off-nadir mosaic sources are orthorectified on it.
    ref_record: dict[str, Any] = {}
    ref_dem = reference_dem(
        dem_grid,
        ref,
        local,
        sm.coarse_grid,
        terrain.regional_composite,
        cfg.reference,
        stream(seed, "mola" if cfg.reference.mola.tracks else "dem_noise"),
        ref_record,
    )
    sources, seams = draw_mosaic(
        cfg.reference.mosaic, cfg.photometry, ortho_grid, stream(seed, "mosaic")
    )
    relief = None
    if any(src.emission_deg > 0 for src in sources):
        relief = _relief_above_reference_dem(sm, ref_dem, dem_grid, ref, local)
    relative = np.zeros(ortho_grid.shape, dtype=np.float32)
    with tqdm(
        total=ortho_grid.rows * len(sources),
        unit="row",
        desc="reference ortho",
        disable=None if progress else True,
        leave=False,
    ) as bar:
        for src in sources:
            model = sm.radiance_model("reference", sun_override=src.sun, haze_override=src.haze)
            ortho_radiance(
                ortho_grid,
                ref,
                local,
                model,
                cfg.reference,
                relative,
                source=src,
                seams=seams,
                progress=bar.update,
                relief=relief,
            )
            del model
    ortho = finish_ortho(relative, cfg.reference, stream(seed, "ortho_noise"))
    del relative
    ref_wkt = ref.crs.to_wkt()
    write_raster(
        root / "reference" / "ortho.tif",
        ortho,
        ortho_grid,
        ref_wkt,
        offset=cfg.reference.ortho_offset_m,
    )
    ref_record["mosaic"] = sources_to_dict(sources, seams)
    ref_record["ortho_offset_m"] = list(cfg.reference.ortho_offset_m)
    (root / "truth" / "reference.json").write_text(
        json.dumps(ref_record, indent=1, sort_keys=True) + "\n", encoding="utf-8"
    )
    (root / "truth" / "change.json").write_text(
        json.dumps(sm.change.to_dict(), indent=1, sort_keys=True) + "\n", encoding="utf-8"
    )
    write_raster(root / "reference" / "dem.tif", ref_dem, dem_grid, ref_wkt, nodata=float("nan"))
    datum: dict[str, str] = {}
    if cfg.reference.mola.areoid and cfg.reference.mola.areoid_declared:
        areoid, areoid_grid = areoid_raster(dem_grid, cfg.reference.mola)
        write_raster(root / "reference" / "areoid.tif", areoid, areoid_grid, ref_wkt)
        # The simulated areoid is a plane near the sphere, not Mars' areoid (whose
        # ellipsoidal shape puts it kilometres from the sphere away from the equator):
        # the scene says so, so the reader's plausibility check warns instead of failing.
        datum = {
            "dem_datum": "areoid",
            "areoid": "reference/areoid.tif",
            "implausible_heights": "warn",
        }
    lap("reference")

    # Truth ---------------------------------------------------------------------------
    dem.to_geotiff(root / "truth" / "dem.tif")
    errors: dict[str, Any] = {}
    cp_rows: list[dict[str, Any]] = []
    for i, s in enumerate(strips):
        frame = s.orbit.frame(np.zeros(1))[0]
        errors[s.strip.id] = {
            "initial_errors": measure_initial_errors(
                s.truth, s.initial, dem, frame, cfg.render.measure_grid
            ),
            "consistency": measure_consistency(s.truth, dem, 8, stream(seed, "consistency", i)),
            "facts": s.facts,
            "jitter": [
                {"axis": a, "amplitude_urad": amp, "frequency_hz": f, "phase_rad": ph}
                for a, amp, f, ph in s.jitter
            ],
            "jitter_random": [
                {"axis": a, "amplitude_urad": amp, "frequency_hz": f, "phase_rad": ph}
                for a, amp, f, ph in s.jitter_random
            ],
            "render": render_stats[s.strip.id],
            "truth_mismatch": s.mismatch,
        }
        if cfg.render.n_checkpoints:
            cp_rows += checkpoints(
                s.truth, dem, s.strip.id, cfg.render.n_checkpoints, stream(seed, "checkpoints", i)
            )
    errors["truth_dem"] = {
        "rows": grid.rows,
        "cols": grid.cols,
        "gsd_m": res,
        "min_height_m": dem.min_height_m,
        "max_height_m": dem.max_height_m,
        "n_craters": len(terrain.craters),
    }
    (root / "truth" / "errors.json").write_text(
        json.dumps(errors, indent=1, sort_keys=True) + "\n", encoding="utf-8"
    )
    _write_csv(
        root / "truth" / "checkpoints.csv",
        cp_rows,
        ["strip", "ccd", "line", "sample", "x_m", "y_m", "z_m", "lon_deg", "lat_deg", "height_m"],
    )
    cr = terrain.craters
    lon, lat = local.map_to_lonlat(cr.x, cr.y)
    _write_csv(
        root / "truth" / "craters.csv",
        [
            {
                "x_m": cr.x[j],
                "y_m": cr.y[j],
                "lon_deg": lon[j],
                "lat_deg": lat[j],
                "diameter_m": cr.diameter_m[j],
                "degradation": cr.degradation[j],
            }
            for j in range(len(cr))
        ],
        ["x_m", "y_m", "lon_deg", "lat_deg", "diameter_m", "degradation"],
    )
    import tomli_w

    (root / "truth" / "config.toml").write_text(
        "# the configuration that made this scene (planetref simulate --config)\n"
        + tomli_w.dumps(cfg.model_dump(mode="json", exclude_none=True)),
        encoding="utf-8",
    )
    lap("truth")

    manifest = SceneManifest(
        name=cfg.name,
        reference=ReferenceSpec(
            ortho="reference/ortho.tif",
            dem="reference/dem.tif",
            **datum,
            **reference_accuracy(cfg.reference.mosaic, ortho_grid.res, ortho_grid),
        ),
        strips=tuple(strip_specs),
        truth=TruthSpec(
            dem="truth/dem.tif",
            cameras={s.strip.id: f"truth/{s.strip.id}.camera.json" for s in strips},
            ortho_offset_m=cfg.reference.ortho_offset_m,
            checkpoints="truth/checkpoints.csv",
            errors="truth/errors.json",
            craters="truth/craters.csv",
            config="truth/config.toml",
        ),
    )
    write_manifest(manifest, root / "scene.toml")
    if preview:
        from planetref.simulate.preview import write_preview

        write_preview(root, root / "preview.png")
        lap("preview")
    return SceneResult(
        root=root, manifest_path=root / "scene.toml", errors=errors, timings_s=timings
    )
