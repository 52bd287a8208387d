"""Illumination, reflectance and the radiance of the truth surface at any ground point.

Frames and angles
-----------------
Shading works in the local east/north/up frame of the truth grid (its map x is east,
y north, see :mod:`planetref.simulate.grid`). The sun is given by its azimuth
(degrees clockwise from north, towards the sun) and elevation (degrees above the
horizontal). ``i`` is the incidence angle (surface normal to sun), ``e`` the emission
angle (normal to observer) and ``g`` the phase angle (sun to observer).

Reflectance models
------------------
* Lambert: ``F = cos i``.
* Lunar-Lambert (McEwen 1991): ``F = 2 L(g) cos i / (cos i + cos e) + (1 - L(g)) cos i``
  with ``L(g) = 1 - 0.019 g + 2.42e-4 g^2 - 1.46e-6 g^3`` (``g`` in degrees).

Radiance (arbitrary linear units) of a point with albedo ``A``::

    L = A (F (1 - s) + k_sky sin(el) (1 + n_z) / 2) + haze * L_flat

where ``s`` in [0, 1] is the cast-shadow fraction, ``k_sky`` the skylight fraction,
``n_z`` the up component of the normal and ``L_flat`` the radiance (without haze) of a
level, unshadowed surface of mean albedo seen at nadir. Because the sun differs
between the reference ortho and the line-scan images, the same surface gives a
non-linear, spatially varying radiometric difference between them.

Sub-DEM detail
--------------
The normal is the DEM's (central differences, interpolated bilinearly) perturbed by the
gradient of a band-limited micro-relief, and the albedo is modulated by a fine albedo
texture. Both come from two periodic tiles of different size and orientation
(:class:`TextureTiles`, synthesised at ``albedo.texture_gsd_m``), so the texture is
continuous, deterministic and aperiodic over any scene, and costs no memory per
square kilometre.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from planetref.arrays import F64
from planetref.simulate.config import AlbedoConfig, PhotometryConfig, SunConfig
from planetref.simulate.grid import MapGrid
from planetref.simulate.terrain import fractal_field

__all__ = [
    "RadianceModel",
    "ShadingFields",
    "TextureTiles",
    "cast_shadow",
    "lambert",
    "lunar_lambert",
    "mcewen_l",
    "reflectance",
    "sun_vector",
]

F32 = NDArray[np.float32]


def sun_vector(sun: SunConfig) -> F64:
    """Unit vector towards the sun in the local (east, north, up) frame."""
    az, el = math.radians(sun.azimuth_deg), math.radians(sun.elevation_deg)
    return np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)])


def mcewen_l(phase_deg: NDArray[np.floating] | float) -> NDArray[np.floating]:
    """McEwen's (1991) lunar-Lambert partition ``L(g)``, phase angle in degrees."""
    g = np.asarray(phase_deg)
    return 1.0 - 0.019 * g + 2.42e-4 * g**2 - 1.46e-6 * g**3


def lambert(cos_i: NDArray[np.floating]) -> NDArray[np.floating]:
    """Lambert reflectance ``max(cos i, 0)``."""
    return np.maximum(cos_i, 0.0)


def lunar_lambert(
    cos_i: NDArray[np.floating],
    cos_e: NDArray[np.floating],
    phase_deg: NDArray[np.floating] | float,
) -> NDArray[np.floating]:
    """Lunar-Lambert reflectance (McEwen 1991); zero where ``cos i <= 0``.

    Args:
        cos_i: Cosine of the incidence angle.
        cos_e: Cosine of the emission angle (clipped to >= 0.01).
        phase_deg: Phase angle in degrees.
    """
    ci = np.maximum(cos_i, 0.0)
    ce = np.maximum(cos_e, 0.01)
    ell = mcewen_l(phase_deg)
    return 2.0 * ell * ci / (ci + ce) + (1.0 - ell) * ci


def reflectance(
    model: str,
    cos_i: NDArray[np.floating],
    cos_e: NDArray[np.floating],
    phase_deg: NDArray[np.floating] | float,
) -> NDArray[np.floating]:
    """``lambert`` or ``lunar-lambert`` reflectance (see the module docstring)."""
    if model == "lambert":
        return lambert(cos_i)
    return lunar_lambert(cos_i, cos_e, phase_deg)


