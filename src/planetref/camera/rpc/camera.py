""":class:`RpcCamera`: the :class:`~planetref.camera.base.Camera` protocol on an RPC.

Image coordinates are planetref's (GDAL's): raw RPC image coordinates plus half a pixel
(see :mod:`planetref.camera.rpc.model`). Heights are above the RPC's body
(:class:`~planetref.camera.rpc.body.RpcBody`); ground is body-fixed XYZ in metres.
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.camera.base import ConstantHeight, ImagePoints, OnMiss, Terrain
from planetref.camera.rpc.body import EARTH_BODY, RpcBody
from planetref.camera.rpc.formats import read
from planetref.camera.rpc.model import Rpc
from planetref.errors import (
    GeometryError,
    InputError,
)
from planetref.geometry.geodesy import (
    Ellipsoid,
    LatitudeKind,
    lonlat_to_xyz,
    xyz_to_lonlat,
)
from planetref.geometry.terrain import first_crossing

__all__ = ["RpcCamera"]


# --------------------------------------------------------------------------- camera

#: Bisection tolerance of terrain intersections in height (metres).
_HEIGHT_TOL_M = 1e-5


class RpcCamera:
    """A :class:`~planetref.camera.base.Camera` defined by an RPC00B model.

    Image coordinates follow planetref's convention (first pixel centre at 0.5), which
    is GDAL's: ``project`` equals ``rasterio.transform.RPCTransformer.rowcol`` without
    rounding, and ``localize`` equals its ``xy(..., offset="ul")``.

    Args:
        rpc: The model.
        ellipsoid: The body the RPC's longitudes, latitudes and heights refer to
            (``EARTH_WGS84`` for Earth imagery, ``MARS_IAU2015_SPHERE`` for Mars).
        latitude_kind: The latitude LAT_OFF/LAT_SCALE refer to: ``"planetographic"``
            (geodetic; Earth RPCs) or ``"planetocentric"``.
        image_size: ``(n_lines, n_samples)`` of the image.
        name: The name of the camera's single CCD.

    Raises:
        InputError: If the latitude kind or image size is invalid.
    """

    def __init__(
        self,
        rpc: Rpc,
        ellipsoid: Ellipsoid,
        latitude_kind: LatitudeKind,
        image_size: tuple[int, int],
        name: str = "rpc",
    ) -> None:
        if latitude_kind not in ("planetocentric", "planetographic"):
            raise InputError(f"unknown latitude kind {latitude_kind!r}", field="latitude_kind")
        try:
            n_lines, n_samples = (int(v) for v in image_size)
        except (TypeError, ValueError):
            raise InputError(
                f"expected (n_lines, n_samples), got {image_size!r}", field="image_size"
            ) from None
        if n_lines <= 0 or n_samples <= 0:
            raise InputError(f"image size must be positive, got {image_size!r}", field="image_size")
        self.rpc = rpc
        self.ellipsoid = ellipsoid
        self.latitude_kind: LatitudeKind = latitude_kind
        self._size = (n_lines, n_samples)
        self.name = name
        #: The file the RPC was read from (set by :meth:`from_file`), else None.
        self.source: Path | None = None

    def __repr__(self) -> str:
        return (
            f"RpcCamera(name={self.name!r}, size={self._size}, "
            f"body={self.ellipsoid.name!r}, latitude={self.latitude_kind!r})"
        )

    @classmethod
    def from_file(
        cls,
        path: str | os.PathLike[str],
        body: str | Ellipsoid | RpcBody | None = None,
        *,
        latitude_kind: LatitudeKind | None = None,
        image_size: tuple[int, int] | None = None,
        name: str | None = None,
    ) -> RpcCamera:
        """Read an RPC file (any format :func:`read_rpc` reads) into a camera.

        Args:
            path: A raster with RPC metadata, or an ``.RPB``/``_RPC.TXT`` file.
            body: ``"earth"``, ``"mars"``, an :class:`Ellipsoid` or an :class:`RpcBody`.
                When None, the body planetref recorded in the file, else Earth WGS84
                with geodetic latitude (the RPC00B standard, which GDAL assumes).
            latitude_kind: Overrides the latitude kind of ``body``.
            image_size: ``(n_lines, n_samples)``. When None: the raster's size, or for
                a sidecar the size of the image next to it (``scene.tif`` for
                ``scene.RPB`` or ``scene_RPC.TXT``).
            name: CCD name (default: the file's stem).

        Raises:
            InputError: If the image size is needed but cannot be found, and the
                errors of :func:`read_rpc`.
        """
        p = Path(path)
        rpc, stored = read(p)
        if body is None:
            resolved = RpcBody.resolve(stored or EARTH_BODY, latitude_kind)
        else:
            resolved = RpcBody.resolve(body, latitude_kind)
        if image_size is None:
            try:
                image_size = _find_image_size(p)
            except InputError:
                # No raster beside the sidecar: the RPC's normalisation domain is the
                # best estimate of the image extent (only ``in_image`` depends on it).
                image_size = (
                    max(1, math.ceil(rpc.line_off + abs(rpc.line_scale) + 0.5)),
                    max(1, math.ceil(rpc.samp_off + abs(rpc.samp_scale) + 0.5)),
                )
                logging.getLogger(__name__).warning(
                    "%s: no raster beside the RPC file; image size taken from the RPC "
                    "domain as %s lines x %s samples",
                    p,
                    *image_size,
                )
        cam = cls(rpc, resolved.ellipsoid, resolved.latitude_kind, image_size, name or p.stem)
        cam.source = p
        return cam

    @property
    def ray_heights_m(self) -> tuple[float, float]:
        """Heights (m) between which the RPC is valid: ``HEIGHT_OFF ± HEIGHT_SCALE``.

        Rays built from two localisations should stay in this domain: a cubic in height
        extrapolated far beyond it (e.g. to ±10 km for a 1 km domain) is meaningless.
        """
        h0, hs = self.rpc.height_off, abs(self.rpc.height_scale)
        return h0 - hs, h0 + hs

    # -- Camera protocol ------------------------------------------------------------

    @property
    def ccd_names(self) -> tuple[str, ...]:
        """The single CCD name."""
        return (self.name,)

    def _check_ccd(self, ccd: str | None) -> None:
        if ccd is not None and ccd != self.name:
            raise InputError(
                f"unknown CCD {ccd!r}; this RPC camera has only {self.name!r}", field="ccd"
            )

    def image_size(self, ccd: str | None = None) -> tuple[int, int]:
        """``(n_lines, n_samples)``."""
        self._check_ccd(ccd)
        return self._size

    def project(
        self, lon_deg: ArrayLike, lat_deg: ArrayLike, height_m: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Ground (lon, lat in this camera's latitude kind, degrees; h, metres) to image.

        Returns:
            ``(line, sample)`` in pixels (first pixel centre at 0.5), broadcast shape.
        """
        return self.rpc.project(lon_deg, lat_deg, height_m)

    def localize(
        self, line: ArrayLike, sample: ArrayLike, height_m: ArrayLike, *, tol_px: float = 1e-8
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Image to lon/lat (degrees, this camera's latitude kind) at given heights (m).

        Newton iterations on the rational polynomials with their analytic Jacobian,
        to ``tol_px`` pixels of reprojection error; NaN where they do not converge.
        """
        return self.rpc.localize(line, sample, height_m, tol_px=tol_px)

    def ground_to_image(self, xyz: ArrayLike, *, ccd: str | None = None) -> ImagePoints:
        """Project body-fixed points (metres, shape ``(M, 3)`` or ``(3,)``) into the image.

        Returns:
            :class:`ImagePoints`; ``valid`` is False only for non-finite input or a zero
            denominator (an RPC extrapolates everywhere, so far-away points are
            "valid" but not ``in_image``).
        """
        self._check_ccd(ccd)
        pts = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        lon, lat, h = xyz_to_lonlat(pts, self.ellipsoid, self.latitude_kind)
        line, sample = self.rpc.project(lon, lat, h)
        valid = np.isfinite(line) & np.isfinite(sample)
        n_lines, n_samples = self._size
        with np.errstate(invalid="ignore"):
            in_image = valid & (line >= 0) & (line < n_lines) & (sample >= 0) & (sample < n_samples)
        return ImagePoints(
            np.where(valid, line, np.nan), np.where(valid, sample, np.nan), valid, in_image
        )

    def image_to_ground(
        self,
        line: ArrayLike,
        sample: ArrayLike,
        terrain: Terrain | float = 0.0,
        *,
        ccd: str | None = None,
        on_miss: OnMiss = "raise",
    ) -> NDArray[np.float64]:
        """Intersect the RPC's lines of sight with a height or a terrain.

        For a height, the RPC is inverted at that height. For a :class:`Terrain`, the
        line of sight (the curve ``h -> localize(line, sample, h)``) is followed from
        above ``max_height_m`` down to below ``min_height_m`` in steps that move at
        most half ``sampling_m`` horizontally by
        :func:`planetref.geometry.terrain.first_crossing` (the one marcher, with its rule
        at terrain holes), and the first crossing is refined by bisection to 10 µm in
        height. Terrain heights are compared as heights above the terrain's own
        ellipsoid at its planetocentric lon/lat.

        Args:
            line: Line coordinates (planetref convention), shape ``(M,)`` or scalar.
            sample: Sample coordinates, same shape.
            terrain: A :class:`Terrain`, or a height in metres above this camera's
                ellipsoid.
            ccd: Must be None or this camera's name.
            on_miss: ``"raise"`` a :class:`GeometryError` if any point has no solution
                (no convergence, terrain hole, no crossing), or return NaN rows.

        Returns:
            Body-fixed XYZ, metres, shape ``(M, 3)``.
        """
        self._check_ccd(ccd)
        ln, sm = np.broadcast_arrays(np.asarray(line, np.float64), np.asarray(sample, np.float64))
        ln, sm = ln.ravel(), sm.ravel()
        if isinstance(terrain, ConstantHeight) and terrain.ellipsoid == self.ellipsoid:
            terrain = float(terrain.height_m)
        if isinstance(terrain, Terrain):
            xyz = self._intersect_terrain(ln, sm, terrain)
        else:
            try:
                h = float(terrain)
            except (TypeError, ValueError):
                raise InputError(
                    f"terrain must be a Terrain or a height in metres, got {terrain!r}",
                    field="terrain",
                ) from None
            lon, lat = self.rpc.localize(ln, sm, h)
            xyz = lonlat_to_xyz(lon, lat, h, self.ellipsoid, self.latitude_kind)
        bad = ~np.all(np.isfinite(xyz), axis=1)
        if on_miss == "raise" and np.any(bad):
            i = int(np.flatnonzero(bad)[0])
            raise GeometryError(
                f"{int(bad.sum())} of {bad.size} image points have no ground intersection "
                f"(first: line {ln[i]:.3f}, sample {sm[i]:.3f}): the RPC inversion did not "
                "converge or the line of sight misses the terrain"
            )
        return xyz

    def _line_of_sight(
        self,
        ln: NDArray[np.float64],
        sm: NDArray[np.float64],
        h: NDArray[np.float64],
        terrain: Terrain,
    ) -> tuple[NDArray[np.float64], ...]:
        """Points of the line of sight at heights ``h`` above the camera's ellipsoid.

        Returns:
            Their heights above the terrain's ellipsoid, the terrain's height below them
            (NaN: unknown terrain) and their body-fixed XYZ (all metres).
        """
        lon, lat = self.rpc.localize(ln, sm, h)
        xyz = lonlat_to_xyz(lon, lat, h, self.ellipsoid, self.latitude_kind)
        tlon, tlat, th = xyz_to_lonlat(xyz, terrain.ellipsoid, "planetocentric")
        surface = np.asarray(terrain.height(tlon, tlat), dtype=np.float64)
        return th, surface, xyz

    def _intersect_terrain(
        self, ln: NDArray[np.float64], sm: NDArray[np.float64], terrain: Terrain
    ) -> NDArray[np.float64]:
        m = ln.size
        lo, hi = float(terrain.min_height_m), float(terrain.max_height_m)
        if not (math.isfinite(lo) and math.isfinite(hi)) or hi < lo:
            raise InputError(
                f"terrain height bounds must be finite with min <= max, got [{lo}, {hi}]",
                field="terrain",
            )
        # The bounds are heights above the terrain's ellipsoid and the march is in
        # heights above the camera's: widen by the largest separation of the two
        # ellipsoids, plus a margin so that a surface touching its bounds is bracketed.
        other = terrain.ellipsoid
        margin = (
            1.0
            + 1e-3 * (hi - lo)
            + abs(other.semi_major_m - self.ellipsoid.semi_major_m)
            + abs(other.semi_minor_m - self.ellipsoid.semi_minor_m)
        )
        top, bottom = hi + margin, lo - margin
        *_, xyz_top = self._line_of_sight(ln, sm, np.full(m, top), terrain)
        *_, xyz_bot = self._line_of_sight(ln, sm, np.full(m, bottom), terrain)
        chord = np.linalg.norm(xyz_top - xyz_bot, axis=1)
        horizontal = np.sqrt(np.maximum(chord**2 - (top - bottom) ** 2, 0.0))
        # Steps move at most half a terrain sample horizontally (as for straight rays).
        half_sample = 0.5 * float(terrain.sampling_m)
        reach = float(np.nanmax(horizontal)) if np.any(np.isfinite(horizontal)) else 0.0
        n_steps = 1
        if math.isfinite(half_sample) and half_sample > 0:
            n_steps = int(min(max(math.ceil(reach / half_sample), 1), 100_000))

        def profile(
            idx: NDArray[np.intp], drop: NDArray[np.float64]
        ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
            # The line of sight is parametrised by the height drop below ``top``.
            th, surface, _ = self._line_of_sight(ln[idx], sm[idx], top - drop, terrain)
            return th, surface

        drop = first_crossing(
            profile,
            np.zeros(m),
            np.full(m, top - bottom),
            (top - bottom) / n_steps,
            max_height_m=hi,
            tol_m=_HEIGHT_TOL_M,
        )
        xyz = np.full((m, 3), np.nan)
        ok = np.flatnonzero(np.isfinite(drop))
        if ok.size:
            lon, lat = self.rpc.localize(ln[ok], sm[ok], top - drop[ok])
            xyz[ok] = lonlat_to_xyz(lon, lat, top - drop[ok], self.ellipsoid, self.latitude_kind)
        return xyz


def _find_image_size(p: Path) -> tuple[int, int]:
    import rasterio
    from rasterio.errors import RasterioIOError

    candidates = [p]
    name = p.name
    if name.lower().endswith("_rpc.txt"):
        stem = name[: -len("_rpc.txt")]
    elif name.lower().endswith(".rpb"):
        stem = name[:-4]
    else:
        stem = None
    if stem is not None:
        candidates = sorted(
            q
            for q in p.parent.glob(stem + ".*")
            if q.suffix.lower() in {".tif", ".tiff", ".ntf", ".jp2", ".img", ".cub", ".vrt"}
        )
    for q in candidates:
        try:
            with rasterio.open(q) as src:
                return (src.height, src.width)
        except RasterioIOError:
            continue
    raise InputError(
        "cannot tell the image size: no raster found next to this RPC file; "
        "pass image_size=(n_lines, n_samples)",
        path=p,
        field="image_size",
    )
