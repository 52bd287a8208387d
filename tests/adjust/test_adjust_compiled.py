"""The adjustment's compiled (numba) pieces against their numpy references.

Compiled: the pattern partials of a line-scan strip
(:func:`planetref.camera.linescan.compiled.fill_partials`), the normal-equation
accumulation over active columns and the cofactor products of the redundancy numbers
(:mod:`planetref.adjust._numba_normal`). Each has a numpy twin that stays the reference.
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest
from adjust_synth import mcp_problem, tie_problem

from planetref.adjust import adjust, linearization, schur
from planetref.adjust.config import validate_config
from planetref.adjust.models import parameterize
from planetref.adjust.redundancy import _diag_cofactor, _PairG, redundancy
from planetref.adjust.schur import Iterate
from planetref.adjust.solver import BundleSolver
from planetref.camera.linescan import compiled

pytestmark = pytest.mark.skipif(
    linearization._compiled() is None or not compiled.available(),
    reason="numba is not installed (the numpy references run)",
)

CONFIG = {
    "solver": {"loss": "linear"},
    # Positions weighted, attitudes free, interior fixed: active and fixed columns mix.
    "linescan": {"position": {"mode": "weighted", "sigma_m": 50.0}},
}


def _solver(net, reference: bool) -> BundleSolver:
    cfg = validate_config(CONFIG)
    models = [parameterize("strip", net.cameras[0], cfg)]
    solver = BundleSolver(net, models, cfg.solver)
    if reference:
        solver.compiled_normal = False
        models[0].compiled_partials = False
    return solver


def _linearize(solver: BundleSolver, net):
    st = solver._structure(np.arange(net.n_obs))
    xyz = net.point_xyz.copy()
    return solver._linearize(solver.x0, xyz, st.lay, st.tie_pos, st.n_tie, st.unknown, xyz)


def test_linearisation_compiled_equals_numpy_reference():
    net, _, _ = mcp_problem(500, seed=4)
    fast, ref = _solver(net, False), _solver(net, True)
    a, b = _linearize(fast, net), _linearize(ref, net)
    act = fast.active
    assert 0 < act.size < fast.n_params  # some columns fixed, some not
    n_a, n_b = a.n_cc[np.ix_(act, act)], b.n_cc[np.ix_(act, act)]
    scale = np.sqrt(np.outer(np.diag(n_b), np.diag(n_b)))
    assert np.abs(n_a - n_b).max() <= 1e-12 * scale.max()
    assert np.all(np.abs(n_a - n_b) <= 1e-10 * scale)
    g_scale = np.sqrt(np.diag(n_b)) * np.sqrt(np.sum(b.weight * b.r**2))
    assert np.all(np.abs(a.g_c[act] - b.g_c[act]) <= 1e-10 * g_scale)
    assert np.abs(a.r - b.r).max() < 1e-9
    assert a.cost == pytest.approx(b.cost, rel=1e-12)
    # The per-slot matrices (one per CCD here) add up to the normal matrix.
    assert a.slot_n.shape[0] == 3
    s_scale = np.abs(b.slot_n).max()
    assert np.abs(a.slot_n - b.slot_n).max() <= 1e-12 * s_scale
    p = fast.n_params
    assert np.allclose(b.slot_n.sum(axis=0)[:p, :p], b.n_cc[:p, :p], rtol=1e-12, atol=0)
    # Only the active columns are accumulated: the fixed ones' rows stay zero.
    fixed = np.flatnonzero(fast.mode == 2)
    assert fixed.size and not np.any(a.n_cc[fixed]) and not np.any(b.n_cc[fixed])
    assert np.all(np.diag(n_b) > 0)


def _captured_rows(monkeypatch, net, loss="linear"):
    """The arguments of every ``linearize_rows`` call of one linearisation, in layout order.

    One thread: with more, the calls arrive in the order the chunks finish, and the
    tests that edit the first chunk would edit another one from run to run (its rows
    3-400 may then lie in pattern 0 already, leaving no short run to test).
    """
    solver = _solver(net, False)
    solver.cfg = solver.cfg.model_copy(update={"threads": 1})
    solver.loss = loss
    fn = solver.normal_kernels()
    calls = []
    real = fn.linearize_rows

    def capture(*args):
        calls.append(args)
        real(*args)

    monkeypatch.setattr(fn, "linearize_rows", capture)
    _linearize(solver, net)
    monkeypatch.setattr(fn, "linearize_rows", real)
    return solver, fn, calls


def _sum_rows(fn, calls, basis: bool):
    """``(N, g, r, s, weight)`` of the captured chunks, moments on or off."""
    n_cc = g_c = None
    outs = []
    for args in calls:
        args = list(args)
        n0, g0 = np.zeros_like(args[8][0]), np.zeros_like(args[8][1])
        args[8] = (n0, g0)
        args[7] = (args[7][0], np.zeros_like(args[7][1]), args[7][2])
        args[9] = tuple(np.full_like(a, np.nan) for a in args[9])
        if not basis:  # the row-by-row form
            args[4] = (*args[4][:4], np.empty(0), np.empty(0, np.intp), np.empty((0, 0, 0)))
        fn.linearize_rows(*args)
        n_cc = n0 if n_cc is None else n_cc + n0
        g_c = g0 if g_c is None else g_c + g0
        outs.append(args[9])
    return n_cc, g_c, [np.concatenate(x) for x in zip(*outs, strict=True)]


@pytest.mark.parametrize("loss", ["linear", "huber"])
def test_moment_form_equals_row_by_row_accumulation(monkeypatch, loss):
    """Runs of a window summed as moments of tau give the row-by-row normal equations.

    Positions weighted and attitudes free: 6 distinct sources, 36 node columns per
    window; some observations are made invalid (weight 0, pattern 0, a window of their
    own) and the runs include short ones, summed row by row.
    """
    net, _, _ = mcp_problem(3000, seed=9)
    solver, fn, calls = _captured_rows(monkeypatch, net, loss)
    # Invalidate a few rows in the first chunk: they must add nothing.
    proj = calls[0][0]
    bad = np.zeros(len(proj[0]), bool)
    bad[[3, 50, 51, 400]] = True
    # As the models leave them: pattern 0, whatever their window (``start``).
    gp0 = np.where(bad, 0, calls[0][5])
    calls[0] = (
        (np.where(bad, np.nan, proj[0]), proj[1], proj[2] & ~bad),
        *calls[0][1:5],
        gp0,
        *calls[0][6:],
    )
    basis = calls[0][4]
    tau, start, coef = basis[4:]
    assert len(tau) == len(start) == len(proj[0]) and coef.shape[1:] == (4, 4)
    gp = np.concatenate([c[5] for c in calls])
    min_run = fn.MIN_MOMENT_RUN
    runs = np.diff(np.flatnonzero(np.diff(gp) != 0))
    assert runs.max() >= min_run and runs.min() < min_run  # both forms run
    n_m, g_m, out_m = _sum_rows(fn, calls, basis=True)
    n_r, g_r, out_r = _sum_rows(fn, calls, basis=False)
    act = solver.active
    nm, nr = n_m[np.ix_(act, act)], n_r[np.ix_(act, act)]
    scale = np.sqrt(np.outer(np.diag(nr), np.diag(nr)))
    assert np.all(np.abs(nm - nr) <= 1e-12 * scale)
    assert np.array_equal(nm, nm.T)
    g_scale = np.sqrt(np.diag(nr)) * np.sqrt(np.nansum(out_r[2] * out_r[0] ** 2))
    assert np.all(np.abs(g_m[act] - g_r[act]) <= 1e-12 * g_scale)
    for a, b in zip(out_m, out_r, strict=True):  # residuals, s, weights: the same code
        assert np.array_equal(a, b, equal_nan=True)
    rows = np.concatenate([c[0][2] for c in calls])
    assert not np.any(out_m[2][~rows]) and np.all(np.isinf(out_m[1][~rows]))
    # Every node's position and attitude is active (the interior is fixed).
    assert act.size == 36 and np.all(np.diag(nr) > 0)


def test_cofactor_products_compiled_equal_numpy_reference():
    net, _, _ = mcp_problem(300, seed=5)
    solver = _solver(net, False)
    rng = np.random.default_rng(0)
    m = 700
    d = rng.normal(size=(m, 2, solver.q))
    gp = np.sort(rng.integers(0, len(solver.cols), m))
    act = solver.active
    root = rng.normal(size=(act.size, act.size))
    q = np.zeros((solver.n_params, solver.n_params))
    q[np.ix_(act, act)] = root @ root.T + act.size * np.eye(act.size)
    fast = _diag_cofactor(solver, d, gp, q)
    idx = np.arange(m)
    ref = _PairG(solver, d, gp, q)(idx, idx)
    assert np.abs(fast - ref).max() <= 1e-12 * np.abs(ref).max()
    assert np.all(ref[:, 0, 0] > 0)


def test_adjustment_identical_with_the_numpy_references(monkeypatch):
    """Whole adjustments (weighted MCPs: the Schur and pair paths too) agree to ~1e-10."""
    net, _, _ = mcp_problem(400, seed=6, ground_sigma_m=3.0)
    cfg = {**CONFIG, "outliers": {"enabled": False}}
    fast = adjust(net, cfg)
    monkeypatch.setattr(compiled, "available", lambda: False)
    monkeypatch.setattr(linearization, "_compiled", lambda: None)
    monkeypatch.setattr(schur, "_compiled", lambda: None)
    ref = adjust(net, cfg)
    act = ref.parameter_mode != 2
    assert np.max(np.abs(fast.x - ref.x)[act] / ref.sigma[act]) < 1e-8
    # Positions against attitudes are ill-conditioned: their sigmas agree to ~4e-9.
    assert np.max(np.abs(fast.sigma - ref.sigma)[act] / ref.sigma[act]) < 1e-8
    assert np.nanmax(np.abs(fast.residual - ref.residual)) < 1e-8
    assert fast.sigma0 == pytest.approx(ref.sigma0, rel=1e-10)
    for key in ("redundancy_real", "redundancy_pseudo"):
        assert fast.variance["dof"][key] == pytest.approx(ref.variance["dof"][key], rel=1e-9)
    assert ref.variance["dof"]["redundancy_real"] > 100


def test_pattern_partials_compiled_equal_numpy_reference():
    net, _, _ = mcp_problem(200, seed=8)
    cfg = validate_config({"linescan": {"ccd_placement": {"mode": "free"}}})
    fast = parameterize("strip", net.cameras[0], cfg)
    ref = parameterize("strip", net.cameras[0], cfg)
    ref.compiled_partials = False
    sel = net.obs_ccd == 1
    xyz = net.point_xyz[net.obs_point[sel]]
    # From converged lines both kernels evaluate at the same line (from cold guesses
    # their chord iterations stop ~1e-9 px apart).
    first = ref.evaluate(ref.x0, xyz, 1, net.obs_line[sel])
    args = (fast.x0, xyz, 1, first.line)
    a = fast.evaluate(*args, rate_guess=first.line_rate)
    b = ref.evaluate(*args, rate_guess=first.line_rate)
    assert a.d_params.shape[2] == 6 * fast._k + 6  # nodes, interior, placement
    for x, y in ((a.d_params, b.d_params), (a.d_ground, b.d_ground)):
        scale = np.abs(y).max(axis=0)
        assert np.all(np.abs(x - y).max(axis=0) <= 1e-12 * scale + 1e-9)
    assert np.array_equal(a.pattern, b.pattern)


def test_point_prior_weights_equal_the_dense_formula():
    """Sparse per-point weights (only weighted points held) index like the dense arrays."""
    net, _, _ = mcp_problem(300, seed=2)
    sig = net.point_sigma_m.copy()
    sig[::3] = [2.0, 3.0, np.inf]  # weighted on two axes, free on the third
    sig[1::7] = np.inf  # free points
    solver = _solver(dataclasses.replace(net, point_sigma_m=sig), False)
    n = net.n_points
    with np.errstate(divide="ignore"):
        dense = np.where((sig > 0) & np.isfinite(sig), 1.0 / sig**2, 0.0)
    idx = np.arange(n)
    assert solver.point_prior_axis_w.shape == (n, 3) and len(solver.point_prior_axis_w) == n
    assert solver.point_prior_w.shape == (n, 3, 3) and len(solver.point_prior_w) == n
    np.testing.assert_array_equal(solver.point_prior_axis_w[idx], dense)
    fr = net.point_frame_matrices(idx)
    want = np.einsum("pki,pk,pkj->pij", fr, dense, fr)
    np.testing.assert_allclose(solver.point_prior_w[idx], want, rtol=1e-15, atol=0)
    weighted = np.zeros(n, bool)
    weighted[::3] = True
    weighted[1::7] = False
    assert weighted.sum() > 50 and np.array_equal(dense.any(axis=1), weighted)


def test_radix_order_equals_numpy_stable_sort():
    from planetref.adjust import _numba_groups
    from planetref.adjust.linearization import group_order

    rng = np.random.default_rng(3)
    keys = rng.integers(0, 50, 20_000)  # many ties: stability matters
    assert np.array_equal(_numba_groups.radix_order(keys, 50)[0], np.argsort(keys, kind="stable"))
    big = rng.integers(0, 3_000_000, 20_000)  # two radix passes
    order, srt = _numba_groups.radix_order(big, 3_000_000)
    assert np.array_equal(order, np.argsort(big, kind="stable"))
    assert np.array_equal(srt, np.sort(big))
    # Digit widths at the pass boundaries: one key, one full 12-bit digit, one bit more
    # (two passes of 7 bits), three passes; the top digit must not be dropped.
    for n_keys in (1, 2, 4096, 4097, 1 << 24, (1 << 24) + 1, 1 << 34):
        k = rng.integers(0, n_keys, 5000)
        k[:50] = n_keys - 1
        order, srt = _numba_groups.radix_order(k, n_keys)
        assert np.array_equal(order, np.argsort(k, kind="stable")), n_keys
        assert np.array_equal(srt, np.sort(k)), n_keys
    assert _numba_groups.radix_order(np.zeros(0, np.int64), 10)[0].size == 0
    # The layout order: by group, then by line (stable), compiled and numpy; with long
    # buckets (many observations of one line) and exact ties.
    key = rng.integers(0, 3, 6000).astype(np.int64)
    line = np.concatenate([rng.uniform(-3.0, 400.0, 5000), rng.uniform(7.0, 7.9, 900)])
    line = np.concatenate([line, line[:100]])  # exact ties
    ref = np.lexsort((np.arange(6000), line, key))
    assert np.array_equal(group_order(key, line), ref)
    keys = key * 1000 + (np.floor(line) + 3).astype(np.int64)
    assert np.array_equal(_numba_groups.group_line_order(keys, 3000, line), ref)


def test_point_matrices_index_like_the_dense_array():
    from planetref.control.network import PointMatrices

    rng = np.random.default_rng(4)
    dense = np.zeros((50, 3, 3))
    on = np.array([3, 17, 40])
    dense[on] = rng.normal(size=(3, 3, 3))
    pm = PointMatrices(50, on, dense[on])
    idx = rng.integers(0, 50, 200)
    assert np.array_equal(pm[idx], dense[idx])
    assert len(pm) == 50 and pm[np.array([17])][0, 1, 2] == dense[17, 1, 2]


def test_point_frames_index_like_the_dense_array():
    from planetref.control.network import PointFrames

    net, _, _ = mcp_problem(60, seed=9, ground_sigma_m=3.0)
    dense = net.point_frame_matrices()
    frames = PointFrames(net)
    idx = np.array([5, 0, 5, net.n_points - 1])
    assert np.array_equal(frames[idx], dense[idx])
    assert len(frames) == net.n_points


def _tie_solver(**kw):
    """A solver of :func:`adjust_synth.tie_problem` (positions weighted, attitudes free)."""
    net = tie_problem(**kw)
    cfg = validate_config({**CONFIG, "outliers": {"enabled": False}})
    models = [parameterize(i, cam, cfg) for i, cam in zip(net.camera_ids, net.cameras, strict=True)]
    solver = BundleSolver(net, models, cfg.solver)
    obs = np.arange(net.n_obs)
    st = solver._structure(obs)
    solver._unknown_ids = st.unknown
    xyz = net.point_xyz.copy()
    lin = solver._linearize(solver.x0, xyz, st.lay, st.tie_pos, st.n_tie, st.unknown, xyz)
    return net, solver, st, lin, Iterate(lin, st.chunks, solver.x0, xyz, xyz, st.unknown)


@pytest.mark.parametrize("pool", [schur._POOL_ELEMENTS, 0])
@pytest.mark.parametrize("lam", [0.0, 1e-3])
def test_tie_point_elimination_compiled_equals_numpy_reference(monkeypatch, pool, lam):
    """Points of 2 and 3 observations, some over two Lagrange windows (patterns): the
    compiled elimination (one ``z z^T`` per point over the union of its columns, summed
    per pattern or straight into S) against the numpy pairs of observations."""
    _, solver, st, lin, at = _tie_solver(n_tie=120, triple=30, tie_sigma_m=30.0)
    starts = np.append([ch.obs[0] + ch.starts for ch in st.chunks], len(lin.a_t))
    mixed = [len(np.unique(lin.gpat_t[a:b])) > 1 for a, b in itertools.pairwise(starts)]
    assert 5 < sum(mixed) < len(mixed)  # both kinds of point
    assert np.max(np.diff(starts)) == 3
    monkeypatch.setattr(schur, "_POOL_ELEMENTS", pool)
    s_mat, rhs, d_c, blocks = solver._reduced(at, lam)
    assert np.array_equal(s_mat, s_mat.T)
    monkeypatch.setattr(schur, "_compiled", lambda: None)
    s_np, rhs_np, d_np, blocks_np = solver._reduced(at, lam)
    act = solver.active
    sa, sn = s_mat[np.ix_(act, act)], s_np[np.ix_(act, act)]
    scale = np.sqrt(np.outer(np.diag(sn), np.diag(sn)))
    assert np.max(np.abs(sa - sn) / scale) < 1e-9
    # The gradient against its largest element (6e-12 here; the compiled elimination
    # before the per-point union, pairs of observations, gave the same 6e-12).
    assert np.max(np.abs(rhs - rhs_np)[act]) < 1e-9 * np.max(np.abs(rhs_np[act]))
    assert np.array_equal(d_c, d_np)
    for (v, bx, dx), (v_np, bx_np, dx_np) in zip(blocks, blocks_np, strict=True):
        assert np.allclose(v, v_np, rtol=1e-9, atol=0.0)
        assert np.allclose(bx, bx_np, rtol=1e-9, atol=1e-12 * np.abs(bx_np).max())
        assert np.allclose(dx, dx_np, rtol=1e-12, atol=0.0)


def test_tie_rows_compiled_equal_numpy_reference():
    """The tie arrays written by the compiled scatter equal the expanded factors'."""
    net, solver, st, lin, _ = _tie_solver(n_tie=60, triple=10)
    solver.compiled_normal = False
    ref = solver._linearize(
        solver.x0, net.point_xyz, st.lay, st.tie_pos, st.n_tie, st.unknown, net.point_xyz
    )
    assert lin.a_t.shape == ref.a_t.shape and np.abs(ref.a_t).max() > 0
    for name in ("a_t", "b_t", "gpat_t", "weight_t", "r_t"):
        assert np.array_equal(getattr(lin, name), getattr(ref, name)), name


