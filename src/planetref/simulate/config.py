"""Typed configuration of the scene simulator, presets and TOML overrides.

A simulation is fully described by a :class:`SimulationConfig` (frozen pydantic models
that reject unknown keys) and a seed. Presets are TOML files shipped in
``planetref/simulate/presets/``; an override file is a TOML document with the same
structure whose tables are merged key by key into the preset (arrays, including arrays
of tables such as ``strips`` and ``jitter``, replace the preset's value as a whole).

Units are in the field names: ``_m`` metres, ``_deg`` degrees, ``_urad`` microradians,
``_s`` seconds, ``_hz`` hertz, ``_px`` pixels, ``_mm`` millimetres, ``_ppm`` parts per
million. Angles of the sun: azimuth clockwise from north towards the sun, elevation
above the local horizontal. Orbit-frame vectors are ``(along-track, cross-track,
radial)``; attitude triples are ``(roll, pitch, yaw)`` = rotations about the along-track,
cross-track and radial axes.
"""

from __future__ import annotations

import tomllib
from importlib import resources
from os import PathLike
from typing import Any, Literal

from pydantic import Field, model_validator

from planetref.errors import InputError
from planetref.runtime.settings import Settings, deep_merge, validate_settings
from planetref.runtime.tomlfile import read_toml
from planetref.simulate.camera_config import (
    CameraConfig,
    InitialErrorConfig,
    JitterComponent,
    JitterRandomConfig,
    OrbitConfig,
    StripConfig,
)
from planetref.simulate.realism import (
    MolaConfig,
    MosaicConfig,
    SurfaceChangeConfig,
    TruthMismatchConfig,
)

__all__ = [
    "DIFFICULTIES",
    "INITIAL_ERROR_LEVELS",
    "STRESS_LADDER",
    "AlbedoConfig",
    "CameraConfig",
    "CraterConfig",
    "DuneConfig",
    "FractalConfig",
    "InitialErrorConfig",
    "JitterComponent",
    "JitterRandomConfig",
    "OrbitConfig",
    "PhotometryConfig",
    "PlainsConfig",
    "RealismNotes",
    "ReferenceConfig",
    "RegionalConfig",
    "RenderConfig",
    "RidgeConfig",
    "SensorConfig",
    "SimulationConfig",
    "SiteConfig",
    "StripConfig",
    "SunConfig",
    "TerrainConfig",
    "available_difficulties",
    "available_presets",
    "load_config",
    "load_difficulty_dict",
    "load_initial_errors_dict",
    "load_preset_dict",
    "merge_overrides",
    "validate_config",
]

Vec3 = tuple[float, float, float]


_Model = Settings


class SunConfig(_Model):
    """Direction of the sun at the scene centre.

    Attributes:
        azimuth_deg: Azimuth towards the sun, degrees clockwise from north, in [0, 360).
        elevation_deg: Elevation above the horizontal, degrees, in (0, 90].
    """

    azimuth_deg: float = Field(ge=0.0, lt=360.0)
    elevation_deg: float = Field(gt=0.0, le=90.0)


class SiteConfig(_Model):
    """Where the scene lies.

    Attributes:
        lat_deg: Planetocentric latitude of the scene centre (degrees, |lat| <= 75).
        lon_deg: East longitude of the scene centre (degrees, |lon| <= 175, so no scene
            crosses the antimeridian of the reference CRS).
        margin_m: The truth DEM and the reference ortho extend this far (metres) beyond
            the union of the truth and initial footprints of all strips.
    """

    lat_deg: float = Field(default=25.1, ge=-75.0, le=75.0)
    lon_deg: float = Field(default=109.9, ge=-175.0, le=175.0)
    margin_m: float = Field(default=600.0, ge=0.0)


class RegionalConfig(_Model):
    """Long-wavelength relief (what MOLA sees), synthesised on a coarse grid.

    Attributes:
        rms_m: RMS height of the regional relief (m).
        hurst: Hurst exponent of its fractal spectrum (0 < H < 1).
        min_wavelength_m: Shortest wavelength (m); shorter relief is the fine fractal's.
    """

    rms_m: float = Field(default=40.0, ge=0.0)
    hurst: float = Field(default=0.8, gt=0.0, lt=1.0)
    min_wavelength_m: float = Field(default=1500.0, gt=0.0)


