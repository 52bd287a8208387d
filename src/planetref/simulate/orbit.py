"""Truth and initial line-scan cameras of a strip, from orbit geometry.

Orbit
-----
A circular orbit of radius ``R + altitude`` around the Mars sphere. At ``t = 0`` (the
strip's centre line) the spacecraft is above the strip centre, and its *body-fixed*
ground track there has the configured heading. With ``orbit.body_rotation`` the orbit
is inertial and Mars turns under it (``omega = 350.89198226 deg/day`` about +Z): the
inertial velocity at ``t = 0`` is solved so that the body-fixed velocity points along
the heading, and positions are rotated into the body-fixed frame at every time.

Orbit frame and attitude
------------------------
The orbit frame ``L(t)`` has x along the body-fixed velocity (made horizontal), z up
(radial) and ``y = z x x`` (to the left of the track). The camera's rotation
(camera -> body-fixed) is ``L(t) @ P @ J(t)`` for the truth and ``L(t) @ P @ E(t)``
for the initial camera, where ``P`` is the strip's fixed pointing, ``J`` the jitter
and ``E`` the attitude bias + drift; each of them is ``Rx(roll) @ Ry(pitch) @
Rz(yaw)`` with right-handed rotations about the orbit-frame axes (a positive roll
turns the boresight, the camera's -z axis, towards +y, the left of the track).
These rotations are converted to the phi/omega/kappa node angles of
:class:`~planetref.camera.linescan.LineScanCamera` relative to ``R0 = L(0)``, and the
camera interpolates them (Lagrange, ``orbit.interpolation_order``) between nodes:
the cameras written to disk *are* the truth; the analytic orbit only generates them.

Time runs from ``-n_lines/2 * period`` (line 0) and is 0 at the centre line.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from planetref.arrays import F64
from planetref.camera.jitter import interpolation_limit_hz, node_nyquist_hz
from planetref.camera.linescan import (
    CcdGeometry,
    InteriorOrientation,
    LineRateTable,
    LineScanCamera,
)
from planetref.camera.orbit import MARS_GM_M3_S2, ccd_row
from planetref.errors import InputError
from planetref.geometry.geodesy import MARS_IAU2015_SPHERE, Ellipsoid, lonlat_to_xyz
from planetref.geometry.rotations import axis_rotation
from planetref.simulate.config import JitterRandomConfig, SimulationConfig, StripConfig
from planetref.simulate.realism import TruthMismatchConfig

__all__ = [
    "MARS_ROTATION_RAD_S",
    "CircularOrbit",
    "StripCameras",
    "angles_from_rotation",
    "build_strip_cameras",
    "random_jitter",
]

log = logging.getLogger(__name__)
JitterTerm = tuple[str, float, float, float]
_AXES = ("roll", "pitch", "yaw")

MARS_ROTATION_RAD_S = math.radians(350.89198226) / 86400.0
"""Sidereal rotation rate of Mars (IAU 2015), rad/s."""


def _rpy(roll: F64, pitch: F64, yaw: F64) -> F64:
    return axis_rotation(0, roll) @ axis_rotation(1, pitch) @ axis_rotation(2, yaw)


def angles_from_rotation(m: F64) -> F64:
    """Inverse of :func:`planetref.geometry.rotations.rotation_matrix`.

    Args:
        m: Rotations ``R_phi(Y) @ R_omega(X) @ R_kappa(Z)``, shape ``(..., 3, 3)``.

    Returns:
        ``(phi, omega, kappa)`` in radians, shape ``(..., 3)`` (``|omega| < pi/2``).
    """
    m = np.asarray(m, dtype=np.float64)
    omega = -np.arcsin(np.clip(m[..., 1, 2], -1.0, 1.0))
    kappa = np.arctan2(m[..., 1, 0], m[..., 1, 1])
    phi = np.arctan2(-m[..., 0, 2], m[..., 2, 2])
    return np.stack([phi, omega, kappa], axis=-1)


@dataclass(frozen=True)
class CircularOrbit:
    """A circular orbit seen from the rotating body (see the module docstring).

    Attributes:
        lat_deg: Planetocentric latitude of the sub-spacecraft point at ``t = 0``.
        lon_deg: East longitude of that point.
        heading_deg: Body-fixed ground-track azimuth there (degrees from north).
        altitude_m: Altitude above the sphere (m).
        body_rotation: Whether the body rotates under the orbit.
        ellipsoid: The body (a sphere is assumed for the orbit radius).
        gm_m3_s2: Gravitational parameter.
    """

    lat_deg: float
    lon_deg: float
    heading_deg: float
    altitude_m: float
    body_rotation: bool = True
    ellipsoid: Ellipsoid = MARS_IAU2015_SPHERE
    gm_m3_s2: float = MARS_GM_M3_S2
    _state: tuple[F64, F64, float, float] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        r = self.ellipsoid.semi_major_m + self.altitude_m
        v = math.sqrt(self.gm_m3_s2 / r)
        up = lonlat_to_xyz(self.lon_deg, self.lat_deg, 0.0, self.ellipsoid)
        up = up / np.linalg.norm(up)
        lon = math.radians(self.lon_deg)
        east = np.array([-math.sin(lon), math.cos(lon), 0.0])
        north = np.cross(up, east)
        h = math.radians(self.heading_deg)
        fwd = math.cos(h) * north + math.sin(h) * east
        w = MARS_ROTATION_RAD_S if self.body_rotation else 0.0
        # Inertial velocity = body-fixed velocity (s * fwd) + w z x r (eastward).
        spin = w * r * math.cos(math.radians(self.lat_deg))
        b = spin * math.sin(h)
        s = -b + math.sqrt(b * b - (spin * spin - v * v))
        v_in = s * fwd + spin * east
        q = v_in / np.linalg.norm(v_in)
        object.__setattr__(self, "_state", (up * r, q * r, v / r, w))

    @property
    def radius_m(self) -> float:
        """Orbit radius (m)."""
        return self.ellipsoid.semi_major_m + self.altitude_m

    def position(self, t: F64) -> F64:
        """Body-fixed positions (m) at times ``t`` (s), shape ``(M, 3)``."""
        p0, q0, n, w = self._state
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        pi = np.cos(n * t)[:, None] * p0 + np.sin(n * t)[:, None] * q0
        return (axis_rotation(2, -w * t) @ pi[..., None])[..., 0]

    def velocity(self, t: F64) -> F64:
        """Body-fixed velocities (m/s) at times ``t`` (s), shape ``(M, 3)``."""
        p0, q0, n, w = self._state
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        vi = n * (-np.sin(n * t)[:, None] * p0 + np.cos(n * t)[:, None] * q0)
        pos = self.position(t)
        spin = axis_rotation(2, -w * t)
        return (spin @ vi[..., None])[..., 0] - w * np.cross([0.0, 0.0, 1.0], pos)

    def frame(self, t: F64) -> F64:
        """Orbit frames ``L(t)`` (columns x along, y left, z up; body-fixed), ``(M, 3, 3)``."""
        pos, vel = self.position(t), self.velocity(t)
        z = pos / np.linalg.norm(pos, axis=-1, keepdims=True)
        x = vel - np.sum(vel * z, axis=-1, keepdims=True) * z
        x /= np.linalg.norm(x, axis=-1, keepdims=True)
        y = np.cross(z, x)
        return np.stack([x, y, z], axis=-1)

    def ground_speed(self) -> float:
        """Speed (m/s) of the sub-spacecraft point on the sphere at ``t = 0``."""
        v = self.velocity(np.zeros(1))[0]
        return float(np.linalg.norm(v) * self.ellipsoid.semi_major_m / self.radius_m)


@dataclass(frozen=True)
class StripCameras:
    """The cameras of one strip.

    Attributes:
        strip: The strip's configuration.
        truth: The true camera (with jitter).
        initial: The initial (navigation) camera, biased and drifting.
        orbit: The orbit that generated them.
        facts: ``focal_length_mm``, ``gsd_m``, ``line_period_s``, ``ground_speed_m_s``,
            ``altitude_m``, ``duration_s``.
        jitter: ``(axis, amplitude_urad, frequency_hz, phase_rad)`` of each component.
        jitter_random: The same for the sinusoids of the band-limited random part
            (:func:`random_jitter`; empty when off).
        mismatch: The truth's drawn model mismatch (per-CCD placement errors,
            oscillation phases, true and nominal line periods).
    """

    strip: StripConfig
    truth: LineScanCamera
    initial: LineScanCamera
    orbit: CircularOrbit
    facts: dict[str, float]
    jitter: tuple[JitterTerm, ...]
    mismatch: dict[str, Any] = field(default_factory=dict)
    jitter_random: tuple[JitterTerm, ...] = ()


def random_jitter(
    cfg: JitterRandomConfig, duration_s: float, rng: np.random.Generator
) -> tuple[JitterTerm, ...]:
    """The sinusoids of the band-limited random jitter (see :class:`JitterRandomConfig`).

    Args:
        cfg: The random part's settings.
        duration_s: The strip's duration (s); sets the number of sinusoids per axis.
        rng: The strip's random generator (drawn from only for axes with an rms > 0).

    Returns:
        ``(axis, amplitude_urad, frequency_hz, phase_rad)`` per sinusoid, roll first.
    """
    out: list[JitterTerm] = []
    band = cfg.max_frequency_hz - cfg.min_frequency_hz
    n = int(min(4096, max(16, math.ceil(2.0 * band * duration_s))))
    width = band / n
    for axis, rms in zip(_AXES, cfg.rms_urad, strict=True):
        if rms <= 0.0:
            continue
        freq = cfg.min_frequency_hz + (np.arange(n) + rng.uniform(0.0, 1.0, n)) * width
        phase = rng.uniform(0.0, 2.0 * np.pi, n)
        amp = freq ** (0.5 * cfg.psd_slope)
        amp *= rms * math.sqrt(2.0) / np.sqrt(np.sum(amp**2))  # sqrt(sum a^2 / 2) = rms
        out += [
            (axis, float(a), float(f), float(p)) for a, f, p in zip(amp, freq, phase, strict=True)
        ]
    return tuple(out)


def _check_node_spacing(
    cfg: SimulationConfig, period_s: float, terms: tuple[JitterTerm, ...]
) -> dict[str, float]:
    """The truth nodes' frequency limits; refuses jitter above their Nyquist frequency.

    Raises:
        InputError: A jitter frequency above the Nyquist frequency of
            ``orbit.truth_node_spacing_lines`` (naming the setting and the largest
            spacing that would carry it).
    """
    orb = cfg.orbit
    spacing = orb.truth_node_spacing_lines
    nyquist = node_nyquist_hz(period_s, spacing)
    limit_1 = interpolation_limit_hz(period_s, spacing, orb.interpolation_order, 0.01)
    limit_5 = interpolation_limit_hz(period_s, spacing, orb.interpolation_order, 0.05)
    f_max = max((f for _, a, f, _ in terms if a > 0.0), default=0.0)
    if cfg.jitter_random.enabled:
        f_max = max(f_max, cfg.jitter_random.max_frequency_hz)
    if f_max > nyquist:
        most = int(1.0 / (2.0 * f_max * period_s))
        raise InputError(
            f"jitter up to {f_max:g} Hz is above the Nyquist frequency {nyquist:.3g} Hz of "
            f"the truth's nodes every {spacing} lines ({1.0 / period_s:.4g} lines/s): set "
            f"orbit.truth_node_spacing_lines to at most {max(most, 1)} "
            f"({max(int(limit_5 / f_max * spacing), 1)} to keep it within 5 %)",
            field="orbit.truth_node_spacing_lines",
        )
    if f_max > limit_5:
        log.warning(
            "jitter up to %g Hz: the truth's nodes every %d lines (orbit."
            "truth_node_spacing_lines) carry it with more than 5 %% interpolation error "
            "(within 5 %% up to %.3g Hz, Nyquist %.3g Hz)",
            f_max,
            spacing,
            limit_5,
            nyquist,
        )
    return {
        "truth_node_nyquist_hz": nyquist,
        "truth_node_1pct_hz": limit_1,
        "truth_node_5pct_hz": limit_5,
        "jitter_max_frequency_hz": f_max,
    }


def _strip_centre(
    cfg: SimulationConfig, strip: StripConfig, heading_deg: float
) -> tuple[float, float]:
    """Lon/lat of the strip's centre, offset from the site along/across the track."""
    ell = MARS_IAU2015_SPHERE
    lat, lon = math.radians(cfg.site.lat_deg), math.radians(cfg.site.lon_deg)
    up = np.array([math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)])
    east = np.array([-math.sin(lon), math.cos(lon), 0.0])
    north = np.cross(up, east)
    h = math.radians(heading_deg)
    fwd = math.cos(h) * north + math.sin(h) * east
    left = np.cross(up, fwd)
    offset = strip.along_offset_m * fwd + strip.cross_offset_m * left
    dist = float(np.linalg.norm(offset))
    if dist == 0:
        return cfg.site.lon_deg, cfg.site.lat_deg
    ang = dist / ell.semi_major_m
    p = math.cos(ang) * up + math.sin(ang) * offset / dist
    return math.degrees(math.atan2(p[1], p[0])), math.degrees(math.asin(p[2]))


