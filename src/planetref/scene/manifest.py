"""The scene manifest ``scene.toml``: what a scene directory contains.

The manifest is the pipeline's entry point for simulated and real data alike; see
``docs/scene-manifest.md`` for the format. Paths are relative to the manifest's
folder (absolute paths are accepted for real data). Unknown keys are rejected with
the list of the valid keys.

Example::

    format = "planetref-scene"
    version = 1
    name = "tiny"

    [body]
    name = "Mars"
    semi_major_m = 3396190.0
    semi_minor_m = 3396190.0

    [reference]
    ortho = "reference/ortho.tif"
    dem = "reference/dem.tif"

    [[strips]]
    id = "strip1"

    [[strips.ccds]]
    name = "ccd1"
    image = "strips/strip1/ccd1.tif"
    camera = "strips/strip1/camera.json"
    camera_ccd = "ccd1"
    rpc = "strips/strip1/ccd1.RPB"

    [truth]
    dem = "truth/dem.tif"
    ortho_offset_m = [0.0, 0.0]

    [truth.cameras]
    strip1 = "truth/strip1.camera.json"
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Final, Literal

from pydantic import Field, model_validator

from planetref.errors import InputError, MissingFileError
from planetref.geometry.geodesy import Ellipsoid
from planetref.runtime.settings import Settings, validate_settings
from planetref.runtime.tomlfile import read_toml

__all__ = [
    "MANIFEST_FORMAT",
    "MANIFEST_NAME",
    "MANIFEST_VERSION",
    "BodySpec",
    "CcdSpec",
    "ReferenceSpec",
    "SceneManifest",
    "StripSpec",
    "TruthSpec",
    "load_manifest",
    "write_manifest",
]

MANIFEST_FORMAT: Final = "planetref-scene"
MANIFEST_VERSION: Final = 1
MANIFEST_NAME = "scene.toml"

#: Strip and CCD ids name folders of the run: no path component (``.``, ``..``) nor a
#: hidden name (planetref's temporaries start with a dot), no separator.
_ID = r"^[A-Za-z0-9_-][A-Za-z0-9_.-]{0,63}$"


_Model = Settings


class BodySpec(_Model):
    """The reference body of every height and latitude in the scene.

    Attributes:
        name: Name of the body (informative).
        semi_major_m: Equatorial radius (m).
        semi_minor_m: Polar radius (m).
    """

    name: str = "Mars"
    semi_major_m: float = Field(default=3396190.0, gt=0)
    semi_minor_m: float = Field(default=3396190.0, gt=0)

    def ellipsoid(self) -> Ellipsoid:
        """The body as an :class:`~planetref.geometry.geodesy.Ellipsoid`."""
        return Ellipsoid(self.semi_major_m, self.semi_minor_m, self.name)


class ReferenceSpec(_Model):
    """The reference data the images are registered to.

    Attributes:
        ortho: Orthoimage (georeferenced raster, any GDAL format, e.g. a CTX mosaic).
        dem: DEM (georeferenced raster of heights in metres above ``dem_datum``).
        ortho_band: 1-based band of the ortho to use.
        dem_band: 1-based band of the DEM.
        dem_datum: What the DEM's heights are above: ``"body"`` (the ``[body]``
            sphere/ellipsoid; CTX/HRSC-like products) or ``"areoid"`` (MOLA MEGDR-like
            products; needs ``areoid``). See :mod:`planetref.raster.datum`.
        areoid: Raster of the areoid's height above ``body`` (metres, any map CRS of the
            body); the DEM is converted to body heights with it when it is read.
        implausible_heights: DEM heights implausible for ``dem_datum`` or an areoid far
            from Mars' are an error (``"error"``, the default) or accepted with a warning
            in the run's log and report (``"warn"``). Values beyond +-1 % of the body's
            radius are always an error. See :mod:`planetref.raster.datum`.
        accuracy_m: The ortho's absolute planimetric accuracy as its producer states it:
            RMS per axis (metres) of the error that the ortho's pixels share over
            ``accuracy_length_m`` (a mosaic source's registration, its smooth warps);
            0 for a reference without geometric error. Sets the adjustment's
            ``[adjust.systematic] reference_sigma_m`` unless the run config does.
        accuracy_length_m: The distance (metres) over which that error is common (a
            mosaic source's width, a warp's wavelength); the adjustment's
            ``reference_patch_m``.
    """

    ortho: str
    dem: str
    ortho_band: int = Field(default=1, ge=1)
    dem_band: int = Field(default=1, ge=1)
    dem_datum: Literal["body", "areoid"] = "body"
    areoid: str | None = None
    implausible_heights: Literal["error", "warn"] = "error"
    accuracy_m: float | None = Field(default=None, ge=0.0)
    accuracy_length_m: float | None = Field(default=None, gt=0.0)

    @model_validator(mode="after")
    def _datum(self) -> ReferenceSpec:
        if self.dem_datum == "areoid" and not self.areoid:
            raise ValueError('dem_datum = "areoid" needs areoid = "<raster of areoid heights>"')
        if self.areoid and self.dem_datum != "areoid":
            raise ValueError('areoid is given but dem_datum is not "areoid"')
        return self


class CcdSpec(_Model):
    """One CCD image of a strip and its camera.

    Attributes:
        name: CCD name, unique within the strip.
        image: The image (GDAL raster; band 1 is used).
        camera: The camera file: native line-scan JSON, USGS CSM ISD or RPC
            (``.RPB``, ``_RPC.TXT`` or a GeoTIFF with RPC tags). The CCDs of a strip
            share one camera file, or each names its own RPC (an RPC strip).
        camera_ccd: Name of this CCD inside a multi-CCD camera file (native JSON),
            default: the camera's first CCD.
        rpc: Optional RPC fitted to the camera (any of the RPC formats).
    """

    name: str = Field(pattern=_ID)
    image: str
    camera: str
    camera_ccd: str | None = None
    rpc: str | None = None


class StripSpec(_Model):
    """A strip: the CCD images taken together (they share one orbit and attitude).

    Attributes:
        id: Strip identifier, unique within the scene.
        ccds: Its CCDs (at least one).
        ccd_accuracy_px: The camera calibration's accuracy as its makers state it: RMS
            per image axis (pixels) of each CCD's placement error in the focal plane.
            Sets the adjustment's ``[adjust.systematic] ccd_offset_sigma_px`` unless the
            run config does.
        initial_uncertainty_m: The a-priori ground uncertainty of the strip's initial
            camera as its navigation states it (metres, a bound on how far its ground
            positions may be off). Sets the front end's ``uncertainty_m`` (how far the
            coarse stage searches) unless the run config does.
    """

    id: str = Field(pattern=_ID)
    ccds: tuple[CcdSpec, ...] = Field(min_length=1)
    ccd_accuracy_px: float | None = Field(default=None, ge=0.0)
    initial_uncertainty_m: float | None = Field(default=None, gt=0.0)

    @model_validator(mode="after")
    def _unique_ccds(self) -> StripSpec:
        names = [c.name for c in self.ccds]
        if len(set(names)) != len(names):
            raise ValueError(f"CCD names must be unique within a strip, got {names}")
        return self


class TruthSpec(_Model):
    """Ground truth of a simulated scene (absent for real data).

    Attributes:
        dem: Full-resolution truth DEM.
        cameras: True camera file (native JSON) of each strip, by strip id.
        ortho_offset_m: ``(dx, dy)`` map offset of the reference ortho: a feature's
            position in the ortho minus its true position.
        checkpoints: CSV of check points (strip, ccd, line, sample, X, Y, Z, lon, lat, h).
        errors: JSON with the measured errors of the initial cameras.
        craters: CSV of the crater population.
        config: The full simulation config (TOML) that made the scene.
    """

    dem: str
    cameras: dict[str, str]
    ortho_offset_m: tuple[float, float] = (0.0, 0.0)
    checkpoints: str | None = None
    errors: str | None = None
    craters: str | None = None
    config: str | None = None


class SceneManifest(_Model):
    """The content of ``scene.toml``.

    Attributes:
        format: Always ``"planetref-scene"``.
        version: Format version (1).
        name: Scene name.
        body: Reference body.
        reference: Reference ortho and DEM.
        strips: The strips (at least one).
        truth: Ground truth (simulated scenes only).
    """

    format: Literal["planetref-scene"] = MANIFEST_FORMAT
    version: Literal[1] = MANIFEST_VERSION
    name: str = "scene"
    body: BodySpec = BodySpec()
    reference: ReferenceSpec
    strips: tuple[StripSpec, ...] = Field(min_length=1)
    truth: TruthSpec | None = None

    @model_validator(mode="after")
    def _check(self) -> SceneManifest:
        ids = [s.id for s in self.strips]
        if len(set(ids)) != len(ids):
            raise ValueError(f"strip ids must be unique, got {ids}")
        if self.truth is not None:
            missing = sorted(set(ids) - set(self.truth.cameras))
            if missing:
                raise ValueError(f"truth.cameras lacks strips {missing}")
        return self

    def resolve(self, root: str | os.PathLike[str], relative: str) -> Path:
        """The absolute path of a manifest path, relative to the manifest folder ``root``."""
        p = Path(relative)
        return p if p.is_absolute() else Path(root) / p

    def paths(self) -> list[str]:
        """Every file path the manifest names (for existence checks)."""
        out = [self.reference.ortho, self.reference.dem]
        if self.reference.areoid:
            out.append(self.reference.areoid)
        for s in self.strips:
            for c in s.ccds:
                out += [c.image, c.camera] + ([c.rpc] if c.rpc else [])
        if self.truth is not None:
            t = self.truth
            out += [t.dem, *t.cameras.values()]
            out += [p for p in (t.checkpoints, t.errors, t.craters, t.config) if p]
        return out

    def strip(self, strip_id: str) -> StripSpec:
        """The strip with this id.

        Raises:
            InputError: Unknown id (the message lists the valid ones).
        """
        for s in self.strips:
            if s.id == strip_id:
                return s
        raise InputError(f"unknown strip {strip_id!r}; strips: {[s.id for s in self.strips]}")


def load_manifest(
    path: str | os.PathLike[str], *, check_files: bool = True
) -> tuple[SceneManifest, Path]:
    """Read and validate a scene manifest.

    Args:
        path: ``scene.toml``, or the scene folder that holds it.
        check_files: Also check that every file it names exists.

    Returns:
        ``(manifest, root)``: the manifest and the folder its paths are relative to.

    Raises:
        MissingFileError: If the manifest (or, with ``check_files``, a file it names)
            does not exist.
        InputError: If it is not valid TOML or not a valid manifest (the message names
            the key at fault and lists the valid keys).
    """
    p = Path(path)
    if p.is_dir():
        p = p / MANIFEST_NAME
    data = read_toml(p, "scene manifest")
    fmt = data.get("format")
    if fmt != MANIFEST_FORMAT:
        raise InputError(
            f"expected format = {MANIFEST_FORMAT!r}, got {fmt!r}", path=p, field="format"
        )
    manifest = validate_settings(SceneManifest, data, source=str(p), what="scene manifest")
    root = p.parent
    if check_files:
        for rel in manifest.paths():
            if not manifest.resolve(root, rel).exists():
                raise MissingFileError(
                    f"file named by the manifest not found: {rel}", path=manifest.resolve(root, rel)
                )
    return manifest, root


def manifest_to_dict(manifest: SceneManifest) -> dict[str, Any]:
    """The manifest as a TOML-ready table (None values left out).

    ``implausible_heights`` is written only when it is not the default: scenes written
    before the key existed read back byte-identical.
    """
    doc = manifest.model_dump(mode="json", exclude_none=True)
    if doc.get("reference", {}).get("implausible_heights") == "error":
        del doc["reference"]["implausible_heights"]
    return doc


def write_manifest(manifest: SceneManifest, path: str | os.PathLike[str]) -> Path:
    """Write ``scene.toml`` (deterministic: same manifest, same bytes).

    Args:
        manifest: The manifest.
        path: Output file.

    Returns:
        The path written.
    """
    import tomli_w

    p = Path(path)
    text = "# planetref scene manifest; see docs/scene-manifest.md\n" + tomli_w.dumps(
        manifest_to_dict(manifest)
    )
    p.write_text(text, encoding="utf-8")
    return p
