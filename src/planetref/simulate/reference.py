"""The CTX-like reference orthoimage and the MOLA-like reference DEM.

Both are north-up rasters of ``reference.crs`` (default ``IAU_2015:49910``, Mars 2015
sphere, equirectangular, clon 0; map metres are ground metres along meridians and
``1/cos(lat)`` of them along parallels), heights in metres above the sphere.

* **Ortho**: each pixel is the mean radiance of ``ortho_sensor.supersample^2`` points
  spread over its footprint, rendered from the truth surface with the *reference* sun,
  albedo and haze, seen from nadir; then PSF, noise and 8-bit quantisation. With
  ``reference.ortho_offset_m = (dx, dy)`` the geotransform written to the file is
  shifted by ``(dx, dy)`` map metres, so every feature appears ``(dx, dy)`` away from
  its true position (a "semi-controlled" mosaic). Its extent is the truth DEM's less a
  small border.
* **DEM**: the truth as seen at the coarse grid spacing (the regional relief plus block
  means of all finer relief), Gaussian-smoothed by ``dem_smoothing_px`` pixels,
  sampled at the pixel centres of a grid of ``dem_pixel_m`` aligned on multiples of the
  pixel size from the map origin (the MEGDR lattice for 1/128 degree), plus noise of
  ``dem_noise_m``. It extends ``dem_pad_m`` beyond the truth DEM, so it lacks all
  relief smaller than a few hundred metres, as MOLA does.
"""

from __future__ import annotations

import os
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter, map_coordinates

from planetref.raster.dem import MapProjection
from planetref.simulate.config import ReferenceConfig
from planetref.simulate.grid import MapGrid
from planetref.simulate.photometry import RadianceModel
from planetref.simulate.sensor import apply_psf, quantize, to_electrons, with_noise

__all__ = [
    "box_in_crs",
    "reference_dem",
    "render_ortho",
    "write_raster",
]

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]


def box_in_crs(
    bounds: tuple[float, float, float, float], src: MapProjection, dst: MapProjection, n: int = 21
) -> tuple[float, float, float, float]:
    """Bounding box in ``dst`` of a box of ``src`` (its edges densified with ``n`` points)."""
    xmin, ymin, xmax, ymax = bounds
    t = np.linspace(0.0, 1.0, n)
    xs = np.concatenate(
        [xmin + t * (xmax - xmin), np.full(n, xmax), xmax - t * (xmax - xmin), np.full(n, xmin)]
    )
    ys = np.concatenate(
        [np.full(n, ymin), ymin + t * (ymax - ymin), np.full(n, ymax), ymax - t * (ymax - ymin)]
    )
    lon, lat = src.map_to_lonlat(xs, ys)
    x, y = dst.lonlat_to_map(lon, lat)
    return float(np.min(x)), float(np.min(y)), float(np.max(x)), float(np.max(y))


