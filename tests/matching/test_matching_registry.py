"""Registry, availability, geometric verification, import hygiene."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from planetref.errors import InputError, WeightsError
from planetref.matching import MATCHERS, Matches, available_matchers, get_matcher
from planetref.matching.ransac import MIN_POINTS, verify_matches

NAMES = [
    "sift",
    "doghardnet-lightglue",
    "disk-lightglue",
    "loftr",
    "aliked-lightglue",
    "xfeat-lighterglue",
    "xfeat-star",
    "ncc",
]


def test_registry_contents():
    assert list(MATCHERS) == NAMES
    for name, spec in MATCHERS.items():
        assert spec.name == name
        assert spec.description
    assert MATCHERS["ncc"].paradigm == "area-based"
    assert MATCHERS["loftr"].paradigm == "detector-free dense"
    assert MATCHERS["xfeat-star"].paradigm == "semi-dense"
    assert MATCHERS["sift"].weights == () and MATCHERS["ncc"].weights == ()


def test_get_matcher_errors(tmp_path):
    with pytest.raises(InputError) as err:
        get_matcher("superglue")
    for name in NAMES:
        assert name in str(err.value)
    with pytest.raises(InputError, match="ratio"):
        get_matcher("sift", bogus=1)
    with pytest.raises(InputError, match="CPU"):
        get_matcher("ncc", device="cuda")
    with pytest.raises(WeightsError) as err:
        get_matcher("loftr", weights_dir=tmp_path)
    assert "loftr_outdoor.ckpt" in str(err.value) and str(tmp_path) in str(err.value)
    with pytest.raises(InputError, match="device"):
        get_matcher("xfeat-star", weights_dir=tmp_path / "none", device="warp-drive")


def test_available_matchers_with_shared_weights(shared_weights):
    avail = {a.name: a for a in available_matchers(shared_weights)}
    assert list(avail) == NAMES
    for name in (
        "sift",
        "ncc",
        "disk-lightglue",
        "aliked-lightglue",
        "xfeat-lighterglue",
        "xfeat-star",
    ):
        assert avail[name].present and avail[name].missing == ()
    assert not avail["loftr"].present and avail["loftr"].missing == ("loftr_outdoor.ckpt",)
    assert set(avail["doghardnet-lightglue"].missing) == {
        "checkpoint_liberty_with_aug.pth",
        "doghardnet_v0-1_arxiv-pth",
    }
    verified = {a.name: a.present for a in available_matchers(shared_weights, verify=True)}
    assert verified["disk-lightglue"] and verified["xfeat-star"]


def test_available_matchers_empty_dir(tmp_path, no_weight_packages):
    for a in available_matchers(tmp_path):
        assert a.present == (MATCHERS[a.name].weights == ())


def test_import_has_no_side_effects():
    code = (
        "import sys; import planetref.matching, planetref.matching.registry, planetref.cli.match;"
        "bad = [m for m in ('torch', 'kornia', 'cv2') if m in sys.modules]; print(bad)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_verify_matches_models_and_degenerate_inputs():
    rng = np.random.default_rng(0)
    k0 = rng.uniform(0, 500, (200, 2))
    good = Matches(k0, k0 + np.array([4.0, -2.0]), np.ones(200))
    bad = Matches(rng.uniform(0, 500, (60, 2)), rng.uniform(0, 500, (60, 2)), np.ones(60))
    both = Matches.concatenate([good, bad])
    for model in ("homography", "affine"):
        v = verify_matches(both, model, threshold=1.0)
        assert v.inliers[:200].all() and v.inliers[200:].mean() < 0.05
        assert v.matrix is not None
    np.testing.assert_allclose(
        verify_matches(good, "affine").matrix, [[1, 0, 4], [0, 1, -2]], atol=1e-3
    )
    for model, n in MIN_POINTS.items():
        few = good.select(np.arange(n - 1))
        v = verify_matches(few, model)
        assert v.matrix is None and v.n_inliers == 0 and v.inliers.shape == (n - 1,)
    same = Matches(np.ones((10, 2)), np.ones((10, 2)), np.zeros(10))
    assert verify_matches(same).n_inliers == 0
    assert verify_matches(Matches.empty()).inliers.shape == (0,)
    with pytest.raises(InputError):
        verify_matches(good, "projective")  # type: ignore[arg-type]
    with pytest.raises(InputError):
        verify_matches(good, threshold=0)
