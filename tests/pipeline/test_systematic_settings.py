"""The adjustment's declared correlated errors: run config, then scene manifest, then defaults."""

from __future__ import annotations

import pytest

from planetref.adjust.config import validate_config
from planetref.control.networks import template_support_m
from planetref.pipeline.systematic import (
    DEFAULT_CCD_ACCURACY_PX,
    DEFAULT_REFERENCE_ACCURACY_REF_PX,
    systematic_settings,
)
from planetref.scene.manifest import CcdSpec, ReferenceSpec, SceneManifest, StripSpec


def _manifest(accuracy_m=None, length_m=None, ccd_px=None) -> SceneManifest:
    return SceneManifest(
        reference=ReferenceSpec(
            ortho="o.tif", dem="d.tif", accuracy_m=accuracy_m, accuracy_length_m=length_m
        ),
        strips=(
            StripSpec(
                id="s1",
                ccds=(CcdSpec(name="c1", image="i.tif", camera="c.json"),),
                ccd_accuracy_px=ccd_px,
            ),
        ),
    )


def test_declared_by_the_scene():
    cfg, src = systematic_settings(
        validate_config({}), _manifest(6.1, 900.0, 2.0), ["s1"], 5.0, 23.0
    )
    s = cfg.systematic
    assert (s.reference_sigma_m, s.reference_patch_m, s.ccd_offset_sigma_px) == (6.1, 900.0, 2.0)
    assert s.measurement_overlap == 23.0
    assert src == {
        "reference_sigma_m": "scene",
        "reference_patch_m": "scene",
        "ccd_offset_sigma_px": "scene",
        "tile_offset_sigma_px": "estimated",
        "measurement_overlap": "matches",
    }
    # A reference declared exact: no reference term.
    cfg, _ = systematic_settings(validate_config({}), _manifest(0.0, 900.0), ["s1"], 5.0)
    assert cfg.systematic.reference_sigma_m == 0.0


def test_defaults_and_the_config_wins():
    cfg, src = systematic_settings(validate_config({}), _manifest(), ["s1"], 5.0)
    s = cfg.systematic
    assert s.reference_sigma_m == pytest.approx(DEFAULT_REFERENCE_ACCURACY_REF_PX * 5.0)
    assert s.ccd_offset_sigma_px == DEFAULT_CCD_ACCURACY_PX and s.reference_patch_m is None
    assert src["reference_sigma_m"] == "default" and src["ccd_offset_sigma_px"] == "default"
    own = validate_config(
        {
            "systematic": {
                "reference_sigma_m": "2 m",
                "ccd_offset_sigma_px": 0,
                "reference_patch_m": 300,
                "tile_offset_sigma_px": 0.4,
            }
        }
    )
    cfg, src = systematic_settings(own, _manifest(6.1, 900.0, 2.0), ["s1"], 5.0)
    s = cfg.systematic
    assert (s.reference_sigma_m, s.reference_patch_m, s.ccd_offset_sigma_px) == (2.0, 300.0, 0.0)
    assert set(src.values()) == {"config", "matches"}
    assert s.tile_offset_sigma_px == 0.4
    off = validate_config({"systematic": {"tile_offset_sigma_px": None}})
    assert systematic_settings(off, _manifest(), ["s1"], 5.0)[1]["tile_offset_sigma_px"] == "none"


def test_template_support():
    # NCC's 21-pixel template (radius 10 at the reference grid) on a twice finer grid.
    assert template_support_m("ncc", {"template_radius": 20}, 2, 5.0) == pytest.approx(102.5)
    assert template_support_m("sift", {}, 2, 5.0) is None


def _declaring(*uncertainties) -> SceneManifest:
    return SceneManifest(
        reference=ReferenceSpec(ortho="o.tif", dem="d.tif"),
        strips=tuple(
            StripSpec(
                id=f"s{k}",
                ccds=(CcdSpec(name="c1", image="i.tif", camera="c.json"),),
                initial_uncertainty_m=u,
            )
            for k, u in enumerate(uncertainties)
        ),
    )


def test_uncertainty_from_the_config_then_the_scene_then_the_default():
    from planetref.frontend.config import FrontendConfig
    from planetref.pipeline.systematic import declared_uncertainty

    # The scene's declared uncertainty (the largest of its strips) when the config is silent.
    fe, src = declared_uncertainty(FrontendConfig(), _declaring(1300.0, None, 800.0))
    assert (fe.uncertainty_m, src) == (1300.0, "scene")
    assert fe.coarse_level(5.0) == 4 and FrontendConfig().uncertainty_m == 300.0
    # A config that sets it wins, even at the default's value.
    fe, src = declared_uncertainty(FrontendConfig(uncertainty_m=300.0), _declaring(1300.0))
    assert (fe.uncertainty_m, src) == (300.0, "config")
    fe, src = declared_uncertainty(
        FrontendConfig.from_mapping({"uncertainty_m": 2000}), _declaring(1300.0)
    )
    assert (fe.uncertainty_m, src) == (2000.0, "config")
    # Nothing declared: the default.
    fe, src = declared_uncertainty(FrontendConfig(), _declaring(None))
    assert (fe.uncertainty_m, src) == (300.0, "default")
    # The resolved value is part of the run's identity.
    resolved, _ = declared_uncertainty(FrontendConfig(), _declaring(1300.0))
    assert resolved.identity()["uncertainty_m"] == 1300.0
    assert FrontendConfig().identity() != resolved.identity()
