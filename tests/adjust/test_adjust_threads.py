"""The adjustment's chunk threads: same numbers as one thread, and a fork afterwards is safe.

The linearisation and the redundancy numbers evaluate the models chunk by chunk in
threads (:meth:`~planetref.adjust.linearization.LinearizationMixin.map_chunks`); each
thread sums its own share and the shares are added in order. One thread is the
reference: the threaded adjustment must reach the same solution to rounding.
"""

from __future__ import annotations

import multiprocessing as mp

import numpy as np
import pytest
from adjust_synth import mcp_problem

from planetref.adjust import adjust
from planetref.adjust.config import validate_config
from planetref.adjust.models import parameterize
from planetref.adjust.solver import BundleSolver
from planetref.errors import InputError
from planetref.threads import compute_threads

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


def test_chunk_shares_cover_the_layout_once():
    net, _, _ = mcp_problem(900, seed=3)
    solver = _solver(net, 3)
    lay = solver._structure(np.arange(net.n_obs)).lay
    parts = solver.chunk_parts(lay)
    assert len(parts) == 3
    rows = np.concatenate([np.arange(a, b) for part in parts for _, _, a, b in part])
    assert np.array_equal(rows, np.arange(net.n_obs))  # in order, each row once
    sizes = [sum(b - a for _, _, a, b in part) for part in parts]
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
    scale = np.abs(a.n_cc).max()
    assert scale > 0
    assert np.abs(a.n_cc - b.n_cc).max() <= 1e-13 * scale
    assert np.abs(a.g_c - b.g_c).max() <= 1e-12 * np.abs(a.g_c).max()
    assert np.array_equal(a.r, b.r) and np.array_equal(a.weight, b.weight)
    assert a.cost == pytest.approx(b.cost, rel=1e-14)


def test_threaded_adjustment_equals_one_thread():
    """Weighted MCPs (Schur complement, redundancy pairs) with 1 and 3 threads."""
    net, _, _ = mcp_problem(700, seed=6, ground_sigma_m=3.0)
    one = adjust(net, _with_threads(1))
    three = adjust(net, _with_threads(3))
    act = one.parameter_mode != 2
    assert np.max(np.abs(one.x - three.x)[act] / one.sigma[act]) < 1e-8
    assert np.nanmax(np.abs(one.residual - three.residual)) < 1e-8
    for key in ("redundancy_real", "redundancy_pseudo"):
        assert three.variance["dof"][key] == pytest.approx(one.variance["dof"][key], rel=1e-10)
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
