"""The reference ortho as a mosaic of source images (CTX-like).

See :class:`~planetref.simulate.realism.MosaicConfig`.

Each source covers a band of the ortho along map x between two meandering seams, has
its own sun, haze and gain, and its own geometric error ``d_s(p) = offset_s +
warp_s(p)`` (map metres of the reference CRS): the pixel at true map point ``p`` shows
the surface at ``p - d_s(p)``, so a feature at ``q`` appears at about ``q + d_s(q)``.
:meth:`MosaicSource.displacement` evaluates ``d_s``; the parameters are written to
``truth/reference.json`` (:func:`sources_to_dict`) so any check can recompute it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.arrays import F64
from planetref.simulate.config import PhotometryConfig, SunConfig
from planetref.simulate.grid import MapGrid
from planetref.simulate.realism import MosaicConfig

__all__ = ["MosaicSource", "Seams", "draw_mosaic", "reference_accuracy", "sources_to_dict"]


@dataclass(frozen=True)
class MosaicSource:
    """One source image of the mosaic.

    Attributes:
        index: Source number (0 = westmost band).
        sun: Its sun.
        haze: Its path radiance relative to a flat mean-albedo surface.
        gain: Its relative brightness (brightness steps at the seams).
        offset_m: ``(dx, dy)`` map offset (m).
        waves: Rows ``(kx, ky, amp_x, amp_y, phase)``: wave vectors (rad/m), amplitudes
            of the x and y displacement (m) and phase (rad) of the warp's plane waves.
        emission_deg: Off-nadir emission angle (0: nadir, no relief displacement).
        look_azimuth_deg: Azimuth from the ground towards the spacecraft (degrees
            clockwise from north).
        bias: Its additive brightness offset, relative to a flat mean-albedo surface
            (with ``gain``, the brightness step at its seams).
    """

    index: int
    sun: SunConfig
    haze: float
    gain: float
    offset_m: tuple[float, float]
    waves: F64
    emission_deg: float = 0.0
    look_azimuth_deg: float = 0.0
    bias: float = 0.0

    def displacement(self, x: F64, y: F64, relief_m: F64 | None = None) -> tuple[F64, F64]:
        """``d_s`` at map points (m): offset plus warp, plus relief displacement.

        Args:
            x: Map x (m).
            y: Map y (m).
            relief_m: Height of the truth above the DEM the source was orthorectified
                on, at the points (m); with an off-nadir source it moves the pixel by
                ``-relief tan(e) v`` (``v`` towards the spacecraft).
        """
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        dx = np.full(x.shape, self.offset_m[0])
        dy = np.full(x.shape, self.offset_m[1])
        for kx, ky, ax, ay, ph in self.waves:
            s = np.sin(kx * x + ky * y + ph)
            dx += ax * s
            dy += ay * s
        if relief_m is not None and self.emission_deg > 0:
            t = math.tan(math.radians(self.emission_deg))
            az = math.radians(self.look_azimuth_deg)
            dx -= relief_m * (t * math.sin(az))
            dy -= relief_m * (t * math.cos(az))
        return dx, dy


@dataclass(frozen=True)
class Seams:
    """Band boundaries ``x = base_k + a_k sin(2 pi y / wl_k + ph_k)`` (map metres)."""

    base: F64
    amplitude: F64
    wavelength: F64
    phase: F64

    def label(self, x: F64, y: F64) -> NDArray[np.intp]:
        """Source index at map points."""
        out = np.zeros(np.shape(x), dtype=np.intp)
        for b, a, wl, ph in zip(
            self.base, self.amplitude, self.wavelength, self.phase, strict=True
        ):
            out += x > b + a * np.sin(2.0 * np.pi * y / wl + ph)
        return out


def reference_accuracy(cfg: MosaicConfig, gsd_m: float, grid: MapGrid) -> dict[str, float]:
    """The mosaic's accuracy as its producer would state it, for the scene manifest.

    ``accuracy_m``: RMS per axis of a source's geometric error, from the distributions
    the sources are drawn from (offset and warp RMS, in pixels of ``gsd_m``), never from
    the drawn values; ``accuracy_length_m``: the distance over which it is common, a
    source's band width, at most the warps' shortest wavelength.

    Args:
        cfg: The mosaic settings.
        gsd_m: Ortho pixel size (m).
        grid: The ortho grid.
    """
    xmin, _, xmax, _ = grid.bounds
    width = (xmax - xmin) / cfg.n_sources
    length = min(width, cfg.warp_wavelength_m) if cfg.warp_px > 0 else width
    return {
        "accuracy_m": float(math.hypot(cfg.offset_px, cfg.warp_px) * gsd_m),
        "accuracy_length_m": float(length),
    }


def draw_mosaic(
    cfg: MosaicConfig,
    photometry: PhotometryConfig,
    grid: MapGrid,
    rng: np.random.Generator,
) -> tuple[list[MosaicSource], Seams]:
    """Draw the sources and seams of a mosaic covering ``grid`` (see the module docstring).

    With one source and zero spreads the source is the plain reference image.
    """
    n = cfg.n_sources
    g = grid.res
    xmin, _, xmax, _ = grid.bounds
    sources = []
    for k in range(n):
        d_az, d_el = rng.normal(0.0, cfg.sun_spread_deg, 2) if n > 1 else (0.0, 0.0)
        ref = photometry.reference_sun
        sun = SunConfig(
            azimuth_deg=float((ref.azimuth_deg + d_az) % 360.0),
            elevation_deg=float(np.clip(ref.elevation_deg + d_el, 5.0, 85.0)),
        )
        haze = photometry.reference_haze * (float(rng.uniform(0.5, 1.5)) if n > 1 else 1.0)
        gain = 1.0 + float(rng.normal(0.0, cfg.gain_spread))
        off = rng.normal(0.0, cfg.offset_px * g, 2)
        waves = np.zeros((3, 5))
        amp = cfg.warp_px * g / math.sqrt(1.5)
        for j in range(3):
            wl = cfg.warp_wavelength_m * rng.uniform(1.0, 3.0)
            th = rng.uniform(0.0, 2.0 * np.pi)
            k_ = 2.0 * np.pi / wl
            dirn = rng.uniform(0.0, 2.0 * np.pi)
            waves[j] = (
                k_ * math.cos(th),
                k_ * math.sin(th),
                amp * math.cos(dirn),
                amp * math.sin(dirn),
                rng.uniform(0.0, 2.0 * np.pi),
            )
        if cfg.warp_px == 0:
            waves = np.zeros((0, 5))
        sources.append(
            MosaicSource(k, sun, haze, max(gain, 0.2), (float(off[0]), float(off[1])), waves)
        )
    width = xmax - xmin
    base = xmin + width * np.arange(1, n) / n
    seams = Seams(
        base=base,
        amplitude=np.full(n - 1, cfg.seam_wander_m),
        wavelength=rng.uniform(800.0, 2500.0, n - 1),
        phase=rng.uniform(0.0, 2.0 * np.pi, n - 1),
    )
    if cfg.emission_max_deg > 0:
        # Drawn last, so mosaics of nadir sources are as they were.
        sources = [
            replace(
                src,
                emission_deg=float(rng.uniform(0.0, cfg.emission_max_deg)),
                look_azimuth_deg=float(rng.choice([90.0, 270.0])),
            )
            for src in sources
        ]
    if cfg.bias_spread > 0:
        # Drawn after the emission angles, so mosaics without offsets are as they were.
        sources = [replace(src, bias=float(rng.normal(0.0, cfg.bias_spread))) for src in sources]
    return sources, seams


def sources_to_dict(sources: list[MosaicSource], seams: Seams) -> dict[str, Any]:
    """JSON-ready parameters of the mosaic (``truth/reference.json``)."""
    return {
        "convention": (
            "the ortho pixel at true map point p (reference CRS) shows the surface at "
            "p - d(p), d = offset_m + sum(amp * sin(kx x + ky y + phase)) - dh(p) tan(emission) "
            "(sin, cos)(look_azimuth), dh = truth (reference epoch) minus reference DEM "
            "height; source index = "
            "number of seams x = base + amplitude sin(2 pi y / wavelength + phase) west of p"
        ),
        "sources": [
            {
                "index": s.index,
                "sun_azimuth_deg": s.sun.azimuth_deg,
                "sun_elevation_deg": s.sun.elevation_deg,
                "haze": s.haze,
                "gain": s.gain,
                **({"bias": s.bias} if s.bias != 0.0 else {}),
                "offset_m": list(s.offset_m),
                "emission_deg": s.emission_deg,
                "look_azimuth_deg": s.look_azimuth_deg,
                "waves": [
                    dict(
                        zip(("kx", "ky", "amp_x_m", "amp_y_m", "phase"), map(float, w), strict=True)
                    )
                    for w in s.waves
                ],
            }
            for s in sources
        ],
        "seams": [
            {
                "base_x_m": float(b),
                "amplitude_m": float(a),
                "wavelength_m": float(w),
                "phase": float(p),
            }
            for b, a, w, p in zip(
                seams.base, seams.amplitude, seams.wavelength, seams.phase, strict=True
            )
        ],
    }
