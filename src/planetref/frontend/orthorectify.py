"""Bring a CCD tile to the reference geometry: orthorectification or plain downsampling.

Both produce an *image side* for matching: an array with a validity mask, plus the two
mappings the front end needs for every keypoint ``(x, y)`` found on it (pixel
coordinates of that array, first pixel centre at ``(0.5, 0.5)``):

* ``to_raw(x, y) -> (line, sample, ok)``: the raw CCD image coordinates of the point;
* ``predicted_ref_pixel(x, y) -> (col, row)``: where the initial camera and the DEM put
  that point on the full-resolution reference grid. Matching the image side against the
  reference gives the actual position; the difference is the tile's offset.

:func:`orthorectify` resamples the tile onto a :class:`~planetref.raster.ortho.RefWindow`
of the reference grid. For a lattice of window points (every ``step`` window pixels,
edges included) the ground point is built from the map coordinates and the DEM height,
then projected exactly into the image with the initial camera; the mapping to raw
``(line, sample)`` is interpolated bilinearly in between (the mapping is smooth over a
few reference pixels). The raw image is first averaged over blocks of half an output
pixel, then sampled bilinearly: together an area pre-filter of about one output pixel,
which imitates the area sampling of the reference and avoids aliasing. ``to_raw`` does not
rely on the interpolation: it projects each point exactly through the DEM and the camera,
which is the geometry the orthoimage was built with.

:func:`downsample_tile` averages the raw tile over ``k x k`` blocks (the seed's way); it
keeps the image's own orientation and scale, so keypoints map back to raw pixels by a
scale and a shift.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from planetref.arrays import F64
from planetref.camera.base import Camera, Terrain
from planetref.camera.mapping import (
    image_to_ref_pixel,
    map_to_ground,
    project_to_image,
)
from planetref.frontend.lineguide import LineGuide
from planetref.frontend.resample import bilinear_blocks
from planetref.frontend.tiles import Tile
from planetref.geometry.lattice import bilinear_lattice, lattice_cell
from planetref.raster.image import CcdImage
from planetref.raster.ortho import ReferenceOrtho, RefWindow

__all__ = [
    "DownsampledTile",
    "ImageSide",
    "LatticeCache",
    "OrthoTile",
    "downsample_tile",
    "lattice_cache",
    "orthorectify",
]

_UNSET = object()  # a lazily built attribute not built yet


class ImageSide(Protocol):
    """What the matcher sees of a CCD tile, and how its pixels map back."""

    image: NDArray[np.float32]
    valid: NDArray[np.bool_]

    def to_raw(self, x: ArrayLike, y: ArrayLike) -> tuple[F64, F64, NDArray[np.bool_]]:
        """Array pixel ``(x, y)`` -> raw ``(line, sample)`` and a success flag."""
        ...

    def predicted_ref_pixel(self, x: ArrayLike, y: ArrayLike) -> tuple[F64, F64]:
        """Array pixel ``(x, y)`` -> reference ``(col, row)`` predicted by the initial camera."""
        ...


def _lattice_nodes(n: int, step: int) -> F64:
    nodes = np.arange(0.0, float(n), float(step))
    return np.append(nodes, float(n)) if nodes[-1] < n else nodes


def _fractional_index(nodes: F64, q: F64) -> F64:
    # Linear extrapolation beyond the end nodes keeps points on the border exact.
    idx = np.interp(q, nodes, np.arange(len(nodes), dtype=np.float64))
    lo, hi = nodes[0], nodes[-1]
    d0 = nodes[1] - nodes[0]
    d1 = nodes[-1] - nodes[-2]
    idx = np.where(q < lo, (q - lo) / d0, idx)
    return np.where(q > hi, len(nodes) - 1 + (q - hi) / d1, idx)


@dataclass
class OrthoTile:
    """A CCD tile resampled onto a reference-grid window.

    Attributes:
        window: The reference window the tile was resampled onto.
        image: ``window.shape`` float32 pixels (0 where invalid).
        valid: ``window.shape`` validity (inside the tile and the image, with data, and
            with a terrain height).
        lattice_x: Window x of the lattice columns (window pixels, edges at 0 and width).
        lattice_y: Window y of the lattice rows.
        lattice_line: Raw line at each lattice node, ``(len(lattice_y), len(lattice_x))``;
            NaN where the DEM has no height or the projection failed.
        lattice_sample: Raw sample at each lattice node.
        prefilter: Side of the raw block average (raw pixels).
    """

    window: RefWindow
    image: NDArray[np.float32]
    valid: NDArray[np.bool_]
    lattice_x: F64
    lattice_y: F64
    lattice_line: F64
    lattice_sample: F64
    prefilter: int
    _camera: Camera = field(repr=False)
    _ccd: str = field(repr=False)
    _ref: ReferenceOrtho = field(repr=False)
    _terrain: Terrain = field(repr=False)

    def raw_coords(self, x: ArrayLike, y: ArrayLike) -> tuple[F64, F64]:
        """Raw ``(line, sample)`` of window pixels ``(x, y)`` interpolated from the lattice."""
        x = np.asarray(x, np.float64)
        y = np.asarray(y, np.float64)
        fx = _fractional_index(self.lattice_x, x.ravel())
        fy = _fractional_index(self.lattice_y, y.ravel())
        return self._interpolate(np.vstack([fy, fx]), x.shape)

    def raw_coords_grid(self, xs: F64, ys: F64) -> tuple[F64, F64]:
        """:meth:`raw_coords` of the grid ``xs x ys``, ``(len(ys), len(xs))`` (same values).

        The lattice's fractional indices are separable, and so is the bilinear
        interpolation (:func:`~planetref.geometry.lattice.bilinear_lattice`): the lattice
        rows are interpolated at every column first, then those rows at every row, two
        gathers of whole rows instead of four gathers of points. The values equal
        :meth:`raw_coords`'s to rounding (~1e-13 px) at points inside the lattice, NaN
        where a node with a non-zero weight is NaN (a point exactly on a node next to a NaN
        node keeps the node's value; pixel centres never fall on nodes).
        """
        fx = _fractional_index(self.lattice_x, np.asarray(xs, np.float64))
        fy = _fractional_index(self.lattice_y, np.asarray(ys, np.float64))
        iy, ty = lattice_cell(fy, len(self.lattice_y))
        ix, tx = lattice_cell(fx, len(self.lattice_x))
        # Columns first: the transposed lattice, rows and columns swapped.
        line = bilinear_lattice(self.lattice_line.T, ix, tx, iy, ty).T
        sample = bilinear_lattice(self.lattice_sample.T, ix, tx, iy, ty).T
        return line, sample

    def _interpolate(self, coords: F64, shape: tuple[int, ...]) -> tuple[F64, F64]:
        """Bilinear lattice line and sample at fractional ``(row, col)`` node indices."""
        line = ndimage.map_coordinates(
            self.lattice_line, coords, order=1, mode="nearest", prefilter=False
        )
        sample = ndimage.map_coordinates(
            self.lattice_sample, coords, order=1, mode="nearest", prefilter=False
        )
        return line.reshape(shape), sample.reshape(shape)

    def predicted_ref_pixel(self, x: ArrayLike, y: ArrayLike) -> tuple[F64, F64]:
        """Reference ``(col, row)`` of window pixels: the orthoimage *is* the prediction."""
        return self.window.to_ref_pixel(x, y)

    def to_raw(self, x: ArrayLike, y: ArrayLike) -> tuple[F64, F64, NDArray[np.bool_]]:
        """Exact raw ``(line, sample)`` of window pixels ``(x, y)``.

        The point's map coordinates and DEM height give a ground point, which the initial
        camera projects into the image (starting from the lattice interpolation).

        Returns:
            ``(line, sample, ok)``; ``ok`` is False where the DEM has no height or the
            projection fails.
        """
        x = np.atleast_1d(np.asarray(x, np.float64))
        y = np.atleast_1d(np.asarray(y, np.float64))
        col, row = self.window.to_ref_pixel(x, y)
        mx, my = self._ref.pixel_to_map(col, row)
        xyz, *_ = map_to_ground(self._ref, self._terrain, mx, my)
        guess, _ = self.raw_coords(x, y)
        line, sample = project_to_image(
            self._camera,
            self._ccd,
            xyz,
            line_guess=np.where(
                np.isfinite(guess), guess, np.nanmedian(guess) if np.isfinite(guess).any() else 0.0
            ),
        )
        ok = np.isfinite(line) & np.isfinite(sample)
        return line, sample, ok


def _project_nodes(
    camera: Camera, ccd: str, ref: ReferenceOrtho, terrain: Terrain, col: F64, row: F64
) -> tuple[F64, F64]:
    """Raw ``(line, sample)`` of a ``(ny, nx)`` grid of reference ``(col, row)`` nodes."""
    ny, nx = col.shape
    mx, my = ref.pixel_to_map(col.ravel(), row.ravel())
    xyz, *_ = map_to_ground(ref, terrain, mx, my)
    # Project a few spread nodes without a guess, fit an affine line(col, row), and use it
    # as the starting line of every node: the guided projection is several times cheaper.
    probe = np.unique(
        np.ravel_multi_index(
            (
                np.array([0, 0, ny - 1, ny - 1, ny // 2, 0, ny - 1, ny // 2, ny // 2]),
                np.array([0, nx - 1, 0, nx - 1, nx // 2, nx // 2, nx // 2, 0, nx - 1]),
            ),
            (ny, nx),
        )
    )
    pl, _ = project_to_image(camera, ccd, xyz[probe])
    good = np.isfinite(pl)
    guess = None
    if good.sum() >= 3:
        cr = np.column_stack([col.ravel(), row.ravel(), np.ones(col.size)])
        coef, *_ = np.linalg.lstsq(cr[probe][good], pl[good], rcond=None)
        guess = cr @ coef
    line, sample = project_to_image(camera, ccd, xyz, line_guess=guess)
    return line.reshape(ny, nx), sample.reshape(ny, nx)


def _lattice(
    camera: Camera, ccd: str, ref: ReferenceOrtho, terrain: Terrain, window: RefWindow, step: int
) -> tuple[F64, F64, F64, F64]:
    lx = _lattice_nodes(window.width, step)
    ly = _lattice_nodes(window.height, step)
    gx, gy = np.meshgrid(lx, ly)
    col, row = window.to_ref_pixel(gx, gy)
    line, sample = _project_nodes(camera, ccd, ref, terrain, col, row)
    return lx, ly, line, sample


class LatticeCache:
    """One CCD's exactly projected lattice on the reference grid, filled chunk by chunk.

    Nodes sit at reference pixel edges ``(col, row) = (j step, i step)`` of the whole
    reference grid, so every window (any coarsening, any fine grid) takes its lattice
    from the same nodes: a tile's neighbours and its coarse stage reuse the projections
    instead of repeating them. Chunks of ``chunk x chunk`` nodes are projected when a
    window first needs them and kept (a node costs 16 bytes). Each node starts from the
    CCD's :class:`~planetref.frontend.lineguide.LineGuide` (built once per cache), so no
    fill pays for a bracketed line search, not even for nodes past the strip's ends.

    Args:
        camera: The initial camera.
        ccd: CCD name.
        ref: The reference orthoimage (grid and CRS).
        terrain: The reference DEM.
        step: Node spacing, full-resolution reference pixels.
        chunk: Nodes per chunk side.
    """

    def __init__(
        self,
        camera: Camera,
        ccd: str,
        ref: ReferenceOrtho,
        terrain: Terrain,
        step: int,
        chunk: int = 8,
    ) -> None:
        self.camera, self.ccd, self.ref, self.terrain = camera, ccd, ref, terrain
        self.step, self.chunk = int(step), int(chunk)
        self._chunks: dict[tuple[int, int], tuple[F64, F64]] = {}
        self._guide: LineGuide | object | None = _UNSET

    def matches(self, camera: Camera, ccd: str, ref: ReferenceOrtho, terrain: Terrain) -> bool:
        """Whether this cache serves these inputs (the very same objects)."""
        return (
            self.camera is camera
            and self.ccd == ccd
            and self.ref is ref
            and self.terrain is terrain
        )

    def _chunk_nodes(self, todo: list[tuple[int, int]]) -> tuple[F64, F64]:
        """Reference ``(col, row)`` of the nodes of chunks, ``(m * chunk * chunk,)`` each."""
        n, s, m = self.chunk, float(self.step), len(todo)
        k = np.arange(n, dtype=np.float64)
        ci = np.array([c[0] for c in todo], np.float64)[:, None, None]
        cj = np.array([c[1] for c in todo], np.float64)[:, None, None]
        col = np.broadcast_to((cj * n + k[None, None, :]) * s, (m, n, n)).ravel()
        row = np.broadcast_to((ci * n + k[None, :, None]) * s, (m, n, n)).ravel()
        return col, row

    def _fill(self, wanted: list[tuple[int, int]]) -> None:
        """Project the missing chunks among ``wanted``, together (a call has a fixed cost).

        Each node's result depends on that node only, not on which chunks are projected
        with it (tile order, scheduler): with a line guide (:meth:`_line_guide`), every
        node starts from the guide's line at its own position and the compiled projection
        iterates every point on its own; without one, :meth:`_fill_probed`.
        """
        todo = [c for c in wanted if c not in self._chunks]
        if not todo:
            return
        guide = self._line_guide()
        if guide is None:
            line, sample = self._fill_probed(todo)
        else:
            line, sample = self._fill_guided(todo, guide)
        n, m = self.chunk, len(todo)
        line, sample = line.reshape(m, n, n), sample.reshape(m, n, n)
        for c, key in enumerate(todo):
            self._chunks[key] = (line[c], sample[c])

    def _line_guide(self) -> LineGuide | None:
        """The CCD's line guide (built on first use), or None for cameras without a span."""
        if self._guide is _UNSET:
            self._guide = LineGuide.build(self.camera, self.ccd, self.ref, self.terrain)
        return self._guide  # type: ignore[return-value]

    def _fill_guided(self, todo: list[tuple[int, int]], guide: LineGuide) -> tuple[F64, F64]:
        """Every node projected from the guide's starting line (see :class:`LineGuide`).

        Nodes inside the guide's table whose guided projection fails get the bracketed
        search (the guide never loses a node that search finds); nodes outside it whose
        guided projection fails lie past the searchable lines and stay NaN.
        """
        col, row = self._chunk_nodes(todo)
        mx, my = self.ref.pixel_to_map(col, row)
        xyz, *_ = map_to_ground(self.ref, self.terrain, mx, my)
        guess, inside = guide(col, row)
        line, sample = project_to_image(self.camera, self.ccd, xyz, guess)
        retry = inside & ~np.isfinite(line) & np.all(np.isfinite(xyz), axis=1)
        if retry.any():
            line[retry], sample[retry] = project_to_image(self.camera, self.ccd, xyz[retry])
        return line, sample

    def _fill_probed(self, todo: list[tuple[int, int]]) -> tuple[F64, F64]:
        """Nodes projected from an affine fit to nine probes of their own chunk.

        Every chunk gets its starting lines from an affine fit to nine probes of its own,
        projected without a guess (a bracketed line search); chunks with fewer than three
        projected probes are searched node by node. (Vectorised arithmetic over arrays of
        other lengths leaves ~1e-12 px, as the warm-started line searches of the
        adjustment do.) The reference of :meth:`_fill_guided`, and the way for cameras
        without a line span.
        """
        n, m = self.chunk, len(todo)
        col, row = self._chunk_nodes(todo)
        mx, my = self.ref.pixel_to_map(col, row)
        xyz, *_ = map_to_ground(self.ref, self.terrain, mx, my)
        ends = (0, n // 2, n - 1)
        local = np.array([a * n + b for a in ends for b in ends])
        probes = (np.arange(m)[:, None] * n * n + local[None, :]).ravel()
        pl, _ = project_to_image(self.camera, self.ccd, xyz[probes])
        pl = pl.reshape(m, len(local))
        design = np.column_stack([col, row, np.ones(col.size)]).reshape(m, n * n, 3)
        guess = np.full((m, n * n), np.nan)
        for c in range(m):
            good = np.isfinite(pl[c])
            if good.sum() >= 3:
                coef, *_ = np.linalg.lstsq(design[c, local][good], pl[c, good], rcond=None)
                guess[c] = design[c] @ coef
        guess = guess.ravel()
        line = np.full(col.size, np.nan)
        sample = np.full(col.size, np.nan)
        guided = np.isfinite(guess)
        for sel, g in ((guided, guess[guided]), (~guided, None)):
            if sel.any():
                line[sel], sample[sel] = project_to_image(self.camera, self.ccd, xyz[sel], g)
        return line, sample

    def nodes(self, window: RefWindow, stride: int = 1) -> tuple[F64, F64, F64, F64]:
        """The lattice of a window: node ``(x, y)`` in window pixels, raw line and sample.

        The nodes cover the window with one node at or beyond each edge, so nothing in the
        window is extrapolated.

        Args:
            window: The window (any grid).
            stride: Take every ``stride``-th node: a lattice of spacing ``stride * step``
                (a coarse stage), made of the very nodes the finer stages use.
        """
        c0, r0, c1, r1 = window.bounds_px
        k, n = max(1, int(stride)), self.chunk
        s = self.step * k
        # lattice indices (spacing s) -> node indices of the cache (spacing step)
        j0, j1 = (c0 // s) * k, -(-c1 // s) * k
        i0, i1 = (r0 // s) * k, -(-r1 // s) * k
        line = np.empty((i1 - i0 + 1, j1 - j0 + 1))
        sample = np.empty_like(line)
        chunks = [
            (ci, cj) for ci in range(i0 // n, i1 // n + 1) for cj in range(j0 // n, j1 // n + 1)
        ]
        self._fill(chunks)
        for ci, cj in chunks:
            cl, cs = self._chunks[(ci, cj)]
            a0, a1 = max(i0, ci * n), min(i1 + 1, (ci + 1) * n)
            b0, b1 = max(j0, cj * n), min(j1 + 1, (cj + 1) * n)
            dst = slice(a0 - i0, a1 - i0), slice(b0 - j0, b1 - j0)
            src = slice(a0 - ci * n, a1 - ci * n), slice(b0 - cj * n, b1 - cj * n)
            line[dst], sample[dst] = cl[src], cs[src]
        line, sample = line[::k, ::k], sample[::k, ::k]
        lx, _ = window.from_ref_pixel(np.arange(j0, j1 + 1, k) * float(self.step), 0.0)
        _, ly = window.from_ref_pixel(0.0, np.arange(i0, i1 + 1, k) * float(self.step))
        return np.asarray(lx, np.float64), np.asarray(ly, np.float64), line, sample


def lattice_cache(
    image: CcdImage, camera: Camera, ccd: str, ref: ReferenceOrtho, terrain: Terrain, step: int
) -> LatticeCache:
    """The :class:`LatticeCache` kept with a CCD reader for these inputs (made when missing).

    It lives in ``image.caches`` (a worker keeps its readers for the whole run), one per
    ``(ccd, step)``; a different camera, reference or DEM object replaces it.
    """
    key = ("ortho-lattice", ccd, int(step))
    cache = image.caches.get(key)
    if not isinstance(cache, LatticeCache) or not cache.matches(camera, ccd, ref, terrain):
        cache = LatticeCache(camera, ccd, ref, terrain, int(step))
        image.caches[key] = cache
    return cache


def orthorectify(
    image: CcdImage,
    camera: Camera,
    ccd: str,
    ref: ReferenceOrtho,
    terrain: Terrain,
    window: RefWindow,
    *,
    bounds: tuple[int, int, int, int] | None = None,
    lattice_step: int = 8,
    prefilter: float = 0.5,
    min_valid_fraction: float = 0.5,
    cache: LatticeCache | None = None,
    stride: int = 1,
) -> OrthoTile:
    """Resample a CCD tile onto a reference-grid window through the camera and the DEM.

    Only the raw pixels the window needs are read (the CCD image around the projected
    lattice, clipped to ``bounds``), averaged block by block in strips, so memory is
    bounded by the window size whatever the image size.

    Args:
        image: The CCD image reader.
        camera: The initial camera.
        ccd: CCD name of ``image``.
        ref: The reference orthoimage (grid and CRS; its pixels are not read).
        terrain: The reference DEM.
        window: Output grid: a window of the reference grid, possibly coarsened.
        bounds: ``(line0, sample0, line1, sample1)``: use only these raw pixels (e.g. a
            tile's); default: the whole image. Filling the window with the tile's real
            neighbourhood rather than no-data avoids artificial edges that some matchers
            latch on to.
        lattice_step: Spacing of the exactly projected lattice, window pixels.
        prefilter: Side of the raw block average as a fraction of an output pixel
            (0.5 imitates area sampling once combined with the bilinear interpolation).
        min_valid_fraction: A pre-filter block needs this fraction of valid raw pixels.
        cache: The CCD's lattice cache (:func:`lattice_cache`): the lattice comes from its
            reference-grid nodes (``lattice_step`` is then ignored) and the raw block
            means from the reader's block cache
            (:meth:`~planetref.raster.image.CcdImage.read_block_mean_cached`), so
            overlapping windows and the two stages of a tile share that work. None: the
            window's own lattice and a direct read.
        stride: With ``cache``: the lattice takes every ``stride``-th node of the cache
            (spacing ``stride * cache.step`` reference px), so a coarse stage uses the
            nodes of the fine ones.

    Returns:
        The orthorectified tile.
    """
    if cache is not None:
        lx, ly, lat_line, lat_sample = cache.nodes(window, stride)
    else:
        lx, ly, lat_line, lat_sample = _lattice(
            camera, ccd, ref, terrain, window, max(1, int(lattice_step))
        )
    h, w = window.shape
    # Raw pixels per output pixel from the lattice's Jacobian sets the pre-filter.
    with np.errstate(invalid="ignore"):
        dl_dx = np.diff(lat_line, axis=1) / np.diff(lx)[None, :]
        ds_dx = np.diff(lat_sample, axis=1) / np.diff(lx)[None, :]
        dl_dy = np.diff(lat_line, axis=0) / np.diff(ly)[:, None]
        ds_dy = np.diff(lat_sample, axis=0) / np.diff(ly)[:, None]
        det = np.abs(dl_dx[:-1] * ds_dy[:, :-1] - ds_dx[:-1] * dl_dy[:, :-1])
    det = det[np.isfinite(det)]
    scale = float(np.sqrt(np.median(det))) if det.size else 1.0
    # Blocks of half an output pixel, then bilinear interpolation: the combined kernel
    # (box k/2 convolved with a triangle of half-width k/2) has about the variance of a
    # box of one output pixel, i.e. it imitates the area sampling of the reference. Whole-
    # pixel blocks followed by bilinear blur three times more (variance k^2/4 vs k^2/12),
    # and matchers then see two different images.
    k = max(1, int(np.floor(prefilter * scale + 1e-6)))

    blank = OrthoTile(
        window,
        np.zeros((h, w), np.float32),
        np.zeros((h, w), bool),
        lx,
        ly,
        lat_line,
        lat_sample,
        k,
        camera,
        ccd,
        ref,
        terrain,
    )
    n_lines, n_samples = image.shape
    l_lo, s_lo, l_hi, s_hi = 0, 0, n_lines, n_samples
    if bounds is not None:
        l_lo, s_lo = max(0, int(bounds[0])), max(0, int(bounds[1]))
        l_hi, s_hi = min(n_lines, int(bounds[2])), min(n_samples, int(bounds[3]))
    fin = np.isfinite(lat_line) & np.isfinite(lat_sample)
    if not fin.any():
        return blank
    # Anchor the read on the block grid of the allowed region so that calls for
    # neighbouring windows average the same blocks.
    r0 = max(l_lo, l_lo + int(np.floor((np.min(lat_line[fin]) - l_lo) / k) - 1) * k)
    c0 = max(s_lo, s_lo + int(np.floor((np.min(lat_sample[fin]) - s_lo) / k) - 1) * k)
    r1 = min(l_hi, int(np.ceil(np.max(lat_line[fin]))) + 2 * k)
    c1 = min(s_hi, int(np.ceil(np.max(lat_sample[fin]))) + 2 * k)
    if r1 <= r0 or c1 <= c0:
        return blank
    read = image.read_block_mean if cache is None else image.read_block_mean_cached
    block, block_valid = read(r0, c0, r1 - r0, c1 - c0, k, min_valid_fraction)

    xs = np.arange(w, dtype=np.float64) + 0.5
    ys = np.arange(h, dtype=np.float64) + 0.5
    line, sample = blank.raw_coords_grid(xs, ys)
    # Block (i, j) has its centre at raw (r0 + (i + 0.5) k, c0 + (j + 0.5) k); scipy puts
    # array element centres at integer coordinates.
    u = (line - r0) / k - 0.5
    v = (sample - c0) / k - 0.5
    finite = np.isfinite(u) & np.isfinite(v)
    out, vfrac = bilinear_blocks(block, block_valid, u, v)
    inside = finite & (line >= l_lo) & (line < l_hi) & (sample >= s_lo) & (sample < s_hi)
    valid = inside & (vfrac > 1.0 - 1e-4)
    blank.image = np.where(valid, out, 0.0).astype(np.float32)
    blank.valid = valid
    return blank


@dataclass
class DownsampledTile:
    """A raw CCD tile averaged over ``factor x factor`` blocks.

    Attributes:
        tile: The tile.
        factor: Block side (raw pixels per array pixel).
        image: The averaged tile, float32 (0 where invalid).
        valid: Validity of each block.
    """

    tile: Tile
    factor: int
    image: NDArray[np.float32]
    valid: NDArray[np.bool_]
    _camera: Camera = field(repr=False)
    _ref: ReferenceOrtho = field(repr=False)
    _terrain: Terrain = field(repr=False)

    def to_raw(self, x: ArrayLike, y: ArrayLike) -> tuple[F64, F64, NDArray[np.bool_]]:
        """Raw ``(line, sample)`` of array pixels: block ``j`` covers raw ``[j k, (j + 1) k)``."""
        x = np.atleast_1d(np.asarray(x, np.float64))
        y = np.atleast_1d(np.asarray(y, np.float64))
        line = self.tile.line0 + y * self.factor
        sample = self.tile.sample0 + x * self.factor
        return line, sample, np.isfinite(line) & np.isfinite(sample)

    def predicted_ref_pixel(self, x: ArrayLike, y: ArrayLike) -> tuple[F64, F64]:
        """Reference ``(col, row)`` where the initial camera and the DEM put the points."""
        line, sample, _ = self.to_raw(x, y)
        return image_to_ref_pixel(
            self._camera, self.tile.ccd, line, sample, self._ref, self._terrain
        )


def downsample_tile(
    image: CcdImage,
    tile: Tile,
    factor: int,
    camera: Camera,
    ref: ReferenceOrtho,
    terrain: Terrain,
    min_valid_fraction: float = 0.5,
) -> DownsampledTile:
    """Average a raw tile down by an integer factor (no geometric correction).

    Args:
        image: The CCD image reader.
        tile: The tile.
        factor: Block side in raw pixels (about the GSD ratio times the stage factor).
        camera: The initial camera (for the predicted reference positions).
        ref: The reference orthoimage.
        terrain: The reference DEM.
        min_valid_fraction: A block needs this fraction of valid raw pixels.
    """
    k = max(1, int(factor))
    block, block_valid = image.read_block_mean(
        tile.line0, tile.sample0, tile.n_lines, tile.n_samples, k, min_valid_fraction
    )
    return DownsampledTile(tile, k, block, block_valid, camera, ref, terrain)
