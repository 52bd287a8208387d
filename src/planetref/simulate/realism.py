"""Configuration of what makes a scene as hard as Mars (the difficulty ladder's knobs).

Three groups of effects, all off by default except where a preset turns them on:

* :class:`TruthMismatchConfig` - the *true* camera departs from the model the
  adjustment estimates (never the initial camera): each CCD's true placement in the
  focal plane (offsets, rotation, pixel scale) differs from the nominal one, the true
  line period differs from the nominal one, and the trajectory carries low-frequency
  oscillations of position and attitude (on top of the jitter), sampled on the truth's
  dense nodes.
* :class:`MosaicConfig` and :class:`MolaConfig` (in :class:`~planetref.simulate.config.
  ReferenceConfig`) - the reference ortho is a mosaic of several source images (own
  sun, haze, gain, geometric offset and smooth warp) and the reference DEM is gridded
  from MOLA-like altimetry tracks (per-track offsets, interpolation between tracks),
  optionally referred to an areoid-like surface.
* :class:`SurfaceChangeConfig` - the ground changed between the reference epoch and the
  image epoch: new small craters, dust-devil tracks, migrated dunes.

Units are in the field names as in :mod:`planetref.simulate.config`.
"""

from __future__ import annotations

from pydantic import Field

from planetref.runtime.settings import Settings

__all__ = [
    "MolaConfig",
    "MosaicConfig",
    "SurfaceChangeConfig",
    "TruthMismatchConfig",
]

Vec3 = tuple[float, float, float]


_Model = Settings


class TruthMismatchConfig(_Model):
    """Departures of the true camera from the estimated camera model (random per CCD).

    Each CCD ``k`` of the truth is the nominal one moved by ``(dx_k, dy_k)`` pixels
    (along, across track; each drawn ``N(0, ccd_offset_px)``), rotated about its centre
    by ``N(0, ccd_rotation_urad)`` and with its pixel pitch scaled by
    ``1 + N(0, ccd_scale_ppm) * 1e-6`` (the linear part of lens distortion over that
    CCD). The true line period is the nominal one times ``1 + line_rate_error_ppm *
    1e-6``. The true trajectory adds, to position and attitude in the orbit frame,
    ``amplitude * sin(2 pi t / oscillation_period_s + phase)`` per axis (random phases).

    Non-linear lens distortion (Brown-Conrady radial ``k1``, ``k2`` and decentering
    ``p1``, ``p2``, :mod:`planetref.camera.linescan.lens`, about the optical axis) is
    given by its displacement at the field edge ``r_max`` (the focal-plane point of the
    CCD row farthest from the axis): ``k1 = radial_k1_px * pitch / r_max^3``,
    ``k2 = radial_k2_px * pitch / r_max^5`` (signed: negative is barrel), and
    ``(p1, p2) = decentering_px * pitch / (3 r_max^2) * (cos a, sin a)`` with a random
    direction ``a`` (at most ``decentering_px`` at the field edge). Along the CCD row
    this stretches the image non-linearly (radial) and bows it along track
    (decentering). Only the truth carries it (its camera file
    has the coefficients per CCD); the estimated model has no distortion term.

    Attributes:
        ccd_offset_px: RMS focal-plane offset of each CCD (pixels, per axis).
        ccd_rotation_urad: RMS rotation of each CCD about its centre (µrad).
        ccd_scale_ppm: RMS relative pixel-pitch error of each CCD (ppm).
        line_rate_error_ppm: Relative error of the nominal line period (ppm).
        position_oscillation_m: (along, cross, radial) amplitudes (m).
        attitude_oscillation_urad: (roll, pitch, yaw) amplitudes (µrad).
        oscillation_period_s: Period of the oscillation (s); ``None`` takes a third
            of the strip's duration.
        radial_k1_px: Displacement of the cubic radial term at the field edge (px).
        radial_k2_px: Displacement of the quintic radial term at the field edge (px).
        decentering_px: Displacement of the decentering terms at the field edge (px).
    """

    ccd_offset_px: float = Field(default=0.0, ge=0.0)
    ccd_rotation_urad: float = Field(default=0.0, ge=0.0)
    ccd_scale_ppm: float = Field(default=0.0, ge=0.0)
    line_rate_error_ppm: float = 0.0
    position_oscillation_m: Vec3 = (0.0, 0.0, 0.0)
    attitude_oscillation_urad: Vec3 = (0.0, 0.0, 0.0)
    oscillation_period_s: float | None = Field(default=None, gt=0.0)
    radial_k1_px: float = Field(default=0.0, ge=-20.0, le=20.0)
    radial_k2_px: float = Field(default=0.0, ge=-20.0, le=20.0)
    decentering_px: float = Field(default=0.0, ge=0.0, le=20.0)


