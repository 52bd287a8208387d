"""Build line-scan cameras from simple orbit geometry (for simulation and tests).

A circular orbit over a sphere or ellipsoid, the spacecraft flying along a great circle
through the point above a given latitude/longitude with a given heading, the camera
looking at nadir with its focal-plane x axis along track.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from planetref.camera.linescan import (
    CcdGeometry,
    InteriorOrientation,
    LineRateTable,
    LineScanCamera,
)
from planetref.errors import InputError
from planetref.geometry.geodesy import MARS_IAU2015_SPHERE, Ellipsoid, lonlat_to_xyz

__all__ = ["MARS_GM_M3_S2", "OrbitGeometry", "ccd_row", "orbit_camera"]

MARS_GM_M3_S2 = 4.282837e13
"""Mars' gravitational parameter (m^3/s^2)."""


@dataclass(frozen=True)
class OrbitGeometry:
    """A circular orbit pass.

    Attributes:
        lat_deg: Planetocentric latitude of the scene centre (degrees).
        lon_deg: East longitude of the scene centre (degrees).
        heading_deg: Ground-track azimuth at the centre, clockwise from north (degrees).
        altitude_m: Altitude above the reference radius (metres).
        gm_m3_s2: Gravitational parameter (sets the orbital speed).
    """

    lat_deg: float
    lon_deg: float
    heading_deg: float = 0.0
    altitude_m: float = 265_000.0
    gm_m3_s2: float = MARS_GM_M3_S2


def ccd_row(
    n_ccds: int,
    n_samples: int,
    n_lines: int,
    pixel_pitch_mm: float,
    overlap_px: int = 0,
    stagger_mm: float = 0.0,
    names: list[str] | None = None,
) -> tuple[CcdGeometry, ...]:
    """CCDs side by side across track, centred on the optical axis.

    Args:
        n_ccds: Number of arrays.
        n_samples: Pixels per array.
        n_lines: Lines of each CCD image.
        pixel_pitch_mm: Pixel size (mm).
        overlap_px: Pixels by which neighbouring arrays overlap across track.
        stagger_mm: Along-track offset of every other array (mm); TDI arrays are staggered.
        names: CCD names (default ``ccd1``, ``ccd2``...).
    """
    if n_ccds < 1 or n_samples < 1 or overlap_px < 0 or overlap_px >= n_samples:
        raise InputError(
            f"bad CCD layout: n_ccds={n_ccds}, n_samples={n_samples}, overlap_px={overlap_px}"
        )
    names = names or [f"ccd{i + 1}" for i in range(n_ccds)]
    width = (n_ccds * n_samples - (n_ccds - 1) * overlap_px) * pixel_pitch_mm
    out = []
    for i in range(n_ccds):
        y0 = -width / 2 + i * (n_samples - overlap_px) * pixel_pitch_mm
        x0 = stagger_mm if i % 2 else 0.0
        out.append(CcdGeometry(names[i], n_lines, n_samples, pixel_pitch_mm, x0, y0))
    return tuple(out)


def orbit_camera(
    orbit: OrbitGeometry,
    *,
    focal_length_mm: float,
    ccds: tuple[CcdGeometry, ...],
    n_nodes: int = 8,
    ellipsoid: Ellipsoid = MARS_IAU2015_SPHERE,
    interpolation_order: int = 4,
    line_period_s: float | None = None,
    node_margin_lines: float = 64.0,
    name: str = "",
    **extra: Any,
) -> tuple[LineScanCamera, dict[str, float]]:
    """A nadir-looking line-scan camera on a circular orbit.

    The orbit frame ``R0`` at the centre time has x along track, y = z x x, z radial up;
    the nodes' ``phi`` follows the orbital rotation (``phi = -omega t``) so the camera
    stays at nadir, ``omega = kappa = 0``. Time is 0 at the centre line.

    Args:
        orbit: The orbit pass.
        focal_length_mm: Focal length (mm).
        ccds: The CCD layout (see :func:`ccd_row`).
        n_nodes: Number of orientation nodes spread over the image lines.
        ellipsoid: The body.
        interpolation_order: Lagrange window size.
        line_period_s: Seconds per line; default: the along-track GSD equals the
            across-track GSD (square pixels at nadir).
        node_margin_lines: Nodes extend this many lines beyond the first and last line.
        name: Camera name.
        **extra: Rejected (typos must not pass silently).

    Returns:
        ``(camera, facts)`` with ``facts`` holding ``gsd_m``, ``ground_speed_m_s``,
        ``line_period_s``, ``orbital_rate_rad_s``.
    """
    if extra:
        raise InputError(f"unknown orbit_camera options: {sorted(extra)}")
    r_surf = ellipsoid.semi_major_m
    r = r_surf + orbit.altitude_m
    v = math.sqrt(orbit.gm_m3_s2 / r)
    w = v / r
    ground_speed = w * r_surf
    pitch = ccds[0].pixel_pitch_mm
    gsd = orbit.altitude_m * pitch / focal_length_mm
    period = line_period_s if line_period_s is not None else gsd / ground_speed
    n_lines = max(c.n_lines for c in ccds)

    g0 = lonlat_to_xyz(orbit.lon_deg, orbit.lat_deg, 0.0, ellipsoid)
    up = g0 / np.linalg.norm(g0)
    lon, _lat = math.radians(orbit.lon_deg), math.radians(orbit.lat_deg)
    east = np.array([-math.sin(lon), math.cos(lon), 0.0])
    north = np.cross(up, east)
    h = math.radians(orbit.heading_deg)
    fwd = math.cos(h) * north + math.sin(h) * east
    side = np.cross(up, fwd)
    r0 = np.stack([fwd, side, up], axis=1)

    t0 = -0.5 * n_lines * period
    rates = LineRateTable(((0.0, t0, period),))
    node_lines = np.linspace(-node_margin_lines, n_lines + node_margin_lines, n_nodes)
    t = rates.time(node_lines)
    pos = r * (np.cos(w * t)[:, None] * up + np.sin(w * t)[:, None] * fwd)
    nodes = np.zeros((n_nodes, 6))
    nodes[:, :3] = pos
    nodes[:, 3] = -w * t
    cam = LineScanCamera(
        ellipsoid=ellipsoid,
        frame_rotation=r0,
        line_rates=rates,
        node_lines=node_lines,
        nodes=nodes,
        interior=InteriorOrientation(focal_length_mm),
        ccds=ccds,
        interpolation_order=interpolation_order,
        name=name,
    )
    facts = {
        "gsd_m": gsd,
        "ground_speed_m_s": ground_speed,
        "line_period_s": period,
        "orbital_rate_rad_s": w,
    }
    return cam, facts
