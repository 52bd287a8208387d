"""The USGS CSM line-scan camera: usgscsm's arithmetic on a typed ISD.

:class:`CsmLineScanCamera` implements the :class:`~planetref.camera.base.Camera`
protocol on a :class:`~planetref.camera.csm.isd.CsmIsd`, reproducing usgscsm's
arithmetic so that both give the same numbers:

* **Positions, pointing, time**: sampled and interpolated as usgscsm does by
  :class:`~planetref.camera.csm.ephemeris.CsmEphemeris`.
* **Focal plane**: samples map to focal-plane mm through ``focal2pixel_samples`` /
  ``focal2pixel_lines`` (inverted), ``detector_center``, ``starting_detector_*`` and
  ``detector_*_summing``; the detector line is the focal-plane position of image line 0
  (usgscsm's ``computeDistortedFocalPlaneCoordinates(0, sample, ...)``). Lens distortion
  is ``radial``, ``transverse`` or ``radtan`` (:mod:`~planetref.camera.csm.distortion`).
* **Sensor frame**: the look direction of a focal-plane point ``(x, y)`` is
  ``(x, y, f)`` in the sensor frame, boresight +Z, as in every real ISD. usgscsm's
  arithmetic does not depend on the boresight's sign (it intersects with the nearer root
  and projects with ``x f / z``); its synthetic orbital test ISDs look along -Z, so the
  sign is chosen per camera such that the image centre looks at the body.

Deliberate differences from usgscsm (documented where they apply): rays that miss the
body give an error or NaN instead of usgscsm's closest point; heights other than 0 are
intersected on the exact surface of constant height (usgscsm uses the ellipsoid of radii
``a + h, b + h``, identical on a sphere); ground-to-image iterates to 1e-9 pixel instead
of usgscsm's 0.001; and the focal-length correction is applied the same way in both
directions (usgscsm uses ``f + p15`` in ``groundToImage`` but ``f (1 - p15 / halfSwath)``
in ``imageToGround``; we use the latter everywhere).

Image coordinates are planetref's (and usgscsm's): ``(line, sample)`` with the centre of
the first pixel at ``(0.5, 0.5)``. Ground coordinates are body-fixed XYZ in metres.
"""

from __future__ import annotations

import copy
import math
import os
import warnings
from dataclasses import replace
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.camera.base import ConstantHeight, ImagePoints, OnMiss, Terrain
from planetref.camera.csm.distortion import apply_distortion, remove_distortion
from planetref.camera.csm.ephemeris import CsmEphemeris
from planetref.camera.csm.isd import CsmCorrection, CsmIsd
from planetref.camera.csm.orientation import euler_matrix
from planetref.camera.csm.reader import read_isd
from planetref.errors import GeometryError, InputError
from planetref.geometry.geodesy import Ellipsoid, LatitudeKind, ray_ellipsoid_intersection
from planetref.geometry.roots import bracket_first_sign_change, refine_bracketed
from planetref.geometry.terrain import intersect_terrain

__all__ = ["CsmLineScanCamera"]


_G2I_TOLERANCE_PX = 1e-9


_G2I_VALID_PX = 1e-6


def _as_1d(x: ArrayLike, name: str) -> NDArray[np.float64]:
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be numeric") from None
    return np.atleast_1d(a).ravel()


