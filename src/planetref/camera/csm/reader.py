"""Parse and check USGS CSM line-scan ISD JSON into a :class:`~.isd.CsmIsd`.

Every field is validated (presence, type, shape, units, monotonic times, frame chain);
a bad field gives one :class:`~planetref.errors.InputError` naming the file and the key.
"""

from __future__ import annotations

import json
import math
import os
import types
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.camera.csm.isd import (
    CORRECTION_KEY,
    CSM_LINE_SCANNER_MODEL,
    J2000,
    SUPPORTED_DISTORTION,
    CsmCorrection,
    CsmIsd,
    CsmOrientations,
    CsmStates,
    frozen_array,
)
from planetref.errors import (
    InputError,
    UnsupportedFormatError,
)
from planetref.runtime.jsonfile import read_json

__all__ = ["read_isd"]


_MISSING: Any = object()


# ---------------------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------------------


class _Fields:
    """Typed access to an ISD dict; every failure is an InputError naming the field."""

    def __init__(self, data: Mapping[str, Any], path: str | None) -> None:
        self.data = data
        self.path = path

    def error(self, key: str, message: str) -> InputError:
        return InputError(message, path=self.path, field=key)

    def raw(self, key: str, default: Any = _MISSING) -> Any:
        node: Any = self.data
        for part in key.split("."):
            if not isinstance(node, Mapping) or part not in node:
                if default is not _MISSING:
                    return default
                raise self.error(key, "missing")
            node = node[part]
        return node

    def has(self, key: str) -> bool:
        return self.raw(key, None) is not None

    def number(
        self, key: str, default: Any = _MISSING, *, positive: bool = False, integer: bool = False
    ) -> float:
        v = self.raw(key, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.error(key, f"expected a number, got {json.dumps(v)[:40]}")
        if not math.isfinite(v):
            raise self.error(key, f"must be finite, got {v}")
        if positive and v <= 0:
            raise self.error(key, f"must be positive, got {v}")
        if integer and v != int(v):
            raise self.error(key, f"must be an integer, got {v}")
        return float(v)

    def string(self, key: str, default: Any = _MISSING) -> str:
        v = self.raw(key, default)
        if not isinstance(v, str):
            raise self.error(key, f"expected a string, got {json.dumps(v)[:40]}")
        return v

    def array(
        self, key: str, width: int | None = None, *, min_rows: int = 1, default: Any = _MISSING
    ) -> NDArray[np.float64]:
        v = self.raw(key, default)
        if v is None:
            return None  # type: ignore[return-value]
        try:
            arr = np.asarray(v, dtype=np.float64)
        except (TypeError, ValueError):
            raise self.error(key, "expected an array of numbers") from None
        expected = "(N,)" if width is None else f"(N, {width})"
        if (width is None and arr.ndim != 1) or (
            width is not None and (arr.ndim != 2 or arr.shape[1] != width)
        ):
            raise self.error(key, f"expected an array of shape {expected}, got {arr.shape}")
        if arr.shape[0] < min_rows:
            raise self.error(key, f"needs at least {min_rows} entries, got {arr.shape[0]}")
        bad = ~np.isfinite(arr)
        if np.any(bad):
            row = int(np.argwhere(bad)[0][0])
            raise self.error(f"{key}[{row}]", "must be finite (NaN or infinity found)")
        return arr

    def unit(self, key: str, allowed: Sequence[str]) -> str | None:
        """The optional ``unit`` field of an object, checked against ``allowed``."""
        u = self.raw(key, None)
        if u is None:
            return None
        if not isinstance(u, str) or u.strip().lower() not in allowed:
            raise self.error(
                key, f"unit must be {' or '.join(repr(a) for a in allowed)}, got {u!r}"
            )
        return u.strip().lower()


def _check_times(f: _Fields, key: str, times: NDArray[np.float64]) -> None:
    if np.any(np.diff(times) <= 0):
        row = int(np.flatnonzero(np.diff(times) <= 0)[0]) + 1
        raise f.error(f"{key}[{row}]", "ephemeris times must be strictly increasing")


def _require_object(f: _Fields, key: str) -> None:
    if not isinstance(f.raw(key), Mapping):
        raise f.error(key, "expected a JSON object")


def _read_states(f: _Fields, key: str) -> CsmStates:
    _require_object(f, key)
    f.unit(f"{key}.unit", ("km",))
    times = f.array(f"{key}.ephemeris_times", min_rows=2)
    _check_times(f, f"{key}.ephemeris_times", times)
    pos = f.array(f"{key}.positions", 3, min_rows=2)
    if len(pos) != len(times):
        raise f.error(f"{key}.positions", f"has {len(pos)} rows for {len(times)} ephemeris times")
    vel = f.array(f"{key}.velocities", 3, default=None)
    if vel is not None and len(vel) != len(times):
        raise f.error(f"{key}.velocities", f"has {len(vel)} rows for {len(times)} ephemeris times")
    frame = int(f.number(f"{key}.reference_frame", J2000, integer=True))
    known = {"ephemeris_times", "positions", "velocities", "reference_frame"}
    extra = {k: v for k, v in f.raw(key).items() if k not in known}
    return CsmStates(
        frozen_array(times),
        frozen_array(pos),
        None if vel is None else frozen_array(vel),
        frame,
        extra,
    )


def _read_orientations(f: _Fields, key: str) -> CsmOrientations:
    _require_object(f, key)
    times = f.array(f"{key}.ephemeris_times", min_rows=1)
    _check_times(f, f"{key}.ephemeris_times", times)
    q = f.array(f"{key}.quaternions", 4, min_rows=1)
    if len(q) != len(times):
        raise f.error(f"{key}.quaternions", f"has {len(q)} rows for {len(times)} ephemeris times")
    norms = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-5)
    if bad.size:
        i = int(bad[0])
        what = (
            "has zero norm"
            if norms[i] < 1e-12
            else f"is not a unit quaternion (norm {norms[i]:.6g})"
        )
        raise f.error(f"{key}.quaternions[{i}]", f"quaternion {q[i].tolist()} {what}")
    av = f.array(f"{key}.angular_velocities", 3, default=None)
    if av is not None and len(av) != len(times):
        raise f.error(
            f"{key}.angular_velocities", f"has {len(av)} rows for {len(times)} ephemeris times"
        )
    const = f.array(f"{key}.constant_rotation", default=None)
    if const is None:
        const = np.eye(3)
    else:
        if const.shape != (9,):
            raise f.error(f"{key}.constant_rotation", "expected 9 numbers (row-major 3x3)")
        const = const.reshape(3, 3)
        if not np.allclose(const @ const.T, np.eye(3), atol=1e-6) or np.linalg.det(const) < 0:
            raise f.error(f"{key}.constant_rotation", "is not a rotation matrix")
    frame = int(f.number(f"{key}.reference_frame", J2000, integer=True))

    def frames(k: str) -> tuple[int, ...]:
        v = f.raw(f"{key}.{k}", [])
        if not isinstance(v, list) or not all(isinstance(x, (int, float)) for x in v):
            raise f.error(f"{key}.{k}", "expected a list of NAIF frame codes")
        return tuple(int(x) for x in v)

    known = {
        "ephemeris_times",
        "quaternions",
        "angular_velocities",
        "constant_rotation",
        "reference_frame",
        "constant_frames",
        "time_dependent_frames",
    }
    extra = {k: v for k, v in f.raw(key).items() if k not in known}
    return CsmOrientations(
        frozen_array(times),
        frozen_array(q),
        None if av is None else frozen_array(av),
        frozen_array(const),
        frame,
        frames("constant_frames"),
        frames("time_dependent_frames"),
        extra,
    )