class FractalConfig(_Model):
    """Fine fractal relief on the truth DEM grid (spectral synthesis, P(k) ~ k^-(2H+2)).

    Attributes:
        rms_m: RMS height (m) where the terrain is rough (plains scale it down).
        hurst: Hurst exponent (0 < H < 1); lower is rougher at small scales.
        max_wavelength_m: Longest wavelength (m), above which the regional relief takes over.
    """

    rms_m: float = Field(default=3.0, ge=0.0)
    hurst: float = Field(default=0.75, gt=0.0, lt=1.0)
    max_wavelength_m: float = Field(default=1500.0, gt=0.0)


class CraterConfig(_Model):
    """Impact craters with a power-law size-frequency distribution.

    The cumulative number of craters with diameter >= D per km² is
    ``density_per_km2 * (D / d_min_m) ** -sfd_slope`` for ``d_min_m <= D <= d_max_m``.

    Attributes:
        density_per_km2: Craters with D >= d_min_m per km² (before plains thinning).
        d_min_m: Smallest diameter (m).
        d_max_m: Largest diameter (m).
        sfd_slope: Slope of the cumulative SFD (about 2 for small martian craters).
        fresh_fraction: Fraction of fresh craters (sharp raised rims, bright halo); the
            others get a random degradation state.
        depth_diameter: Rim-to-floor depth / diameter of fresh craters (0.2 on Mars).
        rim_diameter: Rim height above the surroundings / diameter of fresh craters.
        rim_irregularity: Relative amplitude of the azimuthal variation of the rim radius.
    """

    density_per_km2: float = Field(default=300.0, ge=0.0)
    d_min_m: float = Field(default=6.0, gt=0.0)
    d_max_m: float = Field(default=600.0, gt=0.0)
    sfd_slope: float = Field(default=2.0, gt=0.0)
    fresh_fraction: float = Field(default=0.3, ge=0.0, le=1.0)
    depth_diameter: float = Field(default=0.2, gt=0.0, le=0.5)
    rim_diameter: float = Field(default=0.04, ge=0.0, le=0.2)
    rim_irregularity: float = Field(default=0.06, ge=0.0, le=0.3)

    @model_validator(mode="after")
    def _check_range(self) -> CraterConfig:
        if self.d_max_m <= self.d_min_m:
            raise ValueError(f"d_max_m ({self.d_max_m}) must exceed d_min_m ({self.d_min_m})")
        return self


class RidgeConfig(_Model):
    """Wrinkle ridges: long sinuous asymmetric rises with a narrow crest.

    Attributes:
        count: Number of ridges crossing the scene.
        height_m: Height of the crest above the surroundings (m).
        width_m: Width of the broad arch (m).
    """

    count: int = Field(default=1, ge=0, le=20)
    height_m: float = Field(default=25.0, ge=0.0)
    width_m: float = Field(default=350.0, gt=0.0)


class PlainsConfig(_Model):
    """Smooth, low-texture plains (young lava/sediment surfaces).

    Attributes:
        fraction: Area fraction covered by plains.
        roughness_factor: Factor on fine relief and albedo texture inside the plains.
        crater_factor: Fraction of craters kept inside the plains (a younger surface).
        feature_size_m: Typical size of a plains patch (m).
    """

    fraction: float = Field(default=0.35, ge=0.0, le=1.0)
    roughness_factor: float = Field(default=0.15, ge=0.0, le=1.0)
    crater_factor: float = Field(default=0.3, ge=0.0, le=1.0)
    feature_size_m: float = Field(default=900.0, gt=0.0)


class DuneConfig(_Model):
    """Dune fields: transverse dunes with sinuous, bifurcating crests.

    Attributes:
        enabled: Whether to add dune fields.
        fraction: Area fraction covered by dune fields.
        wavelength_m: Crest spacing (m).
        height_m: Dune height (m).
        wind_azimuth_deg: Direction the wind blows towards (degrees from north).
        albedo_factor: Albedo factor of the dune sand (dark basaltic sand < 1).
        feature_size_m: Typical size of a dune field (m).
    """

    enabled: bool = True
    fraction: float = Field(default=0.08, ge=0.0, le=1.0)
    wavelength_m: float = Field(default=35.0, gt=0.0)
    height_m: float = Field(default=3.0, ge=0.0)
    wind_azimuth_deg: float = 65.0
    albedo_factor: float = Field(default=0.6, gt=0.0)
    feature_size_m: float = Field(default=700.0, gt=0.0)