def cast_shadow(height: NDArray[np.floating], res_m: float, sun: SunConfig) -> F32:
    """Cast shadows on a north-up height grid, by horizon propagation along the sun azimuth.

    The grid is swept away from the sun one row or column at a time (whichever axis is
    closer to the sun's azimuth). A "shadow surface" (the envelope of sun rays grazing
    the terrain upstream) is carried along: at each step it is interpolated at the point
    where the sun ray through each cell crosses the previous line, lowered by the
    distance times ``tan(elevation)``, compared with the cell's height, and raised to
    the cell's height where the cell sticks out. Cost ``O(rows * cols)``, memory
    ``O(rows + cols)`` besides the output.

    Args:
        height: Heights (m), shape ``(rows, cols)``, north up, square cells.
        res_m: Cell size (m).
        sun: The sun.

    Returns:
        Shadow fraction in [0, 1] (1 = fully in shadow), float32, same shape; the edge is
        softened over a quarter of a cell's height drop.
    """
    h = np.asarray(height, dtype=np.float32)
    az, el = math.radians(sun.azimuth_deg), math.radians(sun.elevation_deg)
    d_col, d_row = math.sin(az), -math.cos(az)  # towards the sun, in index space
    transpose = abs(d_row) > abs(d_col)
    work = h.T if transpose else h
    d_main, d_side = (d_row, d_col) if transpose else (d_col, d_row)
    flip = d_main > 0
    if flip:
        work = work[:, ::-1]
    # Now the sun lies towards decreasing main index; one step toward it moves the side
    # index by t.
    t = d_side / abs(d_main)
    drop = np.float32(res_m * math.sqrt(1.0 + t * t) * math.tan(el))
    soft = np.float32(max(0.25 * float(drop), 1e-3))
    n_side, n_main = work.shape
    side = np.arange(n_side, dtype=np.float64)
    shadow = np.zeros((n_side, n_main), dtype=np.float32)
    env = work[:, 0].astype(np.float32).copy()
    for m in range(1, n_main):
        ray = np.interp(side + t, side, env).astype(np.float32) - drop
        cur = work[:, m]
        shadow[:, m] = np.clip((ray - cur) / soft + np.float32(0.5), 0.0, 1.0)
        env = np.maximum(cur, ray)
    if flip:
        shadow = shadow[:, ::-1]
    if transpose:
        shadow = shadow.T
    return np.ascontiguousarray(shadow)


class TextureTiles:
    """Sub-DEM albedo texture and micro-relief from two periodic tiles.

    Each tile is square (1024 and 512 cells of ``albedo.texture_gsd_m``), rotated
    (0 and 37 degrees) and offset, and holds three channels: a zero-mean unit-RMS albedo
    texture (wavelengths up to 30 m) and the east/north gradient of a micro-relief of
    RMS ``albedo.micro_relief_rms_m`` (wavelengths up to 4 DEM cells). The two tiles'
    channels are averaged (albedo: divided by sqrt 2 to keep unit RMS).

    Args:
        albedo: Albedo configuration.
        dem_gsd_m: The truth DEM spacing (bounds the micro-relief's wavelengths).
        rng: Random generator.
    """

    _SIZES = (1024, 512)  # powers of two: indices wrap with a bit mask
    _ANGLES_DEG = (0.0, 37.0)

    def __init__(self, albedo: AlbedoConfig, dem_gsd_m: float, rng: np.random.Generator) -> None:
        self.gsd = float(albedo.texture_gsd_m)
        self.tiles: list[F32] = []
        self.angles = [math.radians(a) for a in self._ANGLES_DEG]
        self.offsets = [rng.uniform(0, n, 2) for n in self._SIZES]
        max_wl_relief = max(4.0 * dem_gsd_m, 4.0 * self.gsd)
        for n in self._SIZES:
            alb = fractal_field(
                (n, n), self.gsd, rng, hurst=0.5, max_wavelength_m=min(30.0, 0.5 * n * self.gsd)
            )
            relief = fractal_field((n, n), self.gsd, rng, hurst=0.7, max_wavelength_m=max_wl_relief)
            relief *= np.float32(albedo.micro_relief_rms_m)
            # Periodic central differences: d/du along columns, d/dv along rows (metres).
            g_u = (np.roll(relief, -1, axis=1) - np.roll(relief, 1, axis=1)) / (2 * self.gsd)
            g_v = (np.roll(relief, -1, axis=0) - np.roll(relief, 1, axis=0)) / (2 * self.gsd)
            tile = np.ascontiguousarray(np.stack([alb, g_u, g_v], axis=-1), dtype=np.float32)
            self.tiles.append(tile)
        # Each cell's three channels as one 12-byte item, for fast gathering.
        self._cells = [
            t.reshape(-1, 3).view(np.dtype((np.void, 12))).reshape(-1) for t in self.tiles
        ]

    def sample(self, x: F64, y: F64) -> F32:
        """Texture at map points: ``(M, 3)`` = albedo texture, d(relief)/dx, d(relief)/dy."""
        out = np.zeros((len(x), 3), dtype=np.float32)
        for tile, cells, ang, off in zip(
            self.tiles, self._cells, self.angles, self.offsets, strict=True
        ):
            n = tile.shape[0]
            mask = n - 1
            ca, sa = math.cos(ang), math.sin(ang)
            u = (x * (ca / self.gsd) + y * (sa / self.gsd)) + off[0]
            v = (y * (ca / self.gsd) - x * (sa / self.gsd)) + off[1]
            u0f, v0f = np.floor(u), np.floor(v)
            fu = (u - u0f).astype(np.float32)[:, None]
            fv = (v - v0f).astype(np.float32)[:, None]
            u0 = u0f.astype(np.int64) & mask
            v0 = v0f.astype(np.int64) & mask
            u1 = (u0 + 1) & mask
            v1 = ((v0 + 1) & mask) * n
            v0 = v0 * n

            def get(i: NDArray[np.int64], cells: NDArray[np.void] = cells) -> F32:
                return cells.take(i).view(np.float32).reshape(-1, 3)

            top = get(v0 + u0)
            top += (get(v0 + u1) - top) * fu
            bot = get(v1 + u0)
            bot += (get(v1 + u1) - bot) * fu
            val = top + (bot - top) * fv
            # Rotate the gradient from tile axes (u, v) back to map axes (x, y).
            out[:, 0] += val[:, 0]
            out[:, 1] += val[:, 1] * np.float32(ca) - val[:, 2] * np.float32(sa)
            out[:, 2] += val[:, 1] * np.float32(sa) + val[:, 2] * np.float32(ca)
        out[:, 0] /= np.float32(math.sqrt(len(self.tiles)))
        out[:, 1:] /= np.float32(len(self.tiles))
        return out


