"""Stochastic model: redundancy numbers, variance components, datum and estimability."""

from __future__ import annotations

import csv
import logging

import numpy as np
import pytest
from adjust_synth import N_LINES, N_SAMPLES, ground_points, mcp_problem, perturb, true_strip

from planetref.adjust import Network, adjust
from planetref.adjust.diagnostics import SELF_CALIBRATION
from planetref.control.network import enu_rotation
from planetref.report.adjustment import write_outputs

LINEAR = {"solver": {"loss": "linear"}, "outliers": {"enabled": False}}


def _two_strips(n: int, noise_px: float, ground_sigma_m: float, seed: int):
    """Two parallel, overlapping strips seeing the same MCPs (two views per point).

    Image noise ``noise_px`` (each axis), planimetric ground noise ``ground_sigma_m``
    (east and north); heights exact. What makes it easier than reality: the noise is
    Gaussian and white, the camera model is exact, no outliers.
    """
    a = true_strip(lat=20.0, lon=74.0, heading=0.0, name="a")
    # 0.42 km east: about half the swath, so half of each strip overlaps the other.
    b = true_strip(
        lat=20.0,
        lon=74.0 + 420.0 / (3389.5e3 * np.cos(np.radians(20.0))) * 180 / np.pi,
        heading=0.0,
        name="b",
    )
    rng = np.random.default_rng(seed)
    cams = {"a": a, "b": b}
    m = 8 * n
    ccd_a = rng.integers(0, 3, m)
    ln = rng.uniform(50.0, N_LINES - 50.0, m)
    sm = rng.uniform(1.0, N_SAMPLES - 1.0, m)
    xyz = ground_points(a, ccd_a, ln, sm, rng.uniform(-500.0, 500.0, m))
    ccd_b = np.full(m, -1)
    lb, sb = np.full(m, np.nan), np.full(m, np.nan)
    for kb, name in enumerate(b.ccd_names):
        ip = b.ground_to_image(xyz, ccd=name)
        with np.errstate(invalid="ignore"):
            inside = (
                (ccd_b < 0)
                & (ip.line > 1.0)
                & (ip.line < N_LINES - 1.0)
                & (ip.sample > 1.0)
                & (ip.sample < N_SAMPLES - 1.0)
            )
        ccd_b[inside], lb[inside], sb[inside] = kb, ip.line[inside], ip.sample[inside]
    keep = np.flatnonzero(ccd_b >= 0)[:n]
    assert len(keep) == n
    obs_cam, obs_pt, obs_ccd, line, sample = [], [], [], [], []
    xyz_true = {}
    for k, j in enumerate(keep):
        pid = f"p{k}"
        xyz_true[pid] = xyz[j]
        for cam, kk, lv, sv in (("a", ccd_a[j], ln[j], sm[j]), ("b", ccd_b[j], lb[j], sb[j])):
            obs_cam.append(cam)
            obs_pt.append(pid)
            obs_ccd.append(cams[cam].ccd_names[kk])
            line.append(lv + rng.normal(0.0, noise_px))
            sample.append(sv + rng.normal(0.0, noise_px))
    ids = list(xyz_true)
    pts = np.array([xyz_true[p] for p in ids])
    rot = enu_rotation(pts)
    d_enu = np.column_stack([rng.normal(0.0, ground_sigma_m, (len(ids), 2)), np.zeros(len(ids))])
    noisy = pts + np.einsum("pji,pj->pi", rot, d_enu)
    return (
        cams,
        dict(obs_camera=obs_cam, obs_point=obs_pt, obs_ccd=obs_ccd, line=line, sample=sample),
        dict(zip(ids, noisy, strict=True)),
    )


def test_redundancy_numbers_sum_to_the_degrees_of_freedom():
    """sum r_i = n - u (the trace identity) with weighted MCPs, ties and priors."""
    net, _, _ = mcp_problem(200, noise_px=0.5, seed=21, ground_sigma_m=4.0)
    res = adjust(net, {**LINEAR, "variance": {"enabled": False}})
    dof = res.variance["dof"]
    total = dof["redundancy_real"] + dof["redundancy_pseudo"]
    assert total == pytest.approx(res.dof, abs=1e-6)
    # Single-view MCPs: the image measures' redundancy is small (the weighted point
    # absorbs most of its image residual), the ground's large.
    groups = {g["group"]: g for g in res.variance["groups"]}
    img = sum(g["redundancy"] for g in groups.values() if g["kind"] == "image")
    assert img < 0.05 * groups["ground mcp"]["redundancy"]
    assert "confounded" in groups["ground mcp"]["note"]


