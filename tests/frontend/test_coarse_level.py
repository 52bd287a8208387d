"""The coarse stage's level adapts to the a-priori uncertainty with a bounded window."""

from __future__ import annotations

import math

import pytest

from planetref.frontend.config import FrontendConfig
from planetref.frontend.matchers import matcher_options


def _side(cfg: FrontendConfig, gsd: float) -> int:
    """A tile's coarse window side in reference pixels (as the tile stage pads it)."""
    return cfg.tile_size_ref_px + 2 * (math.ceil(cfg.uncertainty_m / gsd) + cfg.fine_pad_ref_px)


def test_default_and_small_uncertainties_keep_the_coarse_factor() -> None:
    # 300 m on a 5 m reference: 256 + 2 * (60 + 16) = 408 ref px, 102 coarse px at 4.
    assert FrontendConfig().coarse_level(5.0) == 4
    assert FrontendConfig(uncertainty_m=1000.0).coarse_level(5.0) == 4  # 688 / 4 = 172 px
    # 2 km: 256 + 2 * (400 + 16) = 1088 ref px > 4 * 256: the smallest factor that fits is 5.
    assert FrontendConfig(uncertainty_m=2000.0).coarse_level(5.0) == 5
    # A 1 m reference at 1 km: 256 + 2 * 1016 = 2288 ref px -> ceil(2288 / 256) = 9.
    assert FrontendConfig(uncertainty_m=1000.0).coarse_level(1.0) == 9
    assert FrontendConfig(coarse_factor=8).coarse_level(5.0) == 8  # never finer than set


@pytest.mark.parametrize("gsd", [0.5, 1.0, 5.0, 6.0])
@pytest.mark.parametrize("max_px", [64, 128, 256])
def test_the_level_is_the_smallest_that_bounds_the_window(gsd: float, max_px: int) -> None:
    previous = 0
    for u in [10.0, 100.0, 300.0, 700.0, 1000.0, 1500.0, 2000.0, 3000.0, 5000.0]:
        cfg = FrontendConfig(uncertainty_m=u, coarse_max_px=max_px)
        f = cfg.coarse_level(gsd)
        side = _side(cfg, gsd)
        assert f >= previous  # grows with the uncertainty
        previous = f
        assert side / f <= max_px  # the window stays bounded
        if f > cfg.coarse_factor:
            assert side / (f - 1) > max_px  # and no finer level would fit


def test_area_based_coarse_radius_covers_the_uncertainty_at_the_adapted_level() -> None:
    gsd = 5.0
    for u in (100.0, 300.0, 1000.0, 2000.0, 5000.0):
        fe = FrontendConfig(uncertainty_m=u)
        f = fe.coarse_level(gsd)
        _, coarse = matcher_options("ncc", {}, fe, gsd)
        assert coarse is not None
        radius = coarse["search_radius"]
        assert radius * f * gsd >= u  # reaches the whole uncertainty
        assert radius <= fe.coarse_max_px // 2 + 4  # and no farther than the window allows
    # 5 km: 256 + 2 * (1000 + 16) = 2288 ref px -> level 9, a radius of 112 + 4 coarse px
    # (at the fixed factor 4 it would have been 254 each way, in a 572 px window).
    fe = FrontendConfig(uncertainty_m=5000.0)
    assert fe.coarse_level(gsd) == 9
    assert matcher_options("ncc", {}, fe, gsd)[1] == {"spacing": 8, "search_radius": 116}


def test_the_coarse_fallback_is_ncc_coarse_search_and_bounded_by_the_window() -> None:
    from planetref.frontend.coarse import coarse_fallback_matcher
    from planetref.matching.ncc import NccMatcher

    gsd = 5.0
    for u in (150.0, 1300.0, 5000.0):
        fe = FrontendConfig(uncertainty_m=u)
        fb = coarse_fallback_matcher(fe, gsd)
        assert isinstance(fb, NccMatcher)
        # NCC's own coarse instance: the same radius, the same template grid
        assert {"spacing": fb.spacing, "search_radius": fb.search_radius} == matcher_options(
            "ncc", {}, fe, gsd
        )[1]
        assert fb.search_radius * fe.coarse_level(gsd) * gsd >= u
        assert fb.search_radius <= fe.coarse_max_px // 2 + 4
        assert coarse_fallback_matcher(fe, gsd) is fb  # one instance per settings
    # 150 m: level 4, 8 + 4 coarse px; 1300 m: still level 4 (808 ref px), 65 + 4
    assert coarse_fallback_matcher(FrontendConfig(uncertainty_m=150.0), gsd).search_radius == 12
    assert coarse_fallback_matcher(FrontendConfig(uncertainty_m=1300.0), gsd).search_radius == 69
    assert coarse_fallback_matcher(FrontendConfig(coarse_fallback="fine"), gsd) is None


def test_tile_results_keep_what_placed_their_fine_window() -> None:
    from planetref.frontend.result import TileResult
    from planetref.frontend.tiles import Tile

    tile = Tile("ccd1:r000c000", "ccd1", 0, 0, 64, 64)
    for source in ("matcher", "ncc", "fine", None):
        r = TileResult(tile=tile, matcher="xfeat-lighterglue", status="ok", coarse_source=source)
        assert TileResult.from_dict(r.to_dict()).coarse_source == source
    doc = TileResult(tile=tile, matcher="sift", status="ok").to_dict()
    del doc["coarse_source"]  # journals written before the field
    assert TileResult.from_dict(doc).coarse_source is None
