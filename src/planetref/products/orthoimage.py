"""Orthorectify a whole CCD image through a camera and a DEM into a GeoTIFF, block by block.

The output grid is in the reference CRS, north-up, at a chosen ground sampling distance.
For every output pixel the DEM height at its map position gives a body-fixed point,
which the camera projects into the raw image; the raw image is sampled bilinearly there.

Cost and accuracy
-----------------
The camera projection (an iterative line search per point) is the expensive part, so it
is computed exactly only on a sparse lattice of output pixels and interpolated
bilinearly (in float64, exact weights) in between. The lattice spacing adapts per block:
it starts at ``lattice_step`` output pixels and is halved while the bilinear
interpolation error bound of the block's lattice, ``(max|D2_rows| + max|D2_cols|) / 4``
of the second differences of line and sample, exceeds ``max_error_px`` image pixels.
The lattice of one block starts its line search from the previous block's lattice
extrapolated along rows, so the search is a few Newton steps instead of a bracketing.

Memory
------
The output is produced in blocks of ``block_rows`` rows, each reading only the raw lines
it needs and written with a windowed write to a temporary file renamed at the end, so
memory stays bounded by the block size whatever the strip length.

Resume
------
Next to each orthoimage a ``.inputs.sha256`` file holds a digest of what it was made
from (the camera, the image file, the DEM, the CRS and the settings); when it matches,
a re-run keeps the orthoimage instead of computing it again.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.arrays import F64
from planetref.camera.base import Camera, Terrain
from planetref.camera.mapping import project_to_image, rays_to_ground
from planetref.errors import GeometryError
from planetref.geometry.lattice import bilinear_lattice
from planetref.geometry.lattice import lattice_cell as _cell

__all__ = ["LatticeProjector", "OrthoGrid", "OrthoSettings", "bilinear_lattice"]

DIGEST_SUFFIX = ".inputs.sha256"


@dataclass(frozen=True)
class OrthoSettings:
    """How an orthoimage is computed.

    Attributes:
        lattice_step: Starting spacing of the exactly projected lattice (output pixels).
        min_lattice_step: The spacing is never refined below this.
        max_error_px: Bound on the bilinear interpolation error of the image coordinates
            (image pixels) that triggers a finer lattice; ``None`` keeps ``lattice_step``.
        block_rows: Output rows per block (bounds the memory).
    """

    lattice_step: int = 64
    min_lattice_step: int = 4
    max_error_px: float | None = 0.02
    block_rows: int = 256


@dataclass(frozen=True)
class OrthoGrid:
    """A north-up output grid: pixel ``(r, c)`` covers map ``[x0 + c g, x0 + (c+1) g)`` in x.

    Attributes:
        ground: The :class:`~planetref.geometry.geodesy.CrsGround` of the output CRS.
        x0: Map x of the left edge.
        y1: Map y of the top edge.
        gsd_m: Pixel size (CRS units, metres).
        width: Columns.
        height: Rows.
    """

    ground: Any
    x0: float
    y1: float
    gsd_m: float
    width: int
    height: int

    def map_xy(self, rows: F64, cols: F64) -> tuple[F64, F64]:
        """Continuous pixel positions (edges at integers, centres at +0.5) to map x, y."""
        return self.x0 + cols * self.gsd_m, self.y1 - rows * self.gsd_m


def footprint(
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


def _error_bounds(lat: F64, inside: NDArray[np.bool_]) -> tuple[float, float]:
    """Bounds on the bilinear interpolation error along rows and along columns.

    A quarter of the largest second difference of the lattice in each direction (a
    curvature contributes an eighth, a kink up to a quarter). Only triples of lattice
    points inside the image count: outside it nothing is sampled, and the camera's
    extrapolation there may bend more than it does over the image.
    """
    out = []
    with np.errstate(invalid="ignore"):
        for a in (lat, lat.T):
            e = 0.0
            if a.shape[0] >= 3:
                m = inside.T if a is not lat else inside
                d = np.abs(a[2:] - 2 * a[1:-1] + a[:-2])[m[2:] & m[1:-1] & m[:-2]]
                if np.isfinite(d).any():
                    e = float(np.nanmax(d)) / 4.0
            out.append(e)
    return out[0], out[1]


class LatticeProjector:
    """Image coordinates of every output pixel, from an adaptive sparse lattice.

    Args:
        camera: The camera.
        ccd: CCD name.
        terrain: The DEM.
        grid: The output grid.
        settings: Lattice settings.
    """

    def __init__(
        self, camera: Camera, ccd: str, terrain: Terrain, grid: OrthoGrid, settings: OrthoSettings
    ) -> None:
        self.camera, self.ccd, self.terrain, self.grid = camera, ccd, terrain, grid
        self.settings = settings
        self._prev: tuple[F64, F64, F64] | None = None  # rows, cols, lines of the last lattice
        self.n_projected = 0
        self.steps_used: list[tuple[int, int]] = []  # (rows, columns) per block

    def exact(self, rows: F64, cols: F64, line_guess: F64 | None = None) -> tuple[F64, F64]:
        """Exact projection at continuous output pixel positions (flat arrays)."""
        mx, my = self.grid.map_xy(np.asarray(rows, float), np.asarray(cols, float))
        ground = self.grid.ground
        lon, lat = ground.map_to_lonlat(mx, my)
        h = np.asarray(self.terrain.height(lon, lat), np.float64)
        xyz = ground.map_to_xyz(mx, my, h)
        self.n_projected += len(xyz)
        return project_to_image(self.camera, self.ccd, xyz, line_guess=line_guess)

    def _guess(self, rows: F64, cols: F64) -> F64 | None:
        if self._prev is None:
            return None
        prows, pcols, plines = self._prev
        if len(prows) < 2:
            return None
        last, before = plines[-1], plines[-2]
        slope = (last - before) / (prows[-1] - prows[-2])
        ok = np.isfinite(last) & np.isfinite(slope)
        if ok.sum() < 2:
            return None
        base = np.interp(cols, pcols[ok], last[ok])
        rate = np.interp(cols, pcols[ok], slope[ok])
        return (base[None, :] + (rows[:, None] - prows[-1]) * rate[None, :]).ravel()

    def block(self, r0: int, r1: int) -> tuple[F64, F64]:
        """Dense ``(line, sample)`` of the pixel centres of output rows ``r0:r1``.

        :meth:`block_lattice` interpolated by :func:`bilinear_lattice`.

        Returns:
            Two ``(r1 - r0, width)`` float64 arrays, NaN where the projection fails.
        """
        lat_l, lat_s, ir, fr, ic, fc = self.block_lattice(r0, r1)
        return bilinear_lattice(lat_l, ir, fr, ic, fc), bilinear_lattice(lat_s, ir, fr, ic, fc)

    def block_lattice(self, r0: int, r1: int) -> tuple[F64, F64, Any, F64, Any, F64]:
        """The lattice of output rows ``r0:r1`` and where each pixel centre falls in it.

        The lattice steps along rows and along columns are refined separately (a line-scan
        camera's mapping bends mostly with time, i.e. along one direction): a direction
        whose error bound exceeds half of ``max_error_px`` is halved (the larger first).

        Returns:
            ``(lat_line, lat_sample, ir, fr, ic, fc)``: the lattice's lines and samples
            (NaN where the projection fails) and the cells and fractions of the rows and
            columns of the pixel centres (see :func:`bilinear_lattice`).
        """
        s = self.settings
        width = self.grid.width
        n_lines, n_samples = self.camera.image_size(self.ccd)
        top = max(1, int(s.lattice_step))
        floor = max(1, int(s.min_lattice_step))
        # Start from twice the previous block's steps: one pass where the bending is the
        # same, and the lattice coarsens again where it relaxes.
        step_r, step_c = (
            (min(top, 2 * self.steps_used[-1][0]), min(top, 2 * self.steps_used[-1][1]))
            if self.steps_used
            else (top, top)
        )
        guess_fn = self._guess
        centres_r = np.arange(r0, r1) + 0.5
        centres_c = np.arange(width) + 0.5
        while True:
            n_r = -(-(r1 - r0) // step_r) + 1
            n_c = -(-width // step_c) + 1
            rows = r0 + step_r * np.arange(n_r, dtype=np.float64)
            cols = step_c * np.arange(n_c, dtype=np.float64)
            rr, cc = np.meshgrid(rows, cols, indexing="ij")
            guess = guess_fn(rows, cols)
            if guess is not None and not np.all(np.isfinite(guess)):
                fill = np.nanmedian(guess) if np.isfinite(guess).any() else np.nan
                guess = None if not np.isfinite(fill) else np.where(np.isfinite(guess), guess, fill)
            line, sample = self.exact(rr.ravel(), cc.ravel(), guess)
            lat_l, lat_s = line.reshape(rr.shape), sample.reshape(rr.shape)
            if s.max_error_px is None:
                break
            with np.errstate(invalid="ignore"):
                inside = (
                    (lat_l > -step_r)
                    & (lat_l < n_lines + step_r)
                    & (lat_s > -step_c)
                    & (lat_s < n_samples + step_c)
                )
            el_r, el_c = _error_bounds(lat_l, inside)
            es_r, es_c = _error_bounds(lat_s, inside)
            e_r, e_c = max(el_r, es_r), max(el_c, es_c)
            half = 0.5 * s.max_error_px
            if e_r > half and step_r > floor and (e_r >= e_c or step_c <= floor or e_c <= half):
                step_r = max(floor, step_r // 2)
            elif e_c > half and step_c > floor:
                step_c = max(floor, step_c // 2)
            else:
                break
            guess_fn = self._coarse_guess(rows, cols, lat_l)
        self._prev = (rows, cols, lat_l)
        self.steps_used.append((step_r, step_c))
        ir, fr = _cell((centres_r - r0) / step_r, n_r)
        ic, fc = _cell(centres_c / step_c, n_c)
        return lat_l, lat_s, ir, fr, ic, fc

    @staticmethod
    def _coarse_guess(rows: F64, cols: F64, lines: F64) -> Any:
        """Starting lines for a finer lattice: the coarse one, interpolated."""

        def guess(rows_f: F64, cols_f: F64) -> F64:
            # The finer lattice's nodes include the coarse ones: those keep their exact
            # lines even next to a NaN node (see bilinear_lattice).
            ir, fr = _cell((rows_f - rows[0]) / (rows[1] - rows[0]), len(rows))
            ic, fc = _cell((cols_f - cols[0]) / (cols[1] - cols[0]), len(cols))
            return bilinear_lattice(lines, ir, fr, ic, fc).ravel()

        return guess


@functools.cache
def compression() -> dict[str, Any]:
    """ZSTD level 1 where GDAL has it (~4x faster than DEFLATE, same size), else DEFLATE.

    GDAL's ZSTD codec is optional: a one-pixel GeoTIFF written in memory and read back
    tells whether this GDAL has it (rasterio's enum only lists the names GDAL may know).
    """
    from affine import Affine
    from rasterio.io import MemoryFile

    profile = {"driver": "GTiff", "width": 1, "height": 1, "count": 1, "dtype": "uint8"}
    profile["transform"] = Affine(2.0, 0.0, 0.0, 0.0, -2.0, 2.0)  # georeferenced: no warning
    try:
        with MemoryFile() as mem:
            with mem.open(**profile, compress="zstd") as ds:
                ds.write(np.zeros((1, 1, 1), np.uint8))
            with mem.open() as ds:
                has_zstd = str(getattr(ds.compression, "value", ds.compression)).upper() == "ZSTD"
    except Exception:  # any GDAL failure: the portable codec
        has_zstd = False
    if has_zstd:
        return {"compress": "zstd", "zstd_level": 1}
    return {"compress": "deflate", "zlevel": 1}


def file_id(path: Any) -> list[Any]:
    try:
        st = os.stat(path)
    except (OSError, TypeError):
        return [str(path)]
    return [str(Path(path).resolve()), st.st_size, st.st_mtime_ns]


def terrain_id(terrain: Terrain) -> list[Any]:
    heights = getattr(terrain, "heights", None)
    if heights is None:
        return [repr(terrain)]
    h = hashlib.sha256(np.ascontiguousarray(heights).tobytes()).hexdigest()
    return [type(terrain).__name__, h, repr(getattr(terrain, "transform", None))]


def inputs_digest(
    image: Any, camera: Camera, ccd: str, terrain: Terrain, crs: Any, gsd_m: float, s: OrthoSettings
) -> str:
    """SHA-256 of what an orthoimage is made from (camera content, input files, settings)."""
    to_dict = getattr(camera, "to_dict", None)
    cam_doc = to_dict() if callable(to_dict) else repr(camera)
    doc = {
        "camera": cam_doc,
        "ccd": ccd,
        "image": file_id(getattr(image, "path", None)),
        "dem": terrain_id(terrain),
        "crs": str(crs),
        "gsd_m": float(gsd_m),
        "settings": [s.lattice_step, s.min_lattice_step, s.max_error_px, s.block_rows],
    }
    blob = json.dumps(doc, sort_keys=True, default=repr).encode()
    return hashlib.sha256(blob).hexdigest()
