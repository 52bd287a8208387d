import numpy as np
import pytest
from adjust_synth import (
    N_LINES,
    N_SAMPLES,
    ground_points,
    mcp_problem,
    perturb,
    shared_data,
    true_strip,
)

from planetref.adjust import adjust
from planetref.adjust.config import CsmParameters, LineScanParameters
from planetref.adjust.models import CsmParameterization, LineScanParameterization
from planetref.camera.linescan import InteriorOrientation
from planetref.errors import InputError


@pytest.fixture(scope="module")
def cam():
    c = perturb(true_strip())
    return c.replace(interior=InteriorOrientation(4640.0, 0.3, -0.2))


def dense(par, ev):
    """The evaluation's partials scattered into (m, 2, n_params)."""
    m = len(ev.line)
    out = np.zeros((m, 2, len(par.x0) + 1))
    cols = np.where(
        par.pattern_columns[ev.pattern] >= 0, par.pattern_columns[ev.pattern], len(par.x0)
    )
    for r in range(2):
        np.add.at(out[:, r], (np.arange(m)[:, None], cols), ev.d_params[:, r])
    return out[:, :, :-1]


@pytest.mark.parametrize("ccd", [0, 2])
@pytest.mark.parametrize("guess_offset", [0.0, 25.0])
def test_linescan_kernel_matches_image_partials(cam, ccd, guess_offset):
    par = LineScanParameterization("s", cam, LineScanParameters())
    rng = np.random.default_rng(ccd)
    n = 400
    line, sample = rng.uniform(0, N_LINES, n), rng.uniform(0, N_SAMPLES, n)
    xyz = ground_points(cam, np.full(n, ccd), line, sample, rng.uniform(-3000, 3000, n))
    name = cam.ccds[ccd].name
    ref = cam.image_partials(xyz, ccd=name, line_guess=line)
    ev = par.evaluate(par.x0, xyz, ccd, line + rng.normal(0, guess_offset, n))
    assert ev.valid.all()
    assert np.abs(ev.line - line).max() < 1e-7
    assert np.abs(ev.sample - sample).max() < 1e-7
    d = dense(par, ev)
    ref_nodes = ref.dense_nodes(cam.n_nodes)
    scale = np.abs(ref_nodes).max(axis=(0, 1)) + 1e-300
    assert (np.abs(d[:, :, : 6 * cam.n_nodes] - ref_nodes) / scale).max() < 1e-7
    np.testing.assert_allclose(
        d[:, :, 6 * cam.n_nodes :],
        ref.d_interior,
        rtol=1e-7,
        atol=1e-7 * np.abs(ref.d_interior).max(),
    )
    np.testing.assert_allclose(
        ev.d_ground, ref.d_ground, rtol=1e-7, atol=1e-7 * np.abs(ref.d_ground).max()
    )
    # Projection only gives the same coordinates.
    ev2 = par.evaluate(par.x0, xyz, ccd, line, partials=False)
    assert np.abs(ev2.line - ev.line).max() < 1e-8 and np.abs(ev2.sample - ev.sample).max() < 1e-8


def test_linescan_names_modes_and_build(cam):
    cfg = LineScanParameters(
        position={"mode": "weighted", "sigma_m": 10.0},
        attitude={"mode": "free"},
        interior={
            "mode": "weighted",
            "scope": "ccd",
            "sigma_principal_point_mm": 0.01,
            "sigma_focal_length_mm": 2.0,
        },
    )
    par = LineScanParameterization("s", cam, cfg)
    n = cam.n_nodes
    assert len(par.x0) == 6 * n + 9
    assert par.names[0] == "node0.X" and par.names[5] == "node0.kappa"
    assert par.names[6 * n] == "interior[ccd1].x0" and par.units[6 * n + 2] == "mm"
    assert np.all(par.sigma[: 6 * n : 6] == 10.0) and np.all(par.mode[3 : 6 * n : 6] == 0)
    assert par.sigma[6 * n + 2] == 2.0
    built = par.build(par.x0)
    np.testing.assert_array_equal(built.nodes, cam.nodes)
    for a, b in zip(built.ccds, cam.ccds, strict=True):
        assert a.x_mm == pytest.approx(b.x_mm) and a.pixel_pitch_mm == pytest.approx(
            b.pixel_pitch_mm
        )
    fixed = LineScanParameterization("s", cam, cfg, fixed=True)
    assert np.all(fixed.mode == 2)


def test_coverage_flags_unobserved_nodes(cam):
    par = LineScanParameterization("s", cam, LineScanParameters(min_obs_per_node=5))
    line = np.linspace(10, N_LINES / 2, 200)  # nodes at lines -64, 562, ..., 2438, 3064
    issues = par.coverage(np.zeros(200, np.intp), line)
    # An observation counts for its nearest node only: node 3 (line 1812) has every
    # observation (up to line 1500) half a spacing or more away, nearer to node 2.
    assert [i.label.split()[1] for i in issues] == ["3", "4", "5"]
    assert issues[0].indices == tuple(range(18, 24)) and issues[0].count == 0
    # One observation just past the midpoint (line 1500) makes it count 1.
    more = np.append(line, 1502.0)
    issues = par.coverage(np.zeros(201, np.intp), more)
    assert issues[0].label.split()[1] == "3" and issues[0].count == 1