def _node_lines(n_lines: int, spacing: int, order: int) -> F64:
    margin = max(order, 4) * spacing
    return np.arange(-margin, n_lines + margin + 0.5 * spacing, spacing, dtype=np.float64)


def _true_ccds(
    ccds: tuple[CcdGeometry, ...], cfg: TruthMismatchConfig, rng: np.random.Generator
) -> tuple[tuple[CcdGeometry, ...], list[dict[str, float]]]:
    """The CCDs' true placement: nominal ones moved, rotated about their centre, scaled."""
    out, facts = [], []
    for c in ccds:
        dx, dy = rng.standard_normal(2) * cfg.ccd_offset_px
        rot = float(rng.standard_normal()) * cfg.ccd_rotation_urad * 1e-6
        scale = float(rng.standard_normal()) * cfg.ccd_scale_ppm * 1e-6
        facts.append(
            {
                "ccd": c.name,
                "offset_along_px": float(dx),
                "offset_across_px": float(dy),
                "rotation_urad": rot * 1e6,
                "scale_ppm": scale * 1e6,
            }
        )
        if dx == 0.0 and dy == 0.0 and rot == 0.0 and scale == 0.0:
            out.append(c)
            continue
        half = 0.5 * c.n_samples * c.pixel_pitch_mm
        cx = c.x_mm + half * math.sin(c.angle_rad) + dx * c.pixel_pitch_mm
        cy = c.y_mm + half * math.cos(c.angle_rad) + dy * c.pixel_pitch_mm
        angle = c.angle_rad + rot
        pitch = c.pixel_pitch_mm * (1.0 + scale)
        h = 0.5 * c.n_samples * pitch
        out.append(
            replace(
                c,
                pixel_pitch_mm=pitch,
                x_mm=cx - h * math.sin(angle),
                y_mm=cy - h * math.cos(angle),
                angle_rad=angle,
            )
        )
    return tuple(out), facts


