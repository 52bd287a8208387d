"""Orthorectify a whole CCD image through a camera and a DEM into a GeoTIFF.

The output grid is in the reference CRS, north-up, at a chosen ground sampling distance.
For every output pixel the DEM height at its map position gives a body-fixed point,
which the camera projects into the raw image; the raw image is sampled bilinearly there.
The projection is computed exactly on a lattice (every ``lattice_step`` output pixels)
and interpolated in between (the mapping is smooth), and the output is produced in
blocks of rows, each reading only the raw lines it needs, so memory stays bounded by the
block size whatever the image size.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.atomic import atomic_path
from planetref.camera.base import Camera, Terrain
from planetref.errors import GeometryError
from planetref.frontend.geometry import project_to_image, rays_to_ground

__all__ = ["orthorectify_ccd"]

F64 = NDArray[np.float64]


def _footprint(
    camera: Camera, ccd: str, terrain: Terrain, ground: Any, n_edge: int = 17
) -> tuple[float, float, float, float]:
    n_lines, n_samples = camera.image_size(ccd)
    t = np.linspace(0.0, 1.0, n_edge)
    line = np.concatenate(
        [t * n_lines, np.full(n_edge, n_lines), (1 - t) * n_lines, np.zeros(n_edge)]
    )
    sample = np.concatenate(
        [np.zeros(n_edge), t * n_samples, np.full(n_edge, n_samples), (1 - t) * n_samples]
    )
    xyz = rays_to_ground(camera, ccd, line, sample, terrain)
    ok = np.all(np.isfinite(xyz), axis=1)
    if not ok.any():
        raise GeometryError(f"CCD {ccd}: no ray of the image border meets the DEM")
    x, y, _ = ground.xyz_to_map(xyz[ok])
    return float(x.min()), float(y.min()), float(x.max()), float(y.max())


def orthorectify_ccd(
    image: Any,
    camera: Camera,
    ccd: str,
    terrain: Terrain,
    crs: Any,
    path: str | os.PathLike[str],
    *,
    gsd_m: float,
    lattice_step: int = 8,
    block_rows: int = 256,
) -> Path:
    """Write the orthoimage of one CCD image.

    Args:
        image: A :class:`~planetref.raster.image.CcdImage` (windowed reads).
        camera: The camera (e.g. the adjusted one).
        ccd: CCD name.
        terrain: The DEM the image is projected onto.
        crs: The output CRS (the reference ortho's), a projected CRS in metres.
        path: Output GeoTIFF (written atomically).
        gsd_m: Output pixel size in CRS units (metres).
        lattice_step: Output pixels between exactly projected lattice points.
        block_rows: Output rows per block.

    Returns:
        The path written. Pixels outside the image or the DEM are nodata (NaN, float32).
    """
    import cv2
    import rasterio
    from rasterio.transform import from_origin

    from planetref.geometry.geodesy import CrsGround

    ground = CrsGround(crs)
    x0, y0, x1, y1 = _footprint(camera, ccd, terrain, ground)
    width = max(1, math.ceil((x1 - x0) / gsd_m))
    height = max(1, math.ceil((y1 - y0) / gsd_m))
    transform = from_origin(x0, y1, gsd_m, gsd_m)
    n_lines, n_samples = camera.image_size(ccd)
    profile = {
        "driver": "GTiff",
        "width": width,
        "height": height,
        "count": 1,
        "dtype": "float32",
        "crs": ground.crs.to_wkt(),
        "transform": transform,
        "nodata": float("nan"),
        "tiled": True,
        "blockxsize": 256,
        "blockysize": 256,
        "compress": "deflate",
    }
    cols = np.arange(0, width + lattice_step, lattice_step, dtype=np.float64)
    cols = np.minimum(cols, width)
    with atomic_path(path) as tmp, rasterio.open(tmp, "w", **profile) as dst:
        guess: F64 | None = None
        for r0 in range(0, height, block_rows):
            r1 = min(height, r0 + block_rows)
            rows = np.arange(r0, r1 + lattice_step, lattice_step, dtype=np.float64)
            rows = np.minimum(rows, r1)
            cc, rr = np.meshgrid(cols, rows)
            mx = x0 + cc.ravel() * gsd_m
            my = y1 - rr.ravel() * gsd_m
            lon, lat = ground.map_to_lonlat(mx, my)
            h = np.asarray(terrain.height(lon, lat), np.float64)
            xyz = ground.map_to_xyz(mx, my, h)
            if guess is not None and len(guess) != len(xyz):
                guess = None  # the last block has fewer lattice rows
            line, sample = project_to_image(camera, ccd, xyz, line_guess=guess)
            good = np.isfinite(line)
            if good.any():
                guess = np.where(good, line, np.nanmedian(line[good]))
            out = np.full((r1 - r0, width), np.nan, np.float32)
            if good.any():
                lat_line = line.reshape(rr.shape)
                lat_sample = sample.reshape(rr.shape)
                # Dense maps by bilinear interpolation of the lattice (output pixel centres).
                fy = (np.arange(r0, r1) + 0.5 - rows[0]) / lattice_step
                fx = (np.arange(width) + 0.5 - cols[0]) / lattice_step
                gy, gx = np.meshgrid(fy.astype(np.float32), fx.astype(np.float32), indexing="ij")
                map_line = cv2.remap(
                    lat_line.astype(np.float32),
                    gx,
                    gy,
                    cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE,
                )
                map_sample = cv2.remap(
                    lat_sample.astype(np.float32),
                    gx,
                    gy,
                    cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE,
                )
                finite = np.isfinite(map_line) & np.isfinite(map_sample)
                inside = (
                    finite
                    & (map_line >= 0)
                    & (map_line < n_lines)
                    & (map_sample >= 0)
                    & (map_sample < n_samples)
                )
                if inside.any():
                    l_lo = max(0, int(np.floor(map_line[inside].min())) - 2)
                    l_hi = min(n_lines, int(np.ceil(map_line[inside].max())) + 2)
                    raw, valid = image.read(l_lo, 0, l_hi - l_lo, n_samples)
                    raw = np.where(valid, raw, np.nan).astype(np.float32)
                    # Pixel centres are at +0.5: remap indexes pixel centres from 0.
                    mx_ = np.where(inside, map_sample - 0.5, -10).astype(np.float32)
                    my_ = np.where(inside, map_line - l_lo - 0.5, -10).astype(np.float32)
                    vals = cv2.remap(
                        raw,
                        mx_,
                        my_,
                        cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT,
                        borderValue=np.nan,
                    )
                    out = np.where(inside, vals, np.nan).astype(np.float32)
            dst.write(out, 1, window=rasterio.windows.Window(0, r0, width, r1 - r0))
    return Path(path)
