"""Batched matching (``match_many(..., batch_size)``) equals one pair at a time.

The learned sparse matchers run the detector/descriptor of same-shaped images in one
forward pass (the GPU path); with the official weights, on the CPU, the matches must be
those of an unbatched call, to float tolerance (as sets: near-equal detector scores may
come in another order). Pairs of another shape and a flat pair in
the same call check the grouping and the order of the results.
"""

from __future__ import annotations

import numpy as np
import pytest

from planetref.errors import InputError
from planetref.matching import get_matcher

SMALL = {
    "disk-lightglue": {"max_keypoints": 512},
    "aliked-lightglue": {"max_keypoints": 512},
    "xfeat-lighterglue": {"max_keypoints": 512},
}


def _sorted(m) -> np.ndarray:
    a = m.to_array()
    return a[np.lexsort(np.round(a[:, 3::-1], 3).T)]


def _pairs(shifted_pair) -> list[tuple[np.ndarray, ...]]:
    pairs = []
    for seed, shift in ((1, (2.2, -1.4)), (2, (-3.1, 0.7)), (3, (0.4, 2.9))):
        a, b = shifted_pair(96, shift, seed=seed)
        pairs.append((a, b))
    a, b = shifted_pair(128, (1.5, 1.5), seed=4)
    pairs.append((a[:80], b[:80]))  # another shape: its own group
    # another shape whose sides round up to 96 like the first pairs': DISK (16) and XFeat
    # (32) pad it into their batch, each image padded on its own
    pairs.append((a[5:95, 3:97], b[5:95, 3:97]))
    flat = np.full((96, 96), 7.0, np.float32)
    pairs.append((flat, pairs[0][1]))  # flat: no matches, order kept
    mask = np.ones((96, 96), bool)
    mask[:, :20] = False
    pairs.append((pairs[1][0], pairs[1][1], mask, None))  # masked
    return pairs


@pytest.mark.parametrize(
    "name",
    [
        "xfeat-lighterglue",  # ~2 CPU-s: the default run's check
        pytest.param("disk-lightglue", marks=pytest.mark.slow),
        pytest.param("aliked-lightglue", marks=pytest.mark.slow),
    ],
)
def test_batched_equals_unbatched_on_cpu(name, shared_weights, shifted_pair, monkeypatch):
    matcher = get_matcher(name, weights_dir=shared_weights, **SMALL[name])
    pairs = _pairs(shifted_pair)
    one = [matcher.match(*p) for p in pairs]
    shapes: list[set] = []
    extract = matcher._extract_batch

    def spy(images):
        shapes.append({im.shape for im in images})
        return extract(images)

    monkeypatch.setattr(matcher, "_extract_batch", spy)
    many = matcher.match_many(pairs, batch_size=4)
    # images of several shapes shared a forward pass exactly where the detector pads
    assert any(len(s) > 1 for s in shapes) == (matcher.pad_multiple > 0)
    assert len(many) == len(pairs)
    assert len(one[5]) == len(many[5]) == 0
    assert sum(len(m) for m in one) > 100
    for a, b in zip(one, many, strict=True):
        assert len(a) == len(b)
        # The same matches as sets: keypoints whose scores differ by float rounding may
        # swap places in the detector's ranking, and LightGlue keeps image 0's order.
        sa, sb = _sorted(a), _sorted(b)
        np.testing.assert_allclose(sb[:, :4], sa[:, :4], atol=1e-3)
        # descriptors equal to ~1e-6 move LightGlue's scores by up to ~3e-4
        np.testing.assert_allclose(sb[:, 4], sa[:, 4], atol=2e-3)
    assert not np.any(many[6].keypoints0[:, 0] < 20)  # the mask holds
    assert matcher.timings["forward"] > 0


def test_batch_size_is_checked(shared_weights, shifted_pair):
    matcher = get_matcher("sift")
    a, b = shifted_pair(96, (1.0, 1.0), seed=1)
    # classical matchers accept any batch size and match one pair at a time
    assert len(matcher.match_many([(a, b)], batch_size=8)[0]) > 0
    with pytest.raises(InputError, match="batch_size"):
        matcher.match_many([(a, b)], batch_size=0)


def test_device_auto_and_a_missing_gpu_are_one_line(tmp_path):
    """``auto`` is the GPU when torch sees one, else the CPU; a missing GPU is one line.

    georef checks the device before it reads anything, so a missing scene does not hide
    the device error.
    """
    import torch
    from click.testing import CliRunner

    from planetref.cli import main
    from planetref.matching._torch import resolve_device

    expected = "cuda" if torch.cuda.is_available() else "cpu"
    assert resolve_device("auto").type == expected
    assert get_matcher("sift", device="auto").name == "sift"  # classical: the CPU
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA: the missing-GPU message cannot be produced")
    with pytest.raises(InputError, match="CUDA is not available") as err:
        resolve_device("cuda")
    assert "\n" not in str(err.value) and "use cpu or auto" in str(err.value)
    r = CliRunner().invoke(
        main,
        [
            *("-q", "georef", str(tmp_path / "nowhere"), "--matcher", "sift"),
            *("--out", str(tmp_path / "run"), "--device", "cuda"),
        ],
    )
    assert r.exit_code != 0
    lines = [x for x in r.output.splitlines() if x.strip()]
    assert len(lines) == 1 and "CUDA is not available" in lines[0], r.output
    assert "Traceback" not in r.output and not (tmp_path / "run").exists()
