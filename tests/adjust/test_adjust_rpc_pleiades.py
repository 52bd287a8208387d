"""The real Pléiades pair (Earth, RPCs only): bias-compensated tie-point adjustment.

Tie points are matched between the two images with planetref's matchers and verified by
a fundamental matrix (1 px); the points are triangulated from the RPCs and adjusted as
free points (no a-priori coordinates); the datum is the bias coefficients' a-priori
weight (10 px). The mutual residual is the reprojection RMSE of the tie points.
Baseline: the same adjustment with the biases fixed (points only), so the reduction is
that of the bias compensation and not of re-triangulating the points.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rasterio
import torch

from planetref.adjust import Network, adjust
from planetref.camera.rpc import RpcCamera
from planetref.matching.ransac import verify_matches
from planetref.matching.registry import get_matcher

torch.set_num_threads(1)

NAMES = ("img_01", "img_02")


def _pair(shared: Path) -> tuple[dict[str, RpcCamera], dict[str, np.ndarray]]:
    folder = shared / "data" / "pleiades_rpc"
    if not all((folder / f"{n}.tif").is_file() for n in NAMES):
        pytest.skip(f"{folder} lacks the Pléiades pair")
    cams = {n: RpcCamera.from_file(folder / f"{n}.tif") for n in NAMES}
    images = {}
    for n in NAMES:
        with rasterio.open(folder / f"{n}.tif") as src:
            images[n] = src.read(1).astype(np.float32)
    return cams, images


def _tie_network(cams, matches) -> Network:
    k0, k1 = matches.keypoints0, matches.keypoints1
    n = len(matches)
    pid = [f"t{i}" for i in range(n)]
    return Network.from_records(
        cams,
        obs_camera=[NAMES[0]] * n + [NAMES[1]] * n,
        obs_point=pid + pid,
        line=np.concatenate([k0[:, 1], k1[:, 1]]),
        sample=np.concatenate([k0[:, 0], k1[:, 0]]),
        point_xyz={p: np.full(3, np.nan) for p in pid},
        point_kind="tie",
        sigma_px=0.5,
    )


def _before_after(cams, matches, bias: str) -> tuple[float, float, float]:
    """Tie RMSE (px): initial triangulation, points-only adjustment, bias-compensated."""
    net = _tie_network(cams, matches)
    fixed = adjust(net, {"rpc": {"bias": "shift", "mode": "fixed"}, "solver": {"loss": "linear"}})
    comp = adjust(
        net,
        {
            "rpc": {"bias": bias, "mode": "weighted", "sigma_px": 10.0},
            "solver": {"loss": "linear"},
        },
    )
    assert comp.converged
    s_fixed, s_comp = fixed.summary(), comp.summary()
    print(
        f"{bias}: {len(matches)} tie points; RMSE initial {s_comp['rmse_px_before']:.3f} px, "
        f"points only {s_fixed['rmse_px']:.3f} px, bias-compensated {s_comp['rmse_px']:.3f} px; "
        f"{dict(zip(comp.parameter_names, np.round(comp.x, 3), strict=True))}"
    )
    return s_comp["rmse_px_before"], s_fixed["rmse_px"], s_comp["rmse_px"]


@pytest.mark.shared
def test_tie_points_of_a_crop_reduce_their_mutual_residual(shared):
    """Fast: NCC matches in the central 512 x 512 pixels, shift bias per image."""
    cams, images = _pair(shared)
    crop = slice(256, 768)
    m = get_matcher("ncc").match(images[NAMES[0]][crop, crop], images[NAMES[1]][crop, crop])
    m = m.shifted((256.0, 256.0), (256.0, 256.0))
    m = m.select(verify_matches(m, "fundamental", threshold=1.0).inliers)
    assert len(m) >= 100
    initial, points_only, compensated = _before_after(cams, m, "shift")
    assert compensated < 0.7 * points_only
    assert compensated < 0.7 * initial


@pytest.mark.shared
@pytest.mark.slow
@pytest.mark.parametrize("bias", ["shift", "affine"])
def test_sift_tie_points_over_the_whole_pair_reduce_their_mutual_residual(shared, bias):
    cams, images = _pair(shared)
    m = get_matcher("sift").match(images[NAMES[0]], images[NAMES[1]])
    m = m.select(verify_matches(m, "fundamental", threshold=1.0).inliers)
    assert len(m) >= 1000
    initial, points_only, compensated = _before_after(cams, m, bias)
    assert compensated < 0.6 * points_only
    assert compensated < 0.6 * initial
