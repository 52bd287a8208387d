"""The output contract, for every matcher.

Matchers whose official weights are available here run with them; LoFTR and
DoG+HardNet+LightGlue run with random weights in the official checkpoint format (see
``random_weights_dir``), with their thresholds at 0 so that random networks still match.
"""

from __future__ import annotations

import numpy as np
import pytest

from planetref.matching import MATCHERS, Matcher, Matches, get_matcher

RANDOM = {
    "loftr": {"confidence_threshold": 0.0},
    "doghardnet-lightglue": {"filter_threshold": 0.0, "max_keypoints": 512},
}
SMALL = {
    "disk-lightglue": {"max_keypoints": 1024},
    "aliked-lightglue": {"max_keypoints": 1024},
    "xfeat-lighterglue": {"max_keypoints": 1024},
    "xfeat-star": {"top_k": 2000},
}

_CACHE: dict[str, Matcher] = {}


@pytest.fixture
def build(request, shared_weights, random_weights_dir):
    def make(name: str) -> Matcher:
        if name not in _CACHE:
            if name in RANDOM:
                _CACHE[name] = get_matcher(
                    name, weights_dir=random_weights_dir, verify_weights=False, **RANDOM[name]
                )
            elif MATCHERS[name].weights:
                _CACHE[name] = get_matcher(name, weights_dir=shared_weights, **SMALL.get(name, {}))
            else:
                _CACHE[name] = get_matcher(name)
        return _CACHE[name]

    return make


def _check_types(m: Matches, shape0, shape1) -> None:
    assert isinstance(m, Matches)
    for k, shape in ((m.keypoints0, shape0), (m.keypoints1, shape1)):
        assert k.dtype == np.float64 and k.ndim == 2 and k.shape[1] == 2
        assert np.all(np.isfinite(k))
        assert np.all(k >= 0) and np.all(k[:, 0] < shape[1]) and np.all(k[:, 1] < shape[0])
    assert m.confidence.dtype == np.float64 and m.confidence.shape == (len(m),)
    assert len(m.keypoints0) == len(m.keypoints1) == len(m)


@pytest.mark.parametrize("name", list(MATCHERS))
def test_contract_textured_masked_blank(name, build, shifted_pair):
    matcher = build(name)
    assert isinstance(matcher, Matcher)
    assert matcher.name == name

    a, b = shifted_pair(160, (4.0, -3.0), seed=7)
    mask0 = np.ones(a.shape, bool)
    mask0[40:90, 60:120] = False
    mask1 = np.ones(b.shape, bool)
    mask1[100:150, 0:70] = False
    a = a.copy()
    b = b.copy()
    a[~mask0] = -3.4028226e38  # ISIS NULL must not wreck the normalisation
    b[~mask1] = np.nan

    m = matcher.match(a, b, mask0, mask1)
    _check_types(m, a.shape, b.shape)
    assert len(m) > 0, f"{name} found no match on a textured pair"
    c0 = np.floor(m.keypoints0).astype(int)
    c1 = np.floor(m.keypoints1).astype(int)
    assert mask0[c0[:, 1], c0[:, 0]].all(), "keypoint on a masked pixel of image 0"
    assert mask1[c1[:, 1], c1[:, 0]].all(), "keypoint on a masked pixel of image 1"
    assert set(matcher.timings) >= {"normalise", "forward", "total"}

    blank = np.full((160, 160), 0.3, np.float32)
    for pair in ((blank, blank), (a, blank), (blank, b)):
        e = matcher.match(*pair)
        _check_types(e, (160, 160), (160, 160))
        assert len(e) == 0

    none_valid = matcher.match(a, b, np.zeros(a.shape, bool), None)
    assert len(none_valid) == 0
    tiny = matcher.match(a[:8, :8], b[:8, :8])
    assert len(tiny) == 0


def test_match_many_and_bad_inputs(build, shifted_pair):
    matcher = build("xfeat-star")
    a, b = shifted_pair(128, (2.0, 1.0), seed=3)
    out = matcher.match_many([(a, b), (a, b, None, None)])
    assert len(out) == 2 and len(out[0]) == len(out[1]) > 0
    from planetref.errors import InputError

    with pytest.raises(InputError):
        matcher.match(a[None], b)
    with pytest.raises(InputError):
        matcher.match(a, b, np.ones((3, 3), bool))
    with pytest.raises(InputError):
        matcher.match_many([(a,)])
