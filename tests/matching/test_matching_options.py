"""The typed settings of the torch matchers and the flat options users write."""

from __future__ import annotations

import dataclasses

import pytest

from planetref.errors import InputError
from planetref.matching import MATCHERS, get_matcher
from planetref.matching.options import LightGlueSettings, TorchSettings, split_options

TORCH_KEYS = ["weights_dir", "device", "verify_weights", "polish"]
LIGHTGLUE_KEYS = [
    *TORCH_KEYS,
    "max_keypoints",
    "max_size",
    "filter_threshold",
    "depth_confidence",
    "width_confidence",
]
# the keys of ``[matchers.<name>]`` as they were before the settings value (must not change)
FLAT_KEYS = {
    "disk-lightglue": [*LIGHTGLUE_KEYS, "nms_window", "score_threshold"],
    "aliked-lightglue": [*LIGHTGLUE_KEYS, "detection_threshold", "nms_radius"],
    "doghardnet-lightglue": [
        *LIGHTGLUE_KEYS,
        "contrast_threshold",
        "edge_threshold",
        "n_octave_layers",
    ],
    "xfeat-lighterglue": [*LIGHTGLUE_KEYS, "detection_threshold"],
    "xfeat-star": [*TORCH_KEYS, "top_k", "scales", "fine_confidence", "max_size"],
    "loftr": [*TORCH_KEYS, "max_size", "confidence_threshold"],
}


def test_lightglue_settings_defaults_coercion_and_overrides():
    s = LightGlueSettings()
    assert (s.max_keypoints, s.max_size, s.filter_threshold) == (4096, 2048, 0.1)
    assert s.lightglue_overrides() == {"filter_threshold": 0.1}
    s = LightGlueSettings(max_keypoints=512.0, max_size=None, depth_confidence=-1, polish="ncc")
    assert s.max_keypoints == 512 and type(s.max_keypoints) is int and s.max_size is None
    assert s.lightglue_overrides() == {"filter_threshold": 0.1, "depth_confidence": -1.0}
    assert type(s.lightglue_overrides()["depth_confidence"]) is float
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.max_keypoints = 3  # type: ignore[misc]


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"max_keypoints": 1}, "field 'max_keypoints': must be >= 2, got 1"),
        ({"max_size": 8}, "field 'max_size': must be >= 32 or None, got 8"),
        ({"polish": "lsq"}, "field 'polish': must be None or 'ncc', got 'lsq'"),
        ({"max_keypoints": "many"}, "field 'max_keypoints': expected int, got 'many'"),
        ({"filter_threshold": "high"}, "field 'filter_threshold': expected float, got 'high'"),
    ],
)
def test_lightglue_settings_errors_are_one_line(options, message):
    with pytest.raises(InputError) as err:
        LightGlueSettings(**options)
    assert str(err.value) == message


def test_split_options_sends_each_key_to_its_place():
    settings, own = split_options(
        LightGlueSettings, {"max_keypoints": 100, "nms_radius": 3, "polish": "ncc"}
    )
    assert settings == LightGlueSettings(max_keypoints=100, polish="ncc")
    assert own == {"nms_radius": 3}
    settings, own = split_options(TorchSettings, {"max_size": 512})
    assert settings == TorchSettings() and own == {"max_size": 512}


@pytest.mark.parametrize("name", sorted(FLAT_KEYS))
def test_flat_option_names_are_unchanged(name):
    import importlib

    module, cls = {
        "disk-lightglue": ("disk_lightglue", "DiskLightGlueMatcher"),
        "aliked-lightglue": ("aliked_lightglue", "AlikedLightGlueMatcher"),
        "doghardnet-lightglue": ("doghardnet_lightglue", "DogHardNetLightGlueMatcher"),
        "xfeat-lighterglue": ("xfeat", "XFeatLighterGlueMatcher"),
        "xfeat-star": ("xfeat", "XFeatStarMatcher"),
        "loftr": ("loftr", "LoftrMatcher"),
    }[name]
    target = getattr(importlib.import_module(f"planetref.matching.{module}"), cls)
    assert sorted(target.option_names()) == sorted(FLAT_KEYS[name])
    # the registry lists the weight files the class loads (availability, downloads)
    assert MATCHERS[name].weights == target.weight_files and target.name == name


def test_get_matcher_builds_settings_and_own_options(shared_weights):
    m = get_matcher(
        "aliked-lightglue",
        weights_dir=shared_weights,
        max_keypoints=300,
        depth_confidence=-1,
        nms_radius=3,
        polish="ncc",
    )
    assert m.settings == LightGlueSettings(
        weights_dir=shared_weights, max_keypoints=300, depth_confidence=-1, polish="ncc"
    )
    assert m.nms_radius == 3 and m.detection_threshold == 0.0
    star = get_matcher("xfeat-star", weights_dir=shared_weights, top_k=100, max_size=None)
    assert star.settings == TorchSettings(weights_dir=shared_weights)
    assert (star.top_k, star.max_size) == (100, None)
    with pytest.raises(InputError, match="takes LightGlueSettings, got TorchSettings"):
        type(m)(TorchSettings(weights_dir=shared_weights))