def _lens_distortion(
    nominal: tuple[CcdGeometry, ...],
    ccds: tuple[CcdGeometry, ...],
    cfg: TruthMismatchConfig,
    rng: np.random.Generator,
) -> tuple[tuple[CcdGeometry, ...], dict[str, float]]:
    """The truth's lens distortion (see :class:`TruthMismatchConfig`) on every CCD.

    The decentering direction is drawn last from ``rng`` (only when decentering is on),
    so turning distortion on does not change the other draws.
    """
    if cfg.radial_k1_px == 0.0 and cfg.radial_k2_px == 0.0 and cfg.decentering_px == 0.0:
        return ccds, {}
    ends = [c.focal_plane(np.array([0.0, float(c.n_samples)])) for c in nominal]
    r_max = max(float(np.max(np.hypot(x, y))) for x, y in ends)
    pitch = nominal[0].pixel_pitch_mm
    a = float(rng.uniform(0.0, 2.0 * np.pi)) if cfg.decentering_px > 0.0 else 0.0
    dec = cfg.decentering_px * pitch / (3.0 * r_max**2)  # 3 p r^2 at the row's end
    coeffs = (
        cfg.radial_k1_px * pitch / r_max**3,
        cfg.radial_k2_px * pitch / r_max**5,
        dec * math.cos(a),
        dec * math.sin(a),
    )
    lens = {
        "k1_per_mm2": coeffs[0],
        "k2_per_mm4": coeffs[1],
        "p1_per_mm": coeffs[2],
        "p2_per_mm": coeffs[3],
        "field_edge_mm": r_max,
        "decentering_direction_rad": a,
    }
    return tuple(replace(c, distortion=coeffs) for c in ccds), lens


