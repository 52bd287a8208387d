"""Typed, immutable USGS CSM line-scan ISDs and their writer.

An ISD ("image support data") is the JSON that ALE writes and usgscsm's
``USGS_ASTRO_LINE_SCANNER_SENSOR_MODEL`` reads. :class:`CsmIsd` holds one (states in
km and km/s, J2000; quaternions scalar-first J2000 -> sensor; times in seconds relative
to ``center_ephemeris_time``); :func:`write_isd` writes one (or a camera's, with its
correction) atomically. Parsing is in :mod:`planetref.camera.csm.reader`.
"""

from __future__ import annotations

import copy
import json
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, ClassVar, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.errors import (
    InputError,
)
from planetref.runtime.atomic import write_text_atomic

__all__ = [
    "CORRECTION_KEY",
    "CORRECTION_PARAMETER_NAMES",
    "CSM_LINE_SCANNER_MODEL",
    "J2000",
    "MIN_EPHEMERIS_NODES",
    "SUPPORTED_DISTORTION",
    "CsmCorrection",
    "CsmIsd",
    "CsmOrientations",
    "CsmStates",
    "write_isd",
]


CSM_LINE_SCANNER_MODEL = "USGS_ASTRO_LINE_SCANNER_SENSOR_MODEL"


#: ISD key under which :func:`write_isd` stores a :class:`CsmCorrection` (usgscsm ignores it).
CORRECTION_KEY = "planetref_correction"


#: NAIF code of the J2000 frame, the ISDs' inertial reference.
J2000 = 1


#: usgscsm resamples the ephemeris to at least this many epochs.
MIN_EPHEMERIS_NODES = 25


#: Distortion models this reader implements.
SUPPORTED_DISTORTION = ("radial", "transverse", "radtan")


CORRECTION_PARAMETER_NAMES = (
    "in_track_m",
    "cross_track_m",
    "radial_m",
    "in_track_rate_m",
    "cross_track_rate_m",
    "radial_rate_m",
    "omega_m",
    "phi_m",
    "kappa_m",
    "omega_rate_m",
    "phi_rate_m",
    "kappa_rate_m",
    "omega_accel_m",
    "phi_accel_m",
    "kappa_accel_m",
    "focal_m",
)


# ---------------------------------------------------------------------------------------
# Typed ISD
# ---------------------------------------------------------------------------------------


class CsmIsdSource(Protocol):
    """Anything :func:`write_isd` can write besides a :class:`CsmIsd` (a CSM camera)."""

    def to_isd(self) -> CsmIsd:
        """The ISD that describes the object."""
        ...


def frozen_array(a: ArrayLike) -> NDArray[np.float64]:
    arr = np.array(a, dtype=np.float64)
    arr.flags.writeable = False
    return arr


