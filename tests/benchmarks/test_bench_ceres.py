"""The Ceres side-by-side benchmark's problem file and C++ twin (benchmarks/ceres/).

The round trip of the ``PRCERES1`` file always runs; the twin's checks run where Ceres
builds (Debian: ``apt-get install -y libceres-dev g++ cmake``) and are skipped with the
reason elsewhere. Timings are never asserted.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"


@pytest.fixture(scope="module")
def bench():
    sys.path.insert(0, str(BENCH))
    try:
        import bench_adjust
        import ceres_problem

        yield bench_adjust, ceres_problem
    finally:
        sys.path.remove(str(BENCH))


@pytest.fixture(scope="module")
def tiny(bench):
    bench_adjust, _ = bench
    return bench_adjust.build_problem(1500, 3, 0.3, 12, 0)


@pytest.fixture(scope="module")
def tiny_ties(bench):
    """1500 observations of which 400 on 200 free tie points (20 m off at the start)."""
    bench_adjust, _ = bench
    return bench_adjust.build_problem(1500, 4, 0.3, 12, 200)


def test_problem_file_round_trips(bench, tiny, tmp_path):
    _, cp = bench
    net, _ = tiny
    p = cp.problem_of(net, position_free=False, attitude_free=True)
    path = tmp_path / "p.bin"
    cp.write_problem(p, path)
    q = cp.read_problem(path)
    for name in p.__dataclass_fields__:
        a, b = getattr(p, name), getattr(q, name)
        if isinstance(a, np.ndarray):
            assert a.dtype == b.dtype and a.shape == b.shape, name
            np.testing.assert_array_equal(a, b, err_msg=name)
        else:
            assert a == b, name
    cam = net.cameras[0]
    assert q.nodes.shape == (cam.n_nodes, 6) and q.obs_sigma.shape == (len(net.obs_line), 2)
    np.testing.assert_array_equal(q.obs_sigma[:, 0], net.obs_sigma_px[:, 0])
    # A truncated or foreign file is refused with its name.
    path.write_bytes(path.read_bytes()[:-4])
    with pytest.raises(ValueError, match="truncated"):
        cp.read_problem(path)
    path.write_bytes(b"NOTCERES" + bytes(80))
    with pytest.raises(ValueError, match="not a PRCERES1"):
        cp.read_problem(path)


def test_problem_refuses_weighted_points(bench, tiny_ties):
    _, cp = bench
    net, _ = tiny_ties
    p = cp.problem_of(net, position_free=False, attitude_free=True)
    np.testing.assert_array_equal(p.point_free, np.isinf(net.point_sigma_m[:, 0]))
    assert p.point_free.sum() == 200
    bad = net.__class__(**{**net.__dict__, "point_sigma_m": np.ones_like(net.point_sigma_m)})
    with pytest.raises(ValueError, match=r"known .* or unknown"):
        cp.problem_of(bad, position_free=False, attitude_free=True)


@pytest.fixture(scope="module")
def ceres_exe(bench):
    _, cp = bench
    exe, why = cp.build()
    if exe is None:
        pytest.skip(f"Ceres twin not built: {why}")
    return exe


@pytest.mark.parametrize(
    ("solver", "network"),
    [("DENSE_SCHUR", "tiny"), ("SPARSE_SCHUR", "tiny"), ("SPARSE_SCHUR", "tiny_ties")],
)
def test_ceres_reaches_planetrefs_optimum(bench, request, ceres_exe, tmp_path, solver, network):
    bench_adjust, cp = bench
    from planetref.adjust import adjust

    net, _ = request.getfixturevalue(network)
    res = adjust(net, bench_adjust.CONFIG)
    path = tmp_path / "p.bin"
    cp.write_problem(cp.problem_of(net, position_free=False, attitude_free=True), path)
    n = net.cameras[0].n_nodes
    run = cp.run(ceres_exe, path, n, solver, 1, extra=cp_stop(), covariance=True)
    s = run.summary
    assert s["termination"] == "CONVERGENCE", s["message"]
    # With tie points, the points are the eliminated group (Ceres's ordering [200, 12]).
    n_free = int(np.isinf(net.point_sigma_m[:, 0]).sum())
    assert s["free_points"] == n_free
    if n_free:
        assert s["linear_solver_ordering_used"] == [n_free, n]
    # The same model: the same cost at the initial cameras (planetref's cost is half the
    # weighted sum of squares, as Ceres's) and at the optimum.
    rnd = res.rounds[0]
    assert s["initial_cost"] == pytest.approx(rnd["cost_initial"], rel=1e-9)
    assert s["final_cost"] == pytest.approx(rnd["cost_final"], rel=1e-9)
    act = res.parameter_mode != 2
    x = np.concatenate([run.nodes.ravel(), res.x[6 * n :]])
    assert np.max(np.abs(x - res.x)[act] / res.sigma[act]) < 0.01
    # Fixed parameters are untouched; the attitude covariance is planetref's (unit
    # weight times sigma0).
    np.testing.assert_array_equal(x[~act], res.x[~act])
    np.testing.assert_allclose(run.attitude_sigma * res.sigma0, res.sigma[act], rtol=1e-6)


def cp_stop() -> tuple[str, ...]:
    sys.path.insert(0, str(BENCH))
    try:
        from bench_adjust_ceres import CERES_STOP
    finally:
        sys.path.remove(str(BENCH))
    return CERES_STOP