class TerrainConfig(_Model):
    """The truth surface.

    Attributes:
        dem_gsd_m: Spacing (m) of the truth DEM grid (a local equirectangular map whose
            standard parallel is the scene's latitude, so map metres are ground metres).
        regional: Long-wavelength relief.
        fractal: Fine fractal relief.
        craters: Crater population.
        ridges: Wrinkle ridges.
        plains: Smooth plains.
        dunes: Dune fields.
    """

    dem_gsd_m: float = Field(default=1.0, gt=0.0)
    regional: RegionalConfig = RegionalConfig()
    fractal: FractalConfig = FractalConfig()
    craters: CraterConfig = CraterConfig()
    ridges: RidgeConfig = RidgeConfig()
    plains: PlainsConfig = PlainsConfig()
    dunes: DuneConfig = DuneConfig()


class AlbedoConfig(_Model):
    """Normal albedo of the surface and its sub-DEM texture.

    Attributes:
        mean: Mean albedo.
        variation: Relative RMS of the low-frequency albedo field.
        variation_wavelength_m: Typical scale of the albedo field (m).
        crater_halo: Relative brightening of the ejecta and walls of fresh craters.
        texture_rms: Relative RMS of the fine albedo texture (regolith, boulders).
        texture_gsd_m: Sampling of the fine texture tiles (m); the texture's detail is
            what the image resolves below the DEM spacing.
        micro_relief_rms_m: RMS height (m) of the fine relief used for shading only
            (normal perturbation; geometry uses the truth DEM).
        reference_change: Relative RMS albedo change in the reference ortho (dust,
            season), so the two images differ beyond illumination.
    """

    mean: float = Field(default=0.22, gt=0.0, le=1.0)
    variation: float = Field(default=0.12, ge=0.0, le=1.0)
    variation_wavelength_m: float = Field(default=500.0, gt=0.0)
    crater_halo: float = Field(default=0.15, ge=0.0, le=2.0)
    texture_rms: float = Field(default=0.06, ge=0.0, le=1.0)
    texture_gsd_m: float = Field(default=0.25, gt=0.0)
    micro_relief_rms_m: float = Field(default=0.06, ge=0.0)
    reference_change: float = Field(default=0.04, ge=0.0, le=1.0)


class PhotometryConfig(_Model):
    """Illumination and reflectance.

    Attributes:
        model: ``"lambert"`` or ``"lunar-lambert"`` (McEwen 1991, L(g) polynomial).
        target_sun: Sun of the line-scan images.
        reference_sun: Sun of the reference ortho.
        sky_fraction: Diffuse skylight relative to direct flux on a flat surface
            (what lights the shadows).
        target_haze: Additive atmospheric path radiance of the line-scan images,
            relative to the radiance of a flat mean-albedo surface.
        reference_haze: The same for the reference ortho.
    """

    model: Literal["lambert", "lunar-lambert"] = "lunar-lambert"
    target_sun: SunConfig = SunConfig(azimuth_deg=215.0, elevation_deg=40.0)
    # 35 deg of azimuth and 6 deg of elevation apart: a non-linear radiometric difference
    # every matcher must bear, without the cross-lighting that no point matcher survives
    # (at 70 deg apart SIFT matches no tile of the hiric-strip scene).
    reference_sun: SunConfig = SunConfig(azimuth_deg=250.0, elevation_deg=34.0)
    sky_fraction: float = Field(default=0.06, ge=0.0, le=1.0)
    target_haze: float = Field(default=0.03, ge=0.0)
    reference_haze: float = Field(default=0.10, ge=0.0)


