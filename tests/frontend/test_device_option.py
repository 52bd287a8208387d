"""The torch device is a run option: passed to the learned matchers when they are built."""

from __future__ import annotations

import pytest

from planetref.frontend.config import FrontendConfig
from planetref.frontend.matchers import matcher_recipes
from planetref.frontend.tasks import MatcherRecipe


@pytest.fixture
def built(monkeypatch):
    """Record the keywords ``get_matcher`` is called with instead of building."""
    import planetref.matching.registry as registry

    calls: list[dict] = []

    def fake(name, **kwargs):
        calls.append({"name": name, **kwargs})
        return object()

    monkeypatch.setattr(registry, "get_matcher", fake)
    return calls


@pytest.mark.parametrize(
    ("name", "expected"),
    [("disk-lightglue", "cuda:1"), ("xfeat-star", "cuda:1"), ("sift", "cpu"), ("ncc", "cpu")],
)
def test_the_run_device_reaches_learned_matchers_only(built, name, expected):
    pair = matcher_recipes(name, {}, FrontendConfig(), 5.0, device="cuda:1")
    pair.built()
    assert built, "no matcher built"
    assert {c["device"] for c in built} == {expected}
    # the recipes travel to the workers as JSON: the device goes with them
    assert MatcherRecipe.from_dict(pair.fine.to_dict()) == pair.fine


def test_a_matcher_option_device_wins(built):
    MatcherRecipe("disk-lightglue", {"device": "cpu"}, None, "cuda:0").build()
    assert built[-1]["device"] == "cpu"
