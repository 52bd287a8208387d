"""The truth terrain: heights, albedo and surface-type masks on the truth DEM grid.

Scales
------
* **Regional relief** (what MOLA resolves): a fractal field on a coarse grid
  (``32 x`` the DEM spacing) that covers the whole reference DEM, interpolated onto the
  truth grid with cubic convolution.
* **Truth DEM** (geometry of every ray): the regional relief plus fine fractal relief
  (spectral synthesis, ``P(k) ~ k^-(2H+2)``), craters, wrinkle ridges and dunes on a
  grid of ``terrain.dem_gsd_m`` (1 m for ``hiric-strip``: 2 HiRIC pixels), interpolated
  bilinearly (:class:`~planetref.raster.dem.GridTerrain`).
* **Sub-DEM detail** (what the image resolves below the DEM spacing): periodic albedo
  and micro-relief texture tiles at ``albedo.texture_gsd_m`` (0.25 m), see
  :mod:`planetref.simulate.photometry`; they change the radiance, never the geometry.

Crater profiles
---------------
Fresh simple craters have a parabolic bowl of rim-to-floor depth ``depth_diameter * D``
and a raised rim of height ``rim_diameter * D`` whose ejecta blanket thins as
``(r/R)^-3`` out to ``3 R``; the rim radius varies with azimuth. Degraded craters
(degradation ``k`` in ``(0, 1)``) are shallower (depth ``x (1 - 0.85 k)``, rim ``x (1 -
0.9 k)``) and smoothed radially (Gaussian of ``0.35 k R``), as by diffusion and infill.
The cumulative size-frequency distribution is a truncated power law (see
:class:`~planetref.simulate.config.CraterConfig`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter, gaussian_filter1d

from planetref.arrays import F64
from planetref.simulate.config import SimulationConfig, TerrainConfig
from planetref.simulate.grid import MapGrid, cubic_resample

__all__ = [
    "CraterPopulation",
    "TruthTerrain",
    "crater_profile",
    "fractal_field",
    "generate_terrain",
    "sample_crater_population",
    "smooth_noise",
    "smooth_noise_at",
    "soft_mask",
    "stamp_craters",
]

F32 = NDArray[np.float32]


# ------------------------------------------------------------------------ noise fields
def fractal_field(
    shape: tuple[int, int],
    res_m: float,
    rng: np.random.Generator,
    *,
    hurst: float,
    min_wavelength_m: float | None = None,
    max_wavelength_m: float | None = None,
) -> F32:
    """A zero-mean, unit-RMS fractal (fBm-like) surface by spectral synthesis.

    The amplitude spectrum is ``k^-(H+1)`` (power ``k^-(2H+2)``), rolled off smoothly
    below ``1/max_wavelength_m`` and above ``1/min_wavelength_m``. The field is periodic
    over the grid.

    Args:
        shape: ``(rows, cols)``.
        res_m: Cell size (m).
        rng: Random generator (consumed).
        hurst: Hurst exponent in (0, 1).
        min_wavelength_m: Shortest wavelength kept (default: none, up to Nyquist).
        max_wavelength_m: Longest wavelength kept (default: the grid size).

    Returns:
        float32 array of ``shape``.
    """
    rows, cols = shape
    ky = np.fft.fftfreq(rows, d=res_m).astype(np.float32)[:, None]
    kx = np.fft.rfftfreq(cols, d=res_m).astype(np.float32)[None, :]
    k = np.sqrt(kx * kx + ky * ky)
    k[0, 0] = 1.0
    amp = k ** np.float32(-(hurst + 1.0))
    if max_wavelength_m is not None:
        amp *= np.float32(1.0) - np.exp(-((k * np.float32(max_wavelength_m)) ** 4))
    if min_wavelength_m is not None:
        amp *= np.exp(-((k * np.float32(min_wavelength_m)) ** 4))
    amp[0, 0] = 0.0
    del k
    spec = np.empty(amp.shape, dtype=np.complex64)
    spec.real = rng.standard_normal(amp.shape, dtype=np.float32)
    spec.imag = rng.standard_normal(amp.shape, dtype=np.float32)
    spec *= amp
    del amp
    field = scipy.fft.irfft2(spec, s=shape, workers=1).astype(np.float32, copy=False)
    del spec
    field -= field.mean(dtype=np.float64)
    rms = float(np.sqrt(np.mean(field.astype(np.float64) ** 2)))
    if rms > 0:
        field /= np.float32(rms)
    return field


def _coarse_noise(
    grid: MapGrid, feature_size_m: float, rng: np.random.Generator
) -> tuple[MapGrid, F64]:
    """The coarse noise field of :func:`smooth_noise`: ``(coarse grid, field)``.

    White noise on a coarse grid (``feature_size_m / 8`` cells, 4 cells of margin around
    ``grid``), Gaussian-filtered (sigma 2 cells), normalised to zero mean and unit RMS.
    """
    step = max(feature_size_m / 8.0, grid.res)
    xmin, ymin, xmax, ymax = grid.bounds
    pad = 4 * step
    coarse = MapGrid.covering(xmin - pad, ymin - pad, xmax + pad, ymax + pad, step, align=step)
    white = rng.standard_normal(coarse.shape)
    field = gaussian_filter(white, 2.0, mode="reflect")
    field -= field.mean()
    field /= max(float(field.std()), 1e-12)
    return coarse, field


def smooth_noise(grid: MapGrid, feature_size_m: float, rng: np.random.Generator) -> F32:
    """Smooth zero-mean unit-RMS noise with blobs of about ``feature_size_m``, on ``grid``.

    The coarse field of :func:`_coarse_noise`, interpolated (cubic) onto ``grid``.
    """
    coarse, field = _coarse_noise(grid, feature_size_m, rng)
    return cubic_resample(field, coarse, grid)


def smooth_noise_at(grid: MapGrid, feature_size_m: float, rng: np.random.Generator) -> object:
    """Like :func:`smooth_noise`, but a function ``f(x, y)`` evaluating it at map points.

    The coarse field is interpolated bilinearly, so memory is spent only where the noise
    is needed.
    """
    from scipy.ndimage import map_coordinates

    coarse, field = _coarse_noise(grid, feature_size_m, rng)

    def f(x: F64, y: F64) -> F64:
        r, c = coarse.to_index(np.asarray(x, float), np.asarray(y, float))
        return map_coordinates(field, [r, c], order=1, mode="nearest")

    return f


def soft_mask(noise: F32, fraction: float, width: float = 0.35) -> F32:
    """A mask in [0, 1] that is 1 on about ``fraction`` of the area.

    The highest noise values are covered; the edge is a smoothstep ``width`` noise-RMS
    wide.
    """
    if fraction <= 0:
        return np.zeros_like(noise, dtype=np.float32)
    if fraction >= 1:
        return np.ones_like(noise, dtype=np.float32)
    thr = float(
        np.quantile(
            noise[:: max(1, noise.shape[0] // 256), :: max(1, noise.shape[1] // 256)],
            1.0 - fraction,
        )
    )
    t = noise.astype(np.float32, copy=True)
    t -= np.float32(thr)
    t *= np.float32(1.0 / width)
    t += np.float32(0.5)
    np.clip(t, 0.0, 1.0, out=t)
    out = t * np.float32(-2.0)  # smoothstep t^2 (3 - 2t), with one temporary
    out += np.float32(3.0)
    out *= t
    out *= t
    return out


# ---------------------------------------------------------------------------- craters
@dataclass(frozen=True)
class CraterPopulation:
    """Craters of a scene (all arrays of shape ``(N,)``).

    Attributes:
        x: Map x of the centres (m, truth grid CRS).
        y: Map y of the centres (m).
        diameter_m: Rim diameters (m).
        degradation: 0 for fresh craters, up to 1 for the most degraded.
    """

    x: F64
    y: F64
    diameter_m: F64
    degradation: F64

    def __len__(self) -> int:
        return len(self.x)

    @property
    def fresh(self) -> NDArray[np.bool_]:
        """True for fresh craters."""
        return self.degradation == 0.0


def sample_crater_population(
    cfg: TerrainConfig,
    bounds: tuple[float, float, float, float],
    rng: np.random.Generator,
    keep_probability: object = None,
) -> CraterPopulation:
    """Draw craters with a truncated power-law SFD over a map box.

    Centres are uniform over ``bounds`` grown by ``0.75 * d_max_m`` (so craters centred
    just outside still reach in), the count is Poisson with mean ``density_per_km2 *
    area``, diameters follow ``N(>=D) ~ D^-sfd_slope`` on ``[d_min_m, d_max_m]``.

    Args:
        cfg: Terrain configuration (``cfg.craters`` is used).
        bounds: ``(xmin, ymin, xmax, ymax)`` in map metres.
        rng: Random generator.
        keep_probability: Optional callable ``f(x, y) -> p`` thinning the population
            (e.g. fewer craters on young plains).
    """
    c = cfg.craters
    pad = 0.75 * c.d_max_m
    xmin, ymin, xmax, ymax = bounds
    xmin, ymin, xmax, ymax = xmin - pad, ymin - pad, xmax + pad, ymax + pad
    area_km2 = (xmax - xmin) * (ymax - ymin) / 1e6
    n = int(rng.poisson(c.density_per_km2 * area_km2))
    x = rng.uniform(xmin, xmax, n)
    y = rng.uniform(ymin, ymax, n)
    u = rng.uniform(0.0, 1.0, n)
    ratio = (c.d_min_m / c.d_max_m) ** c.sfd_slope
    d = c.d_min_m * (1.0 - u * (1.0 - ratio)) ** (-1.0 / c.sfd_slope)
    fresh = rng.uniform(0.0, 1.0, n) < c.fresh_fraction
    degr = np.where(fresh, 0.0, rng.uniform(0.15, 0.95, n))
    keep = np.ones(n, dtype=bool)
    if keep_probability is not None and n:
        p = np.asarray(keep_probability(x, y), dtype=np.float64)  # type: ignore[operator]
        keep = rng.uniform(0.0, 1.0, n) < p
    order = np.argsort(-d[keep], kind="stable")
    return CraterPopulation(x[keep][order], y[keep][order], d[keep][order], degr[keep][order])


def crater_profile(
    rho: F64, *, depth_ratio: float, rim_ratio: float, diameter_m: float, degradation: float
) -> F64:
    """Height (m) of a crater relative to the pre-impact surface at normalised radii.

    Args:
        rho: Distance from the centre over the rim radius (>= 0).
        depth_ratio: Fresh rim-to-floor depth over diameter.
        rim_ratio: Fresh rim height over diameter.
        diameter_m: Rim diameter (m).
        degradation: 0 (fresh) to 1 (almost erased).

    Returns:
        Heights (m), same shape as ``rho``; zero beyond ``rho = 3``.
    """
    k = float(np.clip(degradation, 0.0, 1.0))
    dr = depth_ratio * diameter_m * (1.0 - 0.85 * k)
    hr = rim_ratio * diameter_m * (1.0 - 0.9 * k)
    grid = np.linspace(-3.5, 3.5, 1401)
    a = np.abs(grid)
    inner = hr - dr + dr * a**2
    with np.errstate(divide="ignore"):
        outer = hr * np.where(a > 0, a, 1.0) ** -3
    taper = np.clip((3.0 - a) / 1.0, 0.0, 1.0)
    taper = taper * taper * (3.0 - 2.0 * taper)
    prof = np.where(a < 1.0, inner, outer * taper)
    if k > 0:
        sigma = 0.35 * k / (grid[1] - grid[0])
        prof = gaussian_filter1d(prof, sigma, mode="nearest")
    out = np.interp(np.asarray(rho, dtype=np.float64), grid[700:], prof[700:], right=0.0)
    return out


def stamp_craters(
    height: F32,
    albedo_mod: F32,
    grid: MapGrid,
    pop: CraterPopulation,
    cfg: TerrainConfig,
    halo: float,
    rng: np.random.Generator,
) -> None:
    """Add crater relief to ``height`` and relative albedo changes to ``albedo_mod``."""
    c = cfg.craters
    res = grid.res
    for i in range(len(pop)):
        d = float(pop.diameter_m[i])
        r = 0.5 * d
        k = float(pop.degradation[i])
        extent = 3.0 * r * (1.0 + 3.0 * c.rim_irregularity)
        col_c, row_c = (pop.x[i] - grid.x0) / res - 0.5, (grid.y0 - pop.y[i]) / res - 0.5
        c0 = max(0, math.floor(col_c - extent / res))
        c1 = min(grid.cols, math.ceil(col_c + extent / res) + 1)
        r0 = max(0, math.floor(row_c - extent / res))
        r1 = min(grid.rows, math.ceil(row_c + extent / res) + 1)
        harm = rng.uniform(0.0, 1.0, 4) * c.rim_irregularity / np.arange(2, 6)
        phase = rng.uniform(0.0, 2 * np.pi, 4)
        if c0 >= c1 or r0 >= r1:
            continue
        dx = (np.arange(c0, c1) - col_c)[None, :] * res
        dy = (row_c - np.arange(r0, r1))[:, None] * res
        dist = np.hypot(dx, dy)
        theta = np.arctan2(dy, dx)
        wobble = np.ones_like(dist)
        for j in range(4):
            wobble += harm[j] * np.cos((j + 2) * theta + phase[j])
        rho = dist / (r * wobble)
        prof = crater_profile(
            rho, depth_ratio=c.depth_diameter, rim_ratio=c.rim_diameter, diameter_m=d, degradation=k
        )
        height[r0:r1, c0:c1] += prof.astype(np.float32)
        if k == 0.0 and halo > 0:
            # Fresh ejecta and walls are brighter (less dust, exposed blocks).
            bright = halo * np.exp(-(((rho - 1.1) / 0.7) ** 2))
            albedo_mod[r0:r1, c0:c1] += bright.astype(np.float32)
        elif k > 0.4:
            # Dust and sand collect on old crater floors.
            albedo_mod[r0:r1, c0:c1] -= (0.06 * k * np.clip(1.0 - rho, 0.0, 1.0)).astype(np.float32)


# ---------------------------------------------------------------------- ridges, dunes
def _wrinkle_ridges(
    height: F32, grid: MapGrid, cfg: TerrainConfig, rng: np.random.Generator
) -> None:
    rcfg = cfg.ridges
    if rcfg.count == 0 or rcfg.height_m == 0:
        return
    xs_all = grid.x_centres().astype(np.float32)[None, :]
    ys_all = grid.y_centres().astype(np.float32)[:, None]
    xmin, ymin, xmax, ymax = grid.bounds
    w = np.float32(rcfg.width_m)
    for _ in range(rcfg.count):
        theta = rng.uniform(0.0, np.pi)
        px = rng.uniform(xmin + 0.3 * (xmax - xmin), xmax - 0.3 * (xmax - xmin))
        py = rng.uniform(ymin + 0.3 * (ymax - ymin), ymax - 0.3 * (ymax - ymin))
        lam = rng.uniform(1500.0, 3500.0, 3)
        amp = rng.uniform(0.1, 0.3, 2) * rcfg.width_m
        ph = rng.uniform(0.0, 2 * np.pi, 3)
        ct, st = np.float32(math.cos(theta)), np.float32(math.sin(theta))
        k = [np.float32(2 * np.pi / v) for v in lam]
        for a in range(0, grid.rows, 256):  # row blocks bound the temporaries
            xs, ys = xs_all - np.float32(px), ys_all[a : a + 256] - np.float32(py)
            u = xs * ct + ys * st
            v = -xs * st + ys * ct
            v -= np.float32(amp[0]) * np.sin(u * k[0] + np.float32(ph[0]))
            v -= np.float32(amp[1]) * np.sin(u * k[1] + np.float32(ph[1]))
            along = np.float32(1.0) + np.float32(0.3) * np.sin(u * k[2] + np.float32(ph[2]))
            arch = np.float32(0.35) * np.exp(-((v / w) ** 2))
            vc = v - np.float32(0.2) * w
            crest_w = np.where(vc > 0, np.float32(0.1) * w, np.float32(0.28) * w)
            crest = np.float32(0.65) * np.exp(-((vc / crest_w) ** 2))
            height[a : a + 256] += np.float32(rcfg.height_m) * (arch + crest) * along


def _dune_relief(grid: MapGrid, mask: F32, cfg: TerrainConfig, rng: np.random.Generator) -> F32:
    """Heights of transverse dunes (two self-similar generations) inside ``mask``."""
    dcfg = cfg.dunes
    out = np.zeros(grid.shape, dtype=np.float32)
    if dcfg.height_m == 0 or not (mask > 0).any():
        return out
    gens = []
    for scale, hfac, dturn in ((1.0, 1.0, 0.0), (0.3, 0.22, 35.0)):
        lam = dcfg.wavelength_m * scale
        az = math.radians(dcfg.wind_azimuth_deg + dturn)
        warp = smooth_noise_at(grid, 4.0 * lam, rng)
        amp_mod = smooth_noise_at(grid, 6.0 * lam, rng)
        gens.append((lam, az, hfac, warp, amp_mod))
    for a in range(0, grid.rows, 256):  # row blocks bound the temporaries
        sub_mask = mask[a : a + 256]
        rows, cols = np.nonzero(sub_mask > 0)
        if rows.size == 0:
            continue
        x = grid.x0 + (cols + 0.5) * grid.res
        y = grid.y0 - (rows + a + 0.5) * grid.res
        total = np.zeros(len(x))
        for lam, az, hfac, warp, amp_mod in gens:
            u = x * math.sin(az) + y * math.cos(az)
            phase = u / lam + 0.45 * warp(x, y)  # type: ignore[operator]
            f = phase - np.floor(phase)
            stoss = 0.75
            prof = np.where(f < stoss, f / stoss, (1.0 - f) / (1.0 - stoss))
            prof = prof * prof * (3.0 - 2.0 * prof)  # round crests and troughs
            total += dcfg.height_m * hfac * prof * np.clip(0.75 + 0.25 * amp_mod(x, y), 0.2, 1.3)  # type: ignore[operator]
        out[a + rows, cols] = (total * sub_mask[rows, cols]).astype(np.float32)
    return out


# ---------------------------------------------------------------------------- terrain
@dataclass
class TruthTerrain:
    """The truth surface on its grid.

    Attributes:
        grid: The truth DEM grid (local equirectangular CRS, see
            :mod:`planetref.simulate.grid`).
        height: Heights above the Mars sphere (m), float32, ``grid.shape``.
        albedo: Normal albedo of the line-scan images' epoch, float16.
        albedo_reference: Albedo of the reference ortho's epoch, float16.
        texture_amplitude: Factor on the sub-DEM texture (1 rough, lower on plains and
            dunes), float16.
        plains: Plains weight in [0, 1], float16.
        dunes: Dune-field weight in [0, 1], float16.
        craters: The crater population.
        regional_grid: Coarse grid of the regional relief (covers the reference DEM).
        regional_composite: Regional relief plus the block means of all finer relief
            where the truth grid exists: the truth as seen at the coarse spacing, the
            input of the reference DEM.
        height_reference: Heights of the reference epoch where the ground changed
            (:mod:`planetref.simulate.change`); None when it equals ``height``.
    """

    grid: MapGrid
    height: F32
    albedo: NDArray[np.float16]
    albedo_reference: NDArray[np.float16]
    texture_amplitude: NDArray[np.float16]
    plains: NDArray[np.float16]
    dunes: NDArray[np.float16]
    craters: CraterPopulation
    regional_grid: MapGrid
    regional_composite: F64
    height_reference: F32 | None = None


def _block_mean_into(coarse: F64, coarse_grid: MapGrid, fine: F32, fine_grid: MapGrid) -> None:
    """Add the block means of ``fine`` to the coarse cells it covers (grids aligned).

    Blocks only partly covered by the fine grid add their mean weighted by the covered
    fraction (blending with the coarse value).
    """
    factor = round(coarse_grid.res / fine_grid.res)
    c_off = round((fine_grid.x0 - coarse_grid.x0) / fine_grid.res)
    r_off = round((coarse_grid.y0 - fine_grid.y0) / fine_grid.res)
    left = c_off % factor
    n_cb = math.ceil((fine_grid.cols + left) / factor)
    bc = (c_off - left) // factor
    row = np.zeros((factor, n_cb * factor), dtype=np.float64)
    cnt = np.zeros((factor, n_cb * factor), dtype=np.float64)
    r = -(r_off % factor)  # first fine row of the first (partial) coarse row
    while r < fine_grid.rows:
        lo, hi = max(r, 0), min(r + factor, fine_grid.rows)
        row[:] = 0.0
        cnt[:] = 0.0
        row[lo - r : hi - r, left : left + fine_grid.cols] = fine[lo:hi]
        cnt[lo - r : hi - r, left : left + fine_grid.cols] = 1.0
        s = row.reshape(factor, n_cb, factor).sum(axis=(0, 2))
        n = cnt.reshape(factor, n_cb, factor).sum(axis=(0, 2))
        mean = np.where(n > 0, s / np.maximum(n, 1.0), 0.0)
        br = (r_off + r) // factor
        coarse[br, bc : bc + n_cb] += (n / (factor * factor)) * mean
        r += factor


def generate_terrain(
    cfg: SimulationConfig,
    grid: MapGrid,
    regional_grid: MapGrid,
    streams: dict[str, np.random.Generator],
) -> TruthTerrain:
    """Synthesise the truth terrain.

    Args:
        cfg: The simulation config.
        grid: The truth DEM grid (cell size ``cfg.terrain.dem_gsd_m``).
        regional_grid: The coarse grid of the regional relief; it must contain ``grid``
            and its cells must be aligned on ``grid``'s cells.
        streams: Random generators by component name (``"regional"``, ``"fractal"``,
            ``"plains"``, ``"dunes"``, ``"craters"``, ``"ridges"``, ``"albedo"``).

    Returns:
        The truth terrain.
    """
    t = cfg.terrain
    # Regional relief on the coarse grid (also the reference DEM's source).
    regional = fractal_field(
        regional_grid.shape,
        regional_grid.res,
        streams["regional"],
        hurst=t.regional.hurst,
        min_wavelength_m=t.regional.min_wavelength_m,
    ).astype(np.float64)
    regional *= t.regional.rms_m

    plains = soft_mask(
        smooth_noise(grid, t.plains.feature_size_m, streams["plains"]), t.plains.fraction
    )
    if t.dunes.enabled:
        dunes = soft_mask(
            smooth_noise(grid, t.dunes.feature_size_m, streams["dunes"]), t.dunes.fraction
        ).astype(np.float16)
    else:
        dunes = np.zeros(grid.shape, dtype=np.float16)
    plains = plains.astype(np.float16)

    # Fine relief (zero mean): fractal scaled down on plains, ridges, craters, dunes.
    height = fractal_field(
        grid.shape,
        grid.res,
        streams["fractal"],
        hurst=t.fractal.hurst,
        max_wavelength_m=t.fractal.max_wavelength_m,
    )
    rough_loss = np.float32(1.0 - t.plains.roughness_factor)
    for a in range(0, grid.rows, 512):
        height[a : a + 512] *= np.float32(t.fractal.rms_m) * (
            np.float32(1.0) - rough_loss * plains[a : a + 512]
        )
    _wrinkle_ridges(height, grid, t, streams["ridges"])

    def keep(x: F64, y: F64) -> F64:
        r, c = grid.to_index(x, y)
        r = np.clip(np.round(r).astype(int), 0, grid.rows - 1)
        c = np.clip(np.round(c).astype(int), 0, grid.cols - 1)
        return 1.0 - (1.0 - t.plains.crater_factor) * plains[r, c]

    craters = sample_crater_population(t, grid.bounds, streams["craters"], keep)
    albedo = np.zeros(grid.shape, dtype=np.float32)  # relative crater albedo changes first
    stamp_craters(height, albedo, grid, craters, t, cfg.albedo.crater_halo, streams["craters"])
    # Dunes sit on top of everything (sand fills lows and crater floors alike).
    height += _dune_relief(grid, dunes.astype(np.float32), t, streams["dunes"])

    composite = regional.copy()
    _block_mean_into(composite, regional_grid, height, grid)
    height += cubic_resample(regional, regional_grid, grid)

    # Albedo: low-frequency variation, darker plains and dunes, crater halos, texture.
    a_cfg = cfg.albedo
    arng = streams["albedo"]
    variation = smooth_noise(grid, a_cfg.variation_wavelength_m, arng)
    change = smooth_noise(grid, 0.6 * a_cfg.variation_wavelength_m, arng)
    albedo_ref = np.empty(grid.shape, dtype=np.float16)
    texture = np.empty(grid.shape, dtype=np.float16)
    dune_loss = np.float32(1.0 - t.dunes.albedo_factor)
    for a in range(0, grid.rows, 512):
        sl = slice(a, a + 512)
        p, d = plains[sl], dunes[sl]
        base = np.float32(1.0) + np.float32(a_cfg.variation) * variation[sl]
        base *= np.float32(1.0) - np.float32(0.08) * p
        base *= np.float32(1.0) - dune_loss * d
        base *= np.float32(1.0) + albedo[sl]
        albedo[sl] = np.clip(np.float32(a_cfg.mean) * base, 0.02, 0.9)
        albedo_ref[sl] = np.clip(
            albedo[sl] * (np.float32(1.0) + np.float32(a_cfg.reference_change) * change[sl]),
            0.02,
            0.9,
        )
        texture[sl] = np.clip(np.float32(1.0) - rough_loss * p - np.float32(0.5) * d, 0.05, 1.0)
    del variation, change
    return TruthTerrain(
        grid=grid,
        height=height.astype(np.float32, copy=False),
        albedo=albedo.astype(np.float16),
        albedo_reference=albedo_ref,
        texture_amplitude=texture,
        plains=plains,
        dunes=dunes,
        craters=craters,
        regional_grid=regional_grid,
        regional_composite=composite,
    )
