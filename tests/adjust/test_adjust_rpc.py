"""RPC images in the bundle adjustment: partials, recovery of known biases, CLI outputs."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from adjust_synth import N_LINES, N_SAMPLES, ground_points, perturb, true_strip
from click.testing import CliRunner

from planetref.adjust import Network, adjust
from planetref.adjust.metrics import geolocation_error
from planetref.adjust.models import parameterize
from planetref.adjust.models.rpc import RpcParameterization
from planetref.adjust.rpc_config import RpcParameters
from planetref.camera.rpc import EARTH_BODY, MARS_BODY, RpcCamera, fit_rpc, read_rpc, write_rpc
from planetref.camera.rpc.bias import BIAS_TERMS, BiasedRpcCamera, RpcBias
from planetref.camera.rpc.strip import RpcStripCamera, write_refined_rpcs
from planetref.cli.adjust import adjust_command
from planetref.errors import AdjustmentError, InputError

HEIGHTS = (-3000.0, 3000.0)
TRUE_BIAS = (2.5, -1.75, 1.2, -0.8, 0.6, 0.9)
HEADER = "point_id point_type apriori_x_m apriori_y_m apriori_z_m image_id sample line".split()


@pytest.fixture(scope="module")
def strips():
    """The true strip, a perturbed one (~50 m off) and RPCs fitted to the perturbed CCDs."""
    true = true_strip()
    init = perturb(true)
    rpcs = {}
    for ccd in init.ccd_names:
        rpc, rep = fit_rpc(init, height_range_m=HEIGHTS, ccd=ccd, grid=(15, 11, 5))
        assert rep.check_max_px < 1e-3
        rpcs[ccd] = RpcCamera(rpc, init.ellipsoid, init.latitude_kind, (N_LINES, N_SAMPLES), ccd)
    return true, init, rpcs


@pytest.mark.parametrize("bias", ["shift", "shift+drift", "affine"])
def test_partials_match_finite_differences(strips, bias):
    _, _, rpcs = strips
    cam = rpcs["ccd2"]
    start = BiasedRpcCamera(cam, RpcBias(cam.image_size(), (0.5, -0.3, 0.2, 0.1, -0.4, 0.3)))
    par = parameterize("c", start, validate({"rpc": {"bias": bias}}))
    assert isinstance(par, RpcParameterization)
    n = {"shift": 2, "shift+drift": 4, "affine": 6}[bias]
    assert par.names == BIAS_TERMS[:n] and par.units == ("px",) * n
    assert np.all(par.mode == 0) and par.pattern_columns.shape == (1, n)
    rng = np.random.default_rng(0)
    line, sample = rng.uniform(0, N_LINES, 25), rng.uniform(0, N_SAMPLES, 25)
    xyz = ground_points(strips[1], np.ones(25, int), line, sample, rng.uniform(-2000, 2000, 25))
    x = par.x0 + rng.normal(0, 2.0, n)
    ev = par.evaluate(x, xyz, 0, line)
    assert ev.valid.all() and ev.d_params.shape == (25, 2, n)
    for j in range(n):
        step = np.zeros(n)
        step[j] = 1e-3
        hi = par.evaluate(x + step, xyz, 0, line, partials=False)
        lo = par.evaluate(x - step, xyz, 0, line, partials=False)
        fd = np.stack([hi.line - lo.line, hi.sample - lo.sample], 1) / 2e-3
        np.testing.assert_allclose(ev.d_params[:, :, j], fd, atol=1e-8)
    for k in range(3):
        e = np.zeros(3)
        e[k] = 0.5
        hi = par.evaluate(x, xyz + e, 0, line, partials=False)
        lo = par.evaluate(x, xyz - e, 0, line, partials=False)
        fd = np.stack([hi.line - lo.line, hi.sample - lo.sample], 1) / 1.0
        # ~0.2 px per metre (5 m pixels at 400 km... here ~2 px/m): 1e-7 relative.
        np.testing.assert_allclose(ev.d_ground[:, :, k], fd, atol=1e-7 * np.abs(fd).max())
    # The built camera projects as the evaluation does.
    ip = par.build(x).ground_to_image(xyz)
    np.testing.assert_allclose(ip.line, ev.line, atol=1e-9)
    np.testing.assert_allclose(ip.sample, ev.sample, atol=1e-9)


def validate(cfg):
    from planetref.adjust.config import validate_config

    return validate_config(cfg)


def test_known_affine_bias_recovered_from_mcps_and_tie_points(strips):
    """Three RPC images, biased by known affine terms: MCPs and CCD-overlap tie points."""
    _, init, rpcs = strips
    truth = {c: BiasedRpcCamera(r, RpcBias(r.image_size(), TRUE_BIAS)) for c, r in rpcs.items()}
    rng = np.random.default_rng(4)
    cams, pts, line, sample, xyz, kind = [], [], [], [], {}, {}
    for k, ccd in enumerate(init.ccd_names):
        ln, sm = rng.uniform(0, N_LINES, 80), rng.uniform(0, N_SAMPLES, 80)
        g = truth[ccd].image_to_ground(ln, sm, 500.0)
        for i in range(80):
            pid = f"m{k}_{i}"
            cams.append(ccd), pts.append(pid), line.append(ln[i]), sample.append(sm[i])
            xyz[pid], kind[pid] = g[i], "mcp"
    # Tie points in the 16-px overlaps of neighbouring CCDs (unknown ground).
    for a, b in (("ccd1", "ccd2"), ("ccd2", "ccd3")):
        ln = rng.uniform(100, N_LINES - 100, 30)
        g = truth[a].image_to_ground(ln, np.full(30, N_SAMPLES - 6.0), 200.0)
        ip = truth[b].ground_to_image(g)
        assert np.all(ip.in_image)
        for i in range(30):
            pid = f"t{a}{b}_{i}"
            for ccd, (lv, sv) in ((a, (ln[i], N_SAMPLES - 6.0)), (b, (ip.line[i], ip.sample[i]))):
                cams.append(ccd), pts.append(pid), line.append(lv), sample.append(sv)
            xyz[pid], kind[pid] = g[i] + rng.normal(0, 20.0, 3), "tie"
    net = Network.from_records(
        rpcs,
        obs_camera=cams,
        obs_point=pts,
        line=np.asarray(line),
        sample=np.asarray(sample),
        point_xyz=xyz,
        point_sigma_m={p: (0.0 if kind[p] == "mcp" else 200.0) for p in xyz},
        point_kind=kind,
        sigma_px=0.3,
    )
    r = adjust(net, {"rpc": {"bias": "affine"}, "outliers": {"enabled": False}})
    assert r.converged
    got = np.asarray(r.x).reshape(3, 6)
    # Noise-free image measures; the tie points' a-priori coordinates (20 m off, weighted
    # with 200 m) pull the solution by a few 1e-5 px.
    print(got - TRUE_BIAS)
    np.testing.assert_allclose(got, np.tile(TRUE_BIAS, (3, 1)), atol=5e-4)
    assert r.summary()["rmse_px"] < 1e-3 < 1.0 < r.summary()["rmse_px_before"]
    for ccd in init.ccd_names:
        err = geolocation_error(r.cameras[ccd], truth[ccd], terrain=0.0)
        assert err["max_px"] < 1e-3
    # The physical block states the bias model.
    assert r.models[0].physical(r.x[:6])["bias_model"] == "affine"


def test_shift_model_with_too_few_observations_is_an_error(strips):
    _, _, rpcs = strips
    cam = rpcs["ccd1"]
    g = cam.image_to_ground([100.0], [100.0], 0.0)
    net = Network.mcps(cam, line=[100.0], sample=[100.0], xyz=g, camera_id="one")
    with pytest.raises(AdjustmentError, match="cannot determine its 6 bias"):
        adjust(net, {"rpc": {"bias": "affine"}})
    with pytest.raises(InputError, match="needs sigma_px"):
        validate({"rpc": {"mode": "weighted"}})
    with pytest.raises(InputError):
        validate({"rpc": {"bias": "quadratic"}})
    weighted = RpcParameterization("w", cam, RpcParameters(mode="weighted", sigma_px=3.0))
    assert np.all(weighted.sigma == 3.0) and np.all(weighted.mode == 1)


def test_cli_adjusts_rpc_images_and_writes_refined_rpcs(strips, tmp_path):
    true, init, rpcs = strips
    files = {}
    for ccd, cam in rpcs.items():
        files[ccd] = write_rpc(cam.rpc, tmp_path / f"{ccd}.RPB", body=MARS_BODY)
    before = {c: p.read_bytes() for c, p in files.items()}
    rng = np.random.default_rng(7)
    rows = []
    for k, ccd in enumerate(init.ccd_names):
        ln, sm = rng.uniform(0, N_LINES, 60), rng.uniform(0, N_SAMPLES, 60)
        g = ground_points(true, np.full(60, k), ln, sm, rng.uniform(-1500, 1500, 60))
        for i in range(60):
            ln_obs, sm_obs = ln[i] + rng.normal(0, 0.3), sm[i] + rng.normal(0, 0.3)
            rows.append([f"m{k}_{i}", "Fixed", *g[i], f"img/{ccd}", sm_obs, ln_obs])
    with open(tmp_path / "measures.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(HEADER)
        w.writerows(rows)
    (tmp_path / "network.toml").write_text(
        'measures = "measures.csv"\nconvention = "csm"\n[images]\n'
        + "".join(f'"img/{c}" = "{c}.RPB"\n' for c in files)
    )
    out = tmp_path / "out"
    r = CliRunner().invoke(
        adjust_command,
        [
            str(tmp_path / "network.toml"),
            "--out",
            str(out),
            "--rpc-bias",
            "shift+drift",
            "--no-plots",
        ],
        obj={"quiet": True},
        catch_exceptions=False,
    )
    assert r.exit_code == 0, r.output
    report = json.loads((out / "report.json").read_text())
    assert report["config"]["rpc"]["bias"] == "shift+drift"
    adj = report["adjustment"]
    print("RMSE px", adj["rmse_px_before"], "->", adj["rmse_px"])
    assert adj["rmse_px"] < 0.5 and adj["rmse_px_before"] > 5.0
    for ccd in files:
        cid = f"img/{ccd}"
        fit = report["rpc_fits"][cid][ccd]
        assert fit["bias_model"] == "shift+drift" and fit["method"] == "refit"
        assert fit["check_max_px"] < 0.01
        assert report["corrections_physical"][cid]["bias_model"] == "shift+drift"
        refined = out / "cameras" / f"img_{ccd}.RPB"
        assert refined.is_file()
        # The refined RPC reproduces the adjusted camera (read back in the same format).
        cam = RpcCamera.from_file(refined, image_size=(N_LINES, N_SAMPLES))
        ln, sm = _grid()
        d = cam.image_to_ground(ln, sm, 0.0) - true.image_to_ground(ln, sm, 0.0, ccd=ccd)
        rms_m = float(np.sqrt(np.mean(np.sum(d**2, axis=1))))
        print(ccd, "true error m", rms_m)
        assert rms_m < 2.0
        assert read_rpc(files[ccd]) == rpcs[ccd].rpc and files[ccd].read_bytes() == before[ccd]
    assert "bias model 'shift+drift'" in (out / "report.md").read_text()


def _grid():
    ll, ss = np.meshgrid(np.linspace(1, N_LINES - 1, 9), np.linspace(1, N_SAMPLES - 1, 5))
    return ll.ravel(), ss.ravel()


def test_rpc_strip_gets_one_bias_per_ccd(strips, tmp_path):
    """A strip of three RPC images (one per CCD): per-CCD patterns, partials, recovery."""
    rpcs = strips[2]
    strip = RpcStripCamera(rpcs)
    par = parameterize("strip", strip, validate({"rpc": {"bias": "shift+drift"}}))
    assert par.names[:4] == tuple(f"ccd1.{t}" for t in BIAS_TERMS[:4]) and len(par.names) == 12
    np.testing.assert_array_equal(par.pattern_columns, np.arange(12).reshape(3, 4))
    rng = np.random.default_rng(5)
    ln, sm = rng.uniform(0, N_LINES, 10), rng.uniform(0, N_SAMPLES, 10)
    xyz = rpcs["ccd3"].image_to_ground(ln, sm, 300.0)
    x = rng.normal(0, 2.0, 12)
    ev = par.evaluate(x, xyz, 2, ln)
    assert np.all(ev.pattern == 2)
    for j in range(4):
        step = np.zeros(12)
        step[8 + j] = 1e-3
        hi = par.evaluate(x + step, xyz, 2, ln, partials=False)
        lo = par.evaluate(x - step, xyz, 2, ln, partials=False)
        fd = np.stack([hi.line - lo.line, hi.sample - lo.sample], 1) / 2e-3
        np.testing.assert_allclose(ev.d_params[:, :, j], fd, atol=1e-8)
    # Known per-CCD biases come back from MCPs.
    true_bias = {c: (1.0 + k, -0.5 * k, 0.3 * k, 0.7, 0.0, 0.0) for k, c in enumerate(rpcs)}
    truth = RpcStripCamera(
        {c: BiasedRpcCamera(r, RpcBias(r.image_size(), true_bias[c])) for c, r in rpcs.items()}
    )
    lines, samples, ccds, ground = [], [], [], []
    for c in rpcs:
        ln, sm = rng.uniform(0, N_LINES, 30), rng.uniform(0, N_SAMPLES, 30)
        lines.append(ln), samples.append(sm), ccds.append([c] * 30)
        ground.append(truth.image_to_ground(ln, sm, 100.0, ccd=c))
    net = Network.mcps(
        strip,
        line=np.concatenate(lines),
        sample=np.concatenate(samples),
        xyz=np.concatenate(ground),
        ccd=np.concatenate(ccds),
    )
    r = adjust(net, {"rpc": {"bias": "shift+drift"}})
    got = np.asarray(r.x).reshape(3, 4)
    np.testing.assert_allclose(got, [true_bias[c][:4] for c in rpcs], atol=1e-6)
    assert isinstance(r.cameras["strip"], RpcStripCamera)
    # Refined RPCs, one per CCD (no input file: _RPC.TXT), exact to the corrected camera.
    paths, reports = write_refined_rpcs(r.cameras["strip"], tmp_path, "strip")
    assert sorted(p.name for p in paths) == [f"strip_ccd{k}_RPC.TXT" for k in (1, 2, 3)]
    assert all(rep["check_max_px"] < 0.01 for rep in reports.values())
    # Too few observations of one CCD name that CCD.
    few = Network.mcps(
        strip, line=lines[0][:2], sample=samples[0][:2], xyz=ground[0][:2], ccd=["ccd1"] * 2
    )
    with pytest.raises(AdjustmentError, match="CCD ccd1: 2 observation"):
        adjust(few, {"rpc": {"bias": "shift+drift"}})
    with pytest.raises(InputError, match="share a body"):
        earth = write_rpc(rpcs["ccd2"].rpc, tmp_path / "earth.RPB", body=EARTH_BODY)
        RpcStripCamera({"a": rpcs["ccd1"], "b": RpcCamera.from_file(earth, image_size=(9, 9))})
