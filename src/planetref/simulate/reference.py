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

import math
import os
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter, map_coordinates

from planetref.arrays import F64
from planetref.raster.dem import MapProjection
from planetref.simulate.config import ReferenceConfig
from planetref.simulate.grid import MapGrid
from planetref.simulate.mosaic import MosaicSource, Seams
from planetref.simulate.photometry import RadianceModel
from planetref.simulate.sensor import apply_psf, quantize, to_electrons, with_noise

__all__ = [
    "box_in_crs",
    "finish_ortho",
    "ortho_radiance",
    "reference_dem",
    "render_ortho",
    "write_raster",
]

F32 = NDArray[np.float32]


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


def ortho_radiance(
    grid: MapGrid,
    projection: MapProjection,
    truth_projection: MapProjection,
    radiance: RadianceModel,
    cfg: ReferenceConfig,
    out: F32,
    *,
    source: MosaicSource | None = None,
    seams: Seams | None = None,
    progress: Callable[[int], None] | None = None,
    relief: Callable[[F64, F64], F64] | None = None,
) -> None:
    """Footprint-mean radiance of the ortho pixels of one source, relative to its flat radiance.

    Writes ``L / (L_flat (1 + haze)) * gain + bias`` into ``out`` where the pixel belongs to
    ``source`` (all pixels without a mosaic). With a source, the pixel at true map
    point ``p`` shows the surface at ``p - d_s(p)`` (its geometric error).

    Args:
        grid: Ortho grid in the reference CRS.
        projection: The reference CRS.
        truth_projection: The truth grid's CRS (where ``radiance`` is evaluated).
        radiance: Radiance model of this source's illumination (reference epoch).
        cfg: Reference configuration (sensor, supersampling).
        out: float32 array of ``grid.shape`` (written where the source is).
        source: The mosaic source (None: the plain reference image).
        seams: The mosaic's seams (with ``source``).
        progress: Called with the number of rows done after each block.
        relief: Height (m) of the truth above the DEM the sources were orthorectified
            on, at reference-CRS map points (relief displacement of off-nadir sources).
    """
    ss = cfg.ortho_sensor.supersample
    offs = (np.arange(ss) + 0.5) / ss
    xc = grid.x0 + np.arange(grid.cols) * grid.res
    nadir = np.array([0.0, 0.0, 1.0], dtype=np.float32)
    block = max(1, (1 << 18) // grid.cols)
    scale = 1.0 / (radiance.flat_radiance() * (1.0 + radiance.haze))
    if source is not None:
        scale *= source.gain
    for a in range(0, grid.rows, block):
        b = min(grid.rows, a + block)
        yc = grid.y0 - np.arange(a, b) * grid.res
        shape = (b - a, grid.cols)
        if source is not None and seams is not None:
            cx = np.broadcast_to((xc + 0.5 * grid.res)[None, :], shape)
            cy = np.broadcast_to((yc - 0.5 * grid.res)[:, None], shape)
            mine = seams.label(cx, cy) == source.index
            if not mine.any():
                if progress is not None:
                    progress(b - a)
                continue
        else:
            mine = np.ones(shape, dtype=bool)
        rr, cc = np.nonzero(mine)
        acc = np.zeros(len(rr), dtype=np.float32)
        for fy in offs:
            for fx in offs:
                x = xc[cc] + fx * grid.res
                y = yc[rr] - fy * grid.res
                if source is not None:
                    dh = relief(x, y) if relief is not None and source.emission_deg > 0 else None
                    dx, dy = source.displacement(x, y, dh)
                    x, y = x - dx, y - dy
                lon, lat = projection.map_to_lonlat(x, y)
                tx, ty = truth_projection.lonlat_to_map(lon, lat)
                acc += radiance.evaluate(tx, ty, nadir)
        acc *= np.float32(scale / (ss * ss))
        if source is not None and source.bias != 0.0:
            acc += np.float32(source.bias)
        out[a + rr, cc] = acc
        if progress is not None:
            progress(b - a)


def finish_ortho(
    relative: F32, cfg: ReferenceConfig, rng: np.random.Generator
) -> NDArray[np.integer]:
    """PSF, noise and quantisation of the ortho (radiance relative to a flat surface)."""
    sensor = cfg.ortho_sensor
    e = with_noise(to_electrons(apply_psf(relative, sensor), 1.0, sensor), sensor, rng)
    return quantize(e, sensor)


def render_ortho(
    grid: MapGrid,
    projection: MapProjection,
    truth_projection: MapProjection,
    radiance: RadianceModel,
    cfg: ReferenceConfig,
    rng: np.random.Generator,
    progress: Callable[[int], None] | None = None,
) -> NDArray[np.integer]:
    """Render a single-image reference ortho on ``grid`` (no mosaic).

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
    rel = np.zeros(grid.shape, dtype=np.float32)
    ortho_radiance(grid, projection, truth_projection, radiance, cfg, rel, progress=progress)
    return finish_ortho(rel, cfg, rng)


def reference_dem(
    grid: MapGrid,
    projection: MapProjection,
    truth_projection: MapProjection,
    coarse_grid: MapGrid,
    coarse: F64,
    cfg: ReferenceConfig,
    rng: np.random.Generator,
    record: dict[str, Any] | None = None,
) -> F32:
    """Sample the smoothed coarse truth at the reference DEM's pixel centres.

    With ``cfg.mola.tracks`` the truth is sampled along tracks and gridded
    (:func:`gridded_tracks`); with ``cfg.mola.areoid`` the heights are given above the
    areoid-like surface (:func:`areoid_height`).

    Args:
        grid: Reference DEM grid (reference CRS).
        projection: The reference CRS.
        truth_projection: The CRS of ``coarse_grid``.
        coarse_grid: Grid of ``coarse``.
        coarse: Heights (m) of the truth at the coarse spacing (regional composite).
        cfg: Reference configuration.
        rng: Noise generator.
        record: If given, receives the tracks' and areoid's parameters.

    Returns:
        float32 heights (m) of ``grid.shape``.
    """
    sigma = cfg.dem_smoothing_px * cfg.dem_pixel_m / coarse_grid.res
    smooth = gaussian_filter(coarse, sigma, mode="nearest") if sigma > 0 else coarse

    def truth_at(x: F64, y: F64) -> F64:
        lon, lat = projection.map_to_lonlat(x, y)
        tx, ty = truth_projection.lonlat_to_map(lon, lat)
        r, c = coarse_grid.to_index(tx, ty)
        return map_coordinates(smooth, [r, c], order=1, mode="nearest")

    xx, yy = np.meshgrid(grid.x_centres(), grid.y_centres())
    mola = cfg.mola
    if mola.tracks:
        h = gridded_tracks(xx, yy, truth_at, cfg, rng, record)
    else:
        h = truth_at(xx.ravel(), yy.ravel()).reshape(grid.shape)
        if cfg.dem_noise_m > 0:
            h = h + cfg.dem_noise_m * rng.standard_normal(grid.shape)
    if mola.areoid:
        h = h - areoid_height(xx, yy, mola)
        if record is not None:
            record["areoid"] = {
                "offset_m": mola.areoid_offset_m,
                "tilt_m_per_km": mola.areoid_tilt_m_per_km,
                "tilt_azimuth_deg": mola.track_azimuth_deg + 90.0,
                "centre_xy_m": [float(xx.mean()), float(yy.mean())],
            }
    return h.astype(np.float32)


def areoid_height(x: F64, y: F64, mola: Any, centre: tuple[float, float] | None = None) -> F64:
    """Height (m) of the areoid-like surface above the sphere at reference map points.

    ``areoid_offset_m`` plus ``areoid_tilt_m_per_km`` times the distance (km) from
    ``centre`` (default: the points' mean) towards azimuth ``track_azimuth_deg + 90``.
    """
    cx, cy = (float(x.mean()), float(y.mean())) if centre is None else centre
    az = math.radians(mola.track_azimuth_deg + 90.0)
    d = (x - cx) * math.sin(az) + (y - cy) * math.cos(az)
    return mola.areoid_offset_m + mola.areoid_tilt_m_per_km * d / 1000.0


def areoid_raster(grid: MapGrid, mola: Any, margin_px: int = 2) -> tuple[F64, MapGrid]:
    """The areoid-like surface of :func:`reference_dem` as a raster, for ``scene.toml``.

    Heights (m) above the sphere on the reference DEM's grid widened by ``margin_px``
    pixels on every side (so that bilinear sampling at every DEM pixel centre stays
    inside it), centred as in :func:`reference_dem`: at the DEM's pixel centres the
    values are the ones subtracted there (the surface is a plane, so bilinear sampling
    reproduces it exactly).

    Args:
        grid: The reference DEM's grid.
        mola: The ``[reference.mola]`` configuration.
        margin_px: Extra pixels on each side.

    Returns:
        ``(heights, grid)``: float64 heights and their grid.
    """
    xx, yy = np.meshgrid(grid.x_centres(), grid.y_centres())
    centre = (float(xx.mean()), float(yy.mean()))
    m = int(margin_px)
    pad = m * grid.res
    wide = MapGrid(grid.x0 - pad, grid.y0 + pad, grid.res, grid.rows + 2 * m, grid.cols + 2 * m)
    wx, wy = np.meshgrid(wide.x_centres(), wide.y_centres())
    return np.asarray(areoid_height(wx, wy, mola, centre), np.float64), wide


def gridded_tracks(
    xx: F64,
    yy: F64,
    truth_at: Callable[[F64, F64], F64],
    cfg: ReferenceConfig,
    rng: np.random.Generator,
    record: dict[str, Any] | None = None,
) -> F64:
    """MOLA-like DEM: shots along tracks, per-track offsets, tilts and shifts, linear gridding.

    Between tracks the grid is the linear interpolation of the two nearest tracks'
    shots, so its error grows with the distance ``u`` from the nearest track: for
    ground of curvature ``h''`` across the tracks it is ``h'' u (s - u) / 2`` between
    tracks ``s`` apart (0 on a track, ``h'' s^2 / 8`` midway), on top of the tracks'
    own errors (offset, tilt, and ``slope x shift`` from their horizontal shift).

    Args:
        xx: Map x of the grid's pixel centres (reference CRS), 2-D.
        yy: Map y, 2-D.
        truth_at: Heights (m) of the smoothed truth at map points.
        cfg: Reference configuration (``mola``, ``dem_noise_m`` per shot).
        rng: Random generator.
        record: If given, receives the tracks' parameters (``tracks``).

    Returns:
        Heights (m) of the grid.
    """
    from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator

    m = cfg.mola
    az = math.radians(m.track_azimuth_deg)
    u = np.array([math.sin(az), math.cos(az)])  # along track
    v = np.array([math.cos(az), -math.sin(az)])  # across track
    pad = 2.0 * m.track_spacing_m
    pts = np.stack([xx.ravel(), yy.ravel()], axis=1)
    a = pts @ u
    c = pts @ v
    a0, a1 = a.min() - pad, a.max() + pad
    c0, c1 = c.min() - pad, c.max() + pad
    n_tracks = math.ceil((c1 - c0) / m.track_spacing_m) + 1
    across = c0 + m.track_spacing_m * (np.arange(n_tracks) + rng.uniform(-0.3, 0.3, n_tracks))
    along = np.arange(a0, a1 + m.shot_spacing_m, m.shot_spacing_m)
    offsets = rng.normal(0.0, m.track_offset_m, n_tracks)
    tilts = rng.normal(0.0, m.track_tilt_m, n_tracks)
    # Horizontal geolocation error per track (along, across); drawn only when set, so
    # DEMs without it are as they were.
    shifts = (
        rng.normal(0.0, m.track_shift_m, (n_tracks, 2))
        if m.track_shift_m > 0
        else np.zeros((n_tracks, 2))
    )
    frac = (along - 0.5 * (a0 + a1)) / max(a1 - a0, 1.0)
    shots_xy, shots_h = [], []
    for k in range(n_tracks):
        xy = along[:, None] * u[None, :] + across[k] * v[None, :]
        # The shot measured the ground at xy + shift but is placed at xy.
        at = xy + (shifts[k, 0] * u + shifts[k, 1] * v)[None, :]
        h = truth_at(at[:, 0], at[:, 1]) + offsets[k] + tilts[k] * frac
        if cfg.dem_noise_m > 0:
            h = h + cfg.dem_noise_m * rng.standard_normal(len(h))
        shots_xy.append(xy)
        shots_h.append(h)
    sxy = np.concatenate(shots_xy)
    sh = np.concatenate(shots_h)
    lin = LinearNDInterpolator(sxy, sh)(pts)
    bad = ~np.isfinite(lin)
    if bad.any():
        lin[bad] = NearestNDInterpolator(sxy, sh)(pts[bad])
    if record is not None:
        record["tracks"] = {
            "azimuth_deg": m.track_azimuth_deg,
            "across_m": [float(x) for x in across],
            "offset_m": [float(x) for x in offsets],
            "tilt_m": [float(x) for x in tilts],
            **(
                {"shift_along_across_m": [[float(a), float(b)] for a, b in shifts]}
                if m.track_shift_m > 0
                else {}
            ),
            "shot_spacing_m": m.shot_spacing_m,
        }
    return lin.reshape(xx.shape)


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
