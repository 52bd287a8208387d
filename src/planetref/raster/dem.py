"""A height grid in a map CRS that implements the :class:`~planetref.camera.base.Terrain` protocol.

:class:`GridTerrain` holds a DEM in memory (a 2-D array of heights in metres above the
reference body of the CRS, plus an affine geotransform and a CRS), interpolates it
bilinearly and intersects camera rays with it exactly (to a tolerance well under a
millimetre). It serves both the reference DEM of real data (:meth:`GridTerrain.from_geotiff`)
and the truth DEM of the simulator.

Conventions
-----------
* Raster pixel ``(row, col)`` covers ``[col, col+1) x [row, row+1)`` in pixel space, so its
  centre is at ``transform * (col + 0.5, row + 0.5)`` (GDAL's "area" convention).
* Heights are sampled with bilinear interpolation between pixel centres. Between the
  outermost pixel centres and the raster edge the edge values are held constant
  (clamped), outside the raster's extent the height is NaN. A NaN (nodata) pixel makes
  every interpolated value that touches it NaN. :meth:`GridTerrain.from_geotiff` fills
  small interior holes when it reads a file and refuses large ones (see
  :mod:`planetref.raster.dem_holes`); an in-memory grid is used as given.
* Rays meet the DEM through :func:`planetref.geometry.terrain.intersect_terrain`, whose
  rule at holes (unknown terrain) every camera shares.
* Longitudes/latitudes are planetocentric degrees, east-positive (see
  :mod:`planetref.geometry.geodesy`); XYZ are body-fixed metres.
"""

from __future__ import annotations

import warnings
from functools import cached_property
from os import PathLike
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.errors import (
    CrsError,
    InputError,
    MissingFileError,
    UnsupportedFormatError,
    library_reason,
)
from planetref.geometry.geodesy import (
    Ellipsoid,
    ray_ellipsoid_intersection,
)
from planetref.geometry.terrain import TOP_MARGIN_M, intersect_terrain
from planetref.raster.dem_holes import DemHoles, fill_dem_holes
from planetref.raster.mapproj import MapProjection

__all__ = ["GridTerrain", "MapProjection", "RayHits"]

#: Height tolerance (m) of the fixed-point solver of :meth:`GridTerrain.first_hit_guess`.
_FIXED_POINT_TOL_M = 1e-5
#: Iterations of the fixed-point solver before the ray is left to marching.
_FIXED_POINT_MAX_ITER = 60
#: Tolerance (m along the ray) of the marched intersections.
_MARCH_TOL_M = 1e-6


def _row_blocks(rows: int, block: int = 256) -> list[tuple[int, int]]:
    """``[r0, r1)`` row ranges of at most ``block`` rows covering ``[0, rows)``."""
    return [(r0, min(r0 + block, rows)) for r0 in range(0, rows, block)]


