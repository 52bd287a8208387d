"""Configuration of the simulated camera: focal plane, orbit, strips, jitter, initial errors.

Part of :class:`~planetref.simulate.config.SimulationConfig` (re-exported by
:mod:`planetref.simulate.config`). Units are in the field names as there; orbit-frame
vectors are ``(along-track, cross-track, radial)`` and attitude triples ``(roll, pitch,
yaw)``.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from planetref.runtime.settings import Settings

__all__ = [
    "CameraConfig",
    "InitialErrorConfig",
    "JitterComponent",
    "JitterRandomConfig",
    "OrbitConfig",
    "StripConfig",
]

Vec3 = tuple[float, float, float]


_Model = Settings


class CameraConfig(_Model):
    """HiRIC-like focal plane: line-array CCDs side by side with small overlaps.

    CCD ``k`` (0-based) has its sample-0 edge at ``y = (-W/2 + k*(n_samples - overlap))
    * pitch`` with ``W = n_ccds*n_samples - (n_ccds-1)*overlap``; odd CCDs sit
    ``ccd_stagger_mm`` ahead (along-track ``x``), as on staggered butted arrays.

    Attributes:
        n_ccds: Number of CCDs.
        n_samples: Samples per CCD.
        overlap_samples: Samples shared by neighbouring CCDs.
        n_lines: Lines of each strip.
        pixel_pitch_mm: Detector pitch (mm).
        gsd_m: Nadir ground sampling distance at the datum (m); sets the focal length
            ``f = pitch * altitude / gsd``.
        ccd_stagger_mm: Along-track offset of the odd CCDs (mm).
        line_period_s: Line period (s); ``None`` gives square pixels at nadir.
    """

    n_ccds: int = Field(default=3, ge=1, le=16)
    n_samples: int = Field(default=2048, ge=8)
    overlap_samples: int = Field(default=64, ge=0)
    n_lines: int = Field(default=8000, ge=8)
    pixel_pitch_mm: float = Field(default=0.010, gt=0.0)
    gsd_m: float = Field(default=0.5, gt=0.0)
    ccd_stagger_mm: float = 0.4
    line_period_s: float | None = Field(default=None, gt=0.0)

    @model_validator(mode="after")
    def _check_overlap(self) -> CameraConfig:
        if self.overlap_samples >= self.n_samples:
            raise ValueError(
                f"overlap_samples ({self.overlap_samples}) must be smaller than "
                f"n_samples ({self.n_samples})"
            )
        return self


class OrbitConfig(_Model):
    """Circular orbit of the spacecraft.

    Attributes:
        altitude_m: Altitude above the reference sphere (m).
        heading_deg: Azimuth of the ground track at the scene centre (degrees from north).
        body_rotation: Include the rotation of Mars (the ground track then differs from
            the orbit plane's trace).
        truth_node_spacing_lines: Lines between orientation nodes of the true camera
            (dense enough to carry the jitter: the simulator refuses jitter above the
            nodes' Nyquist frequency ``1 / (2 * spacing * line_period)``, warns above
            the frequency their Lagrange interpolation keeps within 1 %, and writes both
            to ``truth/errors.json``).
        initial_node_spacing_lines: Lines between nodes of the initial camera.
        interpolation_order: Lagrange interpolation order of the nodes.
    """

    altitude_m: float = Field(default=265_000.0, gt=10_000.0)
    heading_deg: float = -8.0
    body_rotation: bool = True
    truth_node_spacing_lines: int = Field(default=32, ge=1)
    initial_node_spacing_lines: int = Field(default=512, ge=1)
    interpolation_order: int = Field(default=4, ge=2, le=8)


class StripConfig(_Model):
    """One line-scan strip (one pass).

    Attributes:
        id: Identifier (letters, digits, ``-``/``_``), used in file names.
        along_offset_m: Offset of the strip centre from the site centre along track (m).
        cross_offset_m: Offset of the ground track across track (m, positive to the
            left of the track, the +y axis of the orbit frame).
        heading_deg: Ground-track heading; ``None`` takes the orbit's.
        pointing_deg: Fixed ``(roll, pitch, yaw)`` of the camera in the orbit frame
            (degrees), e.g. a roll for an off-nadir strip.
    """

    id: str = Field(default="strip1", pattern=r"^[A-Za-z0-9_-]{1,32}$")
    along_offset_m: float = 0.0
    cross_offset_m: float = 0.0
    heading_deg: float | None = None
    pointing_deg: Vec3 = (0.0, 0.0, 0.0)


class JitterComponent(_Model):
    """One sinusoid of attitude jitter in the true orientation (random phase).

    Attributes:
        axis: ``"roll"``, ``"pitch"`` or ``"yaw"``.
        amplitude_urad: Amplitude (microradians).
        frequency_hz: Frequency (Hz).
    """

    axis: Literal["roll", "pitch", "yaw"]
    amplitude_urad: float = Field(ge=0.0)
    frequency_hz: float = Field(gt=0.0)


class JitterRandomConfig(_Model):
    """Band-limited random attitude jitter of the true orientation (besides the sinusoids).

    Per axis a sum of ``n`` sinusoids, one in each of ``n`` equal bins of the band
    ``[min_frequency_hz, max_frequency_hz]`` (its frequency uniform in the bin, its
    phase uniform), with amplitudes ``a_k ~ f_k ** (psd_slope / 2)`` scaled so that
    ``sqrt(sum a_k**2 / 2)`` -- the process' rms over a long strip -- is ``rms_urad``:
    a random-phase realisation of a power spectral density ``~ f ** psd_slope`` inside
    the band and zero outside it. ``n = max(16, ceil(2 * band * duration))`` (bins of
    at most half the strip's frequency resolution; at most 4096). Drawn from the strip's
    random stream after the sinusoids' phases, only for an axis whose rms is above 0, so
    the sinusoids (and every other part of the scene) do not change when it is turned
    on. Off (all rms 0) unless a preset or difficulty sets it: no published jitter
    spectrum of HiRIC was at hand, and for HiRISE (1 urad pixels, staggered CCDs) Sutton
    et al. 2017 (ISPRS Arch. XLII-3/W1, 141) resolve the jitter from the CCD overlaps
    without a power spectral density to copy; a scene that sets it should cite its
    figure in ``[sources]`` (``"jitter_random.rms_urad"``).

    Attributes:
        rms_urad: ``(roll, pitch, yaw)`` rms of the random part (microradians).
        min_frequency_hz: Lower edge of the band (Hz).
        max_frequency_hz: Upper edge of the band (Hz).
        psd_slope: Exponent of the power spectral density inside the band (0: flat,
            -2: a random walk's fall-off).
    """

    rms_urad: Vec3 = (0.0, 0.0, 0.0)
    min_frequency_hz: float = Field(default=1.0, gt=0.0)
    max_frequency_hz: float = Field(default=20.0, gt=0.0)
    psd_slope: float = Field(default=0.0, ge=-6.0, le=6.0)

    @model_validator(mode="after")
    def _check_band(self) -> JitterRandomConfig:
        if self.max_frequency_hz <= self.min_frequency_hz:
            raise ValueError(
                f"max_frequency_hz ({self.max_frequency_hz}) must be above "
                f"min_frequency_hz ({self.min_frequency_hz})"
            )
        if any(r < 0.0 for r in self.rms_urad):
            raise ValueError(f"rms_urad must be >= 0, got {list(self.rms_urad)}")
        return self

    @property
    def enabled(self) -> bool:
        """Whether any axis has a random part."""
        return any(r > 0.0 for r in self.rms_urad)


class InitialErrorConfig(_Model):
    """How the initial (navigation) camera departs from the truth.

    The initial camera has no jitter; its position is the truth plus
    ``position_bias_m + position_drift_m_per_s * t`` and its attitude the jitter-free
    truth rotated by ``attitude_bias_urad + attitude_drift_urad_per_s * t`` (``t``
    seconds from the strip's centre time), in the orbit frame. Its focal length is
    ``f * (1 + focal_length_error_ppm * 1e-6)``.

    Attributes:
        position_bias_m: (along, cross, radial) position bias (m).
        position_drift_m_per_s: (along, cross, radial) position drift (m/s).
        attitude_bias_urad: (roll, pitch, yaw) attitude bias (µrad).
        attitude_drift_urad_per_s: (roll, pitch, yaw) attitude drift (µrad/s).
        focal_length_error_ppm: Relative focal-length error (ppm).
        declared_uncertainty_m: The a-priori ground uncertainty of the initial camera as
            a navigation team would state it (metres, a bound on the ground error); the
            scene manifest declares it (each strip's ``initial_uncertainty_m``) and the
            front end's coarse stage searches that far unless the run's config sets
            ``frontend.uncertainty_m``. None: not declared (the front end's default).

    What each term does on the ground at HiRIC's 265 km (a 3 km swath, 4 km strips of
    1.2 s): a position bias moves the ground 1:1 (radial: scale ``dh / h``, 1 km of it
    ``3.8e-3``, 5.7 m at the swath edge); roll and pitch move it by ``h * angle`` (1 mrad:
    265 m); yaw about the boresight rotates it about the strip centre (200 urad: 0.3 m at
    the swath edge, 0.4 m at the strip ends); a focal-length error scales it (300 ppm:
    0.45 m at the swath edge); drifts act over +-0.6 s (50 urad/s: 8 m). Over a strip a
    km of initial error is thus a translation to within metres.
    See the named levels in ``presets/initial_errors``
    (:data:`planetref.simulate.config.INITIAL_ERROR_LEVELS`).
    """

    position_bias_m: Vec3 = (40.0, -25.0, 15.0)
    position_drift_m_per_s: Vec3 = (2.0, -1.0, 0.5)
    attitude_bias_urad: Vec3 = (150.0, -250.0, 300.0)
    attitude_drift_urad_per_s: Vec3 = (20.0, -15.0, 10.0)
    focal_length_error_ppm: float = 300.0
    declared_uncertainty_m: float | None = Field(default=None, gt=0.0)