@pytest.mark.parametrize("how", ["weight", "smooth"])
def test_weaken_returns_a_new_model_and_leaves_this_one(cam, how):
    cfg = LineScanParameters(min_obs_per_node=5, weak_nodes=how)
    par = LineScanParameterization("s", cam, cfg)
    mode0, sigma0 = par.mode.copy(), par.sigma.copy()
    issues = par.coverage(np.zeros(200, np.intp), np.linspace(10, N_LINES / 2, 200))
    new, messages = par.weaken(issues)
    assert new is not par and messages and "weak node" in messages[0]
    # The original parameterisation is untouched.
    np.testing.assert_array_equal(par.mode, mode0)
    np.testing.assert_array_equal(par.sigma, sigma0)
    assert par.constraints is None
    weak = [j for i in issues for j in i.indices if mode0[j] != 2]
    assert len(weak) == 18  # nodes 3, 4, 5 x 6 parameters
    if how == "weight":
        assert np.all(new.mode[weak] == 1)
        pos = [j for j in weak if j % 6 < 3]
        att = [j for j in weak if j % 6 >= 3]
        np.testing.assert_array_equal(new.sigma[pos], cfg.weak_node_position_sigma_m)
        np.testing.assert_array_equal(new.sigma[att], cfg.weak_node_attitude_sigma_rad)
        assert new.constraints is None
    else:
        np.testing.assert_array_equal(new.mode, mode0)
        a, w = new.constraints
        assert a.shape == (18, len(par.x0)) and w.shape == (18,)
        # Node 5's X position: d5 - 2 d4 + d3 = 0 (towards the middle of the strip).
        row = a[np.flatnonzero(a[:, 30])[0]]
        assert (row[30], row[24], row[18]) == (1.0, -2.0, 1.0)
        assert np.count_nonzero(row) == 3
        np.testing.assert_allclose(w[0], 1.0 / cfg.weak_node_smooth_sigma_m**2)
    # No issues: the same model, no messages.
    assert par.weaken([]) == (par, [])


def test_csm_parameterization_on_a_real_isd():
    data = shared_data()
    pytest.importorskip("planetref.camera.csm", reason="the CSM camera module is missing")
    from planetref.camera.csm import CsmCorrection, CsmLineScanCamera

    cam = CsmLineScanCamera.from_file(data / "ctx_syrtis" / "P15_006844_2009_XN_20N286W.lev1.json")
    n_lines, n_samples = cam.image_size()
    rng = np.random.default_rng(0)
    line, sample = rng.uniform(0, n_lines, 60), rng.uniform(0, n_samples, 60)
    xyz = cam.image_to_ground(line, sample, -1500.0)
    par = CsmParameterization("ctx", cam, CsmParameters())
    assert par.names == (
        "omega_m",
        "phi_m",
        "kappa_m",
        "omega_rate_m",
        "phi_rate_m",
        "kappa_rate_m",
    )
    # Physical sigmas become usgscsm's metre units with the camera's scale factors.
    assert par.sigma[0] == pytest.approx(1e-3 * cam.flying_height_m)
    assert par.sigma[5] == pytest.approx(1e-4 * cam.half_swath_m * cam.half_time_s)
    x = np.array([30.0, -10.0, 2.0, 300.0, 50.0, -5.0])
    ev = par.evaluate(x, xyz, 0, line)
    ip = par.build(x).ground_to_image(xyz)
    np.testing.assert_allclose(ev.line, ip.line, atol=1e-9)
    # Central differences agree with a smaller step (the model is nearly linear).
    fine = CsmParameterization("ctx", cam, CsmParameters(fd_step_m=0.1, fd_ground_step_m=0.1))
    ev2 = fine.evaluate(x, xyz, 0, line)
    np.testing.assert_allclose(
        ev.d_params, ev2.d_params, rtol=1e-5, atol=1e-6 * np.abs(ev.d_params).max()
    )
    np.testing.assert_allclose(
        ev.d_ground, ev2.d_ground, rtol=1e-5, atol=1e-6 * np.abs(ev.d_ground).max()
    )
    # The implicit partials agree with central differences of full ground_to_image
    # solves (an independent route: each perturbed camera's own secant search).
    h = 0.1
    ref = np.zeros((60, 2, 6))
    for j in range(6):
        step = np.zeros(6)
        step[j] = h
        a, b = par.build(x + step).ground_to_image(xyz), par.build(x - step).ground_to_image(xyz)
        ref[:, 0, j], ref[:, 1, j] = (a.line - b.line) / (2 * h), (a.sample - b.sample) / (2 * h)
    cam_x = par.build(x)
    ref_g = np.zeros((60, 2, 3))
    for k in range(3):
        a, b = (
            cam_x.ground_to_image(xyz + h * np.eye(3)[k]),
            cam_x.ground_to_image(xyz - h * np.eye(3)[k]),
        )
        ref_g[:, 0, k], ref_g[:, 1, k] = (
            (a.line - b.line) / (2 * h),
            (a.sample - b.sample) / (2 * h),
        )
    assert np.all(ev.valid) and np.abs(ref).max() > 0.3 and np.abs(ref_g).max() > 0.15
    np.testing.assert_allclose(ev.d_params, ref, rtol=0, atol=1e-8)  # px per usgscsm m
    np.testing.assert_allclose(ev.d_ground, ref_g, rtol=0, atol=1e-8)  # px per m
    phys = par.physical(x)
    assert phys["omega_rad"] == pytest.approx(30.0 / cam.flying_height_m)
    assert phys["kappa_rate_rad_s"] == pytest.approx(-5.0 / (cam.half_swath_m * cam.half_time_s))
    full = np.zeros(16)
    full[[6, 7, 8, 9, 10, 11]] = x
    assert par.build(x).correction == CsmCorrection.from_array(full)


