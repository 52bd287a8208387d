"""Synthetic test texture shared by the matcher tests and benchmarks (numpy and scipy only)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = ["texture"]


def texture(size: int, seed: int = 0, pad: int = 32) -> np.ndarray:
    """Multi-scale noise plus random blobs, lightly blurred so it is nearly band-limited.

    Args:
        size: Side of the useful image, pixels.
        seed: Seed of ``numpy.random.default_rng``; the same seed gives the same texture.
        pad: Margin added on every side (the result is ``size + 2 * pad`` square), so that
            callers can shift the texture periodically and crop the wrap-around away.

    Returns:
        ``(size + 2 * pad, size + 2 * pad)`` float64 array.
    """
    rng = np.random.default_rng(seed)
    n = size + 2 * pad
    img = np.zeros((n, n))
    for sigma, weight in ((1.0, 0.35), (2.0, 0.5), (4.0, 0.8), (8.0, 1.0), (16.0, 1.0)):
        layer = ndimage.gaussian_filter(rng.standard_normal((n, n)), sigma, mode="wrap")
        img += weight * layer / layer.std()
    yy, xx = np.mgrid[0:n, 0:n]
    for _ in range(n * n // 900):
        cy, cx = rng.uniform(0, n, 2)
        r = rng.uniform(2, 9)
        img[(yy - cy) ** 2 + (xx - cx) ** 2 < r * r] += rng.normal(0, 2.0)
    return ndimage.gaussian_filter(img, 1.0, mode="wrap")
