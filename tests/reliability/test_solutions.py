"""No degenerate solution written, no observation counted twice (issue 35, group 2).

RPC-only adjust with collinear MCPs reported "converged" and wrote an RPC whose line
numerator was all zeros; a duplicated measure row was accepted with double weight.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from reliability_helpers import REPO, SHARED, one_line_error, run_cli

from planetref.adjust import Network, adjust
from planetref.errors import AdjustmentError, InputError

sys.path.insert(0, str(REPO / "tests" / "adjust"))
from adjust_synth import N_LINES, N_SAMPLES, perturb, true_strip


@pytest.fixture(scope="module")
def rpc_camera():
    from planetref.camera.rpc import RpcCamera, fit_rpc

    init = perturb(true_strip())
    rpc, rep = fit_rpc(init, height_range_m=(-3000.0, 3000.0), ccd="ccd1", grid=(15, 11, 5))
    assert rep.check_max_px < 1e-3
    return RpcCamera(rpc, init.ellipsoid, init.latitude_kind, (N_LINES, N_SAMPLES), "ccd1")


def _mcps(cam, line: np.ndarray, sample: np.ndarray) -> Network:
    g = cam.image_to_ground(line, sample, 0.0)
    return Network.mcps(cam, line=line, sample=sample, xyz=g, camera_id="one")


@pytest.mark.parametrize(
    ("bias", "where"),
    [
        ("affine", "diagonal"),  # [1, u, v] of rank 2
        ("affine", "one line"),
        ("shift+drift", "one line"),  # [1, u] of rank 1
    ],
)
def test_collinear_mcps_are_refused(rpc_camera, bias: str, where: str) -> None:
    # planetref adjust network.toml --out run, rpc.bias = BIAS, MCPs on a straight line
    t = np.linspace(0.1, 0.9, 40)
    if where == "diagonal":
        line, sample = t * N_LINES, t * N_SAMPLES
    else:
        line, sample = np.full(40, 0.5 * N_LINES), t * N_SAMPLES
    net = _mcps(rpc_camera, line, sample)
    with pytest.raises(AdjustmentError, match=r"degenerate \(collinear .*rank [0-9] of"):
        adjust(net, {"rpc": {"bias": bias}, "outliers": {"enabled": False}})


def test_well_spread_or_weighted_mcps_still_adjust(rpc_camera) -> None:
    rng = np.random.default_rng(0)
    net = _mcps(rpc_camera, rng.uniform(0, N_LINES, 40), rng.uniform(0, N_SAMPLES, 40))
    r = adjust(net, {"rpc": {"bias": "affine"}, "outliers": {"enabled": False}})
    assert r.converged and np.all(np.isfinite(r.x))
    # A shift is determined by MCPs on one line.
    t = np.linspace(0.1, 0.9, 40)
    one_line = _mcps(rpc_camera, np.full(40, 0.5 * N_LINES), t * N_SAMPLES)
    r = adjust(one_line, {"rpc": {"bias": "shift"}, "outliers": {"enabled": False}})
    assert r.converged and np.max(np.abs(r.x)) < 1e-3  # the MCPs are exact
    # Weighted coefficients are held by their a-priori sigma: no rank problem.
    r = adjust(
        one_line,
        {
            "rpc": {"bias": "affine", "mode": "weighted", "sigma_px": 1.0},
            "outliers": {"enabled": False},
        },
    )
    assert np.all(np.isfinite(r.x))


def test_a_duplicated_measure_is_refused(rpc_camera) -> None:
    line = np.array([100.0, 200.0, 300.0, 200.0])
    sample = np.array([50.0, 60.0, 70.0, 60.0])
    g = rpc_camera.image_to_ground(line, sample, 0.0)
    pts = ["a", "b", "c", "b"]
    with pytest.raises(InputError, match=r"observation 1 and observation 3 measure point 'b'"):
        Network.from_records(
            {"one": rpc_camera},
            obs_camera=["one"] * 4,
            obs_point=pts,
            line=line,
            sample=sample,
            point_xyz={p: g[i] for i, p in enumerate(pts)},
            point_sigma_m=0.0,
            point_kind="mcp",
        )


def test_a_duplicated_measure_row_in_a_csv(tmp_path: Path) -> None:
    # planetref adjust network.toml --out run, measures.csv with one row pasted twice
    src = SHARED / "data" / "ctx_syrtis"
    if not (src / "network.toml").is_file():
        pytest.skip("../shared/data/ctx_syrtis is absent")
    net = tmp_path / "net"
    shutil.copytree(src, net)
    measures = net / "measures.csv"
    rows = measures.read_text().splitlines(keepends=True)
    measures.write_text("".join([*rows, rows[5]]))
    r = run_cli("adjust", net / "network.toml", "--out", tmp_path / "run", "--no-plots")
    one_line_error(r, "measures.csv", "twice", "double weight")
    assert not (tmp_path / "run").exists()
