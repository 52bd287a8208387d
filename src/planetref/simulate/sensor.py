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
   DN range (saturation and zero floor). With ``saturation_fraction > 0`` the exposure
   (``mean_signal_e``) is first set per image so that this share of the noise-free
   signal exceeds the full well (:func:`exposure_for_saturation`): an auto-exposure
   that clips the brightest pixels.
5. **Lossy compression** (``compression_quality > 0``): the DN image is coded as 8 x 8
   blocks aligned on the image's first line and sample, each block's orthonormal 2-D
   DCT-II (the JPEG transform, ITU-T T.81 A.3.3) divided by the JPEG luminance table
   (T.81 Table K.1) scaled by the IJG quality rule, rounded, multiplied back and
   inverted (:func:`block_dct_compress`): block edges and ringing at 8-pixel period.

Noise is drawn from a generator per processed block, so results depend only on the
seed and the block layout, never on timing.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter

from planetref.simulate.config import SensorConfig

__all__ = [
    "JPEG_LUMINANCE",
    "apply_psf",
    "block_dct_compress",
    "exposure_for_saturation",
    "jpeg_table",
    "psf_halo",
    "quantize",
    "to_electrons",
    "with_noise",
]

JPEG_LUMINANCE = np.array(
    [
        [16, 11, 10, 16, 24, 40, 51, 61],
        [12, 12, 14, 19, 26, 58, 60, 55],
        [14, 13, 16, 24, 40, 57, 69, 56],
        [14, 17, 22, 29, 51, 87, 80, 62],
        [18, 22, 37, 56, 68, 109, 103, 77],
        [24, 35, 55, 64, 81, 104, 113, 92],
        [49, 64, 78, 87, 103, 121, 120, 101],
        [72, 92, 95, 98, 112, 100, 103, 99],
    ],
    dtype=np.float64,
)
"""JPEG luminance quantisation table (ITU-T T.81, Annex K, Table K.1), 8-bit DN."""

BLOCK = 8
"""Side of a compression block (pixels)."""


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


def jpeg_table(quality: int, bit_depth: int) -> NDArray[np.float64]:
    """The luminance table scaled to ``quality`` (IJG rule) and to ``bit_depth`` bits.

    IJG (libjpeg ``jcparam.c``): ``scale = 5000 / q`` below 50, else ``200 - 2 q`` (%),
    each entry ``floor((T * scale + 50) / 100)`` clipped to ``[1, 255]``; then times
    ``(2^bits - 1) / 255`` so a 16-bit image is quantised like its 8-bit rendering.

    Args:
        quality: 1-100 (100: every step 1 DN of 8 bits).
        bit_depth: DN bits of the image.
    """
    q = int(min(max(quality, 1), 100))
    scale = 5000 // q if q < 50 else 200 - 2 * q
    table = np.clip(np.floor((JPEG_LUMINANCE * scale + 50.0) / 100.0), 1.0, 255.0)
    return table * (((1 << bit_depth) - 1) / 255.0)


def block_dct_compress(
    dn: NDArray[np.integer], quality: int, bit_depth: int
) -> NDArray[np.integer]:
    """Lossy block-DCT coding and decoding of a DN image (what a JPEG round trip leaves).

    The image is cut into 8 x 8 blocks from its first line and sample (a partial block
    at the end is padded by repeating its last line/sample, as JPEG encoders do, and
    cropped after); each block is level-shifted to zero mean of the DN range,
    transformed by the orthonormal 2-D DCT-II (identical to the JPEG FDCT), quantised
    with :func:`jpeg_table` and inverted; the result is rounded and clipped to the DN
    range. Deterministic (no state, no noise).

    Args:
        dn: DN image (lines, samples); rows of whole blocks unless it is an image's end.
        quality: IJG quality 1-100.
        bit_depth: DN bits.

    Returns:
        The decoded DN image, same shape and dtype.
    """
    from scipy.fft import dctn, idctn

    top = (1 << bit_depth) - 1
    n_l, n_s = dn.shape
    pl, ps = (-n_l) % BLOCK, (-n_s) % BLOCK
    x = np.pad(np.asarray(dn, dtype=np.float64), ((0, pl), (0, ps)), mode="edge")
    x -= 0.5 * (top + 1)
    rows, cols = x.shape[0] // BLOCK, x.shape[1] // BLOCK
    blocks = x.reshape(rows, BLOCK, cols, BLOCK).transpose(0, 2, 1, 3)
    coef = dctn(blocks, type=2, axes=(2, 3), norm="ortho")
    table = jpeg_table(quality, bit_depth)
    coef = np.rint(coef / table) * table
    back = idctn(coef, type=2, axes=(2, 3), norm="ortho")
    out = back.transpose(0, 2, 1, 3).reshape(x.shape)[:n_l, :n_s] + 0.5 * (top + 1)
    return np.clip(np.rint(out), 0, top).astype(dn.dtype)


def exposure_for_saturation(signal_e: NDArray[np.floating], sensor: SensorConfig) -> float:
    """``mean_signal_e`` at which ``saturation_fraction`` of ``signal_e`` exceeds the full well.

    ``signal_e`` is a sample of the noise-free signal (electrons) rendered at the
    configured ``mean_signal_e``; the signal scales with the exposure, so the new mean
    signal is ``mean_signal_e * full_well_e / q``, ``q`` the ``1 - saturation_fraction``
    quantile of the sample. Without saturation the configured exposure is returned.

    Args:
        signal_e: Noise-free signal (electrons) at the configured exposure.
        sensor: Sensor configuration.
    """
    f = sensor.saturation_fraction
    if f <= 0:
        return float(sensor.mean_signal_e)
    q = float(np.quantile(np.asarray(signal_e, dtype=np.float64), 1.0 - f))
    if q <= 0:
        return float(sensor.mean_signal_e)
    return float(sensor.mean_signal_e * sensor.full_well_e / q)
