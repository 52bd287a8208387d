"""Fixtures of the simulator tests: a mini scene, smaller than the ``tiny`` preset."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from planetref.simulate.config import SimulationConfig, load_config

MINI: dict[str, Any] = {
    "name": "mini",
    "site": {"margin_m": 150.0},
    "camera": {
        "n_samples": 64,
        "overlap_samples": 8,
        "n_lines": 96,
        "gsd_m": 1.0,
        "ccd_stagger_mm": 0.1,
    },
    "terrain": {
        "dem_gsd_m": 2.0,
        "craters": {"density_per_km2": 200.0, "d_max_m": 120.0},
        "ridges": {"count": 1, "width_m": 120.0},
    },
    "albedo": {"texture_gsd_m": 0.5},  # half an image pixel (tiny's 1.25 m is for 2.5 m)
    "reference": {"dem_pad_m": 500.0},
    "render": {"write_rpc": False, "n_checkpoints": 5, "measure_grid": 4, "chunk_pixels": 4096},
}


def _mini_config(**overrides: Any) -> SimulationConfig:
    from planetref.simulate.config import merge_overrides

    return load_config("tiny", merge_overrides(MINI, overrides))


@pytest.fixture(scope="session")
def mini_config() -> Callable[..., SimulationConfig]:
    """A factory of the mini scene config: ``mini_config(**overrides)``."""
    return _mini_config


@pytest.fixture(scope="session")
def mini_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A mini scene simulated once per session (seed 7)."""
    from planetref.simulate.scene import simulate_scene

    out = tmp_path_factory.mktemp("mini") / "scene"
    simulate_scene(_mini_config(seed=7), out)
    return out
