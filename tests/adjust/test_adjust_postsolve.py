"""What the adjustment computes around the solve, against its numpy references.

Grouped reprojection metrics (:mod:`planetref.adjust._numba_metrics`) against
:func:`~planetref.adjust.metrics.reprojection_metrics` per group, bit for bit; the metric
blocks of :func:`~planetref.adjust.evaluation.reprojection_blocks` with and without the
compiled kernel; the variance components' group passes
(:mod:`planetref.adjust._numba_groups`) against their numpy twins; the redundancy
numbers when the linearisation has no slot matrices.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from adjust_synth import mcp_problem

from planetref.adjust import linearization, metrics, variance
from planetref.adjust.config import validate_config
from planetref.adjust.evaluation import reprojection_blocks
from planetref.adjust.models import parameterize
from planetref.adjust.redundancy import redundancy
from planetref.adjust.solver import BundleSolver
from planetref.control.network import Network
from planetref.runtime.optional import optional_module

compiled_metrics = optional_module(
    "planetref.adjust._numba_metrics", "compiled reprojection metrics"
)
needs_numba = pytest.mark.skipif(
    compiled_metrics is None, reason="numba is not installed (the numpy references run)"
)


@needs_numba
@pytest.mark.parametrize("n", [0, 5, 8, 127, 128, 129, 1000, 20011])
def test_pairwise_sums_equal_numpy_bit_for_bit(n):
    rng = np.random.default_rng(n)
    x = rng.normal(0.01, 0.3, n)
    y = rng.standard_cauchy(n)
    ref = [
        np.sum(x**2 + y**2),
        np.sum(x**2),
        np.sum(y**2),
        np.sum(x),
        np.sum(y),
        np.sum(np.hypot(x, y)),
    ]
    got = [compiled_metrics.pairwise_sum(x, y, 0, n, k) for k in range(6)]
    assert got == ref


def _groups(rng, m):
    """Two partition levels with an empty group and rows in none."""
    lv0 = np.where(rng.random(m) < 0.9, 0, -1)
    lv1 = rng.integers(1, 5, m)  # code 4 used, code 5 left empty
    lv1[rng.random(m) < 0.1] = -1
    return np.stack([lv0, lv1]), 6


@needs_numba
@pytest.mark.parametrize("m", [1, 300, 50_000])
def test_grouped_metrics_equal_reprojection_metrics_bit_for_bit(m):
    rng = np.random.default_rng(m)
    dx, dy = rng.normal(0.0, 0.4, m), rng.normal(0.05, 0.4, m)
    dx[rng.random(m) < 0.05] = np.nan
    dy[rng.random(m) < 0.05] = np.inf
    inlier = rng.random(m) < 0.8
    group, n_groups = _groups(rng, m)
    got = metrics.grouped_reprojection_metrics(dx, dy, inlier, group, n_groups)
    for g in range(n_groups):
        rows = np.any(group == g, axis=0)
        ref = metrics.reprojection_metrics(dx[rows], dy[rows], inlier[rows])
        assert got[g].keys() == ref.keys()
        for k, v in ref.items():
            assert got[g][k] == v or (np.isnan(v) and np.isnan(got[g][k])), (g, k)
    assert got[5]["n_total"] == 0 and np.isnan(got[5]["rmse_px"])


def _two_camera_network():
    net, _, _ = mcp_problem(900, seed=5, check=40)
    cam = net.cameras[0]
    fields = {f.name: getattr(net, f.name) for f in dataclasses.fields(net) if f.init}
    fields |= {
        "cameras": (cam, cam.replace(nodes=cam.nodes.copy())),
        "camera_ids": ("a", "b"),
        "obs_camera": (np.arange(net.n_obs) % 2).astype(np.intp),
    }
    return Network(**fields)


@pytest.mark.parametrize("cameras", [1, 2])
def test_reprojection_blocks_compiled_equal_numpy_reference(monkeypatch, cameras):
    net = mcp_problem(900, seed=5, check=40)[0] if cameras == 1 else _two_camera_network()
    rng = np.random.default_rng(1)
    m = net.n_obs
    res0, res = rng.normal(0.0, 3.0, (m, 2)), rng.normal(0.0, 0.3, (m, 2))
    res0[rng.random(m) < 0.02] = np.nan
    usable = np.isfinite(res0[:, 0]) & (rng.random(m) < 0.97)
    for inlier in (usable.copy(), usable & (rng.random(m) < 0.9)):
        got = reprojection_blocks(net, res0, res, inlier, usable)
        monkeypatch.setattr(metrics, "optional_module", lambda *a: None)
        ref = reprojection_blocks(net, res0, res, inlier, usable)
        monkeypatch.undo()
        assert got == ref
        assert set(got["ccds"]) == (
            {"ccd1", "ccd2", "ccd3"}
            if cameras == 1
            else {f"{c}/ccd{k}" for c in "ab" for k in (1, 2, 3)}
        )
        # The blocks count what they should: every adjusted observation once per level.
        assert got["all"]["after"]["n_total"] == m - 40
        assert sum(v["after"]["n_total"] for v in got["ccds"].values()) == m - 40
        assert got["all"]["before"]["n_inliers"] == np.count_nonzero(inlier & ~net.obs_check)


def _two_kind_solver():
    """Fixed and weighted MCPs of two kinds on one strip, solved (plain least squares)."""
    net, _, _ = mcp_problem(600, seed=9)
    sig = net.point_sigma_m.copy()
    sig[::3] = 3.0  # every third point weighted (an unknown)
    kind = net.point_kind.copy()
    kind[1::4] = "tie"
    net = dataclasses.replace(net, point_sigma_m=sig, point_kind=kind)
    cfg = validate_config({"solver": {"loss": "linear"}, "outliers": {"enabled": False}})
    solver = BundleSolver(net, [parameterize("strip", net.cameras[0], cfg)], cfg.solver)
    obs = np.arange(net.n_obs)
    c, xyz, _, lin, stats = solver.run(solver.x0, net.point_xyz, obs, net.point_xyz)
    return net, solver, obs, (c, xyz, lin, stats)


@pytest.mark.skipif(variance.group_kernels() is None, reason="numba is not installed")
def test_variance_group_passes_compiled_equal_numpy_reference():
    net, solver, obs, (c, xyz, lin, stats) = _two_kind_solver()
    kinds, kind_of_pt = net.point_kind_codes
    sub = obs[np.random.default_rng(2).random(len(obs)) < 0.7]  # gaps, as inliers leave
    args = (sub, net.obs_camera, net.obs_ccd, net.obs_point, kind_of_pt, 3, 3, len(kinds))
    order, bounds = variance.group_kernels().group_order(*args)
    order_ref, bounds_ref = variance._group_order_numpy(*args)
    assert np.array_equal(order, order_ref) and np.array_equal(bounds, bounds_ref)
    assert np.count_nonzero(np.diff(bounds)) == 6  # 2 kinds x 3 CCDs
    red = redundancy(solver, c, xyz, obs, net.point_xyz, stats["cofactor"], lin)
    groups = variance._groups(solver, obs)
    group_of = variance._image_group_of(solver, groups)
    rg = red.row_groups(group_of)
    assert red.slot is not None and np.array_equal(rg, group_of[red.obs])  # slots' groups
    args = (rg, red.obs_w, red.obs_v, len(groups))
    got, ref = variance.group_kernels().group_vtpv(*args), variance._group_vtpv_numpy(*args)
    assert np.array_equal(got, ref) and np.count_nonzero(got) == 6
    # Against the definition: v^T P v of each image group.
    for i, g in enumerate(groups):
        if g.kind == "image":
            rows = np.isin(red.obs, g.obs)
            want = np.sum(red.obs_w[rows] * red.obs_v[rows] ** 2)
            assert got[i] == pytest.approx(want, rel=1e-12)


def test_redundancy_without_slot_matrices_is_evaluated_again(monkeypatch):
    """Slot matrices too large for memory: the linearisation cannot stand in (each
    observation of a fixed point then needs its own number), so the reference runs."""
    monkeypatch.setattr(linearization, "_SLOT_BYTES", 0)
    net, solver, obs, (c, xyz, lin, stats) = _two_kind_solver()
    assert len(lin.slot_n) == 0
    got = redundancy(solver, c, xyz, obs, net.point_xyz, stats["cofactor"], lin)
    ref = redundancy(solver, c, xyz, obs, net.point_xyz, stats["cofactor"])
    assert np.array_equal(got.obs_r, ref.obs_r)
    fixed = solver.point_fixed[net.obs_point[got.obs]]
    assert np.all((got.obs_r[fixed] > 0.5) & (got.obs_r[fixed] < 1.0))
    assert got.total == pytest.approx(stats["dof"], rel=1e-6)
