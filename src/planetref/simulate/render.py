"""Chunked, line-by-line rendering of CCD images through the true line-scan camera.

For every image pixel the renderer follows the model exactly:

1. The rays of the pixel's four corners (continuous image coordinates ``(l, s)``,
   ``(l, s+1)``, ``(l+1, s)``, ``(l+1, s+1)``; the pixel convention puts the first
   pixel's centre at ``(0.5, 0.5)``) are computed from the true camera's exterior
   orientation at each corner's line time (:meth:`LineScanCamera.exterior`) and
   focal-plane position (:meth:`CcdGeometry.focal_plane`), exactly as
   :meth:`LineScanCamera.look_rays` does (a test checks they agree to 1e-12).
2. Each ray is intersected with the truth DEM (:meth:`GridTerrain.intersect_rays`,
   the same bilinear surface that :meth:`LineScanCamera.image_to_ground` intersects
   when given that terrain).
3. The pixel's ground footprint (the quadrilateral of its corners' ground points) is
   sampled on ``supersample x supersample`` points and the radiance averaged: the
   detector's box response and the along-track motion during one line period
   (what TDI integrates). The centroid of the sub-samples is the pixel centre. When
   the footprint is smaller than a DEM cell, the DEM-scale shading fields (bilinear,
   so their footprint mean is their centroid value) are sampled once at the centroid
   and the sub-DEM texture at every sub-sample.
4. The Gaussian PSF is applied (blocks carry a halo of lines so that the result does
   not depend on the block size), then electrons, noise and quantisation
   (:mod:`planetref.simulate.sensor`).

Memory is bounded by the block size (``render.chunk_pixels``): each block of lines is
rendered, processed and written to the GeoTIFF in order. With ``render.processes > 1``
blocks are rendered by forked worker processes (at most two blocks per worker in
flight); each block's noise has its own seed, so the image is the same for any number
of processes.
"""

from __future__ import annotations

import os
import warnings
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.arrays import F64
from planetref.camera.linescan import LineScanCamera
from planetref.errors import GeometryError
from planetref.raster.dem import GridTerrain
from planetref.simulate.config import SensorConfig
from planetref.simulate.photometry import RadianceModel
from planetref.simulate.sensor import (
    BLOCK,
    apply_psf,
    block_dct_compress,
    exposure_for_saturation,
    psf_halo,
    quantize,
    to_electrons,
    with_noise,
)

__all__ = ["corner_rays", "render_ccd", "render_radiance", "write_image_geotiff"]

F32 = NDArray[np.float32]


def corner_rays(camera: LineScanCamera, ccd: str, lines: F64, samples: F64) -> tuple[F64, F64]:
    """Rays of the grid ``lines x samples`` (continuous image coordinates).

    Equivalent to ``camera.look_rays`` on the meshgrid, but the exterior orientation is
    evaluated once per line.

    Args:
        camera: The camera.
        ccd: CCD name.
        lines: Line coordinates, shape ``(L,)``.
        samples: Sample coordinates, shape ``(S,)``.

    Returns:
        ``(origin, direction)`` of shapes ``(L, 3)`` and ``(L, S, 3)`` (unit directions,
        body-fixed).
    """
    c = camera.ccd(ccd)
    origin, rot = camera.exterior(np.asarray(lines, dtype=np.float64))
    x, y = c.focal_plane(np.asarray(samples, dtype=np.float64))
    io = camera.interior
    v_cam = np.stack([x - io.x0_mm, y - io.y0_mm, np.full_like(x, -io.focal_length_mm)], axis=-1)
    d = np.einsum("lij,sj->lsi", rot, v_cam)
    d /= np.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2 + d[..., 2] ** 2)[..., None]
    return origin, d


