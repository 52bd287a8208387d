"""Fixtures of the pipeline tests (the tiny scene is in tests/conftest.py, shared)."""

from __future__ import annotations

import os

import pytest


@pytest.fixture(scope="session")
def weights_dir() -> str | None:
    return os.environ.get("PLANETREF_WEIGHTS")
