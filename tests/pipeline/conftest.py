"""A simulated tiny scene shared by the pipeline tests (simulated once per session)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from planetref.simulate.config import load_config
from planetref.simulate.scene import simulate_scene


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("scenes") / "tiny"
    simulate_scene(load_config("tiny", seed=0), out)
    return out


@pytest.fixture(scope="session")
def weights_dir() -> str | None:
    return os.environ.get("PLANETREF_WEIGHTS")
