"""A kilometre of initial error, found by the coarse stage at the level it adapts to it.

The tiny scene with the ``1km`` initial-error level (every physical term: position,
roll/pitch/yaw, altitude, focal length; ~1.06 km on the ground) declares 1300 m of
a-priori uncertainty in its manifest. With ``coarse_max_px = 128`` the coarse stage
matches at level 7 (35 m pixels) instead of 4: NCC's coarse consensus must still place
every tile, whose offset must then agree with the truth to a fraction of a pixel.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def km_scene(tmp_path_factory) -> Path:
    from planetref.simulate.config import load_config
    from planetref.simulate.scene import simulate_scene

    out = tmp_path_factory.mktemp("scenes") / "tiny-1km"
    simulate_scene(load_config("tiny", seed=0, initial_errors="1km"), out)
    return out


def _offset_truth(tile_result, s) -> np.ndarray:
    """The true mean offset (reference px) of the tile's MCPs: true minus initial position."""
    from planetref.camera.mapping import image_to_ref_pixel

    r, ref = tile_result, s["ref"]
    tc, tr = image_to_ref_pixel(s["true"], r.tile.ccd, r.line, r.sample, ref, s["truth_dem"])
    dx, dy = s["man"].truth.ortho_offset_m
    tc, tr = tc + dx / ref.transform.a, tr + dy / ref.transform.e
    ic, ir = image_to_ref_pixel(s["init"], r.tile.ccd, r.line, r.sample, ref, s["dem"])
    return np.array([np.mean(tc - ic), np.mean(tr - ir)])


def _load(root: Path) -> dict:
    from planetref.camera.linescan import LineScanCamera
    from planetref.raster.dem import GridTerrain
    from planetref.raster.ortho import ReferenceOrtho
    from planetref.scene.manifest import load_manifest

    man, root = load_manifest(root)
    strip = man.strips[0]
    assert man.truth is not None
    return {
        "man": man,
        "init": LineScanCamera.from_json(man.resolve(root, strip.ccds[0].camera)),
        "true": LineScanCamera.from_json(man.resolve(root, man.truth.cameras[strip.id])),
        "ref": ReferenceOrtho(man.resolve(root, man.reference.ortho)),
        "dem": GridTerrain.from_geotiff(man.resolve(root, man.reference.dem)),
        "truth_dem": GridTerrain.from_geotiff(man.resolve(root, man.truth.dem)),
        "images": {c.name: man.resolve(root, c.image) for c in strip.ccds},
    }


def test_a_km_of_initial_error_is_found_by_the_adapted_coarse_stage(km_scene: Path) -> None:
    from planetref.frontend.config import FrontendConfig
    from planetref.frontend.matchers import build_matchers
    from planetref.frontend.tile import match_tile
    from planetref.frontend.tiles import plan_tiles
    from planetref.pipeline.systematic import declared_uncertainty
    from planetref.raster.image import CcdImage

    errors = json.loads((km_scene / "truth" / "errors.json").read_text())
    ground = errors["strip1"]["initial_errors"]["ground_m"]["horizontal"]
    assert 1000.0 < ground["rms"] < 1100.0  # the level's magnitude, measured

    s = _load(km_scene)
    assert s["man"].strips[0].initial_uncertainty_m == 1300.0
    cfg, source = declared_uncertainty(FrontendConfig(fine_upsample=1, coarse_max_px=128), s["man"])
    gsd = float(np.mean(s["ref"].ground_sampling_m()))
    assert (cfg.uncertainty_m, source, cfg.coarse_level(gsd)) == (1300.0, "scene", 7)
    fine, coarse = build_matchers("ncc", {}, cfg, gsd)

    def match(tile, image, ratio):
        return match_tile(
            tile,
            image=image,
            camera=s["init"],
            ref=s["ref"],
            terrain=s["dem"],
            matcher=fine,
            config=cfg,
            ratio=ratio,
            coarse_matcher=coarse,
        )

    results = []
    for ccd, path in s["images"].items():
        with CcdImage(path) as image:
            plan = plan_tiles(s["init"], ccd, s["ref"], s["dem"], cfg)
            for tile in plan.tiles:
                r = match(tile, image, plan.ratio)
                results.append(r)
                assert r.status == "ok", (tile.tile_id, r.message)
                # Found by the coarse stage's consensus (not the fine stage's fallback).
                assert r.n_coarse_inliers >= cfg.coarse_min_matches
                truth = _offset_truth(r, s)
                assert np.hypot(*truth) * gsd > 1000.0  # the tile really was ~1 km off
                # Coarse offset within a coarse pixel, the fine one within 1 ref px.
                assert np.max(np.abs(np.asarray(r.coarse_offset_px) - truth)) < 7.0
                assert np.max(np.abs(np.asarray(r.offset_px) - truth)) < 1.0
    assert len(results) == 6  # every tile of the three CCDs
    # Deterministic: a tile matched again gives the same MCPs and offsets.
    first = results[-1]
    with CcdImage(s["images"][first.tile.ccd]) as image:
        again = match(first.tile, image, plan.ratio)
    np.testing.assert_array_equal(again.line, first.line)
    np.testing.assert_array_equal(again.ref_col, first.ref_col)
    assert (again.coarse_offset_px, again.offset_px) == (first.coarse_offset_px, first.offset_px)


def _tiles(s: dict, cfg) -> list:
    from planetref.frontend.tiles import plan_tiles

    return [
        (tile, ccd, plan.ratio)
        for ccd in s["images"]
        for plan in [plan_tiles(s["init"], ccd, s["ref"], s["dem"], cfg)]
        for tile in plan.tiles
    ]


