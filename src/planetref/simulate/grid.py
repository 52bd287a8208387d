"""Regular map grids of the simulator and their CRSs.

The truth surface lives on a north-up grid of a *local* equirectangular map on the
Mars 2015 sphere whose standard parallel and central meridian are the scene centre's
(:func:`local_crs`). At the scene centre one map metre is one ground metre in both
axes, the map x axis points east and y north, so the grid doubles as a local
east/north frame for shading. Over a few kilometres the scale error is below 1e-3.

Grid convention: cell ``(row, col)`` covers ``[x0 + col*res, x0 + (col+1)*res] x
[y0 - (row+1)*res, y0 - row*res]``; its centre is ``(x0 + (col+0.5)*res,
y0 - (row+0.5)*res)`` (GDAL "area" convention; ``x0, y0`` is the top-left corner).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from planetref.errors import InputError
from planetref.geometry.geodesy import MARS_IAU2015_SPHERE, Ellipsoid

__all__ = ["MapGrid", "cubic_resample", "enu_basis", "local_crs", "local_crs_wkt"]


def local_crs_wkt(lat_deg: float, lon_deg: float) -> str:
    """WKT2 of the local equirectangular CRS centred on ``(lat_deg, lon_deg)``.

    The CRS is PROJ ``eqc`` on the IAU 2015 Mars sphere (base CRS ``IAU_2015:49900``,
    planetocentric) with ``lat_ts = lat_deg`` and ``lon_0 = lon_deg``.
    """
    return local_crs(lat_deg, lon_deg).to_wkt()


def local_crs(lat_deg: float, lon_deg: float) -> object:
    """The local equirectangular CRS (a ``pyproj.CRS``); see :func:`local_crs_wkt`."""
    from pyproj import CRS
    from pyproj.crs import ProjectedCRS
    from pyproj.crs.coordinate_operation import EquidistantCylindricalConversion

    conv = EquidistantCylindricalConversion(
        latitude_first_parallel=float(lat_deg), longitude_natural_origin=float(lon_deg)
    )
    return ProjectedCRS(
        conversion=conv,
        geodetic_crs=CRS.from_user_input("IAU_2015:49900"),
        name=f"Mars 2015 sphere / local equirectangular ({lat_deg:.4f}N, {lon_deg:.4f}E)",
    )


def enu_basis(lat_deg: float, lon_deg: float) -> NDArray[np.float64]:
    """Rows ``east, north, up`` (body-fixed unit vectors) at a planetocentric lon/lat."""
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    up = np.array([math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)])
    east = np.array([-math.sin(lon), math.cos(lon), 0.0])
    north = np.cross(up, east)
    return np.stack([east, north, up])


@dataclass(frozen=True)
class MapGrid:
    """A north-up regular grid.

    Attributes:
        x0: Map x of the left edge (map units, metres).
        y0: Map y of the top edge.
        res: Cell size (metres); cells are square.
        rows: Number of rows.
        cols: Number of columns.
    """

    x0: float
    y0: float
    res: float
    rows: int
    cols: int

    def __post_init__(self) -> None:
        if not (self.res > 0 and self.rows >= 1 and self.cols >= 1):
            raise InputError(f"bad grid: res={self.res}, shape=({self.rows}, {self.cols})")

    @classmethod
    def covering(
        cls,
        xmin: float,
        ymin: float,
        xmax: float,
        ymax: float,
        res: float,
        *,
        align: float | None = None,
    ) -> MapGrid:
        """The smallest grid of cell size ``res`` covering a box.

        Its edges lie on multiples of ``align`` (default ``res``) from the map origin.
        """
        a = res if align is None else align
        x0 = math.floor(xmin / a) * a
        y1 = math.floor(ymin / a) * a
        x1 = math.ceil(xmax / a) * a
        y0 = math.ceil(ymax / a) * a
        cols = max(1, round((x1 - x0) / res))
        rows = max(1, round((y0 - y1) / res))
        return cls(float(x0), float(y0), float(res), int(rows), int(cols))

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, cols)``."""
        return (self.rows, self.cols)

    @property
    def transform(self) -> object:
        """The affine geotransform (``affine.Affine``) pixel ``(col, row)`` -> map."""
        from affine import Affine

        return Affine(self.res, 0.0, self.x0, 0.0, -self.res, self.y0)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)``."""
        return (self.x0, self.y0 - self.rows * self.res, self.x0 + self.cols * self.res, self.y0)

    def x_centres(self) -> NDArray[np.float64]:
        """Map x of the column centres, shape ``(cols,)``."""
        return self.x0 + (np.arange(self.cols) + 0.5) * self.res

    def y_centres(self) -> NDArray[np.float64]:
        """Map y of the row centres, shape ``(rows,)``."""
        return self.y0 - (np.arange(self.rows) + 0.5) * self.res

    def to_index(
        self, x: NDArray[np.float64], y: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Continuous ``(row, col)`` of map points, cell centres at integers."""
        return (self.y0 - y) / self.res - 0.5, (x - self.x0) / self.res - 0.5


def _cubic_weights(pos: NDArray[np.float64], n: int) -> sp.csr_matrix:
    """Keys (a = -0.5) cubic convolution weights, edges clamped, as a sparse matrix.

    Row ``i`` interpolates a length-``n`` signal at continuous index ``pos[i]``.
    """
    pos = np.clip(pos, 0.0, n - 1.0)
    base = np.floor(pos).astype(np.int64)
    t = pos - base
    rows, cols, vals = [], [], []
    a = -0.5
    for k in (-1, 0, 1, 2):
        d = np.abs(t - k)
        w = np.where(
            d <= 1,
            (a + 2) * d**3 - (a + 3) * d**2 + 1,
            np.where(d < 2, a * d**3 - 5 * a * d**2 + 8 * a * d - 4 * a, 0.0),
        )
        idx = np.clip(base + k, 0, n - 1)
        rows.append(np.arange(len(pos)))
        cols.append(idx)
        vals.append(w)
    return sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(len(pos), n)
    )


def cubic_resample(
    values: NDArray[np.floating], src: MapGrid, dst: MapGrid, dtype: type = np.float32
) -> NDArray[np.floating]:
    """Separable cubic interpolation of a grid onto another (edges clamped).

    Args:
        values: Array of shape ``src.shape``.
        src: Grid of ``values``.
        dst: Target grid (any cell size; typically finer).
        dtype: Output dtype.

    Returns:
        Array of shape ``dst.shape``.
    """
    r_idx, _ = src.to_index(np.zeros(dst.rows), dst.y_centres())
    _, c_idx = src.to_index(dst.x_centres(), np.zeros(dst.cols))
    wy = _cubic_weights(r_idx, src.rows)
    wx = _cubic_weights(c_idx, src.cols)
    tmp = wy @ np.asarray(values, dtype=np.float64)  # (dst.rows, src.cols)
    out = np.empty(dst.shape, dtype=dtype)
    wxt = wx.T.tocsr()
    for a in range(0, dst.rows, 512):  # row blocks bound the float64 temporaries
        out[a : a + 512] = tmp[a : a + 512] @ wxt
    return out


def body() -> Ellipsoid:
    """The body of every simulated scene: the IAU 2015 Mars sphere."""
    return MARS_IAU2015_SPHERE