def test_variance_components_recover_image_and_ground_noise():
    """Known image noise (0.7 px) and MCP ground noise (1.5 m) recovered within 15 %."""
    noise_px, ground_m = 0.7, 1.5
    cams, obs, pts = _two_strips(250, noise_px, ground_m, seed=5)
    init = {
        k: perturb(c, pos_bias=(8.0, -5.0, 3.0), pos_drift=(1.0, 1.0, 0.0)) for k, c in cams.items()
    }
    # Deliberately wrong a-priori sigmas: 1 px and 4 m (height 2 m, not estimable).
    sig = {p: (4.0, 4.0, 2.0) for p in pts}
    net = Network.from_records(
        init,
        **obs,
        point_xyz=pts,
        point_sigma_m=sig,
        point_kind="mcp",
        sigma_px=1.0,
        point_sigma_local=True,
    )
    res = adjust(net, LINEAR)
    groups = {g["group"]: g for g in res.variance["groups"]}
    image = [g for g in groups.values() if g["kind"] == "image" and g["estimated"]]
    assert image, groups
    n = sum(g["n_equations"] for g in image)
    est_px = np.sqrt(sum(g["sigma_px"] ** 2 * g["n_equations"] for g in image) / n)
    est_m = groups["ground mcp planimetric"]["sigma_m"]
    print(f"\nimage {est_px:.3f} px (true {noise_px}), ground {est_m:.3f} m (true {ground_m})")
    assert est_px == pytest.approx(noise_px, rel=0.15)
    assert est_m == pytest.approx(ground_m, rel=0.15)
    assert groups["ground mcp planimetric"]["estimated"]
    assert not groups["ground mcp planimetric"]["note"]  # two views: separable
    assert res.variance["converged"]
    assert res.summary()["sigma0_real"] == pytest.approx(1.0, abs=0.05)


def _focal_problem(pos_sigma_m: float, relief_m: float, seed: int):
    """MCPs of a strip whose focal length is 2000 ppm too long (and node positions off)."""
    true = true_strip()
    f_true = true.interior.focal_length_mm
    init = perturb(true, pos_bias=(2.0, -2.0, 1.0), pos_drift=(0.0, 0.0, 0.0))
    init = init.replace(interior=type(true.interior)(focal_length_mm=f_true * (1 + 2000e-6)))
    rng = np.random.default_rng(seed)
    n = 600
    ccd = rng.integers(0, 3, n)
    line = rng.uniform(1.0, N_LINES - 1.0, n)
    sample = rng.uniform(1.0, N_SAMPLES - 1.0, n)
    xyz = ground_points(true, ccd, line, sample, rng.uniform(-relief_m, relief_m, n))
    net = Network.mcps(
        init,
        line=line + rng.normal(0.0, 0.3, n),
        sample=sample + rng.normal(0.0, 0.3, n),
        xyz=xyz,
        ccd=np.array(init.ccd_names)[ccd],
        sigma_px=0.3,
    )
    cfg = {
        **LINEAR,
        "linescan": {
            "position": {"mode": "weighted", "sigma_m": pos_sigma_m},
            "interior": {
                "mode": "weighted",
                "sigma_principal_point_mm": 0.01,
                "sigma_focal_length_mm": 20.0,
            },
        },
    }
    return net, cfg, f_true


def test_focal_error_recovered_with_a_well_known_orbit():
    """2000 ppm focal error, orbit known to 5 m: f recovered within 25 % of the error."""
    net, cfg, f_true = _focal_problem(5.0, 2000.0, seed=31)
    res = adjust(net, cfg)
    i = res.parameter_names.index("strip:interior.f")
    err0 = res.x0[i] - f_true
    err = res.x[i] - f_true
    print(f"\nf {res.x0[i]:.3f} -> {res.x[i]:.3f} mm (true {f_true}), sigma {res.sigma[i]:.3f}")
    assert abs(err) < 0.25 * abs(err0)
    row = next(r for r in res.diagnostics["self_calibration"] if r["name"].endswith(".f"))
    assert row["separable"], row["verdict"]


