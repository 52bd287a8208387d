"""Measurements on simulated cameras: initial geolocation errors, consistency, checkpoints.

Everything here goes through the public camera API
(:meth:`~planetref.camera.linescan.LineScanCamera.image_to_ground` with the truth DEM as
a :class:`~planetref.camera.base.Terrain`, and ``ground_to_image``), independently of
the renderer's own ray code, so the numbers it reports are measured, not assumed.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from planetref.arrays import F64
from planetref.camera.linescan import LineScanCamera
from planetref.geometry.geodesy import xyz_to_lonlat
from planetref.raster.dem import GridTerrain

__all__ = ["checkpoints", "measure_consistency", "measure_initial_errors", "pixel_grid"]


def pixel_grid(n_lines: int, n_samples: int, n: int) -> tuple[F64, F64]:
    """``n x n`` pixel centres spread over an image (first and last pixels included)."""
    lines = np.linspace(0.5, n_lines - 0.5, n)
    samples = np.linspace(0.5, n_samples - 0.5, n)
    ll, ss = np.meshgrid(lines, samples, indexing="ij")
    return ll.ravel(), ss.ravel()


def _stats(v: F64) -> dict[str, float]:
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"mean": float("nan"), "rms": float("nan"), "max": float("nan")}
    return {
        "mean": float(np.mean(v)),
        "rms": float(np.sqrt(np.mean(v * v))),
        "max": float(np.max(np.abs(v))),
    }


def measure_initial_errors(
    truth: LineScanCamera, initial: LineScanCamera, terrain: GridTerrain, frame: F64, n: int
) -> dict[str, Any]:
    """How far the initial camera is from the truth, over all CCDs.

    For an ``n x n`` grid of pixel centres per CCD, the true ground point ``P`` (truth
    camera, truth DEM) and the initial camera's ground point ``Q`` (same pixel, truth
    DEM) are compared in the orbit frame at the strip centre (along, cross, up), and
    ``P`` is projected into the initial camera to get the image-space error.

    Args:
        truth: True camera.
        initial: Initial camera.
        terrain: Truth DEM.
        frame: Orbit frame ``(3, 3)`` (columns along, cross, up; body-fixed).
        n: Grid size per axis.

    Returns:
        ``ground_m`` (``along``/``cross``/``up``/``horizontal`` statistics: mean, rms,
        max) and ``image_px`` (``line``/``sample``/``distance``).
    """
    d_all, dl_all, ds_all = [], [], []
    for c in truth.ccds:
        lines, samples = pixel_grid(c.n_lines, c.n_samples, n)
        p = truth.image_to_ground(lines, samples, terrain, ccd=c.name, on_miss="nan")
        q = initial.image_to_ground(lines, samples, terrain, ccd=c.name, on_miss="nan")
        d_all.append((q - p) @ frame)
        ip = initial.ground_to_image(p, ccd=c.name)
        dl_all.append(ip.line - lines)
        ds_all.append(ip.sample - samples)
    d = np.concatenate(d_all)
    dl, ds = np.concatenate(dl_all), np.concatenate(ds_all)
    return {
        "ground_m": {
            "along": _stats(d[:, 0]),
            "cross": _stats(d[:, 1]),
            "up": _stats(d[:, 2]),
            "horizontal": _stats(np.hypot(d[:, 0], d[:, 1])),
        },
        "image_px": {
            "line": _stats(dl),
            "sample": _stats(ds),
            "distance": _stats(np.hypot(dl, ds)),
        },
        "n_points": int(np.count_nonzero(np.isfinite(d[:, 0]))),
    }


def measure_consistency(
    camera: LineScanCamera, terrain: GridTerrain, n: int, rng: np.random.Generator
) -> dict[str, float]:
    """Round trip pixel -> truth DEM -> pixel, and the renderer's rays against the camera's.

    Args:
        camera: The true camera.
        terrain: Truth DEM.
        n: Random pixels per CCD.
        rng: Random generator (pixel positions).

    Returns:
        ``roundtrip_max_px`` (largest image distance after ``image_to_ground`` with the
        truth DEM and ``ground_to_image``) and ``render_ray_max_m`` (largest distance
        between ``image_to_ground`` and the renderer's ray intersection, the same pixels).
    """
    from planetref.simulate.render import corner_rays

    worst_px, worst_m = 0.0, 0.0
    for c in camera.ccds:
        lines = rng.uniform(0.0, c.n_lines, n)
        samples = rng.uniform(0.0, c.n_samples, n)
        p = camera.image_to_ground(lines, samples, terrain, ccd=c.name)
        ip = camera.ground_to_image(p, ccd=c.name)
        worst_px = max(worst_px, float(np.max(np.hypot(ip.line - lines, ip.sample - samples))))
        for i in range(n):
            o, d = corner_rays(camera, c.name, lines[i : i + 1], samples[i : i + 1])
            hit = terrain.intersect_rays(o, d.reshape(-1, 3))
            worst_m = max(worst_m, float(np.linalg.norm(hit.xyz[0] - p[i])))
    return {"roundtrip_max_px": worst_px, "render_ray_max_m": worst_m}


def checkpoints(
    camera: LineScanCamera, terrain: GridTerrain, strip_id: str, n: int, rng: np.random.Generator
) -> list[dict[str, Any]]:
    """Random true image/ground correspondences of every CCD of a strip.

    Returns:
        Rows with ``strip, ccd, line, sample, x_m, y_m, z_m, lon_deg, lat_deg, height_m``
        (pixel convention of planetref; planetocentric lon/lat; height above the body).
    """
    rows: list[dict[str, Any]] = []
    for c in camera.ccds:
        lines = rng.uniform(0.0, c.n_lines, n)
        samples = rng.uniform(0.0, c.n_samples, n)
        p = camera.image_to_ground(lines, samples, terrain, ccd=c.name)
        lon, lat, h = xyz_to_lonlat(p, camera.ellipsoid)
        for i in range(n):
            rows.append(
                {
                    "strip": strip_id,
                    "ccd": c.name,
                    "line": lines[i],
                    "sample": samples[i],
                    "x_m": p[i, 0],
                    "y_m": p[i, 1],
                    "z_m": p[i, 2],
                    "lon_deg": lon[i],
                    "lat_deg": lat[i],
                    "height_m": h[i],
                }
            )
    return rows