class ShadingFields:
    """Per-cell shading inputs on the truth grid, packed for fast bilinear lookup.

    A float16 array of shape ``(rows, cols, 5)`` holds: east and north height gradients
    (m/m), albedo, texture amplitude and cast-shadow fraction.

    Args:
        grid: The truth grid.
        height: Heights (m), ``grid.shape``.
        albedo: Albedo, ``grid.shape``.
        texture_amplitude: Texture factor, ``grid.shape``.
        shadow: Shadow fraction in [0, 1], ``grid.shape``.
    """

    def __init__(
        self,
        grid: MapGrid,
        height: NDArray[np.floating],
        albedo: NDArray[np.floating],
        texture_amplitude: NDArray[np.floating],
        shadow: NDArray[np.floating],
    ) -> None:
        self.grid = grid
        rows, cols = grid.shape
        st = np.empty((rows, cols, 5), dtype=np.float16)
        inv2 = np.float32(0.5 / grid.res)
        for a in range(0, rows, 512):
            b = min(rows, a + 512)
            lo, hi = max(0, a - 1), min(rows, b + 1)
            blk = np.asarray(height[lo:hi], dtype=np.float32)
            gx = np.empty((hi - lo, cols), dtype=np.float32)
            gx[:, 1:-1] = (blk[:, 2:] - blk[:, :-2]) * inv2
            gx[:, 0] = (blk[:, 1] - blk[:, 0]) * (2 * inv2)
            gx[:, -1] = (blk[:, -1] - blk[:, -2]) * (2 * inv2)
            gy = np.empty_like(gx)
            gy[1:-1] = -(blk[2:] - blk[:-2]) * inv2  # rows run south
            gy[0] = -(blk[1] - blk[0]) * (2 * inv2)
            gy[-1] = -(blk[-1] - blk[-2]) * (2 * inv2)
            st[a:b, :, 0] = gx[a - lo : a - lo + (b - a)]
            st[a:b, :, 1] = gy[a - lo : a - lo + (b - a)]
        st[:, :, 2] = albedo
        st[:, :, 3] = texture_amplitude
        st[:, :, 4] = shadow
        self.stack = st
        # Each cell's five float16 channels as one 10-byte item, for fast gathering.
        self._cells = st.reshape(-1, 5).view(np.dtype((np.void, 10))).reshape(-1)

    def sample(self, x: F64, y: F64) -> F32:
        """Bilinear lookup at map points (edges clamped): ``(M, 5)`` float32."""
        rows, cols = self.grid.shape
        r, c = self.grid.to_index(x, y)
        r = np.clip(r, 0.0, rows - 1.0)
        c = np.clip(c, 0.0, cols - 1.0)
        r0 = np.minimum(r.astype(np.int64), rows - 2)
        c0 = np.minimum(c.astype(np.int64), cols - 2)
        fr = (r - r0).astype(np.float32)[:, None]
        fc = (c - c0).astype(np.float32)[:, None]
        idx = r0 * cols + c0
        cells = self._cells

        def get(i: NDArray[np.int64]) -> F32:
            return cells.take(i).view(np.float16).reshape(-1, 5).astype(np.float32)

        top = get(idx)
        top += (get(idx + 1) - top) * fc
        bot = get(idx + cols)
        bot += (get(idx + (cols + 1)) - bot) * fc
        top += (bot - top) * fr
        return top


