"""Tiles matched in batches (``[frontend] batch_tiles``) give the MCPs of tile-by-tile matching.

With ``batch_tiles > 1`` the stages of several tiles advance together and each round's
matcher calls go through ``Matcher.match_many`` (the learned sparse detectors then run on
batches of images: the GPU path, exercised here on the CPU with the official weights). The
MCPs must be those of tile-by-tile matching as sets, to the matchers' batched tolerance
(keypoints 1e-3 px, confidences 2e-3), and the driver must keep a failure to its tile.
"""

from __future__ import annotations

import numpy as np
import pytest

from planetref.frontend.config import FrontendConfig
from planetref.frontend.journal import journal_digest
from planetref.frontend.strip import match_strip
from planetref.raster.ortho import ReferenceOrtho

# The tile-matching tests' settings (fine stage on the reference grid, 96-px tiles).
CFG = FrontendConfig(tile_size_ref_px=96, uncertainty_m=150.0, coarse_factor=2, fine_upsample=1)


@pytest.fixture(scope="module")
def ref(scene):
    with ReferenceOrtho(scene.ortho_path) as r:
        yield r


def _strip(scene, ref, matcher, batch_tiles, ccds=None, **kw):
    return match_strip(
        scene.init_cam,
        scene.image_paths,
        ref,
        scene.dem,
        matcher,
        CFG.model_copy(update={"batch_tiles": batch_tiles}),
        ccds=ccds,
        progress=False,
        **kw,
    )


def _mcps(strip) -> np.ndarray:
    """``line, sample, ref_col, ref_row, confidence`` of every MCP, sorted as a set."""
    rows = [
        np.column_stack([r.line, r.sample, r.ref_col, r.ref_row, r.confidence])
        for r in strip.tiles
        if r.status == "ok"
    ]
    a = np.concatenate(rows)
    return a[np.lexsort(np.round(a[:, 3::-1], 3).T)]


def _same_tiles(one, many) -> None:
    assert [r.tile_id for r in one.tiles] == [r.tile_id for r in many.tiles]
    assert [r.status for r in one.tiles] == [r.status for r in many.tiles]
    assert [r.n_inliers for r in one.tiles] == [r.n_inliers for r in many.tiles]
    assert [r.funnel for r in one.tiles] == [r.funnel for r in many.tiles]


@pytest.mark.parametrize(
    "name, ccds",
    [
        ("xfeat-lighterglue", ["ccd1"]),  # ~6 CPU-s: the default run's check
        pytest.param("disk-lightglue", None, marks=pytest.mark.slow),
        pytest.param("aliked-lightglue", None, marks=pytest.mark.slow),
        pytest.param("xfeat-lighterglue", None, marks=pytest.mark.slow),
    ],
)
def test_batched_tiles_give_the_mcps_of_tile_by_tile(
    scene, ref, make_matcher, monkeypatch, name, ccds
):
    matcher = make_matcher(name, max_keypoints=512)
    one = _strip(scene, ref, matcher, 1, ccds, raise_errors=True)
    calls: list[int] = []
    extract = matcher._extract_batch

    def spy(images):
        calls.append(len(images))
        return extract(images)

    monkeypatch.setattr(matcher, "_extract_batch", spy)
    many = _strip(scene, ref, matcher, 4, ccds, raise_errors=True)
    n_tiles = len(many.tiles)
    assert n_tiles >= 6 and sum(r.status == "ok" for r in many.tiles) >= n_tiles // 2
    # the detector ran on batches: both images of each of up to 4 tiles per forward pass
    # (DISK and XFeat: all of a round's images round up to one padded shape here; ALIKED
    # batches only images of one exact shape, and tiles' windows differ by a pixel)
    assert max(calls) == 8 and len(calls) <= sum(calls) / (4 if matcher.pad_multiple else 2)
    _same_tiles(one, many)
    a, b = _mcps(one), _mcps(many)
    assert len(a) == len(b) > 100
    np.testing.assert_allclose(b[:, :4], a[:, :4], atol=1e-3)
    np.testing.assert_allclose(b[:, 4], a[:, 4], atol=2e-3)


class _Failing:
    """SIFT whose batched call fails (e.g. a GPU out of memory), or every call."""

    name = "sift"

    def __init__(self, inner, *, every_call: bool = False) -> None:
        self.inner, self.every_call, self.timings = inner, every_call, {}

    def match(self, *pair):
        if self.every_call:
            raise RuntimeError("matcher failed")
        out = self.inner.match(*pair)
        self.timings = self.inner.timings
        return out

    def match_many(self, pairs, *, batch_size=1):
        raise RuntimeError("out of memory")


def test_batched_driver_sift_exact_and_failures_stay_per_tile(scene, ref, make_matcher):
    sift = make_matcher("sift")
    one = _strip(scene, ref, sift, 1, ["ccd1"], raise_errors=True)
    # SIFT matches pair by pair inside match_many: the same numbers bit for bit
    many = _strip(scene, ref, sift, 3, ["ccd1"], raise_errors=True)
    _same_tiles(one, many)
    assert np.array_equal(_mcps(one), _mcps(many))
    # a failed batched call is made again pair by pair: nothing changes
    retried = _strip(scene, ref, _Failing(sift), 3, ["ccd1"], raise_errors=True)
    _same_tiles(one, retried)
    assert np.array_equal(_mcps(one), _mcps(retried))
    # a tile whose own call fails gets status "error"; raise_errors re-raises it
    failed = _strip(scene, ref, _Failing(sift, every_call=True), 3, ["ccd1"])
    assert {r.status for r in failed.tiles} == {"error"}
    assert "matcher failed" in failed.tiles[0].message
    with pytest.raises(RuntimeError, match="matcher failed"):
        _strip(scene, ref, _Failing(sift, every_call=True), 3, ["ccd1"], raise_errors=True)


def test_batch_tiles_is_not_part_of_a_runs_identity():
    from planetref.pipeline.config import config_from_mapping

    assert FrontendConfig().batch_tiles == 1
    plain, batched = FrontendConfig(), FrontendConfig(batch_tiles=8)
    assert journal_digest("sift", plain.identity()) == journal_digest("sift", batched.identity())
    assert "batch_tiles" not in plain.identity()
    run = config_from_mapping({"frontend": {"batch_tiles": 8}})
    assert "batch_tiles" not in config_from_mapping({}).to_json()["frontend"]
    assert run.to_json()["frontend"]["batch_tiles"] == 8  # recorded when set
    assert run.identity_json() == config_from_mapping({}).identity_json()
    with pytest.raises(Exception, match="batch_tiles"):
        FrontendConfig.from_mapping({"batch_tiles": 0})
