"""A native line-scan camera written as USGS CSM line-scan ISDs (one per CCD).

:func:`linescan_to_isd` samples a :class:`~planetref.camera.linescan.LineScanCamera`
into the ISD that usgscsm's ``USGS_ASTRO_LINE_SCANNER_SENSOR_MODEL`` (and planetref's
:class:`~planetref.camera.csm.camera.CsmLineScanCamera`) reads, so that ISIS/ASP users
can continue with an adjusted strip; :func:`write_linescan_isds` writes one ISD per CCD.

Conventions of the ISDs written
-------------------------------
* **Frames.** The native model is body-fixed. ``body_rotation`` is the identity (with
  zero angular velocity) at every epoch, so J2000 coincides with the body-fixed frame and
  ``instrument_position`` / ``instrument_pointing`` are the native body-fixed states.
  usgscsm's arithmetic (positions rotated by ``body_rotation``, pointing composed with
  it) then gives back the native geometry exactly.
* **Ephemeris.** Positions (km), velocities (km/s; central differences of the native
  Lagrange trajectory over half a line) and pointing quaternions are sampled from the
  native model at evenly spaced epochs that cover the image plus ``margin_lines`` on each
  side, about every ``lines_per_sample`` lines and never fewer than 25 (usgscsm resamples
  to at least 25 evenly spaced epochs; evenly spaced input makes that a no-op). Times are
  the native camera's (seconds), used as ephemeris times; ``center_ephemeris_time`` is the
  time of the image's middle line.
* **Sensor frame.** The native camera looks along its ``-z`` axis; the ISD's sensor frame
  is the native camera frame turned 180 degrees about ``x`` (boresight ``+z``, as in real
  ISDs), so ``instrument_pointing`` holds ``(R_cam->body @ diag(1, -1, -1))^T`` as
  scalar-first quaternions (J2000 = body -> sensor), signs kept continuous.
* **Focal plane and detector.** Focal-plane x is along track (lines), y across track
  (samples), in mm about the principal point. The CCD's placement (edge at ``(x_mm,
  y_mm)``, pitch ``p``, angle ``a``) becomes ``focal2pixel_lines = [0, cos a / p, sin a /
  p]``, ``focal2pixel_samples = [0, sin a / p, -cos a / p]`` and a ``detector_center``
  that puts the principal point where the native model has it; no summing, starting
  detector line/sample 0, ``radial`` distortion with zero coefficients (the native model
  has none).
* **Time.** ``line_scan_rate`` rows ``[start_line, t0 - 0.5 period - center, period]``
  reproduce the native table under usgscsm's ``t = t0_k + rate_k (line - line_k + 0.5)``.
* **Pixels.** Both models use ``(line, sample)`` with the first pixel's centre at
  ``(0.5, 0.5)``; no shift is applied.
* ``sun_position`` (which usgscsm requires) is a placeholder far along +x unless given:
  it only affects usgscsm's illumination queries, never the geometry.
"""

from __future__ import annotations

import math
import os
import re
import warnings
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from planetref.camera.csm.isd import (
    J2000,
    MIN_EPHEMERIS_NODES,
    CsmIsd,
    CsmOrientations,
    CsmStates,
    write_isd,
)
from planetref.camera.csm.orientation import _quat_from_matrix
from planetref.errors import InputError

if TYPE_CHECKING:
    from planetref.camera.linescan import LineScanCamera

__all__ = ["isd_agreement_px", "isd_file_name", "linescan_to_isd", "write_linescan_isds"]

#: Native camera frame (boresight -z) -> ISD sensor frame (boresight +z): 180 deg about x.
_FLIP = np.diag([1.0, -1.0, -1.0])
#: Placeholder Sun position (km, body-fixed): 1 AU along +x.
_SUN_KM = (1.495978707e8, 0.0, 0.0)