def render_ortho(
    grid: MapGrid,
    projection: MapProjection,
    truth_projection: MapProjection,
    radiance: RadianceModel,
    cfg: ReferenceConfig,
    rng: np.random.Generator,
    progress: Callable[[int], None] | None = None,
) -> NDArray[np.integer]:
    """Render the reference ortho on ``grid``.

    Pixels show the surface at their true positions; the ortho offset is applied to
    the geotransform when writing.

    Args:
        grid: Ortho grid in the reference CRS.
        projection: The reference CRS.
        truth_projection: The truth grid's CRS (where ``radiance`` is evaluated).
        radiance: Radiance model of the reference illumination and albedo.
        cfg: Reference configuration (sensor, supersampling).
        rng: Noise generator.
        progress: Called with the number of rows done after each block.

    Returns:
        DN array of ``grid.shape`` (uint8 or uint16).
    """
    sensor = cfg.ortho_sensor
    ss = sensor.supersample
    offs = (np.arange(ss) + 0.5) / ss
    rad = np.zeros(grid.shape, dtype=np.float32)
    xc = grid.x0 + np.arange(grid.cols) * grid.res
    nadir = np.array([0.0, 0.0, 1.0], dtype=np.float32)
    block = max(1, (1 << 18) // grid.cols)
    for a in range(0, grid.rows, block):
        b = min(grid.rows, a + block)
        yc = grid.y0 - np.arange(a, b) * grid.res
        acc = np.zeros((b - a, grid.cols), dtype=np.float32)
        for fy in offs:
            for fx in offs:
                x = np.broadcast_to((xc + fx * grid.res)[None, :], acc.shape)
                y = np.broadcast_to((yc - fy * grid.res)[:, None], acc.shape)
                lon, lat = projection.map_to_lonlat(x.ravel(), y.ravel())
                tx, ty = truth_projection.lonlat_to_map(lon, lat)
                acc += radiance.evaluate(tx, ty, nadir).reshape(acc.shape)
        rad[a:b] = acc / np.float32(ss * ss)
        if progress is not None:
            progress(b - a)
    flat = radiance.flat_radiance() * (1.0 + radiance.haze)
    e = with_noise(to_electrons(apply_psf(rad, sensor), flat, sensor), sensor, rng)
    return quantize(e, sensor)


def reference_dem(
    grid: MapGrid,
    projection: MapProjection,
    truth_projection: MapProjection,
    coarse_grid: MapGrid,
    coarse: F64,
    cfg: ReferenceConfig,
    rng: np.random.Generator,
) -> F32:
    """Sample the smoothed coarse truth at the reference DEM's pixel centres.

    Args:
        grid: Reference DEM grid (reference CRS).
        projection: The reference CRS.
        truth_projection: The CRS of ``coarse_grid``.
        coarse_grid: Grid of ``coarse``.
        coarse: Heights (m) of the truth at the coarse spacing (regional composite).
        cfg: Reference configuration.
        rng: Noise generator.

    Returns:
        float32 heights (m) of ``grid.shape``.
    """
    sigma = cfg.dem_smoothing_px * cfg.dem_pixel_m / coarse_grid.res
    smooth = gaussian_filter(coarse, sigma, mode="nearest") if sigma > 0 else coarse
    xx, yy = np.meshgrid(grid.x_centres(), grid.y_centres())
    lon, lat = projection.map_to_lonlat(xx.ravel(), yy.ravel())
    tx, ty = truth_projection.lonlat_to_map(lon, lat)
    r, c = coarse_grid.to_index(tx, ty)
    h = map_coordinates(smooth, [r, c], order=1, mode="nearest").reshape(grid.shape)
    if cfg.dem_noise_m > 0:
        h = h + cfg.dem_noise_m * rng.standard_normal(grid.shape)
    return h.astype(np.float32)


def write_raster(
    path: str | os.PathLike[str],
    data: NDArray[np.generic],
    grid: MapGrid,
    crs_wkt: str,
    *,
    nodata: float | None = None,
    offset: tuple[float, float] = (0.0, 0.0),
) -> None:
    """Write a single-band georeferenced GeoTIFF, byte-reproducibly.

    Args:
        path: Output file.
        data: 2-D array of ``grid.shape``.
        grid: Its grid.
        crs_wkt: CRS as WKT.
        nodata: Nodata value (NaN for float DEMs), or None.
        offset: ``(dx, dy)`` added to the geotransform's origin (map units).
    """
    import rasterio
    from affine import Affine

    transform = Affine(grid.res, 0.0, grid.x0 + offset[0], 0.0, -grid.res, grid.y0 + offset[1])
    floating = np.issubdtype(data.dtype, np.floating)
    profile: dict[str, object] = {
        "driver": "GTiff",
        "width": grid.cols,
        "height": grid.rows,
        "count": 1,
        "dtype": data.dtype.name,
        "crs": rasterio.crs.CRS.from_wkt(crs_wkt),
        "transform": transform,
        "compress": "deflate",
        "predictor": 3 if floating else 2,
    }
    if nodata is not None:
        profile["nodata"] = nodata
    if grid.rows >= 256 and grid.cols >= 256:
        profile.update(tiled=True, blockxsize=256, blockysize=256)
    with rasterio.Env(GDAL_PAM_ENABLED="NO"), rasterio.open(path, "w", **profile) as ds:
        ds.write(data, 1)
