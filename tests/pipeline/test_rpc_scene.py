"""A simulated scene georeferenced from its RPCs alone against the rigorous strip model.

The tiny scene's manifest gives, per CCD, an RPC fitted to the perturbed initial
rigorous camera (``simulate`` writes them). The same MCPs (true ground through the true
camera and the true DEM, 0.3 px Gaussian noise, 60 per CCD, uniform) adjust once the
rigorous strip (default configuration) and once the three RPC images with the affine
bias per CCD (default configuration); the true geolocation error of each result is
measured against the true camera on the true DEM. What makes this easier than a real
run: the MCPs' ground is exact (no reference ortho or DEM error, no matching outliers)
and they cover every CCD evenly.
"""

from __future__ import annotations

import numpy as np
import pytest

from planetref.adjust import Network, adjust
from planetref.camera.io import load_camera
from planetref.camera.rpc import RpcCamera
from planetref.metrics import geolocation_error
from planetref.pipeline.inputs import truth_inputs
from planetref.pipeline.scene import load_manifest


def _rms(values):
    return float(np.sqrt(np.mean(np.square(values))))


@pytest.mark.parametrize("bias", ["affine", "shift+drift"])
def test_rpc_only_true_error_within_1_5x_of_the_rigorous_model(tiny_scene, bias):
    manifest, root = load_manifest(tiny_scene)
    strip = manifest.strips[0]
    truth, dem = truth_inputs(manifest, root)
    true_cam = truth[strip.id]
    rigorous = load_camera(root / strip.ccds[0].camera)
    rpcs = {c.name: RpcCamera.from_file(root / c.rpc, name=c.name) for c in strip.ccds}
    rng = np.random.default_rng(11)
    line, sample, xyz, ccd = [], [], [], []
    for c in strip.ccds:
        n_lines, n_samples = rigorous.image_size(c.name)
        ln, sm = rng.uniform(0, n_lines, 60), rng.uniform(0, n_samples, 60)
        xyz.append(true_cam.image_to_ground(ln, sm, dem, ccd=c.name))
        line.append(ln + rng.normal(0, 0.3, 60))
        sample.append(sm + rng.normal(0, 0.3, 60))
        ccd += [c.name] * 60
    line, sample, xyz = np.concatenate(line), np.concatenate(sample), np.concatenate(xyz)

    rig = adjust(
        Network.mcps(rigorous, line=line, sample=sample, xyz=xyz, ccd=np.array(ccd), sigma_px=0.3)
    )
    pids = [f"m{i}" for i in range(len(line))]
    rpc = adjust(
        Network.from_records(
            rpcs,
            obs_camera=ccd,
            obs_point=pids,
            line=line,
            sample=sample,
            point_xyz=dict(zip(pids, xyz, strict=True)),
            point_sigma_m=0.0,
            point_kind="mcp",
            sigma_px=0.3,
        ),
        {"rpc": {"bias": bias}},
    )

    def true_error(cameras):
        return _rms(
            [
                geolocation_error(cameras[c.name], true_cam, ccd=c.name, terrain=dem)["rms_m"]
                for c in strip.ccds
            ]
        )

    before = true_error(rpcs)
    rig_after = true_error({c.name: rig.cameras["strip"] for c in strip.ccds})
    rpc_after = true_error(rpc.cameras)
    print(
        f"true error (m): initial {before:.2f}; rigorous {rig_after:.3f} "
        f"(RMSE {rig.summary()['rmse_px']:.3f} px); RPC {bias} {rpc_after:.3f} "
        f"(RMSE {rpc.summary()['rmse_px']:.3f} px); ratio {rpc_after / rig_after:.2f}"
    )
    assert before > 50.0
    assert rpc_after <= 1.5 * rig_after
    assert rpc_after < 5.0 and rig_after < 5.0