def linescan_to_isd(
    camera: LineScanCamera,
    ccd: str | None = None,
    *,
    lines_per_sample: float = 32.0,
    margin_lines: float = 64.0,
    sun_position_km: tuple[float, float, float] | None = None,
) -> CsmIsd:
    """The USGS CSM line-scan ISD of one CCD of a native line-scan camera.

    Args:
        camera: The native camera (e.g. an adjusted strip).
        ccd: Which CCD (default: the first).
        lines_per_sample: Image lines between ephemeris epochs (smaller: larger files,
            closer agreement; 32 keeps the ISD within 1e-8 pixel of the native model on
            orbital strips).
        margin_lines: Lines sampled beyond each end of the image.
        sun_position_km: Body-fixed Sun position for usgscsm's illumination queries.

    Returns:
        The ISD (see the module's conventions).

    Raises:
        InputError: Unknown CCD, bad sampling arguments, or a CCD with lens distortion
            (a simulation truth; the export writes a distortion-free ISD).
    """
    if any(camera.ccd(ccd).distortion):
        raise InputError(
            f"CCD {camera.ccd(ccd).name} has lens distortion; the CSM export does not carry it"
        )
    if not (lines_per_sample > 0 and math.isfinite(lines_per_sample)) or not margin_lines >= 0:
        raise InputError(
            f"lines_per_sample must be > 0 and margin_lines >= 0, got {lines_per_sample}, "
            f"{margin_lines}"
        )
    c = camera.ccd(ccd)
    n_lines, n_samples = int(c.n_lines), int(c.n_samples)
    rates = camera.line_rates
    t_first, t_last = rates.time([-margin_lines, n_lines + margin_lines])
    center = float(rates.time(n_lines / 2.0))
    period = float(np.min(rates.period(np.linspace(0.0, n_lines, 64))))
    n = max(math.ceil((t_last - t_first) / (lines_per_sample * period)) + 1, MIN_EPHEMERIS_NODES)
    times = t_first + (t_last - t_first) * np.arange(n) / (n - 1)
    lines = rates.line(times)
    pos, rot = camera.exterior(lines)
    p_plus, _ = camera.exterior(lines + 0.5)
    p_minus, _ = camera.exterior(lines - 0.5)
    vel = (p_plus - p_minus) / (
        np.asarray(rates.time(lines + 0.5)) - np.asarray(rates.time(lines - 0.5))
    )[:, None]
    # J2000 (= body) -> sensor rotations as scalar-first quaternions, signs continuous.
    body_to_sensor = np.swapaxes(rot @ _FLIP, 1, 2)
    quats = np.array([_quat_from_matrix(m) for m in body_to_sensor])
    for i in range(1, n):
        if np.dot(quats[i], quats[i - 1]) < 0:
            quats[i] = -quats[i]
    identity = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    rel = times - center

    io = camera.interior
    sa, ca = math.sin(c.angle_rad), math.cos(c.angle_rad)
    p = c.pixel_pitch_mm
    # Focal plane (mm, about the principal point; y flipped by the sensor frame) of
    # detector (line, sample) = (L, S): (x, y) = (L - Lc) w + (S - Sc) v, with v the
    # sample direction and w the line direction, both of length p.
    v = np.array([p * sa, -p * ca])
    w = np.array([p * ca, p * sa])
    c0 = np.array([c.x_mm - io.x0_mm, -(c.y_mm - io.y0_mm)])
    center_line = -float(np.dot(c0, w)) / (p * p)
    center_sample = -float(np.dot(c0, v)) / (p * p)
    table = np.array(
        [[r[0], r[1] - 0.5 * r[2] - center, r[2]] for r in rates.rows], dtype=np.float64
    )
    ell = camera.ellipsoid
    sun = np.asarray(sun_position_km if sun_position_km is not None else _SUN_KM, float)
    return CsmIsd(
        path=None,
        name_platform="planetref",
        name_sensor=c.name,
        image_lines=n_lines,
        image_samples=n_samples,
        center_ephemeris_time=center,
        starting_ephemeris_time=float(rates.time(0.0)),
        line_scan_rate=table,
        focal_length_mm=float(io.focal_length_mm),
        focal2pixel_lines=np.array([0.0, ca / p, sa / p]),
        focal2pixel_samples=np.array([0.0, sa / p, -ca / p]),
        detector_center_line=center_line,
        detector_center_sample=center_sample,
        starting_detector_line=0.0,
        starting_detector_sample=0.0,
        detector_line_summing=1.0,
        detector_sample_summing=1.0,
        distortion_model="radial",
        distortion_coefficients=np.zeros(3),
        semi_major_km=ell.semi_major_m / 1000.0,
        semi_minor_km=ell.semi_minor_m / 1000.0,
        min_height_m=-10000.0,
        max_height_m=10000.0,
        instrument_position=CsmStates(times, pos / 1000.0, vel / 1000.0, J2000),
        instrument_pointing=CsmOrientations(
            times, quats, np.zeros((n, 3)), np.eye(3), J2000, (), (), {}
        ),
        body_rotation=CsmOrientations(times, identity, np.zeros((n, 3)), np.eye(3), J2000),
        platform_flag=1,
        extra={
            "interpolation_method": "lagrange",
            "sun_position": {
                "ephemeris_times": [center],
                "positions": [sun.tolist()],
                "velocities": [[0.0, 0.0, 0.0]],
                "reference_frame": J2000,
                "unit": "km",
            },
            "planetref": {
                "source": "planetref native line-scan camera",
                "camera_name": getattr(camera, "name", ""),
                "time_relative_seconds": rel[[0, -1]].tolist(),
            },
        },
    )