def render_radiance(
    camera: LineScanCamera,
    ccd: str,
    terrain: GridTerrain,
    radiance: RadianceModel,
    enu: F64,
    line0: int,
    line1: int,
    supersample: int,
) -> F32:
    """Footprint-integrated radiance of image lines ``[line0, line1)`` (all samples).

    Args:
        camera: The true camera.
        ccd: CCD name.
        terrain: The truth DEM (its CRS is the map of ``radiance``'s fields).
        radiance: The radiance model.
        enu: Rows east, north, up (body-fixed unit vectors) of the shading frame.
        line0: First image line (integer).
        line1: One past the last line.
        supersample: Sub-samples per pixel and axis.

    Returns:
        float32 array ``(line1 - line0, n_samples)``.

    Raises:
        GeometryError: If a ray misses the truth DEM (the DEM does not cover the image).
    """
    _, n_samples = camera.image_size(ccd)
    lines = np.arange(line0, line1 + 1, dtype=np.float64)
    samples = np.arange(0, n_samples + 1, dtype=np.float64)
    origin, dirs = corner_rays(camera, ccd, lines, samples)
    nl, ns = len(lines) - 1, n_samples
    o = np.broadcast_to(origin[:, None, :], dirs.shape).reshape(-1, 3)
    hits = terrain.intersect_rays(o, dirs.reshape(-1, 3))
    if not np.all(hits.hit):
        bad = int(np.flatnonzero(~hits.hit)[0])
        raise GeometryError(
            f"the ray of corner (line {lines[bad // (ns + 1)]}, sample {bad % (ns + 1)}) of "
            f"CCD {ccd} misses the truth DEM; enlarge site.margin_m"
        )
    gx = hits.x.reshape(nl + 1, ns + 1)
    gy = hits.y.reshape(nl + 1, ns + 1)
    # View vectors (ground -> camera) in the shading frame, one per pixel.
    v = -(dirs[:-1, :-1] + dirs[:-1, 1:] + dirs[1:, :-1] + dirs[1:, 1:]) @ enu.T
    v /= np.sqrt(v[..., 0] ** 2 + v[..., 1] ** 2 + v[..., 2] ** 2)[..., None]
    view = v.reshape(-1, 3).astype(np.float32)
    acc = np.zeros(nl * ns, dtype=np.float32)
    x00, x01, x10, x11 = gx[:-1, :-1], gx[:-1, 1:], gx[1:, :-1], gx[1:, 1:]
    y00, y01, y10, y11 = gy[:-1, :-1], gy[:-1, 1:], gy[1:, :-1], gy[1:, 1:]
    # DEM-scale fields at the footprint centroid when pixels are smaller than DEM cells.
    fields = None
    footprint = float(np.median(np.hypot(x01 - x00, y01 - y00)))
    if footprint <= terrain.sampling_m:
        xc = 0.25 * (x00 + x01 + x10 + x11)
        yc = 0.25 * (y00 + y01 + y10 + y11)
        fields = radiance.fields.sample(xc.ravel(), yc.ravel())
    offsets = (np.arange(supersample) + 0.5) / supersample
    for a in offsets:  # along the line direction
        for b in offsets:  # along the sample direction
            w00, w01, w10, w11 = (1 - a) * (1 - b), (1 - a) * b, a * (1 - b), a * b
            x = w00 * x00 + w01 * x01 + w10 * x10 + w11 * x11
            y = w00 * y00 + w01 * y01 + w10 * y10 + w11 * y11
            acc += radiance.evaluate(x.ravel(), y.ravel(), view, fields)
    acc /= np.float32(supersample * supersample)
    return acc.reshape(nl, ns)


@dataclass(frozen=True)
class _BlockState:
    camera: LineScanCamera
    ccd: str
    terrain: GridTerrain
    radiance: RadianceModel
    enu: F64
    sensor: SensorConfig
    column_gain: NDArray[np.float32] | None = None


_WORKER_STATE: _BlockState | None = None
"""What forked workers render from (set in the parent just before the fork)."""


