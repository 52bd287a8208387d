"""Fixtures of the reliability battery: a mini scene, small rasters."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from reliability_helpers import MINI_SCENE


@pytest.fixture(scope="session")
def mini_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A mini simulated scene (seed 7), written through ``planetref simulate``'s code."""
    from planetref.cli.simulate import simulate_run
    from planetref.simulate.config import load_config, merge_overrides

    out = tmp_path_factory.mktemp("reliability") / "scene"
    simulate_run(load_config("tiny", merge_overrides(MINI_SCENE, {"seed": 7})), out)
    return out


@pytest.fixture
def image_pair(tmp_path: Path, write_geotiff) -> tuple[Path, Path]:
    """Two 192 x 192 textured GeoTIFF-less rasters, the second shifted by (7, 4) px."""
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(3)
    big = gaussian_filter(rng.random((220, 220)), 1.5)
    big = ((big - big.min()) / np.ptp(big) * 255).astype(np.uint8)
    paths = []
    for name, (r, c) in (("A.tif", (0, 0)), ("B.tif", (4, 7))):
        p = tmp_path / name
        paths.append(write_geotiff(p, big[r : r + 192, c : c + 192]))
    return paths[0], paths[1]
