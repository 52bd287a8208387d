"""``planetref scene init``: a checked ``scene.toml`` from CCD images, cameras and a reference.

Given the CCD images of one strip with their cameras (native line-scan JSON, USGS CSM ISD
or RPC), a reference orthoimage and a DEM (any map CRS of the body), :func:`init_scene`
checks what a run would otherwise find out late, and writes the scene manifest:

* every camera and image opens, and each image has its camera's size;
* the reference ortho and DEM are on the cameras' body (an Earth CRS under a Mars camera
  is refused);
* the footprint of every CCD, through its camera onto the DEM, and the share of it the
  reference covers (none: refused; some: reported);
* the DEM's datum: declared, or told from its heights where they fit only one datum
  (:func:`planetref.raster.datum.datum_warning`); where they fit both (near the equator
  the areoid and the sphere are within Mars' relief of each other) it refuses to guess
  and says what to declare;
* the window of the reference a run needs (the footprint plus a margin), and with
  ``crop`` copies of the ortho and DEM cut to it, so that a run reads only that.

Every error is one line naming the file at fault (:class:`~planetref.errors.InputError`).
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from planetref.errors import InputError

__all__ = ["CcdInput", "SceneInit", "init_scene", "resolve_dem_datum"]

log = logging.getLogger(__name__)

#: Image points per CCD projected for the footprint: lines x samples, border and inside.
GRID = (9, 5)


@dataclass(frozen=True)
class CcdInput:
    """One CCD image and its camera file.

    Attributes:
        image: The CCD image (band 1 is used).
        camera: Its camera file (native JSON, CSM ISD or RPC).
        name: The CCD's name in the scene; default: the camera's CCD of the image's stem
            (e.g. ``ccd2.tif`` -> ``ccd2``), or the stem.
    """

    image: Path
    camera: Path
    name: str | None = None


@dataclass
class SceneInit:
    """What :func:`init_scene` found and wrote.

    Attributes:
        path: The ``scene.toml`` written.
        body: Semi-major and semi-minor axes of the cameras' body (metres).
        footprints: Per CCD, ``[lon_min, lat_min, lon_max, lat_max]`` (degrees,
            planetocentric) of its image points on the DEM.
        outside_share: Per CCD, the share of its image points (9 x 5 grid) that the
            reference ortho and DEM do not cover (0 to 1).
        dem_datum: ``"body"`` or ``"areoid"``.
        datum_reason: Why that datum (declared, or what the heights showed).
        crop: The reference window a run needs, ``[x_min, y_min, x_max, y_max]`` in the
            ortho's CRS units.
        cropped: Files written by ``crop`` (the cut ortho and DEM).
        warnings: What a run will also warn about (partial coverage, a DEM on another
            shape of the body than the cameras').
    """

    path: Path
    body: tuple[float, float]
    footprints: dict[str, list[float]] = field(default_factory=dict)
    outside_share: dict[str, float] = field(default_factory=dict)
    dem_datum: str = "body"
    datum_reason: str = ""
    crop: list[float] = field(default_factory=list)
    cropped: list[Path] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


def _manifest_path(path: Path, root: Path) -> str:
    """``path`` relative to the scene folder when it lies inside it, else absolute."""
    absolute = Path(os.path.abspath(path))
    try:
        return absolute.relative_to(Path(os.path.abspath(root))).as_posix()
    except ValueError:
        return str(absolute)


def _ccd_specs(ccds: list[CcdInput], root: Path) -> list[dict[str, object]]:
    """The ``[[strips.ccds]]`` tables: names and the CCD of each multi-CCD camera file."""
    from planetref.camera.io import load_camera

    if not ccds:
        raise InputError("scene init needs at least one CCD image and its camera (--ccd)")
    specs: list[dict[str, object]] = []
    for c in ccds:
        for p, what in ((c.image, "CCD image"), (c.camera, "camera file")):
            if not Path(p).is_file():
                raise InputError(f"{what} not found", path=p)
        camera = load_camera(c.camera)
        names = tuple(camera.ccd_names)
        name = c.name or Path(c.image).stem
        spec: dict[str, object] = {
            "name": name,
            "image": _manifest_path(c.image, root),
            "camera": _manifest_path(c.camera, root),
        }
        if len(names) > 1:
            if name not in names:
                raise InputError(
                    f"the camera has CCDs {list(names)}; name the CCD of image "
                    f"{Path(c.image).name} after one of them",
                    path=c.camera,
                )
            spec["camera_ccd"] = name
        specs.append(spec)
    return specs


def resolve_dem_datum(
    dem: object, dem_path: Path, declared: str | None, areoid: Path | None
) -> tuple[str, str]:
    """The DEM's datum and why; refuses to guess where its heights fit both datums.

    Args:
        dem: The DEM as read (heights as stored in the file).
        dem_path: Its file (named in the errors).
        declared: The datum the user declared, or ``None`` to tell it from the heights.
        areoid: The areoid raster, if one was given.

    Returns:
        ``(datum, reason)``: ``"body"`` or ``"areoid"``, and why.

    Raises:
        InputError: The declared datum does not fit the heights, the heights fit both
            datums (or neither), or ``areoid`` is needed and missing.
    """
    from planetref.raster.datum import datum_warning

    if declared is not None:
        problem = datum_warning(dem, declared, dem_path)  # type: ignore[arg-type]
        if problem:
            raise InputError(problem.split(": ", 1)[1], path=dem_path)
        if declared == "areoid" and areoid is None:
            raise InputError(
                "dem_datum areoid needs the areoid's height above the body as a raster "
                "(--areoid FILE)",
                path=dem_path,
            )
        return declared, "declared"
    fits = {d: datum_warning(dem, d, dem_path) is None for d in ("body", "areoid")}
    if fits["body"] and fits["areoid"]:
        raise InputError(
            "cannot tell the DEM's datum from its heights (they fit heights above the "
            "body and above the areoid alike here): declare --dem-datum body (heights "
            "above the sphere/ellipsoid: most CTX, HRSC and HiRISE DEMs) or --dem-datum "
            "areoid --areoid FILE (MOLA MEGDR and MOLA-based blends)",
            path=dem_path,
        )
    if fits["body"]:
        return "body", "told from the heights: they fit heights above the body only"
    if fits["areoid"]:
        if areoid is None:
            raise InputError(
                "the DEM's heights fit heights above the areoid only (MOLA-like): declare "
                "--dem-datum areoid --areoid FILE (the areoid's height above the body)",
                path=dem_path,
            )
        return "areoid", "told from the heights: they fit heights above the areoid only"
    raise InputError(
        "the DEM's heights fit neither heights above the body nor above the areoid "
        "(Mars' relief is -7825 to 21183 m): check the units (metres) and that the band "
        "holds heights, not radii",
        path=dem_path,
    )


def _scene_reference(
    scene, root: Path, ortho, dem, dem_datum: str | None
) -> tuple[Path, Path, str, Path | None]:
    """The reference files and datum of an existing scene; given files must be those."""
    spec = scene.reference
    mine = {"ortho": scene.resolve(root, spec.ortho), "dem": scene.resolve(root, spec.dem)}
    for key, given in (("ortho", ortho), ("dem", dem)):
        if given is not None and os.path.abspath(given) != os.path.abspath(mine[key]):
            raise InputError(
                f"the scene's reference {key} is {mine[key]}; a scene has one reference",
                path=given,
            )
    if dem_datum is not None and dem_datum != spec.dem_datum:
        raise InputError(
            f"the scene declares dem_datum = {spec.dem_datum!r}, not {dem_datum!r}",
            path=mine["dem"],
        )
    areoid = None if spec.areoid is None else scene.resolve(root, spec.areoid)
    return mine["ortho"], mine["dem"], spec.dem_datum, areoid


def _footprint(camera, ccd: str, ref, dem) -> tuple[np.ndarray, np.ndarray]:
    """Ground points (XYZ, m) of a grid of the CCD's image points on the DEM, and coverage."""
    from planetref.camera.mapping import rays_to_ground

    n_lines, n_samples = camera.image_size(ccd)
    line, sample = np.meshgrid(
        np.linspace(0.5, n_lines - 0.5, GRID[0]), np.linspace(0.5, n_samples - 0.5, GRID[1])
    )
    xyz = rays_to_ground(camera, ccd, line.ravel(), sample.ravel(), dem)
    ok = np.all(np.isfinite(xyz), axis=1)
    covered = ok.copy()
    if ok.any():
        x, y, _ = ref.ground.xyz_to_map(xyz[ok])
        col, row = ref.map_to_pixel(x, y)
        covered[ok] = ref.contains_pixel(col, row)
    return xyz[ok], covered


def _crop_window(points_xyz: np.ndarray, ref, margin_m: float, body_a_m: float) -> list[float]:
    """``[x_min, y_min, x_max, y_max]`` in the ortho's CRS around the ground points."""
    x, y, _ = ref.ground.xyz_to_map(points_xyz)
    margin = margin_m
    if getattr(ref.crs, "is_geographic", False):
        margin = math.degrees(margin_m / body_a_m)  # degrees of latitude
    return [
        float(np.min(x) - margin),
        float(np.min(y) - margin),
        float(np.max(x) + margin),
        float(np.max(y) + margin),
    ]


def _write_crop(src: Path, bounds: list[float], crs_src: object, out: Path, band: int) -> Path:
    """Cut ``src`` to ``bounds`` (given in ``crs_src``), one band, written atomically."""
    import rasterio
    from rasterio.warp import transform_bounds
    from rasterio.windows import Window, from_bounds

    from planetref.runtime.atomic import atomic_path

    with rasterio.open(src) as ds:
        b = bounds
        if ds.crs != crs_src:
            b = list(transform_bounds(crs_src, ds.crs, *bounds, densify_pts=21))
        win = from_bounds(*b, transform=ds.transform).round_offsets().round_lengths()
        win = win.intersection(Window(0, 0, ds.width, ds.height))
        win = Window(win.col_off - 2, win.row_off - 2, win.width + 4, win.height + 4).intersection(
            Window(0, 0, ds.width, ds.height)
        )  # two pixels more: bilinear sampling at the edge
        data = ds.read(band, window=win)
        profile = {
            "driver": "GTiff",
            "width": int(win.width),
            "height": int(win.height),
            "count": 1,
            "dtype": data.dtype,
            "crs": ds.crs,
            "transform": ds.window_transform(win),
            "nodata": ds.nodatavals[band - 1],
            "compress": "deflate",
            "tiled": True,
        }
        with atomic_path(out, create=False) as tmp, rasterio.open(tmp, "w", **profile) as dst:
            dst.write(data, 1)
    return out


def init_scene(
    out_dir: str | os.PathLike[str],
    ccds: list[CcdInput],
    ortho: str | os.PathLike[str] | None,
    dem: str | os.PathLike[str] | None,
    *,
    strip_id: str = "strip1",
    name: str | None = None,
    dem_datum: str | None = None,
    areoid: str | os.PathLike[str] | None = None,
    margin_m: float = 600.0,
    crop: bool = False,
    overwrite: bool = False,
    append: bool = False,
) -> SceneInit:
    """Check the inputs of one strip against a reference and write ``out_dir/scene.toml``.

    Args:
        out_dir: The scene folder (created if needed); paths inside it are written
            relative to it, others absolute.
        ccds: The strip's CCD images and cameras (the CCDs of a multi-CCD native camera
            share its file; an RPC strip names one RPC per CCD).
        ortho: Reference orthoimage (any map CRS of the cameras' body).
        dem: Reference DEM (metres; any map CRS of the body).
        strip_id: The strip's id.
        name: The scene's name (default: the folder's name).
        dem_datum: ``"body"`` or ``"areoid"``; ``None``: told from the heights where
            they fit one datum only, otherwise refused.
        areoid: Raster of the areoid's height above the body (metres), for ``areoid``.
        margin_m: Margin around the footprint of the reference window a run needs
            (metres; the coarse stage searches ``frontend.uncertainty_m`` around it,
            300 m by default).
        crop: Write the ortho and DEM cut to that window into ``out_dir/reference/`` and
            name those in the manifest.
        overwrite: Replace an existing ``scene.toml`` (and cropped files).
        append: Add the strip to the existing ``scene.toml`` (a campaign of several
            strips): its reference, body and datum are the scene's (``ortho`` and
            ``dem`` may be ``None``; given, they must be the scene's files).

    Returns:
        What was checked and written.

    Raises:
        InputError: One line naming the file at fault: a missing or unreadable file, an
            image of the wrong size, a reference on another body, no overlap, a datum
            that cannot be told.
    """
    from planetref.raster.dem import GridTerrain
    from planetref.raster.ortho import ReferenceOrtho
    from planetref.runtime.atomic import write_text_atomic
    from planetref.runtime.settings import validate_settings
    from planetref.scene.inputs import check_body, strip_cameras
    from planetref.scene.manifest import (
        MANIFEST_FORMAT,
        MANIFEST_NAME,
        SceneManifest,
        load_manifest,
        manifest_to_dict,
    )

    root = Path(out_dir)
    target = root / MANIFEST_NAME
    existing = None
    if append:
        if not target.exists():
            raise InputError("no scene manifest to add the strip to", path=target)
        if crop:
            raise InputError("--crop cuts the reference when a scene is made, not with --append")
        existing, _ = load_manifest(target)
        ortho, dem, dem_datum, areoid = _scene_reference(existing, root, ortho, dem, dem_datum)
        if any(s.id == strip_id for s in existing.strips):
            raise InputError(f"the scene already has a strip {strip_id!r}", path=target)
    elif target.exists() and not overwrite:
        raise InputError(
            "the scene manifest exists; pass --overwrite to replace it or --append to add a strip",
            path=target,
        )
    if ortho is None or dem is None:
        raise InputError("a new scene needs its reference ortho and DEM (--ortho, --dem)")
    ortho, dem = Path(ortho), Path(dem)
    areoid = None if areoid is None else Path(areoid)
    for p, what in ((ortho, "reference ortho"), (dem, "reference DEM"), (areoid, "areoid")):
        if p is not None and not p.is_file():
            raise InputError(f"{what} not found", path=p)
    specs = _ccd_specs(ccds, root)
    ref = ReferenceOrtho(ortho)
    terrain = GridTerrain.from_geotiff(dem)
    try:
        doc: dict[str, object] = {
            "format": MANIFEST_FORMAT,
            "version": 1,
            "name": name or Path(os.path.abspath(root)).name,
            "reference": {"ortho": _manifest_path(ortho, root), "dem": _manifest_path(dem, root)},
            "strips": [{"id": strip_id, "ccds": specs}],
        }
        draft = validate_settings(SceneManifest, doc, source=str(target), what="scene manifest")
        camera, images = strip_cameras(draft, root, draft.strips[0])
        for image in images.values():
            image.close()
        body = camera.ellipsoid
        if existing is not None and (
            abs(existing.body.semi_major_m - float(body.semi_major_m)) > 1.0
            or abs(existing.body.semi_minor_m - float(body.semi_minor_m)) > 1.0
        ):
            raise InputError(
                f"the cameras' body ({float(body.semi_major_m):.0f} / "
                f"{float(body.semi_minor_m):.0f} m) is not the scene's "
                f"({existing.body.semi_major_m:.0f} / {existing.body.semi_minor_m:.0f} m)",
                path=ccds[0].camera,
            )
        check_body(body, ref, "reference ortho", ortho)
        check_body(body, terrain, "reference DEM", dem)
        result = SceneInit(target, (float(body.semi_major_m), float(body.semi_minor_m)))
        points = []
        # images follow the manifest's CCD order, keyed by the camera's CCD names
        for spec, ccd in zip(specs, images, strict=True):
            xyz, covered = _footprint(camera, ccd, ref, terrain)
            key = str(spec["name"])
            result.outside_share[key] = round(float(np.mean(~covered)), 3)
            if len(xyz):
                from planetref.geometry.geodesy import xyz_to_lonlat

                lon, lat, _ = xyz_to_lonlat(xyz, body)
                result.footprints[key] = [
                    round(float(v), 6) for v in (lon.min(), lat.min(), lon.max(), lat.max())
                ]
                points.append(xyz)
        if all(v == 1.0 for v in result.outside_share.values()):
            raise InputError(
                f"strip {strip_id}: no image point of its CCDs falls on the reference "
                "(the footprint misses the ortho, or the rays miss the DEM); is it the "
                "right reference for these images?",
                path=ortho,
            )
        partial = {c: v for c, v in result.outside_share.items() if v > 0}
        if partial:
            result.warnings.append(
                f"strip {strip_id}: part of its footprint lies outside the reference "
                "(share of a 9 x 5 grid of image points per CCD: "
                + ", ".join(f"{c} {100 * v:.0f} %" for c, v in partial.items())
                + "); those parts get no matched control points"
            )
        b_dem = float(terrain.projection.ellipsoid.semi_minor_m)
        if abs(b_dem - float(body.semi_minor_m)) > 1e-4 * float(body.semi_minor_m):
            result.warnings.append(
                f"{dem}: the DEM's CRS is on a body of polar radius {b_dem:.0f} m, the "
                f"cameras' on {float(body.semi_minor_m):.0f} m; its heights are taken "
                "above its own CRS's shape, which differs from the cameras' by up to "
                f"{abs(b_dem - float(body.semi_minor_m)):.0f} m at the poles: check that "
                "the heights are above the shape you mean"
            )
        for message in result.warnings:
            log.warning("%s", message)
        result.dem_datum, result.datum_reason = resolve_dem_datum(terrain, dem, dem_datum, areoid)
        result.crop = _crop_window(np.concatenate(points), ref, margin_m, float(body.semi_major_m))
        reference: dict[str, object] = {"dem_datum": result.dem_datum}
        if crop:
            for src, stem in ((ortho, "ortho"), (dem, "dem")):
                out = root / "reference" / f"{stem}.tif"
                if out.exists() and not overwrite and os.path.abspath(out) != os.path.abspath(src):
                    raise InputError("exists; pass --overwrite to replace it", path=out)
                if os.path.abspath(out) == os.path.abspath(src):
                    raise InputError("the crop would replace this input", path=src)
                result.cropped.append(_write_crop(src, result.crop, ref.crs, out, 1))
            reference["ortho"] = "reference/ortho.tif"
            reference["dem"] = "reference/dem.tif"
        if areoid is not None and result.dem_datum == "areoid":
            reference["areoid"] = _manifest_path(areoid, root)
        doc["reference"] = {**doc["reference"], **reference}  # type: ignore[dict-item]
        doc["body"] = {
            "name": getattr(body, "name", None) or "Mars",
            "semi_major_m": result.body[0],
            "semi_minor_m": result.body[1],
        }
        if existing is not None:  # the scene as it is, plus this strip
            whole = manifest_to_dict(existing)
            whole["strips"].append(doc["strips"][0])  # type: ignore[index]
            doc = whole
        manifest = validate_settings(SceneManifest, doc, source=str(target), what="scene manifest")
    finally:
        ref.close()
    import tomli_w

    text = "# planetref scene manifest (planetref scene init); see docs/scene-manifest.md\n"
    write_text_atomic(target, text + tomli_w.dumps(manifest_to_dict(manifest)))
    load_manifest(target)  # what a run will read: valid, and every file it names exists
    return result