def _render_block(
    state: _BlockState, a: int, b: int, child: np.random.SeedSequence
) -> NDArray[np.integer]:
    """DN of lines ``[a, b)``: radiance with a PSF halo, electrons, noise, quantisation."""
    n_lines, _ = state.camera.image_size(state.ccd)
    halo = psf_halo(state.sensor)
    ra, rb = max(0, a - halo), min(n_lines, b + halo)
    rad = render_radiance(
        state.camera,
        state.ccd,
        state.terrain,
        state.radiance,
        state.enu,
        ra,
        rb,
        state.sensor.supersample,
    )
    blurred = apply_psf(rad, state.sensor)[a - ra : a - ra + (b - a)]
    flat = state.radiance.flat_radiance() * (1.0 + state.radiance.haze)
    signal = to_electrons(blurred, flat, state.sensor)
    if state.column_gain is not None:
        signal *= state.column_gain[None, :]
    e = with_noise(signal, state.sensor, np.random.default_rng(child))
    dn = quantize(e, state.sensor)
    if state.sensor.compression_quality > 0:
        dn = block_dct_compress(dn, state.sensor.compression_quality, state.sensor.bit_depth)
    return dn


def _worker_block(job: tuple[int, int, np.random.SeedSequence]) -> NDArray[np.integer]:
    if _WORKER_STATE is None:  # pragma: no cover - only reachable without fork
        raise RuntimeError("render worker started without state")
    return _render_block(_WORKER_STATE, *job)


