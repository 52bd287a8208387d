"""Orthoimages of a strip: every CCD and their mosaic on one round grid, streamed.

:func:`orthorectify_strip` writes one GeoTIFF per CCD and (optionally) a mosaic of all
of them, in one pass over block rows of a common north-up grid:

* **Grid.** Every output shares one pixel size (``gsd_m``; :func:`round_gsd` turns a
  CCD's native GSD such as 0.4873 m into a round 0.5 m) and one lattice of pixel edges
  at integer multiples of it in the reference CRS, so the CCD orthoimages, the mosaic
  and orthoimages of other strips at the same size overlay pixel for pixel. A CCD's
  file covers its footprint (its top row moved up to the mosaic's block grid so that
  every write fills whole 256-row tiles); every file's width and height are rounded up
  to a multiple of its largest overview factor (nodata at the right and bottom), and
  the mosaic covers every CCD's file.
* **Data type.** The input's type is kept: floating inputs as float32 (float64 stays
  float64) with NaN nodata; unsigned integers with nodata at the type's maximum
  (255, 65535), signed ones at its minimum, valid values rounded and clipped one short
  of it: a valid pixel never reads as nodata (only an input pixel at the type's extreme,
  i.e. saturated, is written one DN below it).
* **Overviews.** Internal overviews (factors 2, 4, ... while the smaller side stays
  >= 256 pixels), averaged over valid pixels: GDAL's ``AVERAGE`` bit for bit, but
  computed from each block as it is written (:mod:`planetref.products.overviews`)
  instead of reading the finished file back.
* **Mosaic, overlap rule.** Where CCDs overlap, a mosaic pixel takes the CCD whose image
  point lies farthest from that CCD's first/last sample (the distance to its nearer
  side edge), so seams run along the middle of each overlap, where both CCDs are
  farthest from their edges; ties go to the CCD listed first.
* **Streaming and atomic writes.** Each block of ``block_rows`` rows is projected
  (:class:`~planetref.products.orthoimage.LatticeProjector`), resampled from the raw
  lines it needs and written with windowed writes into temporary files renamed when
  complete; memory is bounded by the block size (and GDAL's block cache by
  :data:`GDAL_CACHE_MB`).
* **Compiled, parallel blocks.** A block's lattice becomes dense maps and the raw lines
  are sampled bilinearly in compiled kernels that release the GIL
  (:mod:`planetref.products._numba_ortho`; the numpy/OpenCV path
  :func:`_resample_reference` is their reference and the fallback without numba, with
  the same pixels on OpenCV 5, whereas OpenCV 4 quantises positions to 1/32 pixel), so
  the CCDs of a block row run in ``threads`` threads; each raw line is read and decoded
  about once (runs aligned to the input's tiles, kept while the next block needs them),
  and the files' overview levels are written in the same threads at the end.
* **Resume.** A digest of the inputs (cameras, images, DEM, CRS, grid, settings) is
  written next to each file; a re-run with the same digest keeps the files.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import os
from collections.abc import Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.camera.base import Camera, Terrain
from planetref.errors import GeometryError, InputError
from planetref.products.orthoimage import (
    DIGEST_SUFFIX,
    LatticeProjector,
    OrthoGrid,
    OrthoSettings,
    compression,
    file_id,
    footprint,
    terrain_id,
)
from planetref.products.overviews import OverviewPyramid, overview_factors, padded_size
from planetref.runtime.atomic import atomic_path

__all__ = ["PixelType", "StripOrthoResult", "orthorectify_ccd", "orthorectify_strip", "round_gsd"]

F32 = NDArray[np.float32]
#: Round pixel sizes (times a power of ten) that :func:`round_gsd` chooses from.
ROUND_STEPS = (1.0, 1.2, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0)
TILE = 256
log = logging.getLogger(__name__)
#: Key of the mosaic among the outputs (CCD names are the others).
_MOSAIC = "\0mosaic"
#: GDAL's block cache while writing (MB), and during a whole georef run. GDAL's default,
#: 5 % of the RAM, fills with the blocks read and written (raw CCD lines, the outputs and
#: their overviews), so the process grew with the strip length (hiric-strip: ~70 MB more
#: for the mosaic's overviews alone); every block row here completes its tiles and every
#: raw window is read once or twice, so a small cache costs nothing.
GDAL_CACHE_MB = 64


def round_gsd(gsd_m: float) -> float:
    """The round pixel size nearest (in ratio) to ``gsd_m``: 0.4873 -> 0.5, 2.7 -> 2.5.

    The candidates are :data:`ROUND_STEPS` times powers of ten (neighbours differ by at
    most a factor 1.33, so the rounding changes the size by at most ~15 %).
    """
    g = float(gsd_m)
    if not (np.isfinite(g) and g > 0):
        raise InputError(f"pixel size must be positive, got {gsd_m}")
    k = math.floor(math.log10(g))
    cands = [s * 10.0**e for e in (k - 1, k, k + 1) for s in ROUND_STEPS]
    best = min(cands, key=lambda c: abs(math.log(c / g)))
    return float(f"{best:.12g}")


@dataclass(frozen=True)
class PixelType:
    """Output data type and nodata for an input data type (see the module doc).

    Attributes:
        dtype: Output numpy dtype.
        nodata: The nodata value (NaN for floats).
        lo: Smallest valid value (integers), else None.
        hi: Largest valid value (integers), else None.
    """

    dtype: np.dtype[Any]
    nodata: float
    lo: float | None = None
    hi: float | None = None

    @classmethod
    def of(cls, dtype: Any) -> PixelType:
        """The output type of an input dtype."""
        dt = np.dtype(dtype)
        if np.issubdtype(dt, np.floating):
            out = np.dtype(np.float64) if dt.itemsize > 4 else np.dtype(np.float32)
            return cls(out, float("nan"))
        if np.issubdtype(dt, np.unsignedinteger):
            info = np.iinfo(dt)
            return cls(dt, float(info.max), float(info.min), float(info.max) - 1.0)
        if np.issubdtype(dt, np.signedinteger):
            info = np.iinfo(dt)
            return cls(dt, float(info.min), float(info.min) + 1.0, float(info.max))
        return cls(np.dtype(np.float32), float("nan"))

    def cast(self, values: F32) -> NDArray[Any]:
        """Float values (NaN = no data) to the output type, nodata where NaN."""
        if self.lo is None:
            return values.astype(self.dtype, copy=False)
        v = np.rint(values)
        np.clip(v, self.lo, self.hi, out=v)  # NaN stays NaN
        v[np.isnan(values)] = self.nodata
        return v.astype(self.dtype)


@dataclass
class StripOrthoResult:
    """What :func:`orthorectify_strip` wrote.

    Attributes:
        ccds: CCD name -> orthoimage path.
        mosaic: The mosaic's path (None if not asked for).
        gsd_m: The common pixel size.
        dtype: The output data type's name.
        nodata: The nodata value.
        resumed: True when every file was kept from a previous run.
    """

    ccds: dict[str, Path]
    mosaic: Path | None
    gsd_m: float
    dtype: str
    nodata: float
    resumed: bool = False


@dataclass
class _CcdJob:
    ccd: str
    image: Any
    grid: OrthoGrid
    row_off: int
    col_off: int
    projector: LatticeProjector
    n_lines: int
    n_samples: int
    #: Raw lines are read in whole runs of this many (the input's tile height, 256 for
    #: the simulator's and most tiled GeoTIFFs): a tile is decoded once.
    read_align: int = TILE
    #: The raw lines kept from the last read, ``(first line, float32, NaN where invalid)``.
    last_raw: tuple[int, F32] | None = None

    def raw(self, l_lo: int, l_hi: int) -> F32:
        """Raw lines ``l_lo:l_hi`` (all samples) as float32, NaN where invalid.

        Consecutive blocks' windows overlap (hiric-strip: each line falls in ~2.1
        windows). Lines are read in runs aligned to :attr:`read_align` and kept until a
        window no longer needs them, so each line is read and decoded about once.
        """
        k = max(1, int(self.read_align))
        up = min(self.n_lines, -(-l_hi // k) * k)
        down = max(0, (l_lo // k) * k)
        if self.last_raw is not None:
            p0, prev = self.last_raw
            p1 = p0 + len(prev)
            if p0 <= l_lo and l_hi <= p1:
                return prev[l_lo - p0 : l_hi - p0]
            if p0 <= l_lo < p1:  # the window starts inside the kept lines
                kept = self._join(prev[l_lo - p0 :], self._read(p1, up))
                self.last_raw = (l_lo, kept)
                return kept[: l_hi - l_lo]
            if p0 < l_hi <= p1:  # it ends inside them (blocks moving up the image)
                kept = self._join(self._read(down, p0), prev[: l_hi - p0])
                self.last_raw = (down, kept)
                return kept[l_lo - down :]
        kept = self._read(down, up)
        self.last_raw = (down, kept)
        return kept[l_lo - down : l_hi - down]

    def _read(self, a: int, b: int) -> F32:
        if b <= a:
            return np.empty((0, self.n_samples), np.float32)
        raw, valid = self.image.read(a, 0, b - a, self.n_samples)
        raw = np.asarray(raw, np.float32)
        return raw if valid.all() else np.where(valid, raw, np.float32(np.nan))

    @staticmethod
    def _join(head: F32, tail: F32) -> F32:
        if not len(tail):
            return np.ascontiguousarray(head)
        if not len(head):
            return np.ascontiguousarray(tail)
        return np.concatenate([head, tail], axis=0)


def _strip_digest(
    images: Mapping[str, Any],
    camera: Camera,
    terrain: Terrain,
    crs: Any,
    gsd_m: float,
    s: OrthoSettings,
    mosaic: bool,
) -> str:
    to_dict = getattr(camera, "to_dict", None)
    doc = {
        "camera": to_dict() if callable(to_dict) else repr(camera),
        "images": {c: file_id(getattr(im, "path", None)) for c, im in images.items()},
        "dem": terrain_id(terrain),
        "crs": str(crs),
        "gsd_m": float(gsd_m),
        "settings": [s.lattice_step, s.min_lattice_step, s.max_error_px, s.block_rows],
        "mosaic": mosaic,
        "format": 3,
    }
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=repr).encode()).hexdigest()


def _digest_ok(path: Path, digest: str) -> bool:
    """Whether ``path`` may be kept: same inputs (its digest file), same size, decodes.

    The digest file says what the output was made from, not that it is still whole: an
    orthoimage truncated or overwritten afterwards would be kept by a digest alone, so
    its size (recorded beside the digest) is compared and the file is opened and its
    first and last rows of blocks of every band decoded (GDAL writes blocks in row
    order, so a cut file fails there).
    """
    d = path.with_name(path.name + DIGEST_SUFFIX)
    if not (path.is_file() and not path.is_symlink() and d.is_file()):
        return False
    try:
        words = d.read_text(encoding="utf-8").split()
    except (OSError, UnicodeDecodeError):
        return False
    if not words or words[0] != digest:
        return False
    if len(words) >= 3 and words[1] == "size" and words[2] != str(path.stat().st_size):
        log.warning("%s: its size changed since it was written; writing it again", path)
        return False
    problem = _undecodable(path)
    if problem is not None:
        log.warning("%s: cannot be read back (%s); writing it again", path, problem)
        return False
    return True


def _undecodable(path: Path) -> str | None:
    """Why a GeoTIFF cannot be decoded (first and last rows of blocks), or None."""
    import rasterio
    from rasterio.windows import Window

    try:
        with rasterio.open(path) as ds:
            for band in range(1, ds.count + 1):
                rows = min(ds.height, max(1, ds.block_shapes[band - 1][0]))
                for row0 in sorted({0, ds.height - rows}):
                    ds.read(band, window=Window(0, row0, ds.width, rows))
    except Exception as exc:  # any GDAL/rasterio failure: the file is not whole
        return f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}".strip()
    return None


def _kernel() -> Any:
    """The compiled block kernels (:mod:`planetref.products._numba_ortho`), or None."""
    from planetref.runtime.optional import optional_module

    return optional_module("planetref.products._numba_ortho", "compiled orthoimage kernel")


def _resample(job: _CcdJob, r0: int, r1: int, want_dist: bool) -> tuple[F32, F32 | None]:
    """Resampled values of a CCD's rows r0:r1, and their edge distances for the mosaic.

    The compiled kernels (GIL released) when numba is there, else
    :func:`_resample_reference`; the two agree pixel for pixel (see the tests).

    Returns:
        Values (float32, NaN outside) and, if ``want_dist``, each pixel's distance
        (samples) to the CCD's nearer side edge (-inf where there is no value).
    """
    k = _kernel()
    if k is None:
        return _resample_reference(job, r0, r1, want_dist)
    lat_l, lat_s, ir, fr, ic, fc = job.projector.block_lattice(r0, r1)
    shape = (r1 - r0, job.grid.width)
    ml = np.empty(shape, np.float32)
    ms = np.empty(shape, np.float32)
    found, lo, hi = k.lattice_maps(lat_l, lat_s, ir, fr, ic, fc, job.n_lines, job.n_samples, ml, ms)
    empty = np.full(shape, np.nan, np.float32)
    if not found:
        return empty, (np.full_like(empty, -np.inf) if want_dist else None)
    l_lo = max(0, int(np.floor(lo)) - 2)
    l_hi = min(job.n_lines, int(np.ceil(hi)) + 2)
    if l_hi <= l_lo:
        return empty, (np.full_like(empty, -np.inf) if want_dist else None)
    raw = job.raw(l_lo, l_hi)
    dist = np.empty(shape, np.float32) if want_dist else empty
    k.resample_bilinear(raw, l_lo, ml, ms, job.n_lines, job.n_samples, empty, dist, want_dist)
    return empty, (dist if want_dist else None)


def _resample_reference(job: _CcdJob, r0: int, r1: int, want_dist: bool) -> tuple[F32, F32 | None]:
    """:func:`_resample` in numpy and OpenCV (``bilinear_lattice``, ``cv2.remap``)."""
    import cv2

    map_line, map_sample = job.projector.block(r0, r1)
    # float32 maps, as cv2.remap takes them.
    ml = map_line.astype(np.float32)
    ms = map_sample.astype(np.float32)
    with np.errstate(invalid="ignore"):
        inside = (ml > -1) & (ml < job.n_lines + 1) & (ms > -1) & (ms < job.n_samples + 1)
    empty = np.full((r1 - r0, job.grid.width), np.nan, np.float32)
    if not inside.any():
        return empty, (np.full_like(empty, -np.inf) if want_dist else None)
    lines = ml[inside]
    l_lo = max(0, int(np.floor(lines.min())) - 2)
    l_hi = min(job.n_lines, int(np.ceil(lines.max())) + 2)
    if l_hi <= l_lo:
        return empty, (np.full_like(empty, -np.inf) if want_dist else None)
    raw, valid = job.image.read(l_lo, 0, l_hi - l_lo, job.n_samples)
    if not valid.all():
        raw = np.where(valid, raw, np.float32(np.nan))
    # Pixel centres are at +0.5; remap indexes pixel centres from 0. A pixel whose
    # bilinear support leaves the image gets the NaN border.
    outside = ~inside
    mx = ms - np.float32(0.5)
    my = ml - np.float32(l_lo + 0.5)
    mx[outside] = -10.0
    my[outside] = -10.0
    out = cv2.remap(
        raw.astype(np.float32, copy=False),
        mx,
        my,
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=np.nan,
    )
    if not want_dist:
        return out, None
    dist = np.minimum(ms, np.float32(job.n_samples) - ms)
    dist[np.isnan(out)] = -np.inf
    return out, dist


def orthorectify_strip(
    images: Mapping[str, Any],
    camera: Camera,
    terrain: Terrain,
    crs: Any,
    paths: Mapping[str, str | os.PathLike[str]],
    *,
    gsd_m: float,
    mosaic: str | os.PathLike[str] | None = None,
    settings: OrthoSettings | None = None,
    resume: bool = True,
    overviews: bool = True,
    threads: int | None = None,
) -> StripOrthoResult:
    """Orthoimages of the CCDs of one strip and their mosaic (see the module doc).

    Args:
        images: CCD name -> :class:`~planetref.raster.image.CcdImage` (windowed reads), in
            the strip's order (the mosaic's tie-break order).
        camera: The strip's camera (e.g. the adjusted one).
        terrain: The DEM the images are projected onto.
        crs: The output CRS (the reference ortho's), projected, in metres.
        paths: CCD name -> output GeoTIFF.
        gsd_m: The common pixel size (CRS units); see :func:`round_gsd`.
        mosaic: Output GeoTIFF of the mosaic, or None.
        settings: Lattice and block settings.
        resume: Keep existing outputs whose inputs digest matches.
        overviews: Build internal overviews.
        threads: CCDs resampled at once, and files whose overviews are written at
            once (default: OpenCV's thread budget, see :mod:`planetref.runtime.threads`); the
            output does not depend on it.

    Returns:
        What was written.

    Raises:
        GeometryError: No CCD's footprint meets the DEM.
    """
    import cv2
    import rasterio
    from rasterio.enums import Resampling
    from rasterio.transform import from_origin
    from rasterio.windows import Window

    from planetref.geometry.geodesy import CrsGround

    s = settings or OrthoSettings()
    if threads is None:
        threads = cv2.getNumThreads()
    rows_per_block = max(TILE, (int(s.block_rows) // TILE) * TILE)
    g = float(gsd_m)
    dtypes = {np.dtype(getattr(im, "dtype", np.float32)) for im in images.values()}
    ptype = PixelType.of(np.result_type(*dtypes) if dtypes else np.float32)
    targets = {c: Path(paths[c]) for c in images}
    mosaic_path = None if mosaic is None else Path(mosaic)
    every = [*targets.values(), *([mosaic_path] if mosaic_path else [])]
    digest = _strip_digest(images, camera, terrain, crs, g, s, mosaic_path is not None)
    result = StripOrthoResult(targets, mosaic_path, g, ptype.dtype.name, ptype.nodata)
    if resume and all(_digest_ok(p, digest) for p in every):
        result.resumed = True
        return result

    ground = CrsGround(crs)
    boxes: dict[str, tuple[int, int, int, int]] = {}
    for ccd in images:
        try:
            x0, y0, x1, y1 = footprint(camera, ccd, terrain, ground)
        except GeometryError:
            continue
        boxes[ccd] = (
            math.floor(x0 / g),
            math.floor(y0 / g),
            max(math.ceil(x1 / g), math.floor(x0 / g) + 1),
            max(math.ceil(y1 / g), math.floor(y0 / g) + 1),
        )
    if not boxes:
        raise GeometryError("no CCD's image border meets the DEM: no orthoimage")
    mx0 = min(b[0] for b in boxes.values())
    my1 = max(b[3] for b in boxes.values())
    mx1 = max(b[2] for b in boxes.values())
    my0 = min(b[1] for b in boxes.values())
    jobs: list[_CcdJob] = []
    for ccd, (ix0, iy0, ix1, iy1) in boxes.items():
        row_off = ((my1 - iy1) // rows_per_block) * rows_per_block
        col_off = ix0 - mx0
        width, height = padded_size(ix1 - ix0, (my1 - iy0) - row_off)
        grid = OrthoGrid(ground, ix0 * g, (my1 - row_off) * g, g, width, height)
        n_lines, n_samples = camera.image_size(ccd)
        jobs.append(
            _CcdJob(
                ccd,
                images[ccd],
                grid,
                row_off,
                col_off,
                LatticeProjector(camera, ccd, terrain, grid, s),
                int(n_lines),
                int(n_samples),
            )
        )

    # The mosaic holds every CCD's (padded) grid.
    m_width, m_height = padded_size(
        max(mx1 - mx0, *(j.col_off + j.grid.width for j in jobs)),
        max(my1 - my0, *(j.row_off + j.grid.height for j in jobs)),
    )
    m_grid = OrthoGrid(ground, mx0 * g, my1 * g, g, m_width, m_height)

    def profile(grid: OrthoGrid) -> dict[str, Any]:
        return {
            "driver": "GTiff",
            "width": grid.width,
            "height": grid.height,
            "count": 1,
            "dtype": ptype.dtype.name,
            "crs": ground.crs.to_wkt(),
            "transform": from_origin(grid.x0, grid.y1, g, g),
            "nodata": ptype.nodata,
            "tiled": True,
            "blockxsize": TILE,
            "blockysize": TILE,
            "BIGTIFF": "IF_SAFER",
            **compression(),
        }

    for p in every:
        d = p.with_name(p.name + DIGEST_SUFFIX)
        if d.exists():
            d.unlink()
    with contextlib.ExitStack() as stack:
        stack.enter_context(rasterio.Env(GDAL_PAM_ENABLED="NO", GDAL_CACHEMAX=GDAL_CACHE_MB))
        dst: dict[str, Any] = {}
        tmps: dict[str, Path] = {}
        pyramids: dict[str, OverviewPyramid | None] = {}
        kernel = _kernel()

        def create(key: str, target: Path, grid: OrthoGrid) -> Any:
            tmp = tmps[key] = stack.enter_context(atomic_path(target))
            ds = stack.enter_context(rasterio.open(tmp, "w", **profile(grid)))
            factors = overview_factors(grid.width, grid.height) if overviews else []
            pyramids[key] = None
            if factors:
                # The overview directories, made while the file is empty (nothing to
                # read or average); their pixels come from the pyramid at the end.
                ds.build_overviews(factors, Resampling.nearest)
                ds.update_tags(ns="rio_overview", resampling="average")
                pyr = OverviewPyramid(
                    grid.width,
                    grid.height,
                    factors,
                    ptype.dtype,
                    ptype.nodata,
                    tmp.parent,
                    kernel,
                )
                stack.callback(pyr.close)
                pyramids[key] = pyr
            return ds

        for j in jobs:
            dst[j.ccd] = create(j.ccd, targets[j.ccd], j.grid)
        m_dst = None
        if mosaic_path is not None:
            m_dst = create(_MOSAIC, mosaic_path, m_grid)
        # The CCDs of a block are resampled and written in threads (separate files and
        # readers; OpenCV, GDAL and numpy's large operations release the GIL).
        n_threads = min(len(jobs), max(1, int(threads or 1)))
        pool = (
            stack.enter_context(ThreadPoolExecutor(n_threads, thread_name_prefix="ortho"))
            if n_threads > 1
            else None
        )
        writer = stack.enter_context(ThreadPoolExecutor(1, thread_name_prefix="mosaic"))
        writing: Future[None] | None = None
        for r0 in range(0, m_grid.height, rows_per_block):
            r1 = min(m_grid.height, r0 + rows_per_block)
            m_val = m_dist = None
            if m_dst is not None:
                m_val = np.full((r1 - r0, m_grid.width), np.nan, np.float32)
                m_dist = np.full((r1 - r0, m_grid.width), -np.inf, np.float32)
            todo = []
            for j in jobs:
                a0, a1 = max(r0 - j.row_off, 0), min(r1 - j.row_off, j.grid.height)
                if a1 > a0:
                    todo.append((j, a0, a1))

            def one(job: _CcdJob, a0: int, a1: int) -> tuple[F32, F32 | None]:
                val, dist = _resample(job, a0, a1, m_dst is not None)
                win = Window(0, a0, job.grid.width, a1 - a0)
                _write_block(dst[job.ccd], ptype, val, win, pyramids[job.ccd])
                return val, dist

            if pool is not None and len(todo) > 1:
                done = [f.result() for f in [pool.submit(one, *t) for t in todo]]
            else:
                done = [one(*t) for t in todo]
            for (j, a0, a1), (val, dist) in zip(todo, done, strict=True):
                if m_val is not None and m_dist is not None and dist is not None:
                    rs = slice(a0 + j.row_off - r0, a1 + j.row_off - r0)
                    cs = slice(j.col_off, j.col_off + j.grid.width)
                    better = dist > m_dist[rs, cs]
                    np.copyto(m_val[rs, cs], val, where=better)
                    np.copyto(m_dist[rs, cs], dist, where=better)
            if m_dst is not None and m_val is not None:
                # The mosaic's block is written while the next block is resampled (one
                # write at a time, in block order).
                if writing is not None:
                    writing.result()
                win = Window(0, r0, m_grid.width, r1 - r0)
                writing = writer.submit(_write_block, m_dst, ptype, m_val, win, pyramids[_MOSAIC])
        if writing is not None:
            writing.result()
        # The full resolution is complete: close each file, then fill its overviews.
        keys = [*dst, *([_MOSAIC] if m_dst is not None else [])]
        for key in keys:
            (m_dst if key == _MOSAIC else dst[key]).close()

        def fill(key: str) -> None:
            pyr = pyramids[key]
            if pyr is not None:
                pyr.write_into(tmps[key])

        if pool is not None:
            for f in [pool.submit(fill, k) for k in keys]:
                f.result()
        else:
            for k in keys:
                fill(k)
    for p in targets.values() if len(jobs) == len(targets) else [targets[j.ccd] for j in jobs]:
        _write_digest(p, digest)
    if mosaic_path is not None:
        _write_digest(mosaic_path, digest)
    result.ccds = {j.ccd: targets[j.ccd] for j in jobs}
    return result


def _cast(ptype: PixelType, values: F32) -> NDArray[Any]:
    """``ptype.cast(values)``, by the compiled kernel for integer types when there is one."""
    k = _kernel() if ptype.lo is not None else None
    if k is None or values.ndim != 2:
        return ptype.cast(values)
    out = np.empty(values.shape, ptype.dtype)
    k.cast_block(values, ptype.lo, ptype.hi, ptype.nodata, out)
    return out


def _write_block(
    ds: Any, ptype: PixelType, values: F32, window: Any, pyramid: OverviewPyramid | None
) -> None:
    pixels = _cast(ptype, values)
    ds.write(pixels, 1, window=window)
    if pyramid is not None:
        pyramid.push(pixels)


def _write_digest(path: Path, digest: str) -> None:
    """Write the inputs' digest and the file's size beside it (see :func:`_digest_ok`)."""
    with atomic_path(path.with_name(path.name + DIGEST_SUFFIX)) as tmp:
        tmp.write_text(f"{digest}\nsize {path.stat().st_size}\n", encoding="utf-8")


def orthorectify_ccd(
    image: Any,
    camera: Camera,
    ccd: str,
    terrain: Terrain,
    crs: Any,
    path: str | os.PathLike[str],
    *,
    gsd_m: float,
    settings: OrthoSettings | None = None,
    resume: bool = True,
) -> Path:
    """Write the orthoimage of one CCD image, streamed block by block.

    One CCD of :func:`~planetref.products.ortho_strip.orthorectify_strip` (its grid,
    data type, nodata, overviews and resume rules), without a mosaic.

    Args:
        image: A :class:`~planetref.raster.image.CcdImage` (windowed reads).
        camera: The camera (e.g. the adjusted one).
        ccd: CCD name.
        terrain: The DEM the image is projected onto.
        crs: The output CRS (the reference ortho's), a projected CRS in metres.
        path: Output GeoTIFF (written to a temporary name, renamed at the end).
        gsd_m: Output pixel size in CRS units (metres).
        settings: Lattice and block settings (defaults: :class:`OrthoSettings`).
        resume: Keep an existing orthoimage whose inputs digest matches.

    Returns:
        The path written. Pixels outside the image or the DEM are nodata.

    Raises:
        GeometryError: The image's border does not meet the DEM.
    """
    res = orthorectify_strip(
        {ccd: image},
        camera,
        terrain,
        crs,
        {ccd: path},
        gsd_m=gsd_m,
        settings=settings,
        resume=resume,
    )
    return res.ccds[ccd]
