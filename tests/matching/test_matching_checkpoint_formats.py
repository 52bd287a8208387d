"""Checkpoint formats of the weights that are not available here (LoFTR, HardNet,
LightGlue "doghardnet"), and of the LightGlue files that are.

The official files cannot be obtained on this machine, so random weights are saved in the
official formats (``random_weights_dir`` in conftest) and the full matcher code path runs on
them. The sha256 check is skipped for these files explicitly with ``verify_weights=False``.
The expected key layouts below are the official names: zju3dv LoFTR's Lightning checkpoint
(module attribute ``matcher.``), DagnyT/hardnet's ``{"state_dict"}`` and cvg/LightGlue's
raw state dict (``transformers.<i>`` or the first release's ``self_attn.<i>``).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from planetref.errors import WeightsError
from planetref.matching import get_matcher
from planetref.matching._torch import build_lightglue, lightglue_state_dict
from planetref.matching.doghardnet_lightglue import hardnet_state_dict
from planetref.matching.loftr import loftr_state_dict

# keys that every official LoFTR outdoor checkpoint holds under "state_dict"
LOFTR_OFFICIAL_KEYS = [
    "matcher.backbone.conv1.weight",
    "matcher.backbone.layer3_outconv.weight",
    "matcher.loftr_coarse.layers.0.q_proj.weight",
    "matcher.loftr_coarse.layers.7.merge.weight",
    "matcher.fine_preprocess.down_proj.weight",
    "matcher.fine_preprocess.merge_feat.weight",
    "matcher.loftr_fine.layers.1.mlp.0.weight",
]
LOFTR_PREFIXES = {"backbone", "loftr_coarse", "fine_preprocess", "loftr_fine"}

HARDNET_CONV = [0, 3, 6, 9, 12, 15, 19]
HARDNET_BN = [1, 4, 7, 10, 13, 16, 20]
HARDNET_OFFICIAL_KEYS = [f"features.{i}.weight" for i in HARDNET_CONV] + [
    f"features.{i}.{s}" for i in HARDNET_BN for s in ("running_mean", "running_var")
]

LIGHTGLUE_DOGHARDNET_SHAPES = {
    "posenc.Wr.weight": (32, 4),  # x, y, scale, orientation
    "input_proj.weight": (256, 128),
    "transformers.0.self_attn.Wqkv.weight": (768, 256),
    "transformers.8.cross_attn.to_qk.weight": (256, 256),
    "log_assignment.8.matchability.weight": (1, 256),
    "token_confidence.7.token.0.weight": (1, 256),
}


def test_loftr_key_layout():
    import kornia.feature as KF

    kornia_keys = set(KF.LoFTR(None).state_dict())
    assert {k.split(".")[0] for k in kornia_keys} == LOFTR_PREFIXES
    for key in LOFTR_OFFICIAL_KEYS:
        assert key.removeprefix("matcher.") in kornia_keys
    official = {"epoch": 1, "state_dict": {f"matcher.{k}": torch.zeros(1) for k in kornia_keys}}
    assert set(loftr_state_dict(official)) == kornia_keys
    unprefixed = {"state_dict": {k: torch.zeros(1) for k in kornia_keys}}
    assert set(loftr_state_dict(unprefixed)) == kornia_keys
    with pytest.raises(WeightsError):
        loftr_state_dict({k: torch.zeros(1) for k in kornia_keys})  # not a Lightning checkpoint


def test_hardnet_key_layout():
    import kornia.feature as KF

    kornia_keys = {
        k for k in KF.HardNet(False).state_dict() if not k.endswith("num_batches_tracked")
    }
    assert kornia_keys == set(HARDNET_OFFICIAL_KEYS)
    assert (
        set(hardnet_state_dict({"epoch": 3, "state_dict": dict.fromkeys(HARDNET_OFFICIAL_KEYS)}))
        == kornia_keys
    )
    with pytest.raises(WeightsError):
        hardnet_state_dict(dict.fromkeys(HARDNET_OFFICIAL_KEYS))


def test_lightglue_doghardnet_layouts_both_releases():
    import kornia.feature as KF

    conf = {k: v for k, v in KF.LightGlue.features["doghardnet"].items() if k != "weights"}
    ref = KF.LightGlue(None, **conf).state_dict()
    for key, shape in LIGHTGLUE_DOGHARDNET_SHAPES.items():
        assert tuple(ref[key].shape) == shape
    learned = {k: v for k, v in ref.items() if k != "confidence_thresholds"}
    legacy = {}
    for k, v in learned.items():
        parts = k.split(".")
        if parts[0] == "transformers":  # first-release layout: self_attn.<i>.*, cross_attn.<i>.*
            k = ".".join([parts[2], parts[1], *parts[3:]])
        legacy[k] = v
    assert "self_attn.0.Wqkv.weight" in legacy and "cross_attn.8.to_out.weight" in legacy
    for state in (learned, legacy, {f"matcher.{k}": v for k, v in learned.items()}):
        model = build_lightglue("doghardnet", state, what="test")
        assert not model.training
        for k, v in learned.items():
            assert torch.equal(model.state_dict()[k], v)
    broken = dict(learned)
    broken.pop("posenc.Wr.weight")
    with pytest.raises(WeightsError, match="missing"):
        build_lightglue("doghardnet", broken, what="test")
    with pytest.raises(WeightsError):
        build_lightglue("doghardnet", {**learned, "bogus.weight": torch.zeros(1)}, what="test")


def test_real_lightglue_files_map_onto_kornia(shared_weights):
    """The two LightGlue files present here use the two official layouts; both load fully."""
    from planetref.matching.weights import load_checkpoint

    disk = load_checkpoint("disk_lightglue_v0-1_arxiv-pth", shared_weights)
    aliked = load_checkpoint("aliked_lightglue_v0-1_arxiv-pth", shared_weights)
    assert "self_attn.0.Wqkv.weight" in disk  # first release
    assert "transformers.0.self_attn.Wqkv.weight" in aliked  # later layout
    for raw, feats in ((disk, "disk"), (aliked, "aliked")):
        mapped = lightglue_state_dict(raw, 9)
        assert "transformers.8.cross_attn.to_out.weight" in mapped
        assert not build_lightglue(feats, raw, what=feats).training
    lighter = load_checkpoint("xfeat-lighterglue.pt", shared_weights)
    assert any(k.startswith("extractor.") for k in lighter)
    assert not build_lightglue("xfeat", lighter, what="xfeat-lighterglue.pt").training


@pytest.mark.parametrize(
    ("name", "options"),
    [
        ("loftr", {"confidence_threshold": 0.0, "max_size": 128}),
        ("doghardnet-lightglue", {"filter_threshold": 0.0, "max_keypoints": 256}),
    ],
)
def test_random_weights_end_to_end(name, options, random_weights_dir, shifted_pair):
    verified = get_matcher(name, weights_dir=random_weights_dir, **options)
    if name == "loftr":  # no reference checksum is known for the LoFTR file: warn, load
        with pytest.warns(UserWarning, match="cannot be verified"):
            verified.build()
    else:  # random files are not the official ones
        with pytest.raises(WeightsError, match="sha256"):
            verified.build()
    matcher = get_matcher(name, weights_dir=random_weights_dir, verify_weights=False, **options)
    a, b = shifted_pair(160, (3.0, 2.0), seed=1)
    m = matcher.match(a, b)
    assert len(m) > 0
    assert m.keypoints0.dtype == np.float64
    assert np.all(m.keypoints0 >= 0) and np.all(m.keypoints0[:, 0] < 160)
    assert "build" in matcher.timings
    model = matcher._model
    modules = model.values() if isinstance(model, dict) else [model]
    assert all(not mod.training for mod in modules)


def test_loftr_resizes_to_multiples_of_8_and_maps_back(random_weights_dir, shifted_pair):
    matcher = get_matcher(
        "loftr",
        weights_dir=random_weights_dir,
        verify_weights=False,
        confidence_threshold=0.0,
        max_size=96,
    )
    a, b = shifted_pair(150, (2.0, 2.0), seed=2)
    a = a[:, :137]  # 150 x 137 -> network sees 96 x 88
    assert matcher._network_size(a.shape) == (96, 88)
    m = matcher.match(a, b)
    assert len(m) > 0
    assert np.all(m.keypoints0[:, 0] < 137) and np.all(m.keypoints0[:, 1] < 150)
    # coarse keypoints of image 0 sit on the 8-px grid of the network image, scaled back
    grid_x = m.keypoints0[:, 0] * 88 / 137 / 8
    assert np.allclose(grid_x, np.round(grid_x), atol=1e-6)