class RayHits:
    """Intersections of rays with a :class:`GridTerrain`.

    The map coordinates and heights are computed from the points on first access (the
    front end needs only ``xyz``).

    Attributes:
        xyz: Body-fixed points in metres, shape ``(M, 3)``; NaN rows for misses.
        x: Map x (CRS units) of the points, shape ``(M,)``; NaN for misses.
        y: Map y (CRS units), shape ``(M,)``; NaN for misses.
        height: Terrain height (m) at the points, shape ``(M,)``; NaN for misses.
    """

    def __init__(self, xyz: NDArray[np.float64], terrain: GridTerrain) -> None:
        self.xyz = xyz
        self._terrain = terrain

    @cached_property
    def _map(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        m = len(self.xyz)
        x, y, h = np.full(m, np.nan), np.full(m, np.nan), np.full(m, np.nan)
        hit = np.flatnonzero(np.all(np.isfinite(self.xyz), axis=1))
        if hit.size:
            xh, yh, _ = self._terrain.xyz_to_map(self.xyz[hit])
            x[hit], y[hit] = xh, yh
            h[hit] = self._terrain.height_at_map(xh, yh)
        return x, y, h

    @property
    def x(self) -> NDArray[np.float64]:
        """Map x of the points (NaN for misses)."""
        return self._map[0]

    @property
    def y(self) -> NDArray[np.float64]:
        """Map y of the points (NaN for misses)."""
        return self._map[1]

    @property
    def height(self) -> NDArray[np.float64]:
        """Terrain height (m) at the points (NaN for misses)."""
        return self._map[2]

    @property
    def hit(self) -> NDArray[np.bool_]:
        """True where the ray met the terrain."""
        return np.all(np.isfinite(self.xyz), axis=1)


class GridTerrain:
    """A DEM held in memory: heights on a regular grid of a map CRS.

    Implements the :class:`~planetref.camera.base.Terrain` protocol (``height`` takes
    planetocentric lon/lat in degrees) and adds map-coordinate access and an exact ray
    intersection (:meth:`intersect_rays`).

    Args:
        heights: Heights in metres above the CRS's reference body, shape ``(rows, cols)``.
            Stored as given (float32 is kept as float32); NaN marks nodata.
        transform: Affine geotransform (``rasterio.Affine``, or the six GDAL coefficients
            ``(x0, dx, rx, y0, ry, dy)``) from pixel ``(col, row)`` to map ``(x, y)``.
        crs: The map CRS (anything ``pyproj.CRS.from_user_input`` accepts). It must not be
            geocentric.
        nodata: A value in ``heights`` that means "no data"; such pixels become NaN
            (the array is then copied to floating point).

    Raises:
        InputError: If the array is not 2-D, has fewer than 2 x 2 pixels, holds no finite
            value or the transform is singular.
        CrsError: If the CRS is invalid or geocentric.
    """

    def __init__(
        self, heights: ArrayLike, transform: object, crs: object, *, nodata: float | None = None
    ) -> None:
        from affine import Affine

        h = np.asarray(heights)
        if h.ndim != 2 or h.shape[0] < 2 or h.shape[1] < 2:
            raise InputError(f"heights must be a 2-D array of at least 2 x 2, got {h.shape}")
        if not np.issubdtype(h.dtype, np.floating):
            h = h.astype(np.float64)
        if nodata is not None and np.isfinite(nodata):
            h = np.where(h == nodata, np.nan, h).astype(h.dtype)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all NaN: refused below
            # NaN-ignoring reductions without a grid-sized mask or copy (a truth DEM of
            # a long strip is hundreds of MB).
            lo, hi = float(np.nanmin(h)), float(np.nanmax(h))
        if not (np.isfinite(lo) and np.isfinite(hi)):  # all NaN, or infinite heights
            finite = np.isfinite(h)
            if not finite.any():
                raise InputError("the DEM holds no finite height")
            lo, hi = float(np.min(h[finite])), float(np.max(h[finite]))
        self.heights: NDArray[np.floating] = h
        if isinstance(transform, Affine):
            self.transform = transform
        else:
            coeffs = tuple(float(v) for v in transform)  # type: ignore[union-attr]
            if len(coeffs) != 6:
                raise InputError(f"transform needs 6 coefficients, got {len(coeffs)}")
            self.transform = Affine.from_gdal(*coeffs)
        if abs(self.transform.determinant) == 0.0:
            raise InputError(f"singular geotransform {tuple(self.transform)[:6]}")
        self._inverse = ~self.transform
        self.projection = MapProjection(crs)
        self.crs = self.projection.crs
        self.ellipsoid: Ellipsoid = self.projection.ellipsoid
        self.min_height_m, self.max_height_m = lo, hi
        self._max_slope: float | None = None
        self._holes: NDArray[np.int64] | bool | None = None
        self._pixel_m: float | None = None
        self._flat = np.ascontiguousarray(h).reshape(-1)

    # -- construction -------------------------------------------------------------------
    @classmethod
    def from_geotiff(
        cls, path: str | PathLike[str], *, band: int = 1, holes: DemHoles | None = None
    ) -> GridTerrain:
        """Read a DEM from a GeoTIFF (or any raster GDAL reads).

        Args:
            path: The raster file.
            band: 1-based band index holding the heights (metres).
            holes: How nodata holes are treated (default :class:`DemHoles()`: holes of at
                most 64 cells, 1% of the DEM together, are filled with a warning naming
                the file; larger ones are an error). Nodata touching the raster's edge is
                the limit of coverage and stays NaN.

        Returns:
            The DEM, with remaining nodata pixels (the band's nodata value, and NaN) as NaN.

        Raises:
            MissingFileError: If the file does not exist.
            UnsupportedFormatError: If GDAL cannot read it.
            CrsError: If the raster has no CRS.
            InputError: If the band does not exist, holds no finite height, or has holes
                larger than ``holes`` allows.
        """
        import rasterio
        from rasterio.errors import RasterioIOError

        p = Path(path)
        if not p.exists():
            raise MissingFileError("DEM file not found", path=p)
        try:
            with rasterio.open(p) as ds:
                if not 1 <= band <= ds.count:
                    raise InputError(
                        f"band {band} does not exist (the file has {ds.count})", path=p
                    )
                if ds.crs is None:
                    raise CrsError("the DEM has no CRS", path=p)
                data = ds.read(band)
                nodata = ds.nodatavals[band - 1]
                transform, crs = ds.transform, ds.crs
        except RasterioIOError as exc:
            raise UnsupportedFormatError(
                f"cannot read raster ({library_reason(exc)})", path=p
            ) from None
        if not np.issubdtype(data.dtype, np.floating):
            data = data.astype(np.float32 if data.itemsize <= 2 else np.float64)
        if nodata is not None and np.isfinite(nodata):
            data = np.where(data == nodata, np.nan, data).astype(data.dtype)
        data, _ = fill_dem_holes(data, holes if holes is not None else DemHoles(), p)
        try:
            return cls(data, transform, crs)
        except InputError as exc:
            raise InputError(str(exc), path=p) from None

    def to_geotiff(self, path: str | PathLike[str], *, compress: str = "deflate") -> None:
        """Write the DEM as a single-band GeoTIFF (NaN nodata, tiled, no timestamps).

        Args:
            path: Output file; overwritten if it exists.
            compress: GDAL compression name ("deflate", "lzw", "none").
        """
        import rasterio

        profile = {
            "driver": "GTiff",
            "width": self.shape[1],
            "height": self.shape[0],
            "count": 1,
            "dtype": self.heights.dtype.name,
            "crs": rasterio.crs.CRS.from_wkt(self.crs.to_wkt()),
            "transform": self.transform,
            "nodata": float("nan"),
        }
        if compress != "none":
            profile.update(compress=compress, predictor=3)
        if self.shape[0] >= 256 and self.shape[1] >= 256:
            profile.update(tiled=True, blockxsize=256, blockysize=256)
        with rasterio.Env(GDAL_PAM_ENABLED="NO"), rasterio.open(path, "w", **profile) as ds:
            ds.write(self.heights, 1)

    # -- properties ---------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, cols)`` of the grid."""
        return (int(self.heights.shape[0]), int(self.heights.shape[1]))

    @property
    def sampling_m(self) -> float:
        """Ground distance (m) between neighbouring pixel centres (the smaller axis).

        Measured on the body at the grid's centre.
        """
        rows, cols = self.shape
        c, r = cols / 2.0, rows / 2.0
        pts = [self.transform @ (c, r), self.transform @ (c + 1, r), self.transform @ (c, r + 1)]
        xs = np.array([p[0] for p in pts])
        ys = np.array([p[1] for p in pts])
        xyz = self.map_to_xyz(xs, ys, np.zeros(3))
        return float(min(np.linalg.norm(xyz[1] - xyz[0]), np.linalg.norm(xyz[2] - xyz[0])))

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)`` of the raster's extent in map units."""
        rows, cols = self.shape
        corners = [self.transform @ (c, r) for c in (0, cols) for r in (0, rows)]
        xs = [p[0] for p in corners]
        ys = [p[1] for p in corners]
        return (min(xs), min(ys), max(xs), max(ys))

    @property
    def max_slope(self) -> float:
        """The largest height gradient (m/m) between neighbouring pixels (computed once)."""
        if self._max_slope is None:
            h = self.heights
            res_x = float(np.hypot(self.transform.a, self.transform.d))
            res_y = float(np.hypot(self.transform.b, self.transform.e))
            scale = self.sampling_m / min(res_x, res_y)  # metres per map unit (approx.)
            gx = gy = h.dtype.type(np.nan)  # the grid's precision, as before
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                # Row blocks (overlapping by one row): the differences of a few rows at a
                # time, not of the whole grid; the maxima are the same.
                for r0, r1 in _row_blocks(h.shape[0]):
                    gx = np.fmax(gx, np.nanmax(np.abs(np.diff(h[r0:r1], axis=1))))
                    if len(rows := h[r0 : r1 + 1]) > 1:
                        gy = np.fmax(gy, np.nanmax(np.abs(np.diff(rows, axis=0))))
            gx, gy = gx / (res_x * scale), gy / (res_y * scale)
            self._max_slope = float(np.nanmax([gx, gy, 0.0]) * np.sqrt(2.0))
        return self._max_slope

    # -- coordinates --------------------------------------------------------------------
    def lonlat_to_map(
        self, lon_deg: ArrayLike, lat_deg: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Planetocentric lon/lat (degrees) to map coordinates of the grid's CRS."""
        return self.projection.lonlat_to_map(lon_deg, lat_deg)

    def map_to_lonlat(
        self, x: ArrayLike, y: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Map coordinates to planetocentric lon/lat in degrees."""
        return self.projection.map_to_lonlat(x, y)

    def xyz_to_map(
        self, xyz: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Body-fixed XYZ (m, shape ``(..., 3)``) to map ``x, y`` and height above the body."""
        return self.projection.xyz_to_map(xyz)

    def map_to_xyz(self, x: ArrayLike, y: ArrayLike, height_m: ArrayLike) -> NDArray[np.float64]:
        """Map ``x, y`` and height (m) to body-fixed XYZ (m), shape ``(..., 3)``."""
        return self.projection.map_to_xyz(x, y, height_m)

    def map_to_pixel(
        self, x: ArrayLike, y: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Map coordinates to continuous ``(row, col)`` with pixel centres at integers.

        Pixel ``(0, 0)``'s centre maps to ``(0.0, 0.0)`` here (unlike image coordinates of
        cameras, which put it at ``(0.5, 0.5)``), which is the convenient index space for
        interpolation.
        """
        x, y = np.asarray(x, float), np.asarray(y, float)
        inv = self._inverse
        col = inv.a * x + inv.b * y + inv.c - 0.5
        row = inv.d * x + inv.e * y + inv.f - 0.5
        return row, col

    # -- sampling -----------------------------------------------------------------------
    def height_at_map(self, x: ArrayLike, y: ArrayLike) -> NDArray[np.float64]:
        """Bilinearly interpolated height (m) at map coordinates; NaN outside or in holes."""
        row, col = self.map_to_pixel(x, y)
        return self._bilinear(row, col)

    def height(
        self, lon_deg: NDArray[np.float64], lat_deg: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """Height (m) at planetocentric lon/lat (degrees); NaN outside or in holes."""
        x, y = self.lonlat_to_map(lon_deg, lat_deg)
        return self.height_at_map(x, y)

    def _bilinear(self, row: NDArray[np.float64], col: NDArray[np.float64]) -> NDArray[np.float64]:
        rows, cols = self.shape
        inside = (row >= -0.5) & (row <= rows - 0.5) & (col >= -0.5) & (col <= cols - 0.5)
        # NaN coordinates (a NaN point) are outside; index them at 0 and mask them below.
        r = np.clip(np.where(inside, row, 0.0), 0.0, rows - 1.0)
        c = np.clip(np.where(inside, col, 0.0), 0.0, cols - 1.0)
        r0 = np.minimum(r.astype(np.intp), rows - 2)
        c0 = np.minimum(c.astype(np.intp), cols - 2)
        fr = r - r0
        fc = c - c0
        flat = self._flat
        idx = r0 * cols + c0
        h00 = flat.take(idx)
        h01 = flat.take(idx + 1)
        h10 = flat.take(idx + cols)
        h11 = flat.take(idx + (cols + 1))
        top = h00 + fc * (h01 - h00)
        bot = h10 + fc * (h11 - h10)
        out = top + fr * (bot - top)
        if not inside.all():
            out = np.where(inside, out, np.nan)
        return out.astype(np.float64, copy=False)

    # -- ray intersection ---------------------------------------------------------------
    def intersect_rays(self, origin: ArrayLike, direction: ArrayLike) -> RayHits:
        """First intersection of rays with the (bilinearly interpolated) DEM surface.

        The intersection is :func:`planetref.geometry.terrain.intersect_terrain` (its rule
        at holes: a ray that reaches a NaN cell or leaves the DEM before crossing known
        terrain is a miss), so cameras' ``image_to_ground`` with this DEM give the same
        points. The grid contributes the fast path (:meth:`first_hit_guess`).

        Args:
            origin: Ray origins, body-fixed metres, shape ``(M, 3)``.
            direction: Ray directions (any length), shape ``(M, 3)``.

        Returns:
            The hits; rows are NaN where a ray misses the DEM.
        """
        o = np.atleast_2d(np.asarray(origin, dtype=np.float64))
        d = np.atleast_2d(np.asarray(direction, dtype=np.float64))
        o, d = np.broadcast_arrays(o, d)
        if o.shape[-1] != 3:
            raise InputError(f"rays need a last axis of length 3, got {o.shape}")
        o = o.reshape(-1, 3)
        d = d.reshape(-1, 3)
        if o.shape[0] == 0:
            return RayHits(np.full((0, 3), np.nan), self)
        return RayHits(intersect_terrain(o, d, self, "nan", tol_m=_MARCH_TOL_M), self)

    def first_hit_guess(
        self, origin: NDArray[np.float64], direction: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """Ray parameters of first hits the grid can certify (NaN: march the ray).

        Rays whose direction is close to the local vertical (the slope of the DEM times
        the tangent of the ray's off-vertical angle below 0.5) are solved by the
        fixed-point iteration ``h <- DEM(point of the ray at height h)``, which then
        converges to the unique intersection; for a sphere and an equirectangular CRS in
        closed form. A solution is certified only if the ray's path from 1 m above the
        DEM's top down to it stays inside the grid and meets no NaN cell (the hole rule of
        :mod:`planetref.geometry.terrain`).

        Args:
            origin: Ray origins above the DEM's top, body-fixed metres, ``(M, 3)``.
            direction: Unit ray directions, ``(M, 3)``.

        Returns:
            Metres along ``direction``, shape ``(M,)``; NaN where not certified.
        """
        o, d = origin, direction
        m = o.shape[0]
        s_out = np.full(m, np.nan)
        # Off-vertical angle of each ray at the mean terrain height.
        h_mid = 0.5 * (self.min_height_m + self.max_height_m)
        s_mid = self._sphere_or_ellipsoid_root(o, d, h_mid)
        p_mid = o + s_mid[:, None] * d
        cos_t = -(p_mid[:, 0] * d[:, 0] + p_mid[:, 1] * d[:, 1] + p_mid[:, 2] * d[:, 2])
        cos_t = np.clip(
            cos_t / np.sqrt(p_mid[:, 0] ** 2 + p_mid[:, 1] ** 2 + p_mid[:, 2] ** 2), 1e-9, 1.0
        )
        tan_t = np.sqrt(np.clip(1.0 - cos_t**2, 0.0, None)) / cos_t
        todo = np.flatnonzero(np.isfinite(s_mid) & (tan_t * self.max_slope < 0.5))
        if todo.size:
            oo, dd = o[todo], d[todo]
            if self.ellipsoid.is_sphere and self.projection._fast is not None:
                h, done, s, x, y = self._fixed_point_sphere(oo, dd, h_mid)
            else:
                h, done, s, x, y = self._fixed_point(oo, dd, h_mid)
            done &= self._path_is_known(tan_t[todo], h, x, y)
            idx = todo[done]
            s_out[idx] = s[done]
        return s_out

    def _sphere_or_ellipsoid_root(
        self, o: NDArray[np.float64], d: NDArray[np.float64], h: float
    ) -> NDArray[np.float64]:
        """Ray parameter of the near intersection with the surface at height ``h``."""
        if not self.ellipsoid.is_sphere:
            return ray_ellipsoid_intersection(o, d, self.ellipsoid, h)
        od = o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1] + o[:, 2] * d[:, 2]
        disc = (
            od * od
            - (o[:, 0] ** 2 + o[:, 1] ** 2 + o[:, 2] ** 2)
            + (self.ellipsoid.semi_major_m + h) ** 2
        )
        with np.errstate(invalid="ignore"):
            s = -od - np.sqrt(disc)
        s[~(s >= 0)] = np.nan
        return s

    def _path_is_known(
        self,
        tan_t: NDArray[np.float64],
        h_hit: NDArray[np.float64],
        x_hit: NDArray[np.float64],
        y_hit: NDArray[np.float64],
    ) -> NDArray[np.bool_]:
        """True where a ray's path from above the DEM's top to its hit meets no unknown cell.

        The path's horizontal length is at most its height drop times the tangent of its
        off-vertical angle (plus 1%); the square of pixels that many pixels around the
        hit, grown by two (the support of the bilinear surface), must lie inside the grid
        and hold no NaN cell (a summed-area table answers per ray). A conservative box
        only sends more rays to marching, which applies the same rule exactly.
        """
        rows, cols = self.shape
        r, c = self.map_to_pixel(x_hit, y_hit)
        reach = (self.max_height_m + TOP_MARGIN_M - h_hit) * tan_t * 1.01 / self._min_pixel_m
        rad = np.ceil(np.maximum(reach, 0.0)) + 2.0
        with np.errstate(invalid="ignore"):
            rlo, rhi, clo, chi = r - rad, r + rad, c - rad, c + rad
            inside = (rlo >= -0.5) & (rhi <= rows - 0.5) & (clo >= -0.5) & (chi <= cols - 0.5)
        table = self._hole_table
        if table is None:
            return inside
        ok = inside.copy()
        k = np.flatnonzero(inside)
        a = np.clip(np.floor(rlo[k]), 0, rows).astype(np.intp)
        b = np.clip(np.ceil(rhi[k]) + 1, 0, rows).astype(np.intp)
        e0 = np.clip(np.floor(clo[k]), 0, cols).astype(np.intp)
        e1 = np.clip(np.ceil(chi[k]) + 1, 0, cols).astype(np.intp)
        holes = table[b, e1] - table[a, e1] - table[b, e0] + table[a, e0]
        ok[k] = holes == 0
        return ok

    @property
    def _min_pixel_m(self) -> float:
        """Smallest ground distance (m) between neighbouring pixel centres over the grid.

        Measured at the corners, edge midpoints and centre (map distortion is monotonic
        between them for the CRSs of DEMs), computed once.
        """
        if self._pixel_m is None:
            rows, cols = self.shape
            best = np.inf
            for c in (0.5, cols / 2.0, cols - 1.5):
                for r in (0.5, rows / 2.0, rows - 1.5):
                    pts = [self.transform @ p for p in ((c, r), (c + 1, r), (c, r + 1))]
                    xs = np.array([p[0] for p in pts])
                    ys = np.array([p[1] for p in pts])
                    xyz = self.map_to_xyz(xs, ys, np.zeros(3))
                    dist = min(np.linalg.norm(xyz[1] - xyz[0]), np.linalg.norm(xyz[2] - xyz[0]))
                    best = min(best, float(dist))
            self._pixel_m = best
        return self._pixel_m

    @property
    def _hole_table(self) -> NDArray[np.int64] | None:
        """Summed-area table of NaN cells, shape ``(rows + 1, cols + 1)`` (None: no holes)."""
        if self._holes is None:
            h = self.heights
            if all(np.isfinite(h[r0:r1]).all() for r0, r1 in _row_blocks(h.shape[0])):
                self._holes = False
            else:
                nan = ~np.isfinite(h)
                table = np.zeros((nan.shape[0] + 1, nan.shape[1] + 1), dtype=np.int64)
                table[1:, 1:] = np.cumsum(np.cumsum(nan, axis=0), axis=1)
                self._holes = table
        return None if self._holes is False else self._holes

    def _fixed_point(
        self, o: NDArray[np.float64], d: NDArray[np.float64], h0: float
    ) -> tuple[NDArray[np.float64], ...]:
        """``h <- DEM(ray point at height h)`` for any body and CRS."""
        h = np.full(len(o), h0)
        done = np.zeros(len(o), dtype=bool)
        for _ in range(_FIXED_POINT_MAX_ITER):
            s = ray_ellipsoid_intersection(o, d, self.ellipsoid, h)
            x, y, _ = self.xyz_to_map(o + s[:, None] * d)
            h_new = self.height_at_map(x, y)
            done = np.isfinite(h_new) & (np.abs(h_new - h) < _FIXED_POINT_TOL_M)
            h = np.where(np.isfinite(h_new), h_new, h)
            if np.all(done | ~np.isfinite(h_new)):
                break
        s = ray_ellipsoid_intersection(o, d, self.ellipsoid, h)
        done &= np.isfinite(s)
        x, y, _ = self.xyz_to_map(o + s[:, None] * d)
        return h, done, s, x, y

    def _fixed_point_sphere(
        self, o: NDArray[np.float64], d: NDArray[np.float64], h0: float
    ) -> tuple[NDArray[np.float64], ...]:
        """The same iteration, in closed form for a sphere and an equirectangular map."""
        fast = self.projection._fast
        if fast is None:
            return self._fixed_point(o, d, h0)
        radius = self.ellipsoid.semi_major_m
        ox, oy, oz = (np.ascontiguousarray(o[:, k]) for k in range(3))
        dx, dy, dz = (np.ascontiguousarray(d[:, k]) for k in range(3))
        od = ox * dx + oy * dy + oz * dz
        base = od * od - (ox * ox + oy * oy + oz * oz)
        kx = fast.kx * 180.0 / np.pi  # map metres per radian
        ky = fast.ky * 180.0 / np.pi
        lon0, lat0 = np.radians(fast.lon_0), np.radians(fast.lat_0)

        def to_map(h: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
            with np.errstate(invalid="ignore"):
                s = -od - np.sqrt(base + (radius + h) ** 2)
            px, py, pz = ox + s * dx, oy + s * dy, oz + s * dz
            dlon = np.arctan2(py, px) - lon0
            if dlon.size and (dlon.min() < -np.pi or dlon.max() >= np.pi):
                dlon = (dlon + np.pi) % (2 * np.pi) - np.pi
            lat = np.arctan2(pz, np.hypot(px, py))
            return s, fast.x_0 + kx * dlon, fast.y_0 + ky * (lat - lat0)

        h = np.full(len(o), h0)
        done = np.zeros(len(o), dtype=bool)
        for _ in range(_FIXED_POINT_MAX_ITER):
            _, x, y = to_map(h)
            h_new = self.height_at_map(x, y)
            finite = np.isfinite(h_new)
            done = finite & (np.abs(h_new - h) < _FIXED_POINT_TOL_M)
            h = np.where(finite, h_new, h)
            if np.all(done | ~finite):
                break
        s, x, y = to_map(h)
        done &= np.isfinite(s)
        return h, done, s, x, y
