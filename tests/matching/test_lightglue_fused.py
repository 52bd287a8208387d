"""LightGlue's fused cross-attention (planetref.matching._torch.fused_cross_block).

The fused block must compute what kornia's own ``CrossBlock`` computes (to float32
rounding), keep its weights and keys, and leave LightGlue's matches unchanged.
"""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")
KF = pytest.importorskip("kornia.feature")

from planetref.matching._torch import build_lightglue, fused_cross_block  # noqa: E402


def _lightglue_state(features: str) -> dict:
    torch.manual_seed(0)
    conf = {k: v for k, v in KF.LightGlue.features[features].items() if k != "weights"}
    ref = KF.LightGlue(None, **conf).state_dict()
    return {k: v for k, v in ref.items() if k != "confidence_thresholds"}


def test_fused_cross_block_equals_kornia_block():
    from kornia.feature.lightglue import CrossBlock

    torch.manual_seed(1)
    block = CrossBlock(256, 4).eval()
    x0, x1 = torch.randn(1, 700, 256), torch.randn(1, 513, 256)
    with torch.inference_mode():
        want0, want1 = block(x0, x1)
        keys = set(block.state_dict())
        block.__class__ = fused_cross_block()
        got0, got1 = block(x0, x1)
    assert set(block.state_dict()) == keys
    assert got0.shape == want0.shape and got1.shape == want1.shape
    # float32 sums in another order: differences at the rounding level of values ~1-10
    assert float((got0 - want0).abs().max()) < 1e-4
    assert float((got1 - want1).abs().max()) < 1e-4
    # and not the identity: the messages change the descriptors
    assert float((got0 - x0).abs().max()) > 1e-2


def test_lightglue_matches_unchanged_by_fusion():
    state = _lightglue_state("disk")
    fused = build_lightglue("disk", state, what="test", filter_threshold=0.0)
    assert all(type(t.cross_attn) is fused_cross_block() for t in fused.transformers)
    plain = build_lightglue("disk", state, what="test", filter_threshold=0.0)
    for t in plain.transformers:
        t.cross_attn.__class__ = type(t.cross_attn).__mro__[1]  # kornia's own CrossBlock
    torch.manual_seed(2)
    n = 400
    kpts = torch.rand(1, n, 2) * 490
    desc = torch.nn.functional.normalize(torch.randn(1, n, 128), dim=-1)
    perm = torch.randperm(n)
    data = {
        "image0": {
            "keypoints": kpts,
            "descriptors": desc,
            "image_size": torch.tensor([[500.0, 500.0]]),
        },
        "image1": {
            "keypoints": kpts[:, perm] + 3.0,
            "descriptors": desc[:, perm] + 0.01 * torch.randn(1, n, 128),
            "image_size": torch.tensor([[500.0, 500.0]]),
        },
    }
    with torch.inference_mode():
        a, b = fused(data), plain(data)
    assert a["stop"] == b["stop"]
    assert int((b["matches0"] > -1).sum()) > 0  # random weights still match something
    assert torch.equal(a["matches0"], b["matches0"])
    assert float((a["matching_scores0"] - b["matching_scores0"]).abs().max()) < 1e-4
