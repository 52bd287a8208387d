"""SDU and NCP on hand-made point sets with hand-computed values."""

from __future__ import annotations

import numpy as np
import pytest

from planetref.errors import InputError
from planetref.frontend.stats import ncp_per_ccd, ncp_per_tile, sdu_per_ccd, sdu_percent


def test_sdu_single_point():
    # One occupied cell in each grid: (1/1024 + 1/4096 + 1/16384) / 3 = 21 / 49152.
    assert sdu_percent([0.5], [0.5], 640, 640) == pytest.approx(100 * 21 / 49152, abs=1e-12)
    assert sdu_percent([0.5], [0.5], 640, 640) == pytest.approx(0.042724609375, abs=1e-12)


def test_sdu_one_point_per_coarsest_cell():
    # 640 px / 32 = 20 px cells; one point at the centre of each: the 32 grid is full,
    # and each point fills one cell of the finer grids: (1 + 1/4 + 1/16) / 3 = 43.75 %.
    c = np.arange(32) * 20.0 + 10.0
    ll, ss = np.meshgrid(c, c)
    assert sdu_percent(ll.ravel(), ss.ravel(), 640, 640) == pytest.approx(43.75, abs=1e-12)


def test_sdu_cell_boundaries():
    # Lines 0.5 and 15 share a 20-px cell of the 32 grid, not a 10-px (64) or 5-px (128) one:
    # (1/1024 + 2/4096 + 2/16384) / 3 = 26 / 49152.
    v = sdu_percent([0.5, 15.0], [0.5, 0.5], 640, 640)
    assert v == pytest.approx(100 * 26 / 49152, abs=1e-12)
    # A point exactly on a cell edge belongs to the cell that starts there.
    v = sdu_percent([0.5, 20.0], [0.5, 0.5], 640, 640)
    assert v == pytest.approx(100 * (2 / 1024 + 2 / 4096 + 2 / 16384) / 3, abs=1e-12)


def test_sdu_rectangular_image_outside_and_nan_ignored():
    # 1000 x 320 image: cells are 31.25 x 10 px (32 grid). Two corner points count twice;
    # a point on the far edge (outside), a negative one and a NaN are ignored.
    lines = [0.0, 999.99, 1000.0, -0.1, np.nan]
    samples = [0.0, 319.99, 10.0, 5.0, 5.0]
    v = sdu_percent(lines, samples, 1000, 320)
    assert v == pytest.approx(100 * (2 / 1024 + 2 / 4096 + 2 / 16384) / 3, abs=1e-12)


def test_sdu_full_and_empty():
    ll, ss = np.meshgrid(np.arange(128) + 0.5, np.arange(128) + 0.5)
    assert sdu_percent(ll.ravel(), ss.ravel(), 128, 128) == pytest.approx(100.0)
    assert sdu_percent([], [], 128, 128) == 0.0
    # Custom grids: a 2 x 2 grid with points in 3 cells -> 75 %.
    assert sdu_percent([1, 1, 9], [1, 9, 1], 10, 10, grids=(2,)) == pytest.approx(75.0)


def test_sdu_rejects_bad_input():
    with pytest.raises(InputError):
        sdu_percent([1.0, 2.0], [1.0], 10, 10)
    with pytest.raises(InputError):
        sdu_percent([1.0], [1.0], 0, 10)
    with pytest.raises(InputError):
        sdu_percent([1.0], [1.0], 10, 10, grids=())


def test_ncp_counts():
    table = {
        "ccd": np.array(["a", "a", "b"], dtype=object),
        "tile_id": np.array(["a:r0", "a:r1", "b:r0"], dtype=object),
        "line": np.array([0.5, 20.0, 0.5]),
        "sample": np.array([0.5, 0.5, 0.5]),
    }
    assert ncp_per_ccd(table, ["a", "b", "c"]) == {"a": 2, "b": 1, "c": 0}
    assert ncp_per_tile(table) == {"a:r0": 1, "a:r1": 1, "b:r0": 1}
    sdu = sdu_per_ccd(table, {"a": (640, 640), "b": (640, 640)})
    assert sdu["a"] == pytest.approx(100 * (2 / 1024 + 2 / 4096 + 2 / 16384) / 3)
    assert sdu["b"] == pytest.approx(100 * 21 / 49152)


def _tile(ccd, funnel=None, n_matches=0, n_inliers=0, n_points=0):
    from types import SimpleNamespace

    t = SimpleNamespace(
        tile=SimpleNamespace(ccd=ccd),
        n_matches=n_matches,
        n_inliers=n_inliers,
        line=np.zeros(n_points),
    )
    if funnel is not None:
        t.funnel = funnel
    return t


def test_funnel_ncp_before_thinning_and_rejections_by_stage():
    from planetref.frontend.stats import full_funnel, funnel_table, ncp_verified

    a = _tile(
        "c1",
        {
            "raw": 1000,
            "coarse_gate": 900,
            "ransac": 600,
            "consensus": 540,
            "backprojection": 530,
            "mcp": 200,
        },
    )
    b = _tile(
        "c1",
        {
            "raw": 500,
            "ransac": 400,
            "consensus": 400,
            "backprojection": 390,
            "refine": 380,
            "mcp": 380,
        },
    )
    c = _tile("c2", n_matches=300, n_inliers=250, n_points=250)  # no funnel: old result
    # NCP is the last verification stage, before the cap of 200 (tile a).
    assert ncp_verified(a) == 530
    assert ncp_verified(b) == 380
    assert ncp_verified(c) == 250
    ft = funnel_table([a, b, c])
    c1 = ft["ccds"]["c1"]
    assert c1["stages"] == {
        "raw": 1500,
        "coarse_gate": 900,
        "ransac": 1000,
        "consensus": 940,
        "backprojection": 920,
        "refine": 380,
        "mcp": 580,
    }
    # RANSAC rejected 300 of a's 900 (after the gate) and 100 of b's 500 (raw).
    assert c1["rejected"]["ransac"] == 400
    assert c1["rejected_pct"]["ransac"] == pytest.approx(100 * 400 / 1400)
    assert c1["rejected"]["mcp"] == 330  # a's thinning (530 -> 200), b's none
    assert c1["ncp_verified"] == 910 and c1["n_mcp"] == 580 and c1["thinned"] == 330
    assert ft["total"]["ncp_verified"] == 1160
    rows = full_funnel(ft["total"], n_entered=830, n_inliers=800)
    assert rows[-1] == {
        "stage": "adjustment",
        "count": 800,
        "rejected": 30,
        "rejected_pct": pytest.approx(100 * 30 / 830),
    }
    assert [r["stage"] for r in rows][:2] == ["raw", "coarse_gate"]