def test_poorly_known_orbit_flags_focal_length_not_separable():
    """Node positions known to 2 km only: f trades with the node heights."""
    net, cfg, _ = _focal_problem(2000.0, 20.0, seed=32)
    res = adjust(net, cfg)
    row = next(r for r in res.diagnostics["self_calibration"] if r["name"].endswith(".f"))
    print("\n" + row["verdict"])
    assert not row["separable"]
    assert "NOT separable" in row["verdict"]
    assert any("NOT separable" in w and "interior.f" in w for w in res.warnings)


def test_self_calibration_names():
    for name in ("interior.f", "interior.x0", "interior[ccd1].y0", "focal_m"):
        assert SELF_CALIBRATION.search(name), name
    for name in ("node3.X", "node0.phi", "pointing_omega_m"):
        assert not SELF_CALIBRATION.search(name), name


def test_points_csv_and_movement_warnings(tmp_path, caplog):
    """points.csv lists every point; a tie point placed 1 km off is moved and flagged."""
    true = true_strip()
    init = perturb(true)
    rng = np.random.default_rng(41)
    n_mcp, n_tie = 250, 60
    ccd = rng.integers(0, 3, n_mcp)
    line = rng.uniform(1.0, N_LINES - 1.0, n_mcp)
    sample = rng.uniform(1.0, N_SAMPLES - 1.0, n_mcp)
    mxyz = ground_points(true, ccd, line, sample, rng.uniform(-500, 500, n_mcp))
    # Tie points in the overlap of ccd1 and ccd2.
    tl = rng.uniform(100.0, N_LINES - 100.0, n_tie)
    ts = rng.uniform(N_SAMPLES - 14, N_SAMPLES - 2, n_tie)
    txyz = ground_points(true, np.zeros(n_tie, int), tl, ts, np.zeros(n_tie))
    ip = true.ground_to_image(txyz, ccd="ccd2")
    apriori = txyz.copy()
    apriori[0] += enu_rotation(txyz[:1])[0].T @ np.array([0.0, 0.0, 1000.0])  # 1 km too high
    names = init.ccd_names
    net = Network.from_records(
        {"strip": init},
        obs_camera=["strip"] * (n_mcp + 2 * n_tie),
        obs_point=[f"m{i}" for i in range(n_mcp)] + [f"t{i}" for i in range(n_tie)] * 2,
        obs_ccd=[names[c] for c in ccd] + ["ccd1"] * n_tie + ["ccd2"] * n_tie,
        line=np.concatenate([line, tl, ip.line]),
        sample=np.concatenate([sample, ts, ip.sample]),
        point_xyz={
            **{f"m{i}": mxyz[i] for i in range(n_mcp)},
            **{f"t{i}": apriori[i] for i in range(n_tie)},
        },
        point_sigma_m={
            **{f"m{i}": 0.0 for i in range(n_mcp)},
            **{f"t{i}": 200.0 for i in range(n_tie)},
        },
        point_kind={
            **{f"m{i}": "mcp" for i in range(n_mcp)},
            **{f"t{i}": "tie" for i in range(n_tie)},
        },
        sigma_px=0.3,
    )
    with caplog.at_level(logging.INFO, logger="planetref"):
        res = adjust(net, LINEAR)
    written = write_outputs(res, tmp_path, rpc=False, plots=False)
    with open(written["points"]) as fh:
        rows = {r["point_id"]: r for r in csv.DictReader(fh)}
    assert len(rows) == n_mcp + n_tie
    t0 = rows["t0"]
    # The rays (a weak stereo base: two CCDs 1 mm apart along track) pull it most of
    # the way back down, more than 3 sigma of its 200 m prior.
    up = float(t0["shift_up_m"])
    assert -1000.0 < up < -700.0
    assert float(t0["shift_sigma"]) > 3.0
    assert float(t0["shift_m"]) == pytest.approx(abs(up), rel=0.02)
    assert float(t0["height_m"]) == pytest.approx(float(t0["apriori_height_m"]) + up, abs=0.5)
    assert float(rows["m0"]["shift_m"]) == 0.0
    assert any("moved more than 3 sigma" in w and "t0" in w for w in res.warnings)
    # The others barely move: their a-priori coordinates are the truth.
    others = [float(rows[f"t{i}"]["shift_m"]) for i in range(1, n_tie)]
    assert np.median(others) < 2.0
    assert float(t0["sigma_up_m"]) > 0
    cams = res.diagnostics["camera_shifts"]["strip"]
    assert cams["max_m"] > 30.0  # the perturbation (30/-20/10 m bias) was taken out
    assert any("camera footprint" in w for w in res.warnings) == (cams["max_m"] > 100.0)

    # One blunder among 180 weighted axes is more than chance gives (~0.5): a WARNING
    # the user acts on; a footprint moving is what the adjustment did: a note (INFO).
    def levels(text):
        return [r.levelno for r in caplog.records if text in r.getMessage()]

    assert levels("weighted point(s) moved more than") == [logging.WARNING]
    moved = [logging.INFO] if cams["max_m"] > 100.0 else []
    assert levels("camera footprint(s) moved") == moved


