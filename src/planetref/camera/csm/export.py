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
  detector line/sample 0, ``radial`` distortion with zero coefficients when the CCD has
  no lens distortion.
* **Lens distortion.** A CCD with Brown-Conrady distortion (simulation truths,
  :mod:`planetref.camera.linescan.lens`) gets usgscsm's ``radtan`` model, fitted by
  :func:`fit_radtan` (the inverse direction and centre differ, so the coefficients are
  not a copy), with the fit's affinity folded into ``focal2pixel_*`` and
  ``detector_center``; the fit's largest error is recorded as
  ``planetref.distortion_fit_max_px``. A distortion the fit cannot reproduce to
  ``distortion_tolerance_px`` is refused with an error (never written as zero).
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
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from planetref.camera.csm.distortion import radtan_basis, radtan_displacement
from planetref.camera.csm.isd import (
    J2000,
    MIN_EPHEMERIS_NODES,
    CsmIsd,
    CsmOrientations,
    CsmStates,
    write_isd,
)
from planetref.camera.csm.orientation import quat_from_matrix
from planetref.camera.linescan.lens import ideal_position
from planetref.errors import InputError

if TYPE_CHECKING:
    from planetref.camera.linescan import LineScanCamera

__all__ = [
    "RadtanFit",
    "fit_radtan",
    "isd_agreement_px",
    "isd_file_name",
    "linescan_to_isd",
    "write_linescan_isds",
]

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
    distortion_tolerance_px: float = 1e-4,
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
        distortion_tolerance_px: Largest accepted error (pixels) of the ``radtan`` fit
            of a CCD's lens distortion (:func:`fit_radtan`).

    Returns:
        The ISD (see the module's conventions).

    Raises:
        InputError: Unknown CCD, bad sampling arguments, or a lens distortion that
            usgscsm's ``radtan`` model cannot reproduce to ``distortion_tolerance_px``.
    """
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
    quats = np.array([quat_from_matrix(m) for m in body_to_sensor])
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
    # Focal plane (distorted, mm) -> detector (line, sample) about the detector centre.
    to_pixel = np.array([[ca / p, sa / p], [sa / p, -ca / p]])
    distortion: tuple[str, np.ndarray] = ("radial", np.zeros(3))
    fit_px = None
    if any(c.distortion):
        lens = fit_radtan(camera, c.name)
        if not lens.max_error_px <= distortion_tolerance_px:
            raise InputError(
                f"CCD {c.name}: usgscsm's radtan model reproduces its lens distortion only to "
                f"{lens.max_error_px:.2g} px (tolerance {distortion_tolerance_px:g} px); "
                f"not exported"
            )
        # The fitted affine part goes into the detector map: D = A^-1 (delta - B).
        a_inv = np.linalg.inv(lens.affine)
        shift = to_pixel @ a_inv @ lens.shift_mm
        to_pixel = to_pixel @ a_inv
        center_line -= float(shift[0])
        center_sample -= float(shift[1])
        distortion = ("radtan", lens.coefficients)
        fit_px = lens.max_error_px
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
        focal2pixel_lines=np.array([0.0, *to_pixel[0]]),
        focal2pixel_samples=np.array([0.0, *to_pixel[1]]),
        detector_center_line=center_line,
        detector_center_sample=center_sample,
        starting_detector_line=0.0,
        starting_detector_sample=0.0,
        detector_line_summing=1.0,
        detector_sample_summing=1.0,
        distortion_model=distortion[0],
        distortion_coefficients=distortion[1],
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
                **({} if fit_px is None else {"distortion_fit_max_px": fit_px}),
            },
        },
    )


@dataclass(frozen=True)
class RadtanFit:
    """usgscsm ``radtan`` coefficients (and a detector affinity) for a CCD's lens distortion.

    In the ISD's focal plane (mm about the principal point, sensor frame), a native
    detector position ``D`` of the CCD and its undistorted position ``U`` satisfy
    ``U + f R(U / f) = A D + B`` to ``max_error_px``, with ``R`` the ``radtan``
    displacement (:mod:`planetref.camera.csm.distortion`).

    Attributes:
        coefficients: ``(k1, k2, p1, p2, k3)``.
        affine: ``A``, ``(2, 2)`` (the identity when the distortion is centred on the
            principal point).
        shift_mm: ``B`` (mm), ``(2,)``.
        max_error_px: Largest error of the fit over the CCD (pixels).
    """

    coefficients: np.ndarray
    affine: np.ndarray
    shift_mm: np.ndarray
    max_error_px: float


def fit_radtan(camera: LineScanCamera, ccd: str | None = None) -> RadtanFit:
    """Fit usgscsm's ``radtan`` model to a CCD's Brown-Conrady lens distortion.

    The native lens (:mod:`planetref.camera.linescan.lens`) maps detector positions to
    ideal ones (distorted -> undistorted) about the focal-plane origin; usgscsm's
    ``radtan`` maps undistorted -> distorted about the principal point, on coordinates
    normalised by the focal length, with OpenCV's ``p1``/``p2`` order. The inverse of one
    polynomial is not exactly the other, so the coefficients are fitted (linear least
    squares, together with an affinity that the detector map absorbs) over the CCD: every
    sample from 0 to ``n_samples`` and 2 px either side of the detector line (where
    ground-to-image converges and image-to-ground starts). The error is measured on the
    same points, in pixels.

    Args:
        camera: The native camera.
        ccd: The CCD (default: the first).

    Returns:
        :class:`RadtanFit`.
    """
    c = camera.ccd(ccd)
    io = camera.interior
    f, p = float(io.focal_length_mm), float(c.pixel_pitch_mm)
    sa, ca = math.sin(c.angle_rad), math.cos(c.angle_rad)
    s, o = (
        a.ravel()
        for a in np.meshgrid(np.linspace(0.0, c.n_samples, 257), np.linspace(-2.0, 2.0, 9))
    )
    xd = c.x_mm + p * (s * sa + o * ca)
    yd = c.y_mm + p * (s * ca - o * sa)
    xi, yi = ideal_position(xd, yd, c.distortion)
    # ISD focal plane: about the principal point, y flipped (the sensor frame).
    d = np.stack([xd - io.x0_mm, -(yd - io.y0_mm)], axis=-1)
    u = np.stack([xi - io.x0_mm, -(yi - io.y0_mm)], axis=-1)
    bx, by = radtan_basis(u[:, 0] / f, u[:, 1] / f)
    zero, one = np.zeros(len(s)), np.ones(len(s))
    # Unknowns: A (row-major), B, the radtan coefficients; U = A D + B - f R(U / f).
    rows_x = np.column_stack([d[:, 0], d[:, 1], zero, zero, one, zero, -f * bx])
    rows_y = np.column_stack([zero, zero, d[:, 0], d[:, 1], zero, one, -f * by])
    design = np.concatenate([rows_x, rows_y])
    scale = np.max(np.abs(design), axis=0)
    scale[scale == 0] = 1.0
    theta = np.linalg.lstsq(design / scale, np.concatenate([u[:, 0], u[:, 1]]), rcond=None)[0]
    theta /= scale
    affine, shift, coeffs = theta[:4].reshape(2, 2), theta[4:6], theta[6:]
    # What the ISD computes: delta = U + f R(U / f), then D' = A^-1 (delta - B).
    rx, ry = radtan_displacement(coeffs, u[:, 0] / f, u[:, 1] / f)
    delta = u + f * np.stack([rx, ry], axis=-1)
    d_isd = np.linalg.solve(affine, (delta - shift).T).T
    err = float(np.max(np.hypot(*(d_isd - d).T))) / p
    return RadtanFit(coeffs, affine, shift, err)


def isd_agreement_px(camera: LineScanCamera, ccd: str | None, isd: CsmIsd) -> float:
    """Largest image distance (pixels) between the native camera and the ISD's camera.

    Ground points are made by the native camera from image points on a grid (every
    native node line inside the image, the lines 0.25, 0.5 and 1 line and half a native
    node interval on either side, plus 65 evenly spaced lines; 5 samples across) at the
    height 0, and
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
    # The native orientation bends at its nodes (the Lagrange window moves on) and the
    # ISD's sampled ephemeris cannot follow a bend exactly: its error peaks within a
    # line of a node (1.6e-3 px 0.3 lines from one, where +-1 lines showed 0.8e-3).
    near = np.array([-1.0, -0.5, -0.25, 0.25, 0.5, 1.0])
    lines = np.concatenate(
        [
            nodes,
            (nodes[:, None] + near[None, :]).ravel(),
            nodes - half,
            nodes + half,
            np.linspace(0.5, n_lines - 0.5, 65),
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