def isd_agreement_px(camera: LineScanCamera, ccd: str | None, isd: CsmIsd) -> float:
    """Largest image distance (pixels) between the native camera and the ISD's camera.

    Ground points are made by the native camera from image points on a grid (every
    native node line inside the image, with the lines half a native node interval on
    either side, plus 33 evenly spaced lines; 5 samples across) at the height 0, and
    projected by planetref's CSM camera (usgscsm's arithmetic); the distance to the
    image points they came from is measured.

    Args:
        camera: The native camera.
        ccd: The CCD the ISD describes.
        isd: The ISD.

    Returns:
        The largest distance in pixels (``inf`` if a point cannot be projected).
    """
    from planetref.camera.csm.camera import CsmLineScanCamera

    c = camera.ccd(ccd)
    n_lines, n_samples = int(c.n_lines), int(c.n_samples)
    nodes = np.asarray(camera.node_lines, dtype=np.float64)
    half = 0.5 * float(np.min(np.diff(nodes))) if len(nodes) > 1 else 1.0
    lines = np.concatenate(
        [
            nodes,
            nodes - 1.0,
            nodes + 1.0,
            nodes - half,
            nodes + half,
            np.linspace(0.5, n_lines - 0.5, 33),
        ]
    )
    lines = np.unique(lines[(lines >= 0.5) & (lines <= n_lines - 0.5)])
    gl, gs = np.meshgrid(lines, np.linspace(0.5, n_samples - 0.5, 5), indexing="ij")
    line, sample = gl.ravel(), gs.ravel()
    xyz = camera.image_to_ground(line, sample, 0.0, ccd=c.name, on_miss="nan")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        back = CsmLineScanCamera.from_isd(isd).ground_to_image(xyz)
    err = np.hypot(back.line - line, back.sample - sample)
    return float(np.max(err)) if np.all(np.isfinite(err)) else math.inf


def isd_file_name(stem: str, ccd: str) -> str:
    """``<stem>_<ccd>.json`` with characters outside ``[A-Za-z0-9._-]`` replaced by ``_``."""
    return re.sub(r"[^A-Za-z0-9._-]", "_", f"{stem}_{ccd}") + ".json"


def write_linescan_isds(
    camera: LineScanCamera,
    out_dir: str | os.PathLike[str],
    stem: str,
    *,
    tolerance_px: float = 1e-3,
    lines_per_sample: float = 32.0,
) -> list[Path]:
    """Write one USGS CSM line-scan ISD per CCD of a native camera (atomically).

    Each ISD is checked against the native camera (:func:`isd_agreement_px`); the
    ephemeris is sampled more densely (from every 32 lines down to every half line)
    until the two agree to ``tolerance_px``. The sampling and the agreement reached are
    recorded in the ISD (``planetref.lines_per_sample``, ``planetref.check_max_px``);
    an ISD that cannot reach the tolerance is still written, with a warning that says
    how far off it is.

    Args:
        camera: The native camera (e.g. the adjusted camera of a strip).
        out_dir: Existing folder for the ISDs.
        stem: File name stem; CCD ``c`` goes to ``<stem>_<c>.json`` (see
            :func:`isd_file_name`).
        tolerance_px: Largest accepted disagreement in pixels.
        lines_per_sample: The first (coarsest) ephemeris sampling tried, in lines.

    Returns:
        The paths written, in the camera's CCD order.

    Raises:
        InputError: The folder does not exist or a file cannot be written.
    """
    folder = Path(out_dir)
    if not folder.is_dir():
        raise InputError("the output folder does not exist", path=folder)
    paths = []
    for name in camera.ccd_names:
        lps = float(lines_per_sample)
        while True:
            isd = linescan_to_isd(camera, name, lines_per_sample=lps)
            err = isd_agreement_px(camera, name, isd)
            if err <= tolerance_px or lps <= 0.5:
                break
            lps /= 2.0
        extra = dict(isd.extra)
        extra["planetref"] = {
            **extra["planetref"],
            "lines_per_sample": lps,
            "check_max_px": err,
            "check_tolerance_px": tolerance_px,
        }
        path = folder / isd_file_name(stem, name)
        if not err <= tolerance_px:
            warnings.warn(
                f"{path}: the ISD of CCD {name} agrees with the native camera only to "
                f"{err:.2g} pixel (tolerance {tolerance_px:g})",
                UserWarning,
                stacklevel=2,
            )
        paths.append(write_isd(replace(isd, extra=extra), path))
    return paths
