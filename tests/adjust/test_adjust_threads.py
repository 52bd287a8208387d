"""The adjustment's chunk threads: same numbers as one thread, and a fork afterwards is safe.

The linearisation and the redundancy numbers evaluate the models chunk by chunk in
threads (:meth:`~planetref.adjust.linearization.LinearizationMixin.map_chunks`); each
thread sums its own share and the shares are added in order. One thread is the
reference: the threaded adjustment must reach the same solution to rounding.
"""

from __future__ import annotations

import multiprocessing as mp
from dataclasses import replace

import numpy as np
import pytest
from adjust_synth import mcp_problem

from planetref.adjust import adjust
from planetref.adjust.config import validate_config
from planetref.adjust.linearization import SHARES
from planetref.adjust.models import parameterize
from planetref.adjust.redundancy import redundancy
from planetref.adjust.solver import BundleSolver
from planetref.adjust.variance import _groups, _image_group_of
from planetref.errors import InputError
from planetref.runtime.threads import compute_threads

CONFIG = {
    "solver": {"loss": "linear", "chunk_size": 256},
    "linescan": {"position": {"mode": "weighted", "sigma_m": 50.0}},
    "outliers": {"enabled": False},
}


def _with_threads(n: int) -> dict:
    return {**CONFIG, "solver": {**CONFIG["solver"], "threads": n}}


def _solver(net, threads: int) -> BundleSolver:
    cfg = validate_config(_with_threads(threads))
    return BundleSolver(net, [parameterize("strip", net.cameras[0], cfg)], cfg.solver)


def test_chunk_shares_cover_the_layout_once_whatever_the_threads():
    net, _, _ = mcp_problem(900, seed=3)
    parts = []
    for n in (1, 3):
        solver = _solver(net, n)
        lay = solver._structure(np.arange(net.n_obs)).lay
        parts.append(solver.chunk_parts(lay))
    assert parts[0] == parts[1]  # the split never depends on the thread count
    assert len(parts[0]) == min(SHARES, sum(len(p) for p in parts[0])) > 1
    rows = np.concatenate([np.arange(a, b) for part in parts[0] for _, _, a, b in part])
    assert np.array_equal(rows, np.arange(net.n_obs))  # in order, each row once
    sizes = [sum(b - a for _, _, a, b in part) for part in parts[0]]
    assert max(sizes) - min(sizes) <= 2 * 256


def test_threaded_linearisation_equals_one_thread():
    net, _, _ = mcp_problem(900, seed=4)
    lin = []
    for n in (1, 3):
        solver = _solver(net, n)
        st = solver._structure(np.arange(net.n_obs))
        xyz = net.point_xyz.copy()
        lin.append(solver._linearize(solver.x0, xyz, st.lay, st.tie_pos, st.n_tie, st.unknown, xyz))
    a, b = lin
    assert np.abs(a.n_cc).max() > 0
    # Fixed shares summed in order: bit for bit, whatever the thread count.
    assert np.array_equal(a.n_cc, b.n_cc) and np.array_equal(a.g_c, b.g_c)
    assert np.array_equal(a.r, b.r) and np.array_equal(a.weight, b.weight)
    assert a.cost == pytest.approx(b.cost, rel=1e-14)


def test_threaded_adjustment_equals_one_thread():
    """Weighted MCPs (Schur complement, redundancy pairs) with 1 and 3 threads."""
    net, _, _ = mcp_problem(700, seed=6, ground_sigma_m=3.0)
    one = adjust(net, _with_threads(1))
    three = adjust(net, _with_threads(3))
    act = one.parameter_mode != 2
    assert np.any(act)
    assert np.array_equal(one.x, three.x)
    assert np.array_equal(one.residual, three.residual, equal_nan=True)
    for key in ("redundancy_real", "redundancy_pseudo"):
        assert three.variance["dof"][key] == one.variance["dof"][key]
    assert one.variance["dof"]["redundancy_real"] > 100


def _child(q) -> None:  # pragma: no cover - runs in the forked child
    net, _, _ = mcp_problem(300, seed=2)
    res = adjust(net, _with_threads(2))
    q.put(float(res.sigma0))