def _read_distortion(f: _Fields) -> tuple[str, NDArray[np.float64]]:
    od = f.raw("optical_distortion")
    if not isinstance(od, Mapping) or not od:
        raise f.error("optical_distortion", "expected an object with one distortion model")
    model = next(iter(od))
    if model not in SUPPORTED_DISTORTION:
        raise UnsupportedFormatError(
            f"distortion model {model!r} is not supported (supported: "
            f"{', '.join(SUPPORTED_DISTORTION)})",
            path=f.path,
            field="optical_distortion",
        )
    if model in ("radial", "radtan"):
        n = 3 if model == "radial" else 5
        c = f.array(f"optical_distortion.{model}.coefficients")
        if len(c) != n:
            raise f.error(
                f"optical_distortion.{model}.coefficients",
                f"expected {n} coefficients, got {len(c)}",
            )
        return model, c
    cx = f.array("optical_distortion.transverse.x")
    cy = f.array("optical_distortion.transverse.y")
    if len(cx) > 10 or len(cy) > 10:
        raise f.error("optical_distortion.transverse", "at most 10 coefficients per axis")
    # usgscsm pads each axis to the 10 terms of its cubic polynomial.
    return model, np.concatenate([np.pad(cx, (0, 10 - len(cx))), np.pad(cy, (0, 10 - len(cy)))])


