"""Detector effects: point spread (MTF), photon and read noise, quantisation.

The chain applied to a radiance image (already integrated over each pixel's ground
footprint, which is the detector's box MTF and, along track, the motion during one
line period) is:

1. **PSF**: a Gaussian of ``mtf_sigma_px`` (optics and electronics); the MTF at
   Nyquist is ``exp(-pi^2 sigma^2 / 2)``.
2. **Signal**: electrons ``e = mean_signal_e * L / L_flat``, where ``L_flat`` is the
   radiance of a level mean-albedo surface (so exposure is set like an auto-exposure
   on a flat average scene).
3. **Noise**: photon noise ``N(0, sqrt(e))`` and read noise ``N(0, read_noise_e)``.
4. **Quantisation**: ``DN = round(e * (2^bits - 1) / full_well_e)``, clipped to the
   DN range (saturation and zero floor).

Noise is drawn from a generator per processed block, so results depend only on the
seed and the block layout, never on timing.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter

from planetref.simulate.config import SensorConfig

__all__ = ["apply_psf", "psf_halo", "quantize", "to_electrons", "with_noise"]


def psf_halo(sensor: SensorConfig) -> int:
    """Pixels of context the PSF needs on each side (``ceil(4 sigma) + 1``, 0 without PSF)."""
    if sensor.mtf_sigma_px <= 0:
        return 0
    return math.ceil(4.0 * sensor.mtf_sigma_px) + 1


def apply_psf(image: NDArray[np.floating], sensor: SensorConfig) -> NDArray[np.float32]:
    """Blur with the Gaussian PSF (edges replicated); identity when ``mtf_sigma_px`` is 0."""
    img = np.asarray(image, dtype=np.float32)
    if sensor.mtf_sigma_px <= 0:
        return img
    return gaussian_filter(img, sensor.mtf_sigma_px, mode="nearest", truncate=4.0)


def to_electrons(
    radiance: NDArray[np.floating], flat_radiance: float, sensor: SensorConfig
) -> NDArray[np.float32]:
    """Mean signal in electrons (before noise)."""
    scale = np.float32(sensor.mean_signal_e / flat_radiance)
    return np.asarray(radiance, dtype=np.float32) * scale


def with_noise(
    electrons: NDArray[np.float32], sensor: SensorConfig, rng: np.random.Generator
) -> NDArray[np.float32]:
    """Add photon (Poisson, Gaussian approximation) and read noise."""
    e = np.maximum(electrons, 0.0)
    sigma = np.sqrt(e + np.float32(sensor.read_noise_e) ** 2)
    return e + sigma * rng.standard_normal(e.shape, dtype=np.float32)


def quantize(electrons: NDArray[np.float32], sensor: SensorConfig) -> NDArray[np.integer]:
    """Electrons to DN of ``sensor.bit_depth`` bits (uint8 or uint16), rounded and clipped."""
    top = (1 << sensor.bit_depth) - 1
    dn = np.rint(electrons * np.float32(top / sensor.full_well_e))
    dtype = np.uint8 if sensor.bit_depth == 8 else np.uint16
    return np.clip(dn, 0, top).astype(dtype)
