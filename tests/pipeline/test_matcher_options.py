"""NCC's fine-stage options keep their ground size on any fine grid."""

from __future__ import annotations

from pathlib import Path

import pytest

from planetref.frontend.matchers import matcher_options
from planetref.pipeline.config import config_from_mapping


@pytest.mark.parametrize(
    ("up", "user", "template", "spacing"),
    [(1, {}, 10, 2), (2, {}, 20, 4), (3, {}, 30, 6), (2, {"template_radius": 7}, 14, 4)],
)
def test_ncc_fine_template_and_spacing_scale_with_the_fine_grid(up, user, template, spacing):
    cfg = config_from_mapping({"frontend": {"fine_upsample": up}, "matchers": {"ncc": user}})
    fine, coarse = matcher_options("ncc", cfg.matchers.get("ncc", {}), cfg.frontend, ref_gsd_m=5.0)
    assert fine["template_radius"] == template
    assert fine["dense_spacing_px"] == spacing
    # Search radius in fine pixels: (pad 16 + coarse radius 6 + 4) reference px.
    assert fine["search_radius"] == 26 * up
    # The coarse stage works on the reference grid decimated: the user's template as given.
    assert coarse is not None
    assert coarse.get("template_radius", 10) == user.get("template_radius", 10)


def test_other_matchers_get_their_own_options_only():
    cfg = config_from_mapping({"frontend": {"fine_upsample": 2}})
    fine, coarse = matcher_options("sift", {}, cfg.frontend, ref_gsd_m=5.0)
    assert fine == {} and coarse is None


def test_the_front_end_reads_declarations_not_names():
    """A matcher is set up from its class's declarations: NCC's are what make it special."""
    from planetref.matching.ncc import NccMatcher
    from planetref.matching.sift import SiftMatcher

    assert NccMatcher.search_option == "search_radius" and NccMatcher.runs_dense()
    assert NccMatcher.pixel_options == ("template_radius",)
    assert SiftMatcher.search_option is None and not SiftMatcher.runs_dense()
    src = (Path(matcher_options.__code__.co_filename)).read_text()
    assert '"ncc"' not in src and '"loftr"' not in src
