"""Random streams of the simulator: one independent generator per scene component.

Each component draws from ``SeedSequence(seed, spawn_key=(k, ...))`` with a fixed ``k``
per component (and strip/CCD indices as further keys), so changing one part of the
config does not reshuffle the others, and the same seed gives byte-identical files.
"""

from __future__ import annotations

import numpy as np

__all__ = ["seed_sequence", "stream"]

_STREAMS = {
    "regional": 1,
    "fractal": 2,
    "plains": 3,
    "dunes": 4,
    "craters": 5,
    "ridges": 6,
    "albedo": 7,
    "texture": 8,
    "ortho_noise": 9,
    "dem_noise": 10,
    "checkpoints": 11,
    "consistency": 12,
    "mismatch": 13,
    "change": 14,
    "mosaic": 15,
    "mola": 16,
    "strip": 100,
    "ccd_noise": 200,
}


def stream(seed: int, name: str, *extra: int) -> np.random.Generator:
    """The random generator of a component (see the module docstring)."""
    return np.random.default_rng(seed_sequence(seed, name, *extra))


def seed_sequence(seed: int, name: str, *extra: int) -> np.random.SeedSequence:
    """The seed sequence of a component."""
    return np.random.SeedSequence(seed, spawn_key=(_STREAMS[name], *extra))