@pytest.mark.skipif("fork" not in mp.get_all_start_methods(), reason="no fork on this OS")
def test_fork_after_a_threaded_adjustment_does_not_hang():
    net, _, _ = mcp_problem(300, seed=2)
    parent = adjust(net, _with_threads(2))
    ctx = mp.get_context("fork")
    q = ctx.Queue()
    p = ctx.Process(target=_child, args=(q,))
    p.start()
    p.join(timeout=120)
    hung = p.is_alive()
    if hung:
        p.kill()
    assert not hung and p.exitcode == 0
    assert q.get(timeout=5) == pytest.approx(float(parent.sigma0), rel=1e-12)


def test_thread_count_follows_the_budget(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert compute_threads() == 1
    assert compute_threads(3) == 3
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert compute_threads() >= 1
    with pytest.raises(InputError):
        compute_threads(0)


def _mixed_problem():
    """Fixed and weighted MCPs of two kinds (slots of both, pairs of unknown points)."""
    net, _, _ = mcp_problem(600, seed=9)
    sig = net.point_sigma_m.copy()
    sig[::3] = 3.0  # every third point weighted (an unknown)
    kind = net.point_kind.copy()
    kind[1::4] = "tie"  # a second point kind: more slots
    return replace(net, point_sigma_m=sig, point_kind=kind)


def test_redundancy_from_the_final_linearisation_equals_a_fresh_evaluation():
    """Slot sums ``n_s - tr(Q N_s)`` and reused tie partials against the reference pass."""
    net = _mixed_problem()
    cfg = validate_config({**CONFIG, "solver": {"loss": "linear"}})
    solver = BundleSolver(net, [parameterize("strip", net.cameras[0], cfg)], cfg.solver)
    obs = np.arange(net.n_obs)
    c, xyz, _, lin, stats = solver.run(solver.x0, net.point_xyz, obs, net.point_xyz)
    fast = redundancy(solver, c, xyz, obs, net.point_xyz, stats["cofactor"], lin)
    ref = redundancy(solver, c, xyz, obs, net.point_xyz, stats["cofactor"])
    assert len(fast.slot_r) == 6 and len(ref.slot_r) == 0  # 2 kinds x 3 CCDs
    groups = _groups(solver, obs)
    group_of = _image_group_of(solver, groups)
    a, b = fast.image_sums(group_of, len(groups)), ref.image_sums(group_of, len(groups))
    assert np.count_nonzero(b) == 6 and np.all(b[b != 0] > 10)
    assert np.allclose(a, b, rtol=1e-9, atol=1e-9)
    assert fast.total == pytest.approx(ref.total, rel=1e-10)
    # Observations of unknown points keep their own numbers; the rest are summed.
    unknown = ~solver.point_fixed[net.obs_point[fast.obs]]
    assert np.allclose(fast.obs_r[unknown], ref.obs_r[unknown], atol=1e-9)
    assert not np.any(fast.obs_r[~unknown])
    assert np.allclose(fast.point_cofactor, ref.point_cofactor, rtol=1e-9, atol=1e-12)
    assert np.allclose(fast.point_r, ref.point_r, atol=1e-9)
    assert np.abs(fast.obs_v - ref.obs_v).max() < 1e-8  # projections agree to ~1e-9 px
    # A robust linearisation does not qualify: the reference pass runs.
    lin.loss = "huber"
    again = redundancy(solver, c, xyz, obs, net.point_xyz, stats["cofactor"], lin)
    assert len(again.slot_r) == 0 and np.array_equal(again.obs_r, ref.obs_r)


def test_threaded_projection_equals_one_thread():
    net, _, _ = mcp_problem(900, seed=5)
    obs = np.arange(0, net.n_obs, 2)[::-1]  # any order: results come back in obs order
    out = []
    for n in (1, 3):
        solver = _solver(net, n)
        out.append(solver.project(solver.x0, net.point_xyz, obs))
    (l1, s1, v1), (l3, s3, v3) = out
    assert v1.all() and np.array_equal(v1, v3)
    assert np.array_equal(l1, l3) and np.array_equal(s1, s3)
    # Against the linearisation's projections of the same observations.
    solver = _solver(net, 1)
    st = solver._structure(np.arange(net.n_obs))
    lin = solver._linearize(
        solver.x0, net.point_xyz, st.lay, st.tie_pos, st.n_tie, st.unknown, net.point_xyz
    )
    at = np.empty(net.n_obs, np.intp)
    at[lin.obs] = np.arange(net.n_obs)
    assert np.abs(l3 - lin.line[at[obs]]).max() < 1e-8