def test_a_learned_matcher_finds_every_tile_at_a_km_through_the_bounded_fallback(
    km_scene: Path, make_matcher
) -> None:
    """XFeat-LighterGlue at 1 km: its own coarse stage (20 m pixels) finds no consensus on
    tiny (0-6 matches per tile, measured), so the front end's NCC search of the same coarse
    windows places every tile, and the fine stage searches only around that offset."""
    from planetref.frontend.config import FrontendConfig
    from planetref.frontend.tile import match_tile
    from planetref.pipeline.systematic import declared_uncertainty
    from planetref.raster.image import CcdImage

    s = _load(km_scene)
    cfg, _ = declared_uncertainty(FrontendConfig(fine_upsample=1), s["man"])
    assert cfg.coarse_fallback == "ncc"  # the default
    gsd = float(np.mean(s["ref"].ground_sampling_m()))
    assert cfg.coarse_level(gsd) == 4
    xfeat = make_matcher("xfeat-lighterglue")
    unc_px = cfg.uncertainty_m / gsd  # 260 reference px each way
    sources = []
    for tile, ccd, ratio in _tiles(s, cfg):
        with CcdImage(s["images"][ccd]) as image:
            r = match_tile(
                tile,
                image=image,
                camera=s["init"],
                ref=s["ref"],
                terrain=s["dem"],
                matcher=xfeat,
                config=cfg,
                ratio=ratio,
            )
        assert r.status == "ok", (tile.tile_id, r.message)
        sources.append(r.coarse_source)
        truth = _offset_truth(r, s)
        assert np.hypot(*truth) * gsd > 1000.0
        assert np.max(np.abs(np.asarray(r.coarse_offset_px) - truth)) < 4.0  # a coarse px
        assert np.max(np.abs(np.asarray(r.offset_px) - truth)) < 1.0  # measured <= 0.45
        # The fine window is the footprint plus fine_pad_ref_px, not the uncertainty's
        # (which would be more than 2 * 260 px wider): the cost does not grow with it.
        _, _, width, height, _ = r.search_window
        assert max(width, height) < 2 * unc_px
        assert "coarse_fallback" in r.timings or r.coarse_source == "matcher"
    assert len(sources) == 6
    assert set(sources) <= {"matcher", "ncc"}
    assert sources.count("ncc") >= 4  # XFeat's 20 m coarse stage rarely agrees (0 of 6)


class _Misplaced:
    """A coarse matcher that agrees on the wrong place: NCC's coarse search with every
    reference keypoint reported ``shift`` coarse pixels east (a consistent wrong consensus,
    as XFeat-LighterGlue's 7 of 30 matches 2 km off on one hiric-strip tile at 1 km)."""

    name = "misplaced-ncc"

    def __init__(self, inner, shift: float) -> None:
        self.inner, self.shift = inner, float(shift)

    def match(self, image0, image1, mask0=None, mask1=None):
        from planetref.matching.base import Matches

        m = self.inner.match(image0, image1, mask0, mask1)
        moved = np.asarray(m.keypoints1) + np.array([self.shift, 0.0])
        return Matches(m.keypoints0, moved, m.confidence)


def test_a_wrong_coarse_consensus_is_caught_by_the_fine_stage_and_replaced(
    km_scene: Path, make_matcher
) -> None:
    """XFeat-LighterGlue's fine stage finds too few inliers around a wrong coarse consensus
    (25 coarse px, 500 m off); the front end's NCC search then places the tile, and its
    offset is the truth's to within a reference pixel. With ``coarse_fallback = "fine"``
    (the previous behaviour) nothing replaces the wrong offset and the tile is lost.

    (NCC as the fine matcher would not do here: around a wrong offset its dense,
    overlapping templates can agree on one false peak, 8-87 "inliers" in a corner of the
    tile, and the tile ends ``ok`` at the wrong place; measured on this scene.)"""
    from planetref.frontend.coarse import coarse_fallback_matcher
    from planetref.frontend.config import FrontendConfig
    from planetref.frontend.tile import match_tile
    from planetref.pipeline.systematic import declared_uncertainty
    from planetref.raster.image import CcdImage

    s = _load(km_scene)
    cfg, _ = declared_uncertainty(FrontendConfig(fine_upsample=1), s["man"])
    gsd = float(np.mean(s["ref"].ground_sampling_m()))
    f = cfg.coarse_level(gsd)
    fine = make_matcher("xfeat-lighterglue")
    ncc_coarse = coarse_fallback_matcher(cfg, gsd)
    wrong = _Misplaced(ncc_coarse, 25.0)
    for tile, ccd, ratio in _tiles(s, cfg)[:1]:
        with CcdImage(s["images"][ccd]) as image:
            kw = dict(camera=s["init"], ref=s["ref"], terrain=s["dem"], ratio=ratio, image=image)
            r = match_tile(tile, matcher=fine, config=cfg, coarse_matcher=wrong, **kw)
            old = match_tile(
                tile,
                matcher=fine,
                config=cfg.model_copy(update={"coarse_fallback": "fine"}),
                coarse_matcher=wrong,
                **kw,
            )
        # the wrong consensus was found, and rejected by the fine stage
        assert r.n_coarse_inliers >= cfg.coarse_min_matches
        assert r.status == "ok", r.message
        assert r.coarse_source == "ncc"
        truth = _offset_truth(r, s)
        assert np.max(np.abs(np.asarray(r.offset_px) - truth)) < 1.0
        assert np.max(np.abs(np.asarray(r.coarse_offset_px) - truth)) < f  # a coarse px
        # previously: the fine stage sat 25 coarse px (125 ref px) off, and failed
        assert old.coarse_source == "matcher"
        assert old.status == "too_few_inliers"
        off = np.asarray(old.coarse_offset_px) - truth
        assert abs(off[0] - 25.0 * f) < f and abs(off[1]) < f