PLACEMENT = {"mode": "weighted", "sigma_offset_mm": 0.05, "sigma_angle_rad": 1e-2}


def test_ccd_placement_parameters_and_finite_differences(cam):
    cfg = LineScanParameters(ccd_placement={**PLACEMENT, "reference_ccd": "ccd2"})
    par = LineScanParameterization("s", cam, cfg)
    n = cam.n_nodes
    assert len(par.x0) == 6 * n + 3 + 9
    assert par.names[6 * n + 3] == "ccd[ccd1].x_mm" and par.units[-1] == "rad"
    # The reference CCD is held; the others are weighted with the configured sigmas.
    assert par.mode[6 * n + 6 : 6 * n + 9].tolist() == [2, 2, 2]
    assert par.sigma[6 * n + 3] == 0.05 and par.sigma[-1] == 1e-2
    assert par.pattern_columns.shape[1] == 6 * 4 + 6
    rng = np.random.default_rng(7)
    m = 60
    line, sample = rng.uniform(0, N_LINES, m), rng.uniform(0, N_SAMPLES, m)
    for ccd in (0, 2):
        xyz = ground_points(cam, np.full(m, ccd), line, sample, rng.uniform(-2000, 2000, m))
        ev = par.evaluate(par.x0, xyz, ccd, line)
        d = dense(par, ev)
        base = 6 * n + 3 + 3 * ccd
        for j, h in zip(range(base, base + 3), (1e-4, 1e-4, 1e-6), strict=True):
            xp, xm = par.x0.copy(), par.x0.copy()
            xp[j] += h
            xm[j] -= h
            a = par.build(xp).ground_to_image(xyz, ccd=cam.ccds[ccd].name)
            b = par.build(xm).ground_to_image(xyz, ccd=cam.ccds[ccd].name)
            fd = np.stack([a.line - b.line, a.sample - b.sample], axis=1) / (2 * h)
            assert np.abs(fd).max() > 1e-3, par.names[j]  # the parameter matters
            assert np.abs(fd - d[:, :, j]).max() < 1e-5 * np.abs(fd).max(), par.names[j]
        # Placements of the other CCDs do not touch this CCD's observations.
        other = [j for j in range(6 * n + 3, len(par.x0)) if (j - 6 * n - 3) // 3 != ccd]
        assert np.all(d[:, :, other] == 0.0)
    with pytest.raises(InputError, match="reference_ccd"):
        LineScanParameterization(
            "s", cam, LineScanParameters(ccd_placement={**PLACEMENT, "reference_ccd": "x"})
        )


def test_ccd_placement_recovered_by_the_adjustment():
    true = true_strip()
    cfg = LineScanParameters(ccd_placement={**PLACEMENT, "reference_ccd": "ccd2"})
    par = LineScanParameterization("s", true, cfg)
    x_true = par.x0.copy()
    n = true.n_nodes
    shift = np.array([[0.004, -0.006, 1e-3], [0.0, 0.0, 0.0], [-0.003, 0.005, -1.5e-3]])
    x_true[6 * n + 3 :] += shift.ravel()
    moved = par.build(x_true)
    net, _, _ = mcp_problem(1500, seed=4, true=moved, init=true, noise_px=0.1)
    res = adjust(
        net,
        {
            "linescan": {
                "position": {"mode": "fixed"},
                "attitude": {"mode": "fixed"},
                "ccd_placement": {**PLACEMENT, "reference_ccd": "ccd2"},
            },
            "solver": {"loss": "linear"},
            "outliers": {"enabled": False},
        },
    )
    est = res.x[6 * n + 3 :].reshape(3, 3) - par.x0[6 * n + 3 :].reshape(3, 3)
    sig = res.sigma[6 * n + 3 :].reshape(3, 3)
    # Recovered to within 4 sigma, and the sigmas are far below the shifts.
    for i in (0, 2):
        assert np.all(np.abs(est[i] - shift[i]) < 4 * sig[i])
        assert np.all(sig[i] < 0.1 * np.abs(shift[i]))
    assert np.all(est[1] == 0.0)
    ip = res.cameras["strip"].ground_to_image(net.point_xyz[:5], ccd="ccd3")
    assert np.all(np.isfinite(ip.line))