def _read_correction(f: _Fields) -> tuple[CsmCorrection | None, tuple[float, ...] | None]:
    if not f.has(CORRECTION_KEY):
        return None, None
    corr = CsmCorrection.from_array(f.array(f"{CORRECTION_KEY}.parameters"))
    scales = None
    if f.has(f"{CORRECTION_KEY}.half_time_s"):
        scales = tuple(
            f.number(f"{CORRECTION_KEY}.{k}", positive=True)
            for k in ("half_time_s", "flying_height_m", "half_swath_m")
        )
    return corr, scales


def _isd_from_dict(data: Any, path: str | None) -> CsmIsd:
    f = _Fields(data, path)
    if not isinstance(data, Mapping):
        raise InputError("an ISD must be a JSON object", path=path)
    name = f.raw("name_model")
    if name != CSM_LINE_SCANNER_MODEL:
        raise UnsupportedFormatError(
            f"only {CSM_LINE_SCANNER_MODEL} ISDs are supported, got {name!r}",
            path=path,
            field="name_model",
        )
    radii_unit = f.unit("radii.unit", ("km",))
    a_km = f.number("radii.semimajor", positive=True)
    b_km = f.number("radii.semiminor", positive=True)
    if radii_unit is None and a_km > 1e5:
        raise f.error(
            "radii.semimajor",
            f"{a_km} km is larger than any planet: metres given where km are expected?",
        )
    if b_km > a_km:
        raise f.error("radii.semiminor", f"semiminor {b_km} km > semimajor {a_km} km")
    h_unit = f.unit("reference_height.unit", ("m", "km")) or "m"
    h_scale = 1000.0 if h_unit == "km" else 1.0
    min_h = f.number("reference_height.minheight", -8000.0) * h_scale
    max_h = f.number("reference_height.maxheight", 8000.0) * h_scale
    if min_h > max_h:
        raise f.error("reference_height", f"minheight {min_h} m > maxheight {max_h} m")

    rate = f.array("line_scan_rate", 3)
    if np.any(rate[:, 2] <= 0):
        raise f.error("line_scan_rate", "seconds per line must be positive")
    if np.any(np.diff(rate[:, 0]) <= 0):
        raise f.error("line_scan_rate", "start lines must be increasing")
    f2l = f.array("focal2pixel_lines")
    f2s = f.array("focal2pixel_samples")
    for key, arr in (("focal2pixel_lines", f2l), ("focal2pixel_samples", f2s)):
        if len(arr) != 3:
            raise f.error(key, f"expected 3 numbers, got {len(arr)}")
    if f2l[1] * f2s[2] - f2l[2] * f2s[1] == 0:
        raise f.error("focal2pixel_lines", "focal2pixel_lines/samples are singular")
    model, coeffs = _read_distortion(f)
    position = _read_states(f, "instrument_position")
    pointing = _read_orientations(f, "instrument_pointing")
    body = _read_orientations(f, "body_rotation")
    if len(pointing.times) + len(body.times) < 2:
        raise f.error(
            "instrument_pointing.ephemeris_times", "at least two pointing epochs are needed"
        )
    platform_flag = int(f.number("platform_flag", 1, integer=True))
    if platform_flag not in (0, 1):
        raise f.error("platform_flag", f"must be 0 or 1, got {platform_flag}")
    correction, scales = _read_correction(f)

    known = {
        "name_model",
        "name_platform",
        "name_sensor",
        "image_lines",
        "image_samples",
        "center_ephemeris_time",
        "starting_ephemeris_time",
        "line_scan_rate",
        "focal_length_model",
        "focal2pixel_lines",
        "focal2pixel_samples",
        "detector_center",
        "starting_detector_line",
        "starting_detector_sample",
        "detector_line_summing",
        "detector_sample_summing",
        "optical_distortion",
        "radii",
        "reference_height",
        "instrument_position",
        "instrument_pointing",
        "body_rotation",
        "platform_flag",
        CORRECTION_KEY,
    }
    isd = CsmIsd(
        path=path,
        name_platform=f.string("name_platform", ""),
        name_sensor=f.string("name_sensor", ""),
        image_lines=int(f.number("image_lines", positive=True, integer=True)),
        image_samples=int(f.number("image_samples", positive=True, integer=True)),
        center_ephemeris_time=f.number("center_ephemeris_time"),
        starting_ephemeris_time=f.number("starting_ephemeris_time"),
        line_scan_rate=frozen_array(rate),
        focal_length_mm=f.number("focal_length_model.focal_length", positive=True),
        focal2pixel_lines=frozen_array(f2l),
        focal2pixel_samples=frozen_array(f2s),
        detector_center_line=f.number("detector_center.line"),
        detector_center_sample=f.number("detector_center.sample"),
        starting_detector_line=f.number("starting_detector_line"),
        starting_detector_sample=f.number("starting_detector_sample"),
        detector_line_summing=f.number("detector_line_summing", positive=True),
        detector_sample_summing=f.number("detector_sample_summing", positive=True),
        distortion_model=model,
        distortion_coefficients=frozen_array(coeffs),
        semi_major_km=a_km,
        semi_minor_km=b_km,
        min_height_m=min_h,
        max_height_m=max_h,
        instrument_position=position,
        instrument_pointing=pointing,
        body_rotation=body,
        platform_flag=platform_flag,
        correction=correction,
        correction_scales=scales,  # type: ignore[arg-type]
        extra=types.MappingProxyType({k: v for k, v in data.items() if k not in known}),
    )
    _check_frames(isd, f)
    return isd


