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

import shutil

import numpy as np
import pytest

from planetref.adjust import Network, adjust
from planetref.adjust.metrics import geolocation_error
from planetref.camera.io import load_camera
from planetref.camera.rpc import RpcCamera, RpcStripCamera
from planetref.errors import InputError
from planetref.pipeline.georef import run_georef
from planetref.scene.inputs import strip_cameras, truth_inputs
from planetref.scene.manifest import load_manifest, write_manifest


def _rms(values):
    return float(np.sqrt(np.mean(np.square(values))))


@pytest.mark.parametrize("bias", ["affine", "shift+drift"])
def test_rpc_only_true_error_within_1_5x_of_the_rigorous_model(tiny_scene, bias):
    manifest, root = load_manifest(tiny_scene)
    strip = manifest.strips[0]
    truth, truth_dem = truth_inputs(manifest, root)
    dem = truth_dem.load()
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


def _rpc_only_scene(tiny_scene, dst):
    """A copy of the tiny scene whose CCDs have only their RPCs (no rigorous camera)."""
    shutil.copytree(tiny_scene, dst)
    manifest, _ = load_manifest(dst)
    strips = tuple(
        s.model_copy(
            update={
                "ccds": tuple(
                    c.model_copy(update={"camera": c.rpc, "camera_ccd": None, "rpc": None})
                    for c in s.ccds
                )
            }
        )
        for s in manifest.strips
    )
    write_manifest(manifest.model_copy(update={"strips": strips}), dst / "scene.toml")
    return dst


def test_a_strip_of_rpc_images_is_one_camera(tiny_scene, tmp_path):
    scene = _rpc_only_scene(tiny_scene, tmp_path / "rpc")
    manifest, root = load_manifest(scene)
    camera, images = strip_cameras(manifest, root, manifest.strips[0])
    assert isinstance(camera, RpcStripCamera)
    assert camera.ccd_names == ("ccd1", "ccd2", "ccd3") == tuple(images)
    rigorous = load_camera(tiny_scene / "strips" / "strip1" / "camera.json")
    for ccd in camera.ccd_names:
        assert camera.image_size(ccd) == rigorous.image_size(ccd)
    # Mixing an RPC and a rigorous camera file in one strip is refused.
    strip = manifest.strips[0]
    mixed = strip.model_copy(
        update={
            "ccds": (
                strip.ccds[0].model_copy(update={"camera": "strips/strip1/camera.json"}),
                *strip.ccds[1:],
            )
        }
    )
    with pytest.raises(InputError, match="each have its own RPC"):
        strip_cameras(manifest, root, mixed)


@pytest.mark.slow
def test_georef_from_rpcs_alone_within_1_5x_of_the_rigorous_model(tiny_scene, tmp_path):
    """End to end (SIFT matching, MCPs, adjustment, outputs) on the RPC-only scene."""
    scene = _rpc_only_scene(tiny_scene, tmp_path / "rpc")
    rpc = run_georef(scene, "sift", tmp_path / "run_rpc", progress=False)
    rig = run_georef(tiny_scene, "sift", tmp_path / "run_rig", progress=False)
    c_rpc, c_rig = rpc.report["check"], rig.report["check"]
    print(
        f"true error (m): initial {c_rpc['geoloc_rmse_m_before']:.2f}; rigorous "
        f"{c_rig['geoloc_rmse_m']:.3f}; RPC-only {c_rpc['geoloc_rmse_m']:.3f}"
    )
    assert c_rpc["geoloc_rmse_m_before"] > 50.0
    assert c_rpc["geoloc_rmse_m"] <= 1.5 * c_rig["geoloc_rmse_m"]
    cams = rpc.run_dir / "strip1" / "adjustment" / "cameras"
    assert sorted(p.name for p in cams.iterdir()) == [f"strip1_ccd{k}.RPB" for k in (1, 2, 3)]
    assert len(list((rpc.run_dir / "strip1" / "ortho").glob("ccd*.tif"))) == 3
    report = (rpc.run_dir / "strip1" / "adjustment" / "report.md").read_text()
    assert "bias model 'affine'" in report