class CsmLineScanCamera:
    """A USGS CSM line-scan camera (one CCD) that reproduces usgscsm's numbers.

    Implements :class:`~planetref.camera.base.Camera`; every method is vectorised over
    points. Build it with :meth:`from_file` or :meth:`from_isd`.

    Attributes:
        ellipsoid: The body (radii from the ISD, in metres).
        latitude_kind: ``"planetocentric"``.
        half_time_s: Half the image duration (s), usgscsm's ``m_halfTime``.
        flying_height_m: Distance from the sensor to the image-centre ground point (m),
            usgscsm's ``m_flyingHeight``.
        half_swath_m: Half the image width on the ground (m), usgscsm's ``m_halfSwath``.
        gsd_m: Ground sample distance at the image centre (m), usgscsm's ``m_gsd``.
        reference_point: Ground point of the image centre at height 0, XYZ (m).
    """

    latitude_kind: LatitudeKind = "planetocentric"

    def __init__(self, isd: CsmIsd, correction: CsmCorrection | None = None) -> None:
        self._isd = isd
        self.ellipsoid = Ellipsoid(
            isd.semi_major_km * 1000.0,
            isd.semi_minor_km * 1000.0,
            isd.extra.get("name_target", "") or "",
        )
        self._ccd = isd.name_sensor or "ccd"
        self._ephemeris = CsmEphemeris.from_isd(isd)
        self._build_focal_plane()
        self._correction = CsmCorrection()
        self._zdir = 1.0
        self._zdir = self._boresight_sign()
        self._warn_time_coverage()
        self._compute_scales()
        if isd.correction_scales is not None:
            self.half_time_s, self.flying_height_m, self.half_swath_m = isd.correction_scales
        if correction is None:
            correction = isd.correction or CsmCorrection()
        self._correction = correction

    # -- construction -------------------------------------------------------------------

    @classmethod
    def from_file(
        cls, path: str | os.PathLike[str], correction: CsmCorrection | None = None
    ) -> CsmLineScanCamera:
        """Read an ISD (see :func:`read_isd`) and build its camera.

        Args:
            path: The ISD JSON file.
            correction: Overrides a correction stored in the ISD (default: the stored
                one, or none).
        """
        return cls(read_isd(path), correction)

    @classmethod
    def from_isd(cls, isd: CsmIsd, correction: CsmCorrection | None = None) -> CsmLineScanCamera:
        """Build the camera of a checked ISD (see :func:`read_isd`)."""
        return cls(isd, correction)

    def with_correction(self, correction: CsmCorrection) -> CsmLineScanCamera:
        """A copy of this camera with another correction (same ISD and scale factors)."""
        new = copy.copy(self)
        new._correction = correction
        new.__dict__.pop("_projective", None)
        return new

    def to_isd(self) -> CsmIsd:
        """The ISD to write for this camera: its correction (if not zero) and scale factors.

        :func:`~planetref.camera.csm.isd.write_isd` stores them under the
        ``planetref_correction`` key, so reading the file back gives identical projections.
        """
        return replace(
            self.isd,
            correction=None if self.correction.is_zero else self.correction,
            correction_scales=(self.half_time_s, self.flying_height_m, self.half_swath_m),
        )

    def _build_focal_plane(self) -> None:
        """Focal plane (mm) -> detector (pixels) and its inverse."""
        il, is_ = self._isd.focal2pixel_lines, self._isd.focal2pixel_samples
        self._itrans_l = np.asarray(il)
        self._itrans_s = np.asarray(is_)
        det = il[1] * is_[2] - il[2] * is_[1]
        self._p = np.array([[is_[2], -il[2]], [-is_[1], il[1]]]) / det

    def _warn_time_coverage(self) -> None:
        """Warn when lines are timed outside the ephemeris or the time table jumps."""
        problems = self._ephemeris.coverage_problems(self._isd.image_lines)
        if problems:
            warnings.warn(
                f"{self._isd.path or 'CSM ISD'}: " + "; ".join(problems),
                UserWarning,
                stacklevel=4,
            )

    def _boresight_sign(self) -> float:
        """+1 if the sensor looks along its +Z axis at the body, -1 if along -Z.

        usgscsm never needs this: it intersects with the nearer root whatever the sign of
        its look vector, and projects with ``x * f / z``, which ignores it. Real ISDs
        look along +Z; usgscsm's synthetic orbital test ISDs look along -Z.
        """
        nl = self._isd.image_lines
        origin, look = self._rays(np.array([nl / 2.0]), np.array([self._isd.image_samples / 2.0]))
        return -1.0 if float(np.dot(look[0], origin[0])) > 0 else 1.0

    def _compute_scales(self) -> None:
        """Port of usgscsm's ``updateState``: reference point, GSD, scale factors."""
        isd = self._isd
        nl, ns = isd.image_lines, isd.image_samples
        lines = np.array([nl / 2.0, nl / 2.0 + 1.0])
        samples = np.array([ns / 2.0, ns / 2.0 + 1.0])
        origin, look = self._rays(lines, samples)
        pts = self._usgscsm_intersect(origin, look)
        self.reference_point = pts[0]
        self.gsd_m = float(np.linalg.norm(pts[1] - pts[0]) / math.sqrt(2.0))
        self.flying_height_m = float(np.linalg.norm(origin[0] - pts[0]))
        self.half_swath_m = self.gsd_m * ns / 2.0
        self.half_time_s = self._ephemeris.duration(nl) / 2.0

    def _usgscsm_intersect(
        self, origin: NDArray[np.float64], look: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """Port of usgscsm's ``losEllipsoidIntersect`` at height 0 (closest point when missing)."""
        a, b = self.ellipsoid.semi_major_m, self.ellipsoid.semi_minor_m
        k = a * a / (b * b)
        kv = np.array([1.0, 1.0, k])
        at = np.sum(look * look * kv, axis=1)
        bt = 2.0 * np.sum(look * origin * kv, axis=1)
        ct = np.sum(origin * origin * kv, axis=1) - a * a
        quad = np.maximum(bt * bt - 4.0 * at * ct, 0.0)
        s1, s2 = -bt - np.sqrt(quad), -bt + np.sqrt(quad)
        s = np.where(np.abs(s2) < np.abs(s1), s2, s1) / (2.0 * at)
        return origin + s[:, None] * look

    # -- Camera protocol ----------------------------------------------------------------

    @property
    def isd(self) -> CsmIsd:
        """The ISD the camera was built from."""
        return self._isd

    @property
    def correction(self) -> CsmCorrection:
        """The correction applied to the exterior orientation (all zero: none)."""
        return self._correction

    @property
    def ccd_names(self) -> tuple[str, ...]:
        """One CCD, named after the ISD's ``name_sensor`` (``"ccd"`` if empty)."""
        return (self._ccd,)

    def _check_ccd(self, ccd: str | None) -> None:
        if ccd is not None and ccd != self._ccd:
            raise InputError(f"unknown CCD {ccd!r}; this camera has {self.ccd_names}")

    def image_size(self, ccd: str | None = None) -> tuple[int, int]:
        """``(n_lines, n_samples)`` of the image."""
        self._check_ccd(ccd)
        return self._isd.image_lines, self._isd.image_samples

    def image_time(self, line: ArrayLike) -> NDArray[np.float64]:
        """Acquisition time of image lines, seconds relative to ``center_ephemeris_time``.

        usgscsm's ``getImageTime``: ``t0_k + rate_k * (line - line_k + 0.5)`` with the
        last ``line_scan_rate`` row whose start line is ``<= line`` (the first row before
        the first start line). Lines outside the image extrapolate.

        Args:
            line: Line coordinates (planetref convention), any shape.

        Returns:
            Times in seconds, shape ``(M,)``.
        """
        return self._ephemeris.image_time(_as_1d(line, "line"))

    # -- exterior orientation: the one place where a correction acts -----------------

    def _exterior(
        self, t: NDArray[np.float64], need_velocity: bool = False
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None, NDArray[np.float64]]:
        """Sensor position (m), velocity (m/s) and sensor->body rotation at times ``t``.

        The rotation includes the correction's attitude term (``R = R_q @ A``), so the
        look vector of a sensor-frame direction ``u`` is ``R @ u``.
        """
        corr = self._correction
        eph = self._ephemeris
        pos = eph.position(t)
        vel = eph.velocity(t) if need_velocity or corr.has_position else None
        if corr.has_position and vel is not None:
            radial = pos / np.linalg.norm(pos, axis=1, keepdims=True)
            cross = np.cross(pos, vel)
            cross /= np.linalg.norm(cross, axis=1, keepdims=True)
            in_track = np.cross(cross, radial)
            a_time = (t - eph.t0_position)[:, None]
            rates = (
                np.array([corr.in_track_rate_m, corr.cross_track_rate_m, corr.radial_rate_m])
                / self.half_time_s
            )
            biases = np.array([corr.in_track_m, corr.cross_track_m, corr.radial_m])
            d = biases[None, :] + rates[None, :] * a_time
            vel = vel + in_track * rates[0] + cross * rates[1] + radial * rates[2]
            pos = pos + in_track * d[:, :1] + cross * d[:, 1:2] + radial * d[:, 2:3]
        rot = eph.rotation(t)
        if corr.has_attitude:
            rot = rot @ self._attitude_correction(t)
        return pos, vel, rot

    def _attitude_correction(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        """Port of usgscsm's ``calculateAttitudeCorrection`` at times ``t``, shape ``(M, 3, 3)``."""
        c = self._correction
        n = (np.asarray(t, dtype=np.float64) - self._ephemeris.t0_pointing) / self.half_time_s
        n2 = n * n
        omega = (c.omega_m + c.omega_rate_m * n + c.omega_accel_m * n2) / self.flying_height_m
        phi = (c.phi_m + c.phi_rate_m * n + c.phi_accel_m * n2) / self.flying_height_m
        kappa = (c.kappa_m + c.kappa_rate_m * n + c.kappa_accel_m * n2) / self.half_swath_m
        return euler_matrix(omega, phi, kappa)

    @property
    def _focal_length(self) -> float:
        f = self._isd.focal_length_mm
        return (
            f * (1.0 - self._correction.focal_m / self.half_swath_m)
            if self._correction.focal_m
            else f
        )

    # -- image -> ground ----------------------------------------------------------------

    def _focal_plane(self, sample: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
        """Distorted focal-plane mm of the detector line at image ``sample``."""
        isd = self._isd
        det_sample = sample * isd.detector_sample_summing + isd.starting_detector_sample
        det_line = 0.0 * isd.detector_line_summing + isd.starting_detector_line
        t1 = det_line - isd.detector_center_line - self._itrans_l[0]
        t2 = det_sample - isd.detector_center_sample - self._itrans_s[0]
        (p11, p12), (p21, p22) = self._p
        return p11 * t1 + p12 * t2, p21 * t1 + p22 * t2

    def _rays(
        self, line: NDArray[np.float64], sample: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        t = self.image_time(line)
        pos, _, rot = self._exterior(t)
        dx, dy = self._focal_plane(sample)
        ux, uy = remove_distortion(
            self._isd.distortion_model,
            np.asarray(self._isd.distortion_coefficients),
            dx,
            dy,
            focal_length_mm=self._isd.focal_length_mm,
        )
        look = np.stack([ux, uy, np.full_like(ux, self._focal_length)], axis=-1)
        look *= self._zdir / np.linalg.norm(look, axis=1, keepdims=True)
        return pos, np.einsum("mij,mj->mi", rot, look)

    def _line_sample(
        self, line: ArrayLike, sample: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        li, sa = np.broadcast_arrays(_as_1d(line, "line"), _as_1d(sample, "sample"))
        return li.astype(np.float64), sa.astype(np.float64)

    def sensor_state(self, line: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Sensor position and velocity when image lines were acquired.

        Args:
            line: Line coordinates, any shape.

        Returns:
            ``(position, velocity)``: body-fixed metres and metres per second, each of
            shape ``(M, 3)``, including the correction.
        """
        pos, vel, _ = self._exterior(self.image_time(line), need_velocity=True)
        return pos, vel if vel is not None else np.zeros_like(pos)

    def sensor_position(self, line: ArrayLike) -> NDArray[np.float64]:
        """Body-fixed sensor position (m) when image lines were acquired, shape ``(M, 3)``."""
        return self._exterior(self.image_time(line))[0]

    def look_direction(self, line: ArrayLike, sample: ArrayLike) -> NDArray[np.float64]:
        """Unit look vectors (from the sensor towards the ground) of image points.

        Args:
            line: Line coordinates.
            sample: Sample coordinates (broadcast with ``line``).

        Returns:
            Body-fixed unit vectors, shape ``(M, 3)`` (usgscsm's
            ``imageToRemoteImagingLocus`` direction).
        """
        return self._rays(*self._line_sample(line, sample))[1]

    def image_to_ground(
        self,
        line: ArrayLike,
        sample: ArrayLike,
        terrain: Terrain | float = 0.0,
        *,
        ccd: str | None = None,
        on_miss: OnMiss = "raise",
    ) -> NDArray[np.float64]:
        """Intersect the rays of image points with a height surface or a terrain.

        Args:
            line: Line coordinates (first pixel centre at 0.5).
            sample: Sample coordinates, broadcast with ``line``.
            terrain: A height in metres above the camera's ellipsoid, a
                :class:`~planetref.camera.base.ConstantHeight`, or any
                :class:`~planetref.camera.base.Terrain` (intersected by
                :func:`~planetref.geometry.terrain.intersect_terrain`).
            ccd: Must be ``None`` or the camera's only CCD name.
            on_miss: ``"raise"`` a :class:`~planetref.errors.GeometryError` when a ray
                misses (or meets the surface only behind the sensor), or give NaN rows.

        Returns:
            Body-fixed XYZ in metres, shape ``(M, 3)``.

        Raises:
            GeometryError: A ray misses and ``on_miss == "raise"``.
            InputError: Bad arguments.
        """
        self._check_ccd(ccd)
        if on_miss not in ("raise", "nan"):
            raise InputError(f"on_miss must be 'raise' or 'nan', got {on_miss!r}")
        li, sa = self._line_sample(line, sample)
        origin, look = self._rays(li, sa)
        if isinstance(terrain, (int, float, np.floating, np.integer)):
            terrain = ConstantHeight(self.ellipsoid, float(terrain))
        if not isinstance(terrain, Terrain):
            raise InputError(
                f"terrain must be a height in metres or a Terrain, got {type(terrain).__name__}"
            )
        xyz = intersect_terrain(origin, look, terrain, "nan")
        miss = np.flatnonzero(~np.all(np.isfinite(xyz), axis=1))
        if miss.size and on_miss == "raise":
            i = int(miss[0])
            raise GeometryError(
                f"{self._isd.path or 'CSM camera'}: {miss.size} of {len(li)} image points "
                f"see no ground (first: line {li[i]:.3f}, sample {sa[i]:.3f}): the ray "
                f"misses the surface or meets it only behind the sensor"
            )
        return xyz

    # -- ground -> image ----------------------------------------------------------------

    def detector_offset(
        self, line: NDArray[np.float64], xyz: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Port of usgscsm's ``calcDetectorLineErr``: where the detector sees ``xyz`` at ``line``.

        Public because the adjustment's partials are built on it: the implicit partials of
        ``ground_to_image`` follow from its derivatives along the line and the ground (the
        line that images a point is the root of its line offset), as usgscsm's sensor and
        ground partials do.

        Args:
            line: Image lines (pixel-corner convention), ``(M,)``.
            xyz: Body-fixed points (metres), ``(M, 3)``.

        Returns:
            ``(line_offset, sample, look_z)``: the image-line offset of the point from the
            detector line (0 when the line images it), the image sample it falls on, and
            the sensor-frame depth of the point (<= 0: behind the sensor).
        """
        isd = self._isd
        pos, _, rot = self._exterior(self.image_time(line))
        cam = np.einsum("mji,mj->mi", rot, xyz - pos)
        # Points far outside the field of view (a line guess far from the solution) give
        # huge focal-plane coordinates: the distortion iteration overflows there and falls
        # back to no distortion (as usgscsm does); not a user-facing event.
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            scale = self._focal_length / cam[:, 2]
            fx, fy = cam[:, 0] * scale, cam[:, 1] * scale
            dx, dy = apply_distortion(
                isd.distortion_model,
                np.asarray(isd.distortion_coefficients),
                fx,
                fy,
                focal_length_mm=isd.focal_length_mm,
            )
        il, is_ = self._itrans_l, self._itrans_s
        det_line = il[0] + il[1] * dx + il[2] * dy
        det_sample = is_[0] + is_[1] * dx + is_[2] * dy
        offset = (
            det_line + isd.detector_center_line - isd.starting_detector_line
        ) / isd.detector_line_summing
        sample = (
            det_sample + isd.detector_center_sample - isd.starting_detector_sample
        ) / isd.detector_sample_summing
        return offset, sample, self._zdir * cam[:, 2]

    @cached_property
    def _projective(self) -> tuple[NDArray[np.float64], ...] | None:
        """Port of usgscsm's projective approximation of ground -> image, for initial guesses."""
        nl, ns = self._isd.image_lines, self._isd.image_samples
        u = np.repeat([0.0, 0.5, 1.0], 3) * nl
        v = np.tile([0.0, 0.5, 1.0], 3) * ns
        origin, look = self._rays(u, v)
        s = ray_ellipsoid_intersection(origin, look, self.ellipsoid, 0.0)
        # Rays that miss the body still give points at the closest approach to it.
        s = np.where(np.isfinite(s), s, -np.sum(origin * look, axis=1))
        pts = np.concatenate([origin + s[:, None] * look, origin + (0.99 * s)[:, None] * look])
        lines, samples = np.tile(u, 2), np.tile(v, 2)
        center = pts.mean(axis=0)
        scale = float(np.max(np.std(pts, axis=0))) or 1.0
        x = (pts - center) / scale
        coefs = []
        for target in (lines, samples):
            a = np.column_stack([np.ones(len(x)), x, -target[:, None] * x])
            sol, *_ = np.linalg.lstsq(a, target, rcond=None)
            coefs.append(sol)
        if not all(np.all(np.isfinite(c)) for c in coefs):
            return None
        return center, np.array(scale), coefs[0], coefs[1]

    def _initial_lines(self, xyz: NDArray[np.float64]) -> NDArray[np.float64]:
        nl = self._isd.image_lines
        guess = np.full(len(xyz), nl / 2.0)
        proj = self._projective
        if proj is not None:
            center, scale, cl, _ = proj
            x = (xyz - center) / scale
            with np.errstate(invalid="ignore", divide="ignore"):
                g = (cl[0] + x @ cl[1:4]) / (1.0 + x @ cl[4:7])
            guess = np.where(np.isfinite(g), np.clip(g, -nl, 2.0 * nl), guess)
        return guess

    def _solve_lines(
        self, xyz: NDArray[np.float64], line0: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Secant iterations on the detector line offset (usgscsm's groundToImage)."""
        nl = float(self._isd.image_lines)
        l0 = line0.copy()
        g0 = self.detector_offset(l0, xyz)[0]
        l1 = l0 + 0.1
        g1 = self.detector_offset(l1, xyz)[0]
        done = np.abs(g1) < _G2I_TOLERANCE_PX
        for _ in range(40):
            act = np.flatnonzero(~done & np.isfinite(g1) & np.isfinite(g0))
            if act.size == 0:
                break
            with np.errstate(invalid="ignore", divide="ignore"):
                step = -g1[act] * (l1[act] - l0[act]) / (g1[act] - g0[act])
            step = np.where(np.isfinite(step), step, g1[act])
            step = np.clip(step, -nl, nl)
            l2 = l1[act] + step
            g2 = self.detector_offset(l2, xyz[act])[0]
            l0[act], g0[act] = l1[act], g1[act]
            l1[act], g1[act] = l2, g2
            done[act] = np.abs(g2) < _G2I_TOLERANCE_PX
        bad = np.flatnonzero(~done)
        if bad.size:
            l1[bad], done[bad] = self._bracket_lines(xyz[bad])
        return l1, done

    def _bracket_lines(
        self, xyz: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Fallback: scan lines for a sign change of the offset, then refine it.

        The grid spans half an image before and after the image (65 lines); the root
        is refined by safeguarded secant steps (:mod:`planetref.geometry.roots`) and
        accepted where the offset is below ``_G2I_TOLERANCE_PX``.
        """
        nl = float(self._isd.image_lines)

        def residual(x: NDArray[np.float64], rows: NDArray[np.intp]) -> NDArray[np.float64]:
            return self.detector_offset(x, xyz[rows])[0]

        bracket = bracket_first_sign_change(
            residual, np.linspace(-0.5 * nl, 1.5 * nl, 65), len(xyz)
        )
        line = refine_bracketed(
            bracket,
            residual=residual,
            xtol=1e-12,
            ftol=_G2I_TOLERANCE_PX,
            max_iter=200,
            stop_at_ftol=True,
        )
        return line, np.isfinite(line)

    def ground_to_image(self, xyz: ArrayLike, *, ccd: str | None = None) -> ImagePoints:
        """Project body-fixed points into the image (usgscsm's ``groundToImage``).

        The image line is found by secant iterations on the detector-line offset of the
        point (falling back to a bracketing search), to better than 1e-9 pixel; the
        sample then follows from the focal plane. Points outside the image are projected
        by extrapolating the line-time table and the ephemeris as usgscsm does and come
        back with ``in_image`` False; their accuracy degrades far from the image.

        Args:
            xyz: Body-fixed points in metres, shape ``(M, 3)`` or ``(3,)``.
            ccd: Must be ``None`` or the camera's only CCD name.

        Returns:
            :class:`~planetref.camera.base.ImagePoints`; ``valid`` is False (and line and
            sample NaN) where the point is behind the sensor, not finite, or no line
            converged.
        """
        self._check_ccd(ccd)
        x = np.atleast_2d(np.asarray(xyz, dtype=np.float64))
        if x.ndim != 2 or x.shape[1] != 3:
            raise InputError(f"xyz must have shape (M, 3), got {np.shape(xyz)}")
        finite = np.all(np.isfinite(x), axis=1)
        xs = np.where(finite[:, None], x, 0.0)
        line, ok = self._solve_lines(xs, self._initial_lines(xs))
        line = np.where(ok, line, self._isd.image_lines / 2.0)
        offset, sample, depth = self.detector_offset(line, xs)
        line = line + offset
        valid = (
            ok
            & finite
            & (depth > 0)
            & np.isfinite(line)
            & np.isfinite(sample)
            & (np.abs(offset) < _G2I_VALID_PX)
        )
        line = np.where(valid, line, np.nan)
        sample = np.where(valid, sample, np.nan)
        nl, ns = self.image_size()
        with np.errstate(invalid="ignore"):
            in_image = valid & (line >= 0) & (line < nl) & (sample >= 0) & (sample < ns)
        return ImagePoints(line, sample, valid, in_image)