class MosaicConfig(_Model):
    """The reference ortho as a mosaic of source images (CTX-like).

    The ortho is split into ``n_sources`` bands along map x (CTX strips run roughly
    north-south) whose boundaries (seams) meander by ``seam_wander_m``. Source ``s``
    has its own sun (the reference sun's azimuth and elevation plus
    ``N(0, sun_spread_deg)``), haze (``reference_haze * U(0.5, 1.5)``), gain
    (``1 + N(0, gain_spread)``: brightness steps at the seams) and geometric error: a
    pixel of source ``s`` at true map point ``p`` shows the surface at
    ``p - d_s(p)``, where ``d_s = offset_s + warp_s(p)``; ``offset_s`` is drawn
    ``N(0, offset_px)`` per axis and ``warp_s`` is a sum of three plane waves per axis
    with wavelengths in ``[1, 3] x warp_wavelength_m`` and total RMS ``warp_px``
    (reference pixels). The parameters are written to ``truth/reference.json``.

    Attributes:
        n_sources: Number of source images (1 = a single image, no seams).
        offset_px: RMS offset of each source (reference pixels, per axis).
        warp_px: RMS of each source's smooth warp (reference pixels, per axis).
        warp_wavelength_m: Shortest wavelength of the warp (m).
        sun_spread_deg: RMS spread of the sources' sun angles (degrees).
        gain_spread: RMS relative gain difference between sources.
        bias_spread: RMS additive brightness offset of each source, relative to a flat
            mean-albedo surface (with the gain, the brightness step at its seams; drawn
            after the emission angles). 0 (default): none.
        seam_wander_m: Amplitude of the seams' meandering (m).
        emission_max_deg: Off-nadir emission angle of the sources, each drawn
            ``U(0, emission_max_deg)`` and looking east or west (CTX rolls across its
            N-S tracks). Each source is orthorectified on the reference DEM, so relief
            the coarse DEM lacks is displaced: the pixel at ``p`` shows the surface at
            ``p + dh(p) tan(e) v`` (``dh`` = truth minus reference DEM height, ``v`` the
            horizontal unit vector towards the spacecraft). 0 (default): nadir sources.
    """

    n_sources: int = Field(default=1, ge=1, le=12)
    offset_px: float = Field(default=0.0, ge=0.0)
    warp_px: float = Field(default=0.0, ge=0.0)
    warp_wavelength_m: float = Field(default=1500.0, gt=0.0)
    sun_spread_deg: float = Field(default=0.0, ge=0.0)
    gain_spread: float = Field(default=0.0, ge=0.0)
    seam_wander_m: float = Field(default=150.0, ge=0.0)
    emission_max_deg: float = Field(default=0.0, ge=0.0, le=30.0)
    bias_spread: float = Field(default=0.0, ge=0.0, le=0.5)


