"""Rays of image observations through any camera, and their least-squares intersection.

Both work with every camera model that implements ``image_to_ground`` (a ray is the
line through the terrain intersections at two heights) and are used to give free points
their starting coordinates and to express check-point errors in metres.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.arrays import F64
from planetref.control.network import Network
from planetref.geometry.geodesy import ray_ellipsoid_intersection, xyz_to_lonlat

__all__ = ["ground_error_m", "rays", "triangulate"]


def rays(
    camera: Any,
    line: F64,
    sample: F64,
    ccd: str | None,
    heights: tuple[float, float] | None = None,
) -> tuple[F64, F64]:
    """Body-fixed rays of image points of any camera, from two terrain intersections.

    Returns:
        ``(point, unit direction)`` per image point, ``(m, 3)`` each (NaN if a ray misses).
        Without ``heights``: the camera's ``ray_heights_m`` (RPCs: their valid height
        domain), else -10 and +10 km.
    """
    if heights is None:
        heights = getattr(camera, "ray_heights_m", (-10_000.0, 10_000.0))
    lo = camera.image_to_ground(line, sample, heights[0], ccd=ccd, on_miss="nan")
    hi = camera.image_to_ground(line, sample, heights[1], ccd=ccd, on_miss="nan")
    d = lo - hi
    with np.errstate(invalid="ignore", divide="ignore"):
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
    return hi, d


def triangulate(
    network: Network, cameras: list[Any], points: NDArray[np.intp], obs_mask: NDArray[np.bool_]
) -> F64:
    """Least-squares intersection of the rays of each point's observations.

    Args:
        network: The network.
        cameras: Cameras, in the network's order.
        points: Indices of the points to triangulate.
        obs_mask: Observations that may be used.

    Returns:
        ``(len(points), 3)`` XYZ in metres; NaN for points with fewer than two rays or
        parallel rays.
    """
    out = np.full((len(points), 3), np.nan)
    if not len(points):
        return out
    pmap = np.full(network.n_points, -1, np.intp)
    pmap[points] = np.arange(len(points))
    use = obs_mask & (pmap[network.obs_point] >= 0)
    a = np.zeros((len(points), 3, 3))
    b = np.zeros((len(points), 3))
    n = np.zeros(len(points), np.intp)
    for ci, cam in enumerate(cameras):
        for k, name in enumerate(cam.ccd_names):
            sel = np.flatnonzero(use & (network.obs_camera == ci) & (network.obs_ccd == k))
            if not sel.size:
                continue
            o, d = rays(cam, network.obs_line[sel], network.obs_sample[sel], name)
            ok = np.all(np.isfinite(o), axis=1) & np.all(np.isfinite(d), axis=1)
            o, d, sel = o[ok], d[ok], sel[ok]
            proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
            idx = pmap[network.obs_point[sel]]
            np.add.at(a, idx, proj)
            np.add.at(b, idx, np.einsum("mij,mj->mi", proj, o))
            np.add.at(n, idx, 1)
    good = n >= 2
    if np.any(good):
        det = np.linalg.det(a[good])
        scale = np.einsum("pii->p", a[good]) ** 3
        solvable = np.abs(det) > 1e-12 * scale
        gi = np.flatnonzero(good)[solvable]
        out[gi] = np.linalg.solve(a[gi], b[gi][..., None])[..., 0]
    return out


def ground_error_m(network: Network, cameras: list[Any], obs: NDArray[np.intp], xyz: F64) -> F64:
    """Metres between each observation's ray at its point's height and the point."""
    out = np.full(len(obs), np.nan)
    for ci, cam in enumerate(cameras):
        for k, name in enumerate(cam.ccd_names):
            m = (network.obs_camera[obs] == ci) & (network.obs_ccd[obs] == k)
            sel = np.flatnonzero(m)
            if not sel.size:
                continue
            o = obs[sel]
            p = xyz[network.obs_point[o]]
            _, _, h = xyz_to_lonlat(p, cam.ellipsoid)
            origin, d = rays(cam, network.obs_line[o], network.obs_sample[o], name)
            s = ray_ellipsoid_intersection(origin, d, cam.ellipsoid, h)
            # The ray origin lies at the upper height, so the intersection is along +d.
            hit = origin + s[:, None] * d
            out[sel] = np.linalg.norm(hit - p, axis=1)
    return out