class SensorConfig(_Model):
    """Detector and electronics.

    Attributes:
        bit_depth: 8 or 16 bits per pixel.
        mtf_sigma_px: Standard deviation (px) of the Gaussian PSF of optics and
            electronics (on top of the pixel's box footprint).
        full_well_e: Electrons at the top of the DN range.
        mean_signal_e: Electrons for a flat surface of mean albedo.
        read_noise_e: Read noise (electrons RMS).
        supersample: Sub-samples per pixel and axis integrated over the footprint.
        column_gain_rms: Relative RMS of a fixed gain per detector column (what
            flat-fielding leaves of a TDI CCD's column response: vertical striping of
            the line-scan images; the reference ortho ignores it).
        saturation_fraction: Share of the line-scan image's pixels that saturate: the
            exposure (``mean_signal_e``) of each CCD image is set so that this share of
            its noise-free signal (sampled on 64 groups of lines before rendering)
            exceeds ``full_well_e``; 0 keeps ``mean_signal_e`` (saturation only where
            the radiance exceeds the full well). The reference ortho ignores it.
        compression_quality: Lossy block-DCT compression of the line-scan images, as
            an IJG/JPEG quality 1-100 (8 x 8 blocks, JPEG luminance table); 0: none.
            The reference ortho ignores it.
    """

    bit_depth: Literal[8, 16] = 16
    mtf_sigma_px: float = Field(default=0.5, ge=0.0, le=5.0)
    full_well_e: float = Field(default=80_000.0, gt=0.0)
    mean_signal_e: float = Field(default=25_000.0, gt=0.0)
    read_noise_e: float = Field(default=40.0, ge=0.0)
    supersample: int = Field(default=2, ge=1, le=8)
    column_gain_rms: float = Field(default=0.0, ge=0.0, le=0.2)
    saturation_fraction: float = Field(default=0.0, ge=0.0, le=0.5)
    compression_quality: int = Field(default=0, ge=0, le=100)


class ReferenceConfig(_Model):
    """The CTX-like reference ortho and the MOLA-like reference DEM.

    Attributes:
        crs: CRS of both rasters (default: Mars 2015 sphere, equirectangular, clon 0).
        ortho_gsd_m: Ortho pixel size in map units (m).
        ortho_offset_m: Systematic ``(x, y)`` offset of the ortho (map metres): its
            geotransform places every feature this much away from its true place
            (a "semi-controlled" mosaic). Zero for a perfect reference.
        ortho_sensor: Sensor of the ortho (8-bit, broader PSF, more noise).
        dem_pixel_m: Reference DEM pixel size in map units (default 1/128 degree).
        dem_pad_m: How far the reference DEM extends beyond the truth DEM (m).
        dem_smoothing_px: Gaussian smoothing sigma of the truth, in reference DEM pixels.
        dem_noise_m: RMS of noise added to the reference DEM (m).
        mosaic: The ortho as a mosaic of source images (seams, per-source errors).
        mola: The DEM gridded from altimetry tracks, optionally above an areoid.
    """

    crs: str = "IAU_2015:49910"
    ortho_gsd_m: float = Field(default=5.0, gt=0.0)
    ortho_offset_m: tuple[float, float] = (0.0, 0.0)
    ortho_sensor: SensorConfig = SensorConfig(
        bit_depth=8,
        mtf_sigma_px=0.6,
        full_well_e=30_000.0,
        mean_signal_e=10_000.0,
        read_noise_e=60.0,
        supersample=4,
    )
    dem_pixel_m: float = Field(default=463.0836, gt=0.0)
    dem_pad_m: float = Field(default=3000.0, ge=0.0)
    dem_smoothing_px: float = Field(default=0.5, ge=0.0)
    dem_noise_m: float = Field(default=1.0, ge=0.0)
    mosaic: MosaicConfig = MosaicConfig()
    mola: MolaConfig = MolaConfig()


class RenderConfig(_Model):
    """Rendering and output controls.

    Attributes:
        chunk_pixels: Target pixels per rendering block (bounds memory). The images
            do not depend on it, except for the noise, which is drawn per block.
        n_checkpoints: Number of random truth checkpoints written per CCD.
        measure_grid: Pixels per axis of the grid on which initial errors are measured.
        write_rpc: Fit an RPC to each CCD's initial camera and write it (``.RPB``).
        processes: Worker processes rendering image blocks in parallel (1: in this
            process; 0: one per CPU). The images do not depend on it.
    """

    chunk_pixels: int = Field(default=1 << 18, ge=1024)
    n_checkpoints: int = Field(default=50, ge=0)
    measure_grid: int = Field(default=9, ge=2)
    write_rpc: bool = True
    processes: int = Field(default=1, ge=0, le=256)


class RealismNotes(_Model):
    """What a difficulty level says about itself (written to ``truth/config.toml``).

    Attributes:
        easier_than_real: What still makes a scene at this level easier than real data
            (one sentence each); a report of the run prints them.
    """

    easier_than_real: tuple[str, ...] = ()