def _blocks(
    state: _BlockState, jobs: list[tuple[int, int, np.random.SeedSequence]], processes: int
) -> Iterator[tuple[int, int, NDArray[np.integer]]]:
    """Rendered blocks in order; at most ``2 * processes`` blocks in flight."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    global _WORKER_STATE
    if processes <= 1 or len(jobs) < 2 or "fork" not in mp.get_all_start_methods():
        for a, b, child in jobs:
            yield a, b, _render_block(state, a, b, child)
        return
    _WORKER_STATE = state
    try:
        with ProcessPoolExecutor(processes, mp_context=mp.get_context("fork")) as pool:
            pending: deque[tuple[int, int, Any]] = deque()
            todo = iter(jobs)
            for job in todo:
                pending.append((job[0], job[1], pool.submit(_worker_block, job)))
                if len(pending) >= 2 * processes:
                    break
            while pending:
                a, b, fut = pending.popleft()
                nxt = next(todo, None)
                if nxt is not None:
                    pending.append((nxt[0], nxt[1], pool.submit(_worker_block, nxt)))
                yield a, b, fut.result()
    finally:
        _WORKER_STATE = None


def write_image_geotiff(
    path: str | os.PathLike[str], n_lines: int, n_samples: int, dtype: str
) -> object:
    """Open a single-band GeoTIFF for writing an image without georeference.

    Deflate-compressed with horizontal differencing, 256 x 256 tiles when the image is
    large enough, no timestamps or statistics (byte-reproducible).
    """
    import rasterio

    profile: dict[str, object] = {
        "driver": "GTiff",
        "width": n_samples,
        "height": n_lines,
        "count": 1,
        "dtype": dtype,
        "compress": "deflate",
        "predictor": 2,
    }
    if n_lines >= 256 and n_samples >= 256:
        profile.update(tiled=True, blockxsize=256, blockysize=256)
    return rasterio.open(path, "w", **profile)


def render_ccd(
    camera: LineScanCamera,
    ccd: str,
    terrain: GridTerrain,
    radiance: RadianceModel,
    enu: F64,
    sensor: SensorConfig,
    out_path: Path,
    *,
    chunk_pixels: int,
    noise_seed: np.random.SeedSequence,
    progress: Callable[[int], None] | None = None,
    processes: int = 1,
) -> dict[str, float]:
    """Render one CCD image and write it as a GeoTIFF (no georeference).

    Args:
        camera: The true camera.
        ccd: CCD name.
        terrain: The truth DEM.
        radiance: Radiance model of the line-scan images' illumination.
        enu: Shading frame (rows east, north, up).
        sensor: Sensor configuration.
        out_path: Output GeoTIFF.
        chunk_pixels: Target pixels per block (bounds memory).
        noise_seed: Seed sequence of this CCD's noise (one child per block).
        progress: Called with the number of lines done after each block.
        processes: Worker processes rendering blocks in parallel (forked, sharing the
            terrain and shading fields copy-on-write); 1 renders in this process. The
            image does not depend on it.

    Returns:
        Statistics: ``mean_dn``, ``saturated_fraction``, ``zero_fraction`` (and, with
        ``sensor.saturation_fraction``, the ``mean_signal_e`` the exposure was set to).
    """
    from rasterio.errors import NotGeoreferencedWarning
    from rasterio.windows import Window

    n_lines, n_samples = camera.image_size(ccd)
    chunk = max(1, chunk_pixels // n_samples)
    if chunk >= 256:
        chunk -= chunk % 256  # whole tile rows
    elif sensor.compression_quality > 0 and chunk % BLOCK:
        chunk = max(BLOCK, chunk - chunk % BLOCK)  # whole compression blocks
    dtype = "uint8" if sensor.bit_depth == 8 else "uint16"
    top = (1 << sensor.bit_depth) - 1
    total, n_sat, n_zero, n_pix = 0.0, 0, 0, 0
    starts = list(range(0, n_lines, chunk))
    children = noise_seed.spawn(len(starts))
    jobs = [(a, min(n_lines, a + chunk), child) for a, child in zip(starts, children, strict=True)]
    gain = None
    if sensor.column_gain_rms > 0:
        # Spawned after the blocks' children, so the noise is the same with or without.
        rng = np.random.default_rng(noise_seed.spawn(1)[0])
        gain = (1.0 + sensor.column_gain_rms * rng.standard_normal(n_samples)).astype(np.float32)
    extra: dict[str, float] = {}
    if sensor.saturation_fraction > 0:
        sample = _signal_sample(camera, ccd, terrain, radiance, enu, sensor, gain)
        exposure = exposure_for_saturation(sample, sensor)
        sensor = sensor.model_copy(update={"mean_signal_e": exposure})
        extra["mean_signal_e"] = exposure
    state = _BlockState(camera, ccd, terrain, radiance, enu, sensor, gain)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with write_image_geotiff(out_path, n_lines, n_samples, dtype) as ds:  # type: ignore[attr-defined]
            for a, b, dn in _blocks(state, jobs, processes):
                ds.write(dn, 1, window=Window(0, a, n_samples, b - a))
                total += float(dn.sum(dtype=np.float64))
                n_sat += int(np.count_nonzero(dn == top))
                n_zero += int(np.count_nonzero(dn == 0))
                n_pix += dn.size
                if progress is not None:
                    progress(b - a)
    return {
        "mean_dn": total / n_pix,
        "saturated_fraction": n_sat / n_pix,
        "zero_fraction": n_zero / n_pix,
        **extra,
    }


def _signal_sample(
    camera: LineScanCamera,
    ccd: str,
    terrain: GridTerrain,
    radiance: RadianceModel,
    enu: F64,
    sensor: SensorConfig,
    gain: NDArray[np.float32] | None,
    groups: int = 64,
    lines: int = 4,
) -> NDArray[np.float32]:
    """Noise-free signal (electrons, PSF included) of ``groups`` evenly spaced line groups.

    What an auto-exposure sees before the image is taken: ``groups`` groups of
    ``lines`` lines spread over the image, each rendered with its PSF halo.
    """
    n_lines, _ = camera.image_size(ccd)
    halo = psf_halo(sensor)
    flat = radiance.flat_radiance() * (1.0 + radiance.haze)
    starts = np.unique(np.linspace(0, max(0, n_lines - lines), groups).astype(int))
    out = []
    for a in starts:
        b = min(n_lines, int(a) + lines)
        ra, rb = max(0, int(a) - halo), min(n_lines, b + halo)
        rad = render_radiance(camera, ccd, terrain, radiance, enu, ra, rb, sensor.supersample)
        sig = to_electrons(apply_psf(rad, sensor)[a - ra : a - ra + (b - a)], flat, sensor)
        if gain is not None:
            sig = sig * gain[None, :]
        out.append(sig.ravel())
    return np.concatenate(out)