def _check_frames(isd: CsmIsd, f: _Fields) -> None:
    body = isd.body_frame
    allowed = {J2000} | ({body} if body is not None else set())
    for key, frame in (
        ("instrument_position.reference_frame", isd.instrument_position.reference_frame),
        ("instrument_pointing.reference_frame", isd.instrument_pointing.reference_frame),
    ):
        if frame not in allowed:
            raise UnsupportedFormatError(
                f"reference frame {frame} is neither J2000 (1) nor the body frame ({body})",
                path=f.path,
                field=key,
            )
    if isd.body_rotation.reference_frame != J2000:
        raise UnsupportedFormatError(
            f"body_rotation must rotate from J2000 (1), got frame "
            f"{isd.body_rotation.reference_frame}",
            path=f.path,
            field="body_rotation.reference_frame",
        )


def read_isd(path: str | os.PathLike[str]) -> CsmIsd:
    """Read and check a USGS CSM line-scan ISD (the JSON of ALE and usgscsm).

    Accepts the keys ALE writes and the older synthetic keys of usgscsm's test ISDs
    (``t0_ephemeris``, ``dt_quaternion``... which usgscsm recomputes and this reader
    keeps only for writing back).

    Args:
        path: The ISD JSON file.

    Returns:
        The checked ISD.

    Raises:
        MissingFileError: If the file does not exist.
        UnsupportedFormatError: If ``name_model`` is not
            ``USGS_ASTRO_LINE_SCANNER_SENSOR_MODEL``, or the distortion model or a
            reference frame is not supported.
        InputError: If the JSON is malformed, or a field is missing, of the wrong type or
            shape, not finite, in the wrong unit, or inconsistent (the message names the
            file and the field).
    """
    p = Path(path)
    data = read_json(p, "ISD")
    try:
        return _isd_from_dict(data, str(p))
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"malformed ISD ({type(exc).__name__}: {exc})", path=p) from None