@dataclass(frozen=True, eq=False)
class CsmStates:
    """Positions (and velocities) of a body at a series of epochs, as in the ISD.

    Attributes:
        times: Ephemeris times (TDB seconds past J2000), shape ``(N,)``, increasing.
        positions_km: Positions in km, shape ``(N, 3)``, in ``reference_frame``.
        velocities_km_s: Velocities in km/s, shape ``(N, 3)``, or ``None``.
        reference_frame: NAIF frame code of the vectors (1 = J2000).
        extra: Other keys of the ISD object (kept for writing back).
    """

    times: NDArray[np.float64]
    positions_km: NDArray[np.float64]
    velocities_km_s: NDArray[np.float64] | None
    reference_frame: int = J2000
    extra: Mapping[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """The ISD JSON object (lists of floats)."""
        out: dict[str, Any] = {
            "ephemeris_times": self.times.tolist(),
            "positions": self.positions_km.tolist(),
        }
        if self.velocities_km_s is not None:
            out["velocities"] = self.velocities_km_s.tolist()
        out["reference_frame"] = self.reference_frame
        for k, v in self.extra.items():
            out.setdefault(k, copy.deepcopy(v))
        return out


@dataclass(frozen=True, eq=False)
class CsmOrientations:
    """Rotations at a series of epochs, as in the ISD.

    The rotation at epoch ``i`` takes vectors from ``reference_frame`` (the source) to the
    destination frame: ``v_dst = C @ R(q_i) @ v_src`` with ``C = constant_rotation``.

    Attributes:
        times: Ephemeris times (s), shape ``(N,)``, increasing.
        quaternions: Scalar-first unit quaternions ``[w, x, y, z]``, shape ``(N, 4)``.
        angular_velocities: Angular velocities (rad/s), shape ``(N, 3)``, or ``None``.
        constant_rotation: Row-major 3x3 rotation applied on the left, shape ``(3, 3)``.
        reference_frame: NAIF code of the source frame (1 = J2000).
        constant_frames: NAIF codes of the constant chain (informative).
        time_dependent_frames: NAIF codes of the time-dependent chain (informative).
        extra: Other keys of the ISD object (kept for writing back).
    """

    times: NDArray[np.float64]
    quaternions: NDArray[np.float64]
    angular_velocities: NDArray[np.float64] | None
    constant_rotation: NDArray[np.float64]
    reference_frame: int = J2000
    constant_frames: tuple[int, ...] = ()
    time_dependent_frames: tuple[int, ...] = ()
    extra: Mapping[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """The ISD JSON object."""
        out: dict[str, Any] = {
            "ephemeris_times": self.times.tolist(),
            "quaternions": self.quaternions.tolist(),
        }
        if self.angular_velocities is not None:
            out["angular_velocities"] = self.angular_velocities.tolist()
        out["reference_frame"] = self.reference_frame
        if self.time_dependent_frames:
            out["time_dependent_frames"] = list(self.time_dependent_frames)
        if self.constant_frames:
            out["constant_frames"] = list(self.constant_frames)
        if not np.array_equal(self.constant_rotation, np.eye(3)) or self.constant_frames:
            out["constant_rotation"] = self.constant_rotation.ravel().tolist()
        for k, v in self.extra.items():
            out.setdefault(k, copy.deepcopy(v))
        return out


@dataclass(frozen=True)
class CsmCorrection:
    """Port of usgscsm's 16 adjustable parameters of a line-scan image (all in metres).

    The meaning and scaling are usgscsm's (``getAdjSensorPosVel``,
    ``calculateAttitudeCorrection``), so a correction estimated here can be given to
    usgscsm as ``m_currentParameterValue``:

    * position ``d(t) = bias + rate * (t - t0_ephem) / half_time`` along the in-track,
      cross-track and radial unit vectors built from the nominal position and velocity
      (cross = r x v, in = cross x r);
    * pointing angles ``omega, phi = (bias + rate * n + accel * n^2) / flying_height``
      and ``kappa = (...) / half_swath`` with ``n = (t - t0_quat) / half_time``, applied
      as the Euler rotation of usgscsm's ``calculateRotationMatrixFromEuler`` in the
      sensor frame, before the sensor-to-body rotation;
    * focal length ``f * (1 - focal_m / half_swath)``.

    ``half_time`` (s), ``flying_height`` (m) and ``half_swath`` (m) are the camera's
    scale factors (:attr:`CsmLineScanCamera.half_time_s` etc.). All-zero (the default)
    is no correction.
    """

    in_track_m: float = 0.0
    cross_track_m: float = 0.0
    radial_m: float = 0.0
    in_track_rate_m: float = 0.0
    cross_track_rate_m: float = 0.0
    radial_rate_m: float = 0.0
    omega_m: float = 0.0
    phi_m: float = 0.0
    kappa_m: float = 0.0
    omega_rate_m: float = 0.0
    phi_rate_m: float = 0.0
    kappa_rate_m: float = 0.0
    omega_accel_m: float = 0.0
    phi_accel_m: float = 0.0
    kappa_accel_m: float = 0.0
    focal_m: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not isinstance(v, (int, float)) or not math.isfinite(v):
                raise InputError(
                    f"correction parameter must be a finite number, got {v!r}", field=f.name
                )
            object.__setattr__(self, f.name, float(v))

    @classmethod
    def from_array(cls, values: ArrayLike) -> CsmCorrection:
        """From the 16 values in usgscsm's parameter order (metres)."""
        v = np.asarray(values, dtype=np.float64).ravel()
        if v.shape != (16,):
            raise InputError(f"a CSM line-scan correction has 16 parameters, got {v.size}")
        return cls(*(float(x) for x in v))

    def as_array(self) -> NDArray[np.float64]:
        """The 16 values in usgscsm's parameter order (metres), shape ``(16,)``."""
        return np.array([getattr(self, n) for n in CORRECTION_PARAMETER_NAMES])

    @property
    def is_zero(self) -> bool:
        """True when every parameter is zero (no correction)."""
        return not np.any(self.as_array())

    @property
    def has_position(self) -> bool:
        """True when a position parameter (0-5) is non-zero."""
        return bool(np.any(self.as_array()[:6]))

    @property
    def has_attitude(self) -> bool:
        """True when a pointing-angle parameter (6-14) is non-zero."""
        return bool(np.any(self.as_array()[6:15]))


@dataclass(frozen=True, eq=False)
class CsmIsd:
    """A checked USGS CSM line-scan ISD (``USGS_ASTRO_LINE_SCANNER_SENSOR_MODEL``).

    Units are the ISD's: km for radii and positions, seconds for times, millimetres for
    the focal plane, pixels for the detector. Build it with :func:`read_isd`.

    Attributes:
        path: The file it was read from (informative; ``None`` when built in memory).
        name_platform: Spacecraft name.
        name_sensor: Instrument name (also the camera's CCD name).
        image_lines: Number of image lines.
        image_samples: Number of image samples.
        center_ephemeris_time: Reference epoch of all relative times (s past J2000).
        starting_ephemeris_time: Epoch of the start of the first line (s).
        line_scan_rate: Rows ``[line, time relative to center (s), s per line]``,
            shape ``(K, 3)``.
        focal_length_mm: Focal length (mm).
        focal2pixel_lines: Focal plane (mm) to detector line, ``[l0, lx, ly]``.
        focal2pixel_samples: Focal plane (mm) to detector sample, ``[s0, sx, sy]``.
        detector_center_line: Detector line of the focal-plane origin (pixels).
        detector_center_sample: Detector sample of the focal-plane origin (pixels).
        starting_detector_line: Detector line of image line 0.
        starting_detector_sample: Detector sample of image sample 0.
        detector_line_summing: Detector lines per image line.
        detector_sample_summing: Detector samples per image sample.
        distortion_model: ``"radial"``, ``"transverse"`` or ``"radtan"``.
        distortion_coefficients: The model's coefficients, shape ``(n,)`` (mm based;
            ``radtan``: on coordinates normalised by the focal length).
        semi_major_km: Body equatorial radius (km).
        semi_minor_km: Body polar radius (km).
        min_height_m: Lowest terrain height expected (m).
        max_height_m: Highest terrain height expected (m).
        instrument_position: Spacecraft states.
        instrument_pointing: Rotations from ``reference_frame`` to the sensor frame.
        body_rotation: Rotations from J2000 to the body-fixed frame.
        platform_flag: usgscsm's platform flag (1: 8th-order Lagrange, 0: 4th order).
        correction: A correction stored in the ISD by :func:`write_isd`, or ``None``.
        correction_scales: ``(half_time_s, flying_height_m, half_swath_m)`` stored with it.
        extra: Other top-level keys (e.g. ``naif_keywords``, ``sun_position``,
            ``t0_ephemeris``), kept for writing back.
    """

    path: str | None
    name_platform: str
    name_sensor: str
    image_lines: int
    image_samples: int
    center_ephemeris_time: float
    starting_ephemeris_time: float
    line_scan_rate: NDArray[np.float64]
    focal_length_mm: float
    focal2pixel_lines: NDArray[np.float64]
    focal2pixel_samples: NDArray[np.float64]
    detector_center_line: float
    detector_center_sample: float
    starting_detector_line: float
    starting_detector_sample: float
    detector_line_summing: float
    detector_sample_summing: float
    distortion_model: str
    distortion_coefficients: NDArray[np.float64]
    semi_major_km: float
    semi_minor_km: float
    min_height_m: float
    max_height_m: float
    instrument_position: CsmStates
    instrument_pointing: CsmOrientations
    body_rotation: CsmOrientations
    platform_flag: int = 1
    correction: CsmCorrection | None = None
    correction_scales: tuple[float, float, float] | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)

    name_model: ClassVar[str] = CSM_LINE_SCANNER_MODEL

    @property
    def body_frame(self) -> int | None:
        """NAIF code of the body-fixed frame (from ``body_rotation``), if the ISD says."""
        tdf = self.body_rotation.time_dependent_frames
        if tdf:
            return int(tdf[0])
        code = self.extra.get("naif_keywords", {}).get("BODY_FRAME_CODE")
        return None if code is None else int(code)

    def to_dict(self) -> dict[str, Any]:
        """The ISD as a JSON-ready dict (known keys first, then the preserved ones)."""
        out: dict[str, Any] = {
            "name_model": self.name_model,
            "name_platform": self.name_platform,
            "name_sensor": self.name_sensor,
            "image_lines": self.image_lines,
            "image_samples": self.image_samples,
            "center_ephemeris_time": self.center_ephemeris_time,
            "starting_ephemeris_time": self.starting_ephemeris_time,
            "line_scan_rate": self.line_scan_rate.tolist(),
            "focal_length_model": {"focal_length": self.focal_length_mm},
            "focal2pixel_lines": self.focal2pixel_lines.tolist(),
            "focal2pixel_samples": self.focal2pixel_samples.tolist(),
            "detector_center": {
                "line": self.detector_center_line,
                "sample": self.detector_center_sample,
            },
            "starting_detector_line": self.starting_detector_line,
            "starting_detector_sample": self.starting_detector_sample,
            "detector_line_summing": _int_if_whole(self.detector_line_summing),
            "detector_sample_summing": _int_if_whole(self.detector_sample_summing),
            "optical_distortion": _distortion_to_dict(
                self.distortion_model, self.distortion_coefficients
            ),
            "radii": {
                "semimajor": self.semi_major_km,
                "semiminor": self.semi_minor_km,
                "unit": "km",
            },
            "reference_height": {
                "minheight": self.min_height_m,
                "maxheight": self.max_height_m,
                "unit": "m",
            },
            "instrument_position": self.instrument_position.to_dict(),
            "instrument_pointing": self.instrument_pointing.to_dict(),
            "body_rotation": self.body_rotation.to_dict(),
        }
        if self.platform_flag != 1:
            out["platform_flag"] = self.platform_flag
        if self.correction is not None and not self.correction.is_zero:
            c: dict[str, Any] = {
                "names": list(CORRECTION_PARAMETER_NAMES),
                "parameters": self.correction.as_array().tolist(),
            }
            if self.correction_scales is not None:
                c["half_time_s"], c["flying_height_m"], c["half_swath_m"] = self.correction_scales
            out[CORRECTION_KEY] = c
        for k, v in self.extra.items():
            out.setdefault(k, copy.deepcopy(v))
        return out


def _int_if_whole(x: float) -> int | float:
    # ALE writes summing as integers; keep them so for readers that insist.
    return int(x) if float(x).is_integer() else x


def _distortion_to_dict(model: str, coeffs: NDArray[np.float64]) -> dict[str, Any]:
    if model == "transverse":
        n = len(coeffs) // 2
        return {"transverse": {"x": coeffs[:n].tolist(), "y": coeffs[n:].tolist()}}
    return {model: {"coefficients": coeffs.tolist()}}


def write_isd(camera_or_isd: CsmIsdSource | CsmIsd, path: str | os.PathLike[str]) -> Path:
    """Write an ISD JSON file atomically (a temporary file, then a rename).

    A camera's correction (if not zero) is written under the ``planetref_correction`` key
    together with the camera's scale factors, so :func:`read_isd` gives back a camera
    with identical projections. usgscsm and ALE ignore that key.

    Args:
        camera_or_isd: A :class:`CsmLineScanCamera` or a :class:`CsmIsd`.
        path: Destination file; its folder must exist.

    Returns:
        The path written.

    Raises:
        InputError: If the object is neither, or the file cannot be written.
    """
    if isinstance(camera_or_isd, CsmIsd):
        isd = camera_or_isd
    elif callable(getattr(camera_or_isd, "to_isd", None)):
        isd = camera_or_isd.to_isd()
    else:
        raise InputError(
            f"expected a CsmLineScanCamera or CsmIsd, got {type(camera_or_isd).__name__}"
        )
    p = Path(path)
    try:
        # Compact: a strip's ephemeris sampled every line is ~100k numbers, and an
        # indented dump goes through json's pure-Python encoder (~10x slower).
        text = json.dumps(isd.to_dict(), allow_nan=False, separators=(",", ":"))
    except ValueError as exc:
        raise InputError(f"cannot write the ISD: {exc}", path=p) from None
    try:
        write_text_atomic(p, text, parents=False)
    except OSError as exc:
        raise InputError(f"cannot write the ISD ({exc})", path=p) from None
    return p