@pytest.mark.parametrize(("tie_sigma", "tol"), [(30.0, 1e-9), (np.inf, 1e-6)])
def test_tie_redundancy_compiled_equals_numpy_reference(tie_sigma, tol):
    """The redundancy numbers of tie observations and the points' cofactors (compiled
    per point) against the numpy loop over pairs of observations.

    Free tie points are nearly singular (depth along the 1 mm CCD stagger: cond(Q_XX)
    ~1e7): ``H_i`` cancels its large terms, and both sums lose ~1e-7 to rounding (the
    numbers sum to the 264 degrees of freedom within 1e-6 either way)."""
    net, solver, _, _, _ = _tie_solver(n_tie=120, triple=30, tie_sigma_m=tie_sigma)
    obs = np.arange(net.n_obs)
    c, xyz, _, lin, stats = solver.run(solver.x0, net.point_xyz, obs, net.point_xyz)
    fast = redundancy(solver, c, xyz, obs, net.point_xyz, stats["cofactor"], lin)
    solver.compiled_normal = False
    ref = redundancy(solver, c, xyz, obs, net.point_xyz, stats["cofactor"], lin)
    tie = ~solver.point_fixed[net.obs_point[ref.obs]]
    assert tie.sum() == 330  # 270 tie observations, 60 of weighted MCPs
    r_tie = ref.obs_r[tie]
    assert np.all((r_tie > 0.0) & (r_tie < 1.0))
    assert np.max(np.abs(fast.obs_r - ref.obs_r)) < tol
    assert np.array_equal(fast.unknown, ref.unknown)
    q = ref.point_cofactor
    scale = np.sqrt(np.einsum("pii,pjj->pij", q, q))
    assert np.max(np.abs(fast.point_cofactor - q) / scale) < max(tol, 1e-8)
    assert fast.total == pytest.approx(stats["dof"], rel=1e-6)


def test_reused_tie_arrays_give_the_same_adjustment(monkeypatch):
    """A retired linearisation's tie arrays serve the next one: the same solution, bit
    for bit, as with fresh arrays for every pass."""
    net = tie_problem(n_tie=120, triple=30, tie_sigma_m=30.0)
    cfg = {**CONFIG, "outliers": {"enabled": False}}
    retired = []
    real = BundleSolver.retire

    def counting(self, lin):
        retired.append(lin.a_t.shape)
        real(self, lin)

    monkeypatch.setattr(BundleSolver, "retire", counting)
    reused = adjust(net, cfg)
    # 270 tie observations and 60 of weighted MCPs (unknowns too).
    assert len(retired) >= 2 and all(s[0] == 330 for s in retired)
    assert reused.rounds[0]["converged"]
    monkeypatch.setattr(BundleSolver, "retire", lambda self, lin: None)
    fresh = adjust(net, cfg)
    assert np.array_equal(reused.x, fresh.x)
    assert np.array_equal(reused.sigma, fresh.sigma)
    assert np.array_equal(reused.point_xyz, fresh.point_xyz)
