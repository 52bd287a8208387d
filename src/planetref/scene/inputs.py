"""The inputs of a georef run, opened and checked before any tile is matched.

Each check fails with one line naming the file: a strip whose CCDs use several camera
files, a CCD the camera does not know, an image of the wrong size or truncated, a strip
whose footprint misses the reference.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from planetref.errors import InputError, PlanetrefError, library_reason

if TYPE_CHECKING:  # pragma: no cover
    from planetref.camera.base import Camera
    from planetref.raster.dem import GridTerrain
    from planetref.raster.image import CcdImage
    from planetref.raster.ortho import ReferenceOrtho
    from planetref.scene.manifest import SceneManifest, StripSpec

__all__ = [
    "MARS_SEMI_MAJOR_M",
    "TruthDem",
    "check_body",
    "check_overlap",
    "check_strips",
    "open_reference",
    "scene_input_files",
    "scene_path",
    "strip_cameras",
    "truth_inputs",
    "truth_terrain",
    "worker_dem",
]

MARS_SEMI_MAJOR_M = 3396190.0

log = logging.getLogger(__name__)


def scene_path(scene: str | os.PathLike[str]) -> Path:
    """The absolute path of ``scene.toml`` (given it or its folder)."""
    p = Path(scene)
    return (p / "scene.toml" if p.is_dir() else p).resolve()


def scene_input_files(manifest: SceneManifest, root: Path) -> list[Path]:
    """Every file a scene manifest names (reference, images, cameras, truth): run inputs."""
    names = [manifest.reference.ortho, manifest.reference.dem]
    if manifest.reference.areoid:
        names.append(manifest.reference.areoid)
    for strip in manifest.strips:
        for c in strip.ccds:
            names += [c.image, c.camera]
    if manifest.truth is not None:
        names += [manifest.truth.dem, *manifest.truth.cameras.values()]
    paths = {manifest.resolve(root, n) for n in names}
    return sorted(Path(p) for p in paths if Path(p).is_file())


def check_body(body: Any, raster: Any, what: str, path: Any = None) -> None:
    """Refuse a reference on another body than ``body`` (e.g. an Earth CRS), in words."""
    from planetref.errors import CrsError

    crs = getattr(raster, "crs", None)
    ellipsoid = getattr(crs, "ellipsoid", None)
    a_ref = getattr(ellipsoid, "semi_major_metre", None)
    a_cam = float(body.semi_major_m)
    # (A radius implies its CRS and ellipsoid: the two None tests only narrow types.)
    if (
        a_ref is None
        or crs is None
        or ellipsoid is None
        or abs(float(a_ref) - a_cam) <= 0.01 * a_cam
    ):
        return
    name = (
        "Mars"
        if abs(a_cam - MARS_SEMI_MAJOR_M) <= 0.01 * MARS_SEMI_MAJOR_M
        else f"the cameras' body (a = {a_cam:.0f} m)"
    )
    raise CrsError(
        f"the {what}'s CRS is not a {name} CRS ({crs.name}; ellipsoid "
        f"{ellipsoid.name}, a = {float(a_ref):.0f} m) but the cameras are on {name}",
        path=path or getattr(raster, "path", None),
    )


def open_reference(
    manifest: SceneManifest, root: Path, warnings: list[str] | None = None
) -> tuple[ReferenceOrtho, GridTerrain]:
    """The scene's reference orthoimage and DEM, opened and checked.

    Args:
        manifest: The scene.
        root: Its folder.
        warnings: Where the warnings the scene accepted go (implausible heights with
            ``implausible_heights = "warn"``): the run logs them once its log is open
            and writes them into its report. Without it they are logged at once.
    """
    from planetref.raster.datum import open_reference_dem
    from planetref.raster.ortho import ReferenceOrtho

    spec = manifest.reference
    ortho_path = manifest.resolve(root, spec.ortho)
    dem_path = manifest.resolve(root, spec.dem)
    ref = ReferenceOrtho(ortho_path, band=spec.ortho_band)
    _check_readable(ortho_path, spec.ortho_band, "reference ortho")
    areoid = None if spec.areoid is None else manifest.resolve(root, spec.areoid)
    dem = open_reference_dem(
        dem_path,
        band=spec.dem_band,
        datum=spec.dem_datum,
        areoid=areoid,
        implausible=spec.implausible_heights,
        warnings=warnings,
    )
    return ref, dem  # type: ignore[return-value]


def _check_readable(path: Path, band: int, what: str) -> None:
    """Fail now, naming the file, on a raster that opens but cannot be read to its end.

    A truncated GeoTIFF opens fine (its header is whole) and fails on its first missing
    block, which would otherwise fail every tile of a run with a message naming no file.
    Its first and last rows of blocks are read (GDAL writes blocks in row order).
    """
    import rasterio
    from rasterio.windows import Window

    try:
        with rasterio.open(path) as ds:
            rows = min(ds.height, max(1, ds.block_shapes[band - 1][0]))
            for row0 in (0, ds.height - rows):
                ds.read(band, window=Window(0, row0, ds.width, rows))
    except Exception as exc:
        raise InputError(
            f"cannot read the {what} to its end ({library_reason(exc)}); is the file "
            "truncated or damaged?",
            path=path,
        ) from None


def strip_cameras(
    manifest: SceneManifest, root: Path, strip: StripSpec
) -> tuple[Camera, dict[str, CcdImage]]:
    """The strip's camera and its CCD images, keyed by the camera's CCD names."""
    from planetref.camera.io import load_camera
    from planetref.raster.image import CcdImage

    files = {manifest.resolve(root, c.camera) for c in strip.ccds}
    if len(files) != 1:
        camera = _rpc_strip(manifest, root, strip, len(files))
    else:
        camera = load_camera(files.pop())
    images: dict[str, CcdImage] = {}
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


def _rpc_strip(manifest: SceneManifest, root: Path, strip: StripSpec, n_files: int) -> Camera:
    """A strip whose CCDs have one RPC each (e.g. level-2 products): one RPC strip camera."""
    from planetref.camera.io import detect_camera_format
    from planetref.camera.rpc.strip import RpcStripCamera

    files = {c.name: manifest.resolve(root, c.camera) for c in strip.ccds}
    if len(files) != n_files or any(detect_camera_format(f) != "rpc" for f in files.values()):
        raise InputError(
            f"strip {strip.id}: its CCDs use {n_files} camera files; georef adjusts a "
            "strip as one camera, so its CCDs must share one camera file (a multi-CCD "
            "native camera) or each have its own RPC"
        )
    return RpcStripCamera.from_files(files)


def _checked_image(image: CcdImage, camera: Camera, ccd: str) -> CcdImage:
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


def check_overlap(
    camera: Camera,
    images: dict[str, CcdImage],
    ref: ReferenceOrtho,
    dem: GridTerrain,
    strip: str,
) -> None:
    """Refuse a strip whose footprint misses the reference entirely; warn when it is partial.

    A grid of image points of every CCD (pixel centres, 9 lines x 5 samples) is projected
    through the DEM into the reference ortho. None covered is an error; some not covered
    is a warning naming the share per CCD: those parts can get no MCPs, and a strip end
    beyond the DEM or the ortho is then held only by the weak-node rule.
    """
    from planetref.camera.mapping import image_to_ref_pixel

    check_body(camera.ellipsoid, ref, "reference ortho")
    check_body(camera.ellipsoid, dem, "reference DEM")
    outside: dict[str, float] = {}
    for ccd in images:
        n_lines, n_samples = camera.image_size(ccd)
        line, sample = np.meshgrid(
            np.linspace(0.5, n_lines - 0.5, 9), np.linspace(0.5, n_samples - 0.5, 5)
        )
        col, row = image_to_ref_pixel(camera, ccd, line.ravel(), sample.ravel(), ref, dem)
        covered = np.isfinite(col) & np.isfinite(row)
        covered[covered] = ref.contains_pixel(col[covered], row[covered])
        outside[ccd] = float(np.mean(~covered))
    if all(v == 1.0 for v in outside.values()):
        raise InputError(
            f"strip {strip}: its images do not overlap the reference ortho (or "
            "their rays miss the reference DEM); check the scene's reference and "
            "cameras"
        )
    partial = {c: v for c, v in outside.items() if v > 0}
    if partial:
        log.warning(
            "strip %s: part of its footprint lies outside the reference ortho or DEM "
            "(share of a 9 x 5 grid of image points per CCD: %s); those parts get no "
            "matched control points",
            strip,
            ", ".join(f"{c} {100 * v:.0f} %" for c, v in partial.items()),
        )


def check_strips(
    manifest: SceneManifest, root: Path, ref: ReferenceOrtho, dem: GridTerrain
) -> None:
    """Open every strip's camera and CCD images and check that they overlap the reference.

    Run before a run folder is claimed, so that a bad camera or image file, or a strip
    that misses the reference, leaves nothing behind (the images are closed again).
    """
    for strip in manifest.strips:
        camera, images = strip_cameras(manifest, root, strip)
        try:
            check_overlap(camera, images, ref, dem, strip.id)
        finally:
            for image in images.values():
                image.close()


class TruthDem:
    """The truth DEM of a simulated scene: checked when a run starts, read only when used.

    Read whole at the start it stayed resident through the run, orthoimages included,
    where a georef's memory peaks, and it grows with the strip (hiric-strip: 1 m over the
    strip, ~14 MB per 1000 lines). Now :func:`truth_terrain` reads it for the true errors
    and the caller lets it go after them (one read per strip, 0.4-1.0 s on hiric-strip).

    Args:
        path: The GeoTIFF; it must exist, read to its end (:func:`_check_readable`) and
            have a CRS (one-line errors before any tile is matched; holes are checked
            when it is read).

    Raises:
        MissingFileError: The file does not exist.
        InputError: It cannot be read to its end (truncated or damaged).
        CrsError: It has no CRS.
    """

    def __init__(self, path: Path) -> None:
        import rasterio

        from planetref.errors import CrsError, MissingFileError

        if not path.exists():
            raise MissingFileError("truth DEM file not found", path=path)
        _check_readable(path, 1, "truth DEM")
        with rasterio.open(path) as ds:
            if ds.crs is None:
                raise CrsError("the DEM has no CRS", path=path)
        self.path = path

    def load(self) -> GridTerrain:
        """The DEM, read now (the caller holds it as long as it needs it)."""
        from planetref.raster.dem import GridTerrain

        return GridTerrain.from_geotiff(self.path)


def truth_terrain(truth: TruthDem | None, dem: GridTerrain) -> GridTerrain:
    """The terrain of the true errors: the truth DEM, read now, when there is one, else ``dem``.

    The caller drops it (``del``) when the true errors are done, before the orthoimages.
    """
    return dem if truth is None else truth.load()


def truth_inputs(manifest: SceneManifest, root: Path) -> tuple[dict[str, Camera], TruthDem | None]:
    """True cameras per strip id and the true DEM of a simulated scene (empty, None otherwise)."""
    from planetref.camera.io import load_camera

    if manifest.truth is None:
        return {}, None
    cams = {
        sid: load_camera(manifest.resolve(root, p)) for sid, p in manifest.truth.cameras.items()
    }
    return cams, TruthDem(manifest.resolve(root, manifest.truth.dem))


def worker_dem(manifest: SceneManifest, root: Path, dem: GridTerrain, target: Path) -> Path:
    """The DEM file parallel workers read: the scene's, or its body-height conversion.

    A DEM above the areoid is converted once (to ``target``, in the run folder) so that
    every worker reads the same body-relative heights as this process.
    """
    from planetref.runtime.atomic import atomic_path

    if manifest.reference.dem_datum == "body":
        return manifest.resolve(root, manifest.reference.dem)
    if not target.is_file():
        with atomic_path(target) as tmp:
            dem.to_geotiff(tmp)
    return target