class MolaConfig(_Model):
    """The reference DEM gridded from MOLA-like altimetry tracks (off when ``tracks`` is false).

    With ``tracks``, the truth (as seen at the coarse spacing) is sampled along ground
    tracks of azimuth ``track_azimuth_deg`` spaced ``track_spacing_m`` apart (jittered by
    30 %), one shot every ``shot_spacing_m``; every track gets its own height offset
    ``N(0, track_offset_m)`` and a linear drift along it of ``N(0, track_tilt_m)`` over
    its length and a horizontal geolocation error ``N(0, track_shift_m)`` per axis
    (along, across: the shots measured the ground that far from where they are placed),
    and the grid is the linear (Delaunay) interpolation between the shots, as in a
    gridded MEGDR where tracks are sparse: its error grows with the distance from the
    nearest track (``h'' u (s - u) / 2`` at ``u`` from a track for ground of curvature
    ``h''`` across tracks ``s`` apart). With ``areoid``, the heights are
    given above an areoid-like surface: the sphere raised by ``areoid_offset_m`` plus a
    tilt of ``areoid_tilt_m_per_km`` towards ``track_azimuth_deg + 90``. With
    ``areoid_declared`` (default) the scene carries that surface as
    ``reference/areoid.tif`` and ``scene.toml`` declares ``dem_datum = "areoid"``, so the
    DEM is read back as heights above the sphere; without it nothing says so, as with a
    MEGDR read naively, and a pipeline makes a vertical error of that size.

    Attributes:
        tracks: Grid the DEM from tracks.
        track_spacing_m: Mean distance between tracks (m).
        shot_spacing_m: Distance between shots along a track (m).
        track_azimuth_deg: Azimuth of the tracks (degrees from north).
        track_offset_m: RMS height offset per track (m).
        track_tilt_m: RMS height drift along a track, end to end (m).
        track_shift_m: RMS horizontal geolocation error of each track, per axis (m).
        areoid: Refer the heights to the areoid-like surface.
        areoid_offset_m: Height of the areoid-like surface above the sphere (m).
        areoid_tilt_m_per_km: Its slope across the scene (m/km).
        areoid_declared: Write the areoid raster and declare the datum in ``scene.toml``.
    """

    tracks: bool = False
    track_spacing_m: float = Field(default=1500.0, gt=0.0)
    shot_spacing_m: float = Field(default=300.0, gt=0.0)
    track_azimuth_deg: float = 3.0
    track_offset_m: float = Field(default=3.0, ge=0.0)
    track_tilt_m: float = Field(default=2.0, ge=0.0)
    track_shift_m: float = Field(default=0.0, ge=0.0)
    areoid: bool = False
    areoid_offset_m: float = 0.0
    areoid_tilt_m_per_km: float = 0.0
    areoid_declared: bool = True


class SurfaceChangeConfig(_Model):
    """Changes of the ground between the reference epoch and the image epoch.

    The truth DEM and the line-scan images show the image epoch; the reference ortho
    shows the surface before: without the new craters (relief and bright halos),
    without the dust-devil tracks, and with the dunes' crests ``dune_migration_m``
    upwind of where they are now.

    Attributes:
        new_crater_density_per_km2: New craters per km² (diameters from
            ``new_crater_d_min_m`` to ``new_crater_d_max_m``, cumulative slope 2).
        new_crater_d_min_m: Smallest new crater (m).
        new_crater_d_max_m: Largest new crater (m).
        dust_devil_tracks_per_km2: Dust-devil tracks per km².
        dust_devil_width_m: Mean width of a track (m).
        dust_devil_length_m: Mean length of a track (m).
        dust_devil_contrast: Relative albedo decrease along a track's centre line.
        dune_migration_m: Downwind displacement of the dune crests since the reference
            epoch (m).
    """

    new_crater_density_per_km2: float = Field(default=0.0, ge=0.0)
    new_crater_d_min_m: float = Field(default=4.0, gt=0.0)
    new_crater_d_max_m: float = Field(default=40.0, gt=0.0)
    dust_devil_tracks_per_km2: float = Field(default=0.0, ge=0.0)
    dust_devil_width_m: float = Field(default=15.0, gt=0.0)
    dust_devil_length_m: float = Field(default=1200.0, gt=0.0)
    dust_devil_contrast: float = Field(default=0.15, ge=0.0, le=0.9)
    dune_migration_m: float = 0.0