def _field_exists(model: type[Settings], dotted: str) -> bool:
    """Whether ``dotted`` (``"photometry.reference_sun"``) names a field of ``model``."""
    head, _, rest = dotted.partition(".")
    field = model.model_fields.get(head)
    if field is None:
        return False
    if not rest:
        return True
    sub = field.annotation
    return isinstance(sub, type) and issubclass(sub, Settings) and _field_exists(sub, rest)


class SimulationConfig(_Model):
    """Everything that defines a simulated scene (together with ``seed``).

    Attributes:
        name: Scene name (written to the manifest).
        seed: Seed of all random streams (each component draws from its own stream).
        site: Scene location and margins.
        terrain: Truth surface.
        albedo: Albedo and texture.
        photometry: Sun and reflectance.
        camera: Focal plane.
        orbit: Orbit and orientation nodes.
        strips: The strips (at least one).
        jitter: Attitude jitter components of the true orientation (sinusoids).
        jitter_random: Band-limited random attitude jitter of the true orientation.
        initial_errors: Departures of the initial camera from the truth.
        sensor: Detector of the line-scan images.
        reference: Reference ortho and DEM.
        render: Rendering controls.
        truth_mismatch: Departures of the true camera from the estimated model.
        surface_change: Changes of the ground between the reference and the images.
        sources: For realism settings, the real statistic each reproduces and where it
            comes from (a measurement on real data or a published figure), keyed by the
            setting's dotted name (``"photometry.target_haze"``); set by the
            ``realistic`` difficulty, empty for the presets and stress levels.
        realism: What still makes the scene easier than real data.
    """

    name: str = "scene"
    seed: int = Field(default=0, ge=0)
    site: SiteConfig = SiteConfig()
    terrain: TerrainConfig = TerrainConfig()
    albedo: AlbedoConfig = AlbedoConfig()
    photometry: PhotometryConfig = PhotometryConfig()
    camera: CameraConfig = CameraConfig()
    orbit: OrbitConfig = OrbitConfig()
    strips: tuple[StripConfig, ...] = (StripConfig(),)
    jitter: tuple[JitterComponent, ...] = ()
    jitter_random: JitterRandomConfig = JitterRandomConfig()
    initial_errors: InitialErrorConfig = InitialErrorConfig()
    sensor: SensorConfig = SensorConfig()
    reference: ReferenceConfig = ReferenceConfig()
    render: RenderConfig = RenderConfig()
    truth_mismatch: TruthMismatchConfig = TruthMismatchConfig()
    surface_change: SurfaceChangeConfig = SurfaceChangeConfig()
    sources: dict[str, str] = Field(default_factory=dict)
    realism: RealismNotes = RealismNotes()

    @model_validator(mode="after")
    def _check_sources(self) -> SimulationConfig:
        bad = sorted(k for k in self.sources if not _field_exists(SimulationConfig, k))
        if bad:
            raise ValueError(f"sources name no setting: {', '.join(bad)}")
        return self

    @model_validator(mode="after")
    def _check_strips(self) -> SimulationConfig:
        if not self.strips:
            raise ValueError("at least one strip is needed")
        ids = [s.id for s in self.strips]
        if len(set(ids)) != len(ids):
            raise ValueError(f"strip ids must be unique, got {ids}")
        return self


# -- presets and overrides ---------------------------------------------------------------


