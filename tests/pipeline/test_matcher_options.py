"""NCC's fine-stage options keep their ground size on any fine grid."""

from __future__ import annotations

import pytest

from planetref.pipeline.config import config_from_mapping
from planetref.pipeline.matchers import matcher_options


@pytest.mark.parametrize(
    ("up", "user", "template", "spacing"),
    [(1, {}, 10, 2), (2, {}, 20, 4), (3, {}, 30, 6), (2, {"template_radius": 7}, 14, 4)],
)
def test_ncc_fine_template_and_spacing_scale_with_the_fine_grid(up, user, template, spacing):
    cfg = config_from_mapping({"frontend": {"fine_upsample": up}, "matchers": {"ncc": user}})
    fine, coarse = matcher_options("ncc", cfg, ref_gsd_m=5.0)
    assert fine["template_radius"] == template
    assert fine["dense_spacing_px"] == spacing
    # Search radius in fine pixels: (pad 16 + coarse radius 6 + 4) reference px.
    assert fine["search_radius"] == 26 * up
    # The coarse stage works on the reference grid decimated: the user's template as given.
    assert coarse is not None
    assert coarse.get("template_radius", 10) == user.get("template_radius", 10)


def test_other_matchers_get_their_own_options_only():
    cfg = config_from_mapping({"frontend": {"fine_upsample": 2}})
    fine, coarse = matcher_options("sift", cfg, ref_gsd_m=5.0)
    assert fine == {} and coarse is None
