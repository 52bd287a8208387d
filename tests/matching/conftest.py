"""Fixtures of the matcher tests: one torch thread, small synthetic images, shared data."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from planetref.matching._synthetic import texture

os.environ.setdefault("OMP_NUM_THREADS", "1")

try:
    import torch

    torch.set_num_threads(1)
except ImportError:  # pragma: no cover - torch is a dependency
    torch = None

SHARED = Path(__file__).resolve().parents[2].parent / "shared"
SHARED_WEIGHTS = SHARED / "weights"
HIRISE = SHARED / "data" / "hirise_pairs"


def make_shifted_pair(
    size: int = 256,
    shift: tuple[float, float] = (3.3, -2.6),
    seed: int = 0,
    radiometric: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(image0, image1)`` with ``image1(x + dx, y + dy) = f(image0(x, y))``.

    The shift is exact (Fourier phase ramp on a padded texture, padding cropped away), so a
    correct match satisfies ``keypoints1 = keypoints0 + shift``. With ``radiometric`` the
    second image gets a gain, an offset, a gamma and a little noise.
    """
    pad = 32
    base = texture(size, seed, pad)
    moved = np.real(np.fft.ifft2(ndimage.fourier_shift(np.fft.fft2(base), (shift[1], shift[0]))))
    a = base[pad : pad + size, pad : pad + size]
    b = moved[pad : pad + size, pad : pad + size]
    if radiometric:
        rng = np.random.default_rng(seed + 1)
        b = 0.8 * b + 0.3
        b = b + 0.02 * b.std() * rng.standard_normal(b.shape)
        b = 50.0 * (b - b.min() + 1.0) ** 0.9
    return a.astype(np.float32), b.astype(np.float32)


@pytest.fixture(scope="session")
def shifted_pair():
    """Factory fixture: ``shifted_pair(size, shift, seed, radiometric)``."""
    return make_shifted_pair


@pytest.fixture(scope="session")
def shared_weights() -> Path:
    """The shared weights directory, or skip."""
    if not (SHARED_WEIGHTS / "hub" / "checkpoints").is_dir():
        pytest.skip(f"shared weights not found at {SHARED_WEIGHTS}")
    return SHARED_WEIGHTS


@pytest.fixture(scope="session")
def hirise_dir() -> Path:
    """The shared HiRISE pairs, or skip."""
    if not HIRISE.is_dir():
        pytest.skip(f"shared HiRISE pairs not found at {HIRISE}")
    return HIRISE


@pytest.fixture(scope="session")
def random_weights_dir(tmp_path_factory) -> Path:
    """A weights directory holding randomly initialised LoFTR, HardNet and LightGlue
    ("doghardnet") checkpoints, each in its official file format.

    - ``loftr_outdoor.ckpt``: Lightning checkpoint ``{"epoch", "global_step",
      "state_dict": {"matcher.<kornia LoFTR key>": tensor}}``.
    - ``checkpoint_liberty_with_aug.pth``: DagnyT/hardnet ``{"epoch", "state_dict"}``.
    - ``doghardnet_v0-1_arxiv-pth``: raw cvg/LightGlue state dict (``transformers.<i>.*``).

    These are not the official files, so the matchers are built with
    ``verify_weights=False``.
    """
    import kornia.feature as KF

    torch.manual_seed(0)
    root = tmp_path_factory.mktemp("random_weights")
    ckpt = root / "hub" / "checkpoints"
    ckpt.mkdir(parents=True)
    loftr = KF.LoFTR(None)
    torch.save(
        {
            "epoch": 29,
            "global_step": 0,
            "pytorch-lightning_version": "1.3.5",
            "state_dict": {f"matcher.{k}": v for k, v in loftr.state_dict().items()},
        },
        ckpt / "loftr_outdoor.ckpt",
    )
    torch.save(
        {"epoch": 10, "state_dict": KF.HardNet(False).state_dict()},
        ckpt / "checkpoint_liberty_with_aug.pth",
    )
    conf = {k: v for k, v in KF.LightGlue.features["doghardnet"].items() if k != "weights"}
    lg = KF.LightGlue(None, **conf).state_dict()
    torch.save(
        {k: v for k, v in lg.items() if k != "confidence_thresholds"},
        ckpt / "doghardnet_v0-1_arxiv-pth",
    )
    return root