def available_presets() -> tuple[str, ...]:
    """Names of the presets shipped in ``planetref/simulate/presets`` (sorted)."""
    folder = resources.files("planetref.simulate") / "presets"
    return tuple(sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml")))


DIFFICULTIES = ("easy", "moderate", "realistic", "hard", "extreme")
"""The difficulty levels, easiest first (``presets/difficulty/<name>.toml``).

``realistic`` is measured, not placed on the ladder: every one of its realism values
names the real statistic it reproduces (its ``[sources]`` table). ``hard`` and
``extreme`` are stress levels, beyond real data in chosen directions, to find where
each matcher breaks; ``easy`` and ``moderate`` are debugging levels easier than Mars."""

STRESS_LADDER = ("easy", "moderate", "hard", "extreme")
"""The levels ordered by stress (each harder than the previous in every knob it sets)."""


def available_difficulties() -> tuple[str, ...]:
    """Names of the difficulty levels, easiest first."""
    return DIFFICULTIES


def load_difficulty_dict(name: str) -> dict[str, Any]:
    """The overlay table of a difficulty level (merged over a preset).

    Raises:
        InputError: If no difficulty has that name (the message lists the valid names).
    """
    if name not in DIFFICULTIES:
        raise InputError(
            f"unknown difficulty {name!r}; valid difficulties: {', '.join(DIFFICULTIES)}",
            field="difficulty",
        )
    folder = resources.files("planetref.simulate") / "presets" / "difficulty"
    return tomllib.loads((folder / f"{name}.toml").read_text(encoding="utf-8"))


INITIAL_ERROR_LEVELS = ("100m", "1km", "2km")
"""Named magnitudes of the initial orientation error (``presets/initial_errors/<name>.toml``).

Each sets every term of ``[initial_errors]`` (position bias and drift along, across and
radial; roll, pitch and yaw bias and drift; focal length) and the declared a-priori
uncertainty, with the source of each value in ``[sources]``; merged over a preset and
difficulty (``load_config(initial_errors=...)``, ``planetref simulate --initial-errors``)."""


def load_initial_errors_dict(name: str) -> dict[str, Any]:
    """The overlay table of a named initial-error level (merged over a preset).

    Raises:
        InputError: If no level has that name (the message lists the valid names).
    """
    if name not in INITIAL_ERROR_LEVELS:
        raise InputError(
            f"unknown initial-error level {name!r}; valid levels: "
            f"{', '.join(INITIAL_ERROR_LEVELS)}",
            field="initial_errors",
        )
    folder = resources.files("planetref.simulate") / "presets" / "initial_errors"
    return tomllib.loads((folder / f"{name}.toml").read_text(encoding="utf-8"))


def load_preset_dict(name: str) -> dict[str, Any]:
    """The raw (unvalidated) table of a preset.

    Raises:
        InputError: If no preset has that name (the message lists the valid names).
    """
    names = available_presets()
    if name not in names:
        raise InputError(
            f"unknown preset {name!r}; valid presets: {', '.join(names)}", field="preset"
        )
    text = (resources.files("planetref.simulate") / "presets" / f"{name}.toml").read_text(
        encoding="utf-8"
    )
    return tomllib.loads(text)


def merge_overrides(base: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """Deep-merge ``overrides`` into a copy of ``base``.

    Tables merge key by key; any other value (numbers, strings, arrays, arrays of
    tables) replaces the base value.
    """
    return deep_merge(base, overrides)


def validate_config(data: dict[str, Any], *, source: str | None = None) -> SimulationConfig:
    """Validate a raw table into a :class:`SimulationConfig`.

    Raises:
        InputError: Naming every bad key or value; for unknown keys the message lists
            the valid keys of the table in which they appear.
    """
    return validate_settings(SimulationConfig, data, source=source, what="simulation config")


def load_config(
    preset: str = "tiny",
    overrides: str | PathLike[str] | dict[str, Any] | None = None,
    *,
    seed: int | None = None,
    difficulty: str | None = None,
    initial_errors: str | None = None,
) -> SimulationConfig:
    """A preset with optional difficulty, overrides and seed.

    Args:
        preset: Preset name (see :func:`available_presets`); it sets the size and is
            written at the ``moderate`` difficulty.
        overrides: A TOML file (path) or a table merged into the preset (after the
            difficulty).
        seed: If given, replaces the config's seed.
        difficulty: A level of :data:`DIFFICULTIES` merged over the preset (the scene's
            name gets ``-<difficulty>`` appended); None keeps the preset as it is.
        initial_errors: A level of :data:`INITIAL_ERROR_LEVELS` merged after the
            difficulty (the scene's name gets ``-ie<level>`` appended); None keeps the
            preset's (or the difficulty's) initial errors.

    Returns:
        The validated, frozen config.

    Raises:
        InputError: Unknown preset, unreadable TOML, unknown keys or bad values; the
            messages list the valid names or keys.
        MissingFileError: If the override file does not exist.
    """
    data = load_preset_dict(preset)
    if difficulty is not None:
        data = merge_overrides(data, load_difficulty_dict(difficulty))
        data["name"] = f"{data.get('name', preset)}-{difficulty}"
    if initial_errors is not None:
        data = merge_overrides(data, load_initial_errors_dict(initial_errors))
        data["name"] = f"{data.get('name', preset)}-ie{initial_errors}"
    source = None
    if overrides is not None:
        if isinstance(overrides, dict):
            table = overrides
        else:
            source = str(overrides)
            table = read_toml(overrides, "override file")
        data = merge_overrides(data, table)
    if seed is not None:
        data["seed"] = seed
    return validate_config(data, source=source)