class RadianceModel:
    """Radiance of the truth surface for one illumination (see the module docstring).

    Args:
        fields: Shading fields (their shadow channel must belong to ``sun``).
        tiles: Sub-DEM texture.
        sun: The sun.
        photometry: Reflectance model and skylight.
        albedo: Albedo configuration (mean albedo, texture RMS).
        haze: Additive path radiance relative to a flat mean-albedo surface.
    """

    def __init__(
        self,
        fields: ShadingFields,
        tiles: TextureTiles,
        sun: SunConfig,
        photometry: PhotometryConfig,
        albedo: AlbedoConfig,
        haze: float,
    ) -> None:
        self.fields = fields
        self.tiles = tiles
        self.sun = sun
        self.s = sun_vector(sun).astype(np.float32)
        self.model = photometry.model
        self.sky = float(photometry.sky_fraction)
        self.texture_rms = float(albedo.texture_rms)
        self.albedo_mean = float(albedo.mean)
        self.haze = float(haze)

    def flat_radiance(self) -> float:
        """Radiance of a level, unshadowed, mean-albedo surface seen at nadir (no haze)."""
        ci = float(self.s[2])
        f = float(reflectance(self.model, np.array(ci), np.array(1.0), math.degrees(math.acos(ci))))
        return self.albedo_mean * (f + self.sky * ci)

    def evaluate(
        self, x: F64, y: F64, view: NDArray[np.floating], fields: F32 | None = None
    ) -> F32:
        """Radiance at map points of the truth grid.

        Args:
            x: Map x (m), shape ``(M,)``.
            y: Map y (m), shape ``(M,)``.
            view: Unit vectors from the ground towards the observer in (east, north,
                up), shape ``(M, 3)`` or ``(3,)``.
            fields: Shading fields already sampled for these points (``(M, 5)``, from
                :meth:`ShadingFields.sample`); sampled at ``(x, y)`` when None. The
                renderer passes the fields of a pixel's centroid to all its sub-samples
                when the pixel is smaller than a DEM cell (the fields are bilinear, so
                their footprint mean is the centroid value), while the sub-DEM texture
                is always sampled at each point.

        Returns:
            Radiance, float32, shape ``(M,)``.
        """
        f = self.fields.sample(x, y) if fields is None else fields
        tex = self.tiles.sample(x, y)
        tamp = f[:, 3]
        gx = f[:, 0] + tamp * tex[:, 1]
        gy = f[:, 1] + tamp * tex[:, 2]
        inv = np.float32(1.0) / np.sqrt(gx * gx + gy * gy + np.float32(1.0))
        nx, ny, nz = -gx * inv, -gy * inv, inv
        v = np.asarray(view, dtype=np.float32)
        vx, vy, vz = (v[..., 0], v[..., 1], v[..., 2])
        s = self.s
        cos_i = nx * s[0] + ny * s[1] + nz * s[2]
        if self.model == "lambert":
            refl = np.maximum(cos_i, np.float32(0.0))
        else:
            cos_e = nx * vx + ny * vy + nz * vz
            cos_g = np.clip(s[0] * vx + s[1] * vy + s[2] * vz, -1.0, 1.0)
            phase = np.degrees(np.arccos(cos_g)).astype(np.float32)
            refl = lunar_lambert(cos_i, cos_e, phase).astype(np.float32, copy=False)
        direct = refl * (np.float32(1.0) - f[:, 4])
        sky = np.float32(self.sky * s[2] * 0.5) * (np.float32(1.0) + nz)
        alb = f[:, 2] * (np.float32(1.0) + np.float32(self.texture_rms) * tamp * tex[:, 0])
        alb = np.maximum(alb, np.float32(0.005))
        out = alb * (direct + sky)
        if self.haze:
            out += np.float32(self.haze * self.flat_radiance())
        return out.astype(np.float32, copy=False)
