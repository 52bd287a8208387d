"""Synthetic line-scan problems for the adjustment tests (small, deterministic)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from planetref.adjust import Network
from planetref.camera.orbit import OrbitGeometry, ccd_row, orbit_camera
from planetref.geometry.geodesy import ray_ellipsoid_intersection

SHARED = Path(__file__).resolve().parents[2].parent / "shared"

N_LINES, N_SAMPLES, N_NODES = 3000, 512, 6


def true_strip(
    n_nodes: int = N_NODES,
    lat: float = 20.0,
    lon: float = 74.0,
    heading: float = 30.0,
    name: str = "",
):
    ccds = ccd_row(3, N_SAMPLES, N_LINES, 0.010, overlap_px=16, stagger_mm=1.0)
    cam, _ = orbit_camera(
        OrbitGeometry(lat, lon, heading),
        focal_length_mm=4640.0,
        ccds=ccds,
        n_nodes=n_nodes,
        name=name,
    )
    return cam


def perturb(
    cam,
    *,
    pos_bias=(30.0, -20.0, 10.0),
    pos_drift=(5.0, 3.0, -2.0),
    att_bias=(2e-5, -3e-5, 1e-5),
    att_drift=(1e-6, 2e-6, -1e-6),
):
    """Biases and linear drifts of the node EOPs (metres, radians)."""
    nodes = cam.nodes.copy()
    t = np.linspace(-1.0, 1.0, cam.n_nodes)[:, None]
    nodes[:, :3] += np.asarray(pos_bias) + t * np.asarray(pos_drift)
    nodes[:, 3:] += np.asarray(att_bias) + t * np.asarray(att_drift)
    return cam.replace(nodes=nodes)


def ground_points(cam, ccd_idx, line, sample, heights):
    """Ground XYZ that ``cam`` sees at the given pixels and heights above the sphere."""
    xyz = np.empty((len(line), 3))
    for k, name in enumerate(cam.ccd_names):
        m = ccd_idx == k
        if not np.any(m):
            continue
        o, d = cam.look_rays(line[m], sample[m], ccd=name)
        s = ray_ellipsoid_intersection(o, d, cam.ellipsoid, heights[m])
        xyz[m] = o + s[:, None] * d
    return xyz


def mcp_problem(
    n: int = 600,
    *,
    noise_px: float = 0.3,
    seed: int = 0,
    gross: int = 0,
    ground_sigma_m: float = 0.0,
    check: int = 0,
    init=None,
    true=None,
):
    """An MCP network of a perturbed strip: returns ``(network, true camera, info)``."""
    true = true if true is not None else true_strip()
    init = init if init is not None else perturb(true)
    rng = np.random.default_rng(seed)
    ccd = rng.integers(0, 3, n)
    line = rng.uniform(1.0, N_LINES - 1.0, n)
    sample = rng.uniform(1.0, N_SAMPLES - 1.0, n)
    xyz = ground_points(true, ccd, line, sample, rng.uniform(-2000.0, 2000.0, n))
    obs_line = line + rng.normal(0.0, noise_px, n)
    obs_sample = sample + rng.normal(0.0, noise_px, n)
    bad = rng.choice(n, gross, replace=False) if gross else np.zeros(0, int)
    if gross:
        ang = rng.uniform(0, 2 * np.pi, gross)
        mag = rng.uniform(8.0, 40.0, gross)
        obs_line[bad] += mag * np.sin(ang)
        obs_sample[bad] += mag * np.cos(ang)
    chk = np.zeros(n, bool)
    if check:
        chk[rng.choice(np.setdiff1d(np.arange(n), bad), check, replace=False)] = True
    if ground_sigma_m:
        xyz = xyz + rng.normal(0.0, ground_sigma_m / 4.0, xyz.shape)
    net = Network.mcps(
        init,
        line=obs_line,
        sample=obs_sample,
        xyz=xyz,
        ccd=np.array(init.ccd_names)[ccd],
        sigma_px=noise_px,
        ground_sigma_m=ground_sigma_m,
        check=chk,
    )
    return net, true, {"gross": bad, "check": chk}


def true_parameters(cam):
    """The parameter vector of a strip (nodes, then strip interior)."""
    return np.concatenate([cam.nodes.ravel(), cam.interior.as_array()])


def shared_data() -> Path:
    """``../shared/data``; skips the calling test when it is absent."""
    if not SHARED.is_dir():
        pytest.skip(f"{SHARED} not found (the real data of this test live in ../shared)")
    return SHARED / "data"


def tie_problem(
    n_tie: int = 80,
    n_mcp: int = 60,
    *,
    seed: int = 7,
    tie_sigma_m: float = np.inf,
    mcp_sigma_m: float = 5.0,
    triple: int = 0,
):
    """Tie points in the overlaps of neighbouring CCDs plus weighted MCPs.

    Each tie point is seen in both CCDs of its overlap (2 observations; ``triple`` of
    them also by a second strip, ``strip2``, a differently perturbed copy, in the second
    CCD), its a-priori XYZ 20 m off with sigma ``tie_sigma_m`` (``inf``: free). The
    CCDs' 1 mm stagger puts the two observations ~100 lines apart, so some straddle a
    change of Lagrange window (two patterns). Returns the network.
    """
    true = true_strip()
    init = perturb(true)
    rng = np.random.default_rng(seed)
    first = rng.integers(0, 2, n_tie)  # overlap ccd1/ccd2 or ccd2/ccd3
    line = rng.uniform(200, N_LINES - 200, n_tie)
    sample = rng.uniform(N_SAMPLES - 14, N_SAMPLES - 2, n_tie)
    xyz_t = ground_points(true, first, line, sample, rng.uniform(-500, 500, n_tie))
    other = np.empty((n_tie, 2))
    for k in range(2):
        m = first == k
        ip = true.ground_to_image(xyz_t[m], ccd=true.ccd_names[k + 1])
        other[m] = np.stack([ip.line, ip.sample], 1)
    ccd_m = rng.integers(0, 3, n_mcp)
    lm, sm = rng.uniform(0, N_LINES, n_mcp), rng.uniform(0, N_SAMPLES, n_mcp)
    xyz_m = ground_points(true, ccd_m, lm, sm, rng.uniform(-500, 500, n_mcp))
    names = np.array(true.ccd_names)
    t3 = np.arange(triple)
    obs_point = [f"t{i}" for i in range(n_tie)] * 2 + [f"t{i}" for i in t3]
    obs_point += [f"m{i}" for i in range(n_mcp)]
    cams = ["strip"] * (2 * n_tie) + ["strip2"] * triple + ["strip"] * n_mcp
    ccd = np.concatenate([names[first], names[first + 1], names[first[t3] + 1], names[ccd_m]])
    obs_line = np.concatenate([line, other[:, 0], other[t3, 0], lm])
    obs_sample = np.concatenate([sample, other[:, 1], other[t3, 1], sm])
    n_obs = len(obs_line)
    pts = {f"t{i}": xyz_t[i] + rng.normal(0, 20, 3) for i in range(n_tie)}
    pts.update({f"m{i}": xyz_m[i] for i in range(n_mcp)})
    sig = {f"t{i}": tie_sigma_m for i in range(n_tie)}
    sig.update({f"m{i}": mcp_sigma_m for i in range(n_mcp)})
    second = perturb(true, pos_bias=(-10.0, 15.0, 5.0), att_bias=(-1e-5, 2e-5, 2e-5))
    cameras = {"strip": init, "strip2": second} if triple else {"strip": init}
    return Network.from_records(
        cameras,
        obs_camera=cams,
        obs_point=obs_point,
        obs_ccd=list(ccd),
        line=obs_line + rng.normal(0, 0.3, n_obs),
        sample=obs_sample + rng.normal(0, 0.3, n_obs),
        point_xyz=pts,
        point_sigma_m=sig,
        point_kind={
            **{f"t{i}": "tie" for i in range(n_tie)},
            **{f"m{i}": "mcp" for i in range(n_mcp)},
        },
        sigma_px=0.3,
    )