def test_per_axis_metrics_hand_computed():
    from planetref.adjust.metrics import reprojection_metrics

    m = reprojection_metrics([3.0, -1.0, 50.0], [4.0, 1.0, 0.0], [True, True, False])
    assert m["rmse_x_px"] == pytest.approx(np.sqrt(5.0))
    assert m["rmse_y_px"] == pytest.approx(np.sqrt(8.5))
    assert m["rmse_px"] == pytest.approx(np.sqrt(27.0 / 2.0))
    assert m["mean_x_px"] == pytest.approx(1.0) and m["mean_y_px"] == pytest.approx(2.5)
    assert m["outlier_ratio_pct"] == pytest.approx(100.0 / 3.0)


def test_mcp_weight_share_keeps_the_mcps_own_sigma():
    """MCPs adjusted with a quarter of their weight: VCE still finds their own noise.

    ``mcps_by_overlap(net, 4)`` doubles the MCPs' sigmas (four overlapping templates are
    one measurement) and ``variance.mcp_weight_share = 0.25`` keeps that share through
    the re-weighting: the groups' sigmas come out at twice the true noise (0.7 px, 1.5 m),
    i.e. the noise itself at the share's weight.
    """
    from planetref.adjust.jitter import mcps_by_overlap

    noise_px, ground_m = 0.7, 1.5
    cams, obs, pts = _two_strips(250, noise_px, ground_m, seed=5)
    init = {
        k: perturb(c, pos_bias=(8.0, -5.0, 3.0), pos_drift=(1.0, 1.0, 0.0)) for k, c in cams.items()
    }
    sig = {p: (4.0, 4.0, 2.0) for p in pts}
    net = Network.from_records(
        init,
        **obs,
        point_xyz=pts,
        point_sigma_m=sig,
        point_kind="mcp",
        sigma_px=1.0,
        point_sigma_local=True,
    )
    scaled = mcps_by_overlap(net, 4.0)
    np.testing.assert_allclose(scaled.obs_sigma_px, 2.0)
    np.testing.assert_allclose(scaled.point_sigma_m, np.tile([8.0, 8.0, 4.0], (net.n_points, 1)))
    assert mcps_by_overlap(net, 1.0) is net
    res = adjust(scaled, {**LINEAR, "variance": {"mcp_weight_share": 0.25}})
    groups = {g["group"]: g for g in res.variance["groups"]}
    image = [g for g in groups.values() if g["kind"] == "image" and g["estimated"]]
    n = sum(g["n_equations"] for g in image)
    est_px = np.sqrt(sum(g["sigma_px"] ** 2 * g["n_equations"] for g in image) / n)
    est_m = groups["ground mcp planimetric"]["sigma_m"]
    assert 0.5 * est_px == pytest.approx(noise_px, rel=0.15)
    assert 0.5 * est_m == pytest.approx(ground_m, rel=0.15)
    assert res.variance["converged"]
    # Ordinary VCE on the scaled network would undo the share: sigmas back at the noise.
    plain = adjust(scaled, LINEAR)
    g1 = {g["group"]: g for g in plain.variance["groups"]}
    assert g1["ground mcp planimetric"]["sigma_m"] == pytest.approx(ground_m, rel=0.15)