def build_strip_cameras(
    cfg: SimulationConfig,
    strip: StripConfig,
    rng: np.random.Generator,
    mismatch_rng: np.random.Generator | None = None,
) -> StripCameras:
    """The truth and initial cameras of a strip.

    Args:
        cfg: The simulation config (camera, orbit, jitter, initial errors, truth
            mismatch).
        strip: The strip.
        rng: Random generator of this strip (jitter phases).
        mismatch_rng: Random generator of the truth's model mismatch (CCD placement,
            oscillation phases); a fixed default stream when None.

    Returns:
        The strip's cameras and facts.
    """
    cam_cfg, orb = cfg.camera, cfg.orbit
    heading = orb.heading_deg if strip.heading_deg is None else strip.heading_deg
    lon, lat = _strip_centre(cfg, strip, heading)
    orbit = CircularOrbit(lat, lon, heading, orb.altitude_m, orb.body_rotation)
    focal = cam_cfg.pixel_pitch_mm * orb.altitude_m / cam_cfg.gsd_m
    ground_speed = orbit.ground_speed()
    period = cam_cfg.line_period_s or cam_cfg.gsd_m / ground_speed
    n_lines = cam_cfg.n_lines
    rates = LineRateTable(((0.0, -0.5 * n_lines * period, period),))
    mm = cfg.truth_mismatch
    true_period = period * (1.0 + mm.line_rate_error_ppm * 1e-6)
    true_rates = LineRateTable(((0.0, -0.5 * n_lines * true_period, true_period),))
    mrng = mismatch_rng if mismatch_rng is not None else np.random.default_rng(0)
    ccds = ccd_row(
        cam_cfg.n_ccds,
        cam_cfg.n_samples,
        n_lines,
        cam_cfg.pixel_pitch_mm,
        overlap_px=cam_cfg.overlap_samples,
        stagger_mm=cam_cfg.ccd_stagger_mm,
    )
    r0 = orbit.frame(np.zeros(1))[0]
    pointing = _rpy(*np.radians(np.asarray(strip.pointing_deg, dtype=np.float64)))

    jitter = tuple(
        (j.axis, j.amplitude_urad, j.frequency_hz, float(rng.uniform(0, 2 * np.pi)))
        for j in cfg.jitter
    )
    duration = n_lines * period
    # After the sinusoids' phases: turning the random part on changes nothing else.
    jitter_rand = random_jitter(cfg.jitter_random, duration, rng)
    node_facts = _check_node_spacing(cfg, true_period, jitter + jitter_rand)

    def jitter_angles(t: F64) -> F64:
        out = np.zeros((len(t), 3))
        for terms in (jitter, jitter_rand):
            for axis, amp, freq, ph in terms:
                k = _AXES.index(axis)
                out[:, k] += amp * 1e-6 * np.sin(2 * np.pi * freq * t + ph)
        return out

    osc_period = mm.oscillation_period_s or duration / 3.0
    osc_phase = mrng.uniform(0.0, 2.0 * np.pi, 6)
    osc_amp = np.concatenate(
        [np.asarray(mm.position_oscillation_m), 1e-6 * np.asarray(mm.attitude_oscillation_urad)]
    )

    def oscillation(t: F64) -> F64:
        return osc_amp * np.sin(2.0 * np.pi * t[:, None] / osc_period + osc_phase)

    def nodes_for(lines: F64, attitude: F64, position_offset: F64, rt: LineRateTable) -> F64:
        t = rt.time(lines)
        frames = orbit.frame(t)
        rot = frames @ pointing @ _rpy(attitude[:, 0], attitude[:, 1], attitude[:, 2])
        rel = np.einsum("ji,mjk->mik", r0, rot)  # R0^T @ R
        nodes = np.empty((len(lines), 6))
        nodes[:, :3] = orbit.position(t) + np.einsum("mij,mj->mi", frames, position_offset)
        nodes[:, 3:] = angles_from_rotation(rel)
        return nodes

    order = orb.interpolation_order
    t_lines = _node_lines(n_lines, orb.truth_node_spacing_lines, order)
    t_truth = true_rates.time(t_lines)
    osc = oscillation(t_truth)
    truth_nodes = nodes_for(t_lines, jitter_angles(t_truth) + osc[:, 3:], osc[:, :3], true_rates)
    true_ccds, ccd_facts = _true_ccds(ccds, mm, mrng)
    true_ccds, lens = _lens_distortion(ccds, true_ccds, mm, mrng)
    truth = LineScanCamera(
        ellipsoid=MARS_IAU2015_SPHERE,
        frame_rotation=r0,
        line_rates=true_rates,
        node_lines=t_lines,
        nodes=truth_nodes,
        interior=InteriorOrientation(focal_length_mm=focal),
        ccds=true_ccds,
        interpolation_order=order,
        name=f"{strip.id} (truth)",
    )

    e = cfg.initial_errors
    i_lines = _node_lines(n_lines, orb.initial_node_spacing_lines, order)
    t_init = rates.time(i_lines)[:, None]
    att = (
        np.asarray(e.attitude_bias_urad) + np.asarray(e.attitude_drift_urad_per_s) * t_init
    ) * 1e-6
    pos = np.asarray(e.position_bias_m) + np.asarray(e.position_drift_m_per_s) * t_init
    init_nodes = nodes_for(i_lines, att, pos, rates)
    initial = LineScanCamera(
        ellipsoid=MARS_IAU2015_SPHERE,
        frame_rotation=r0,
        line_rates=rates,
        node_lines=i_lines,
        nodes=init_nodes,
        interior=InteriorOrientation(
            focal_length_mm=focal * (1.0 + e.focal_length_error_ppm * 1e-6)
        ),
        ccds=ccds,
        interpolation_order=order,
        name=f"{strip.id} (initial)",
    )
    facts = {
        "focal_length_mm": focal,
        "gsd_m": cam_cfg.gsd_m,
        "line_period_s": period,
        "ground_speed_m_s": ground_speed,
        "altitude_m": orb.altitude_m,
        "duration_s": n_lines * period,
        "centre_lon_deg": lon,
        "centre_lat_deg": lat,
        "heading_deg": heading,
        "true_line_period_s": true_period,
        "oscillation_period_s": osc_period,
        **node_facts,
    }
    return StripCameras(
        strip=strip,
        truth=truth,
        initial=initial,
        orbit=orbit,
        facts=facts,
        jitter=jitter,
        jitter_random=jitter_rand,
        mismatch={
            "ccds": ccd_facts,
            "oscillation_phase_rad": [float(p) for p in osc_phase],
            "oscillation_period_s": osc_period,
            "true_line_period_s": true_period,
            "nominal_line_period_s": period,
            "lens": lens,
        },
    )
