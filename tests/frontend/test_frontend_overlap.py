"""CCD-overlap tie points of one strip see the truth's jitter (and nothing without it)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from planetref.camera.jitter import overlap_transfer
from planetref.frontend.config import CcdOverlapConfig
from planetref.frontend.overlap import OverlapTies, find_overlap_ties

# The tiny preset with strong jitter at frequencies the overlap sees (the stagger of
# 20 lines is 15.6 ms: gains 0.68 at 7 Hz and 1.03 at 11 Hz); 8 urad of roll moves the
# 2.5 m pixels by 0.85 px across, 6 urad of pitch by 0.64 px along.
JITTER = [
    {"axis": "roll", "amplitude_urad": 8.0, "frequency_hz": 11.0},
    {"axis": "pitch", "amplitude_urad": 6.0, "frequency_hz": 7.0},
]


def _scene(root: Path, jitter: list[dict[str, object]]) -> Path:
    from planetref.simulate.config import load_config
    from planetref.simulate.scene import simulate_scene

    # The truth's slow attitude oscillation (a third of tiny's 0.5 s strip: 6 Hz) is
    # jitter too: off, so that "without jitter" means none.
    still = {"attitude_oscillation_urad": [0.0, 0.0, 0.0], "position_oscillation_m": [0.0] * 3}
    overrides = {"jitter": jitter, "render": {"n_checkpoints": 0}, "truth_mismatch": still}
    cfg = load_config("tiny", overrides, seed=3)
    simulate_scene(cfg, root)
    return root


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("overlap")
    return {
        "jitter": _scene(base / "jitter", JITTER),
        "still": _scene(base / "still", []),
    }


def _load(root: Path):  # type: ignore[no-untyped-def]
    from planetref.raster.dem import GridTerrain
    from planetref.scene.inputs import open_reference, strip_cameras, truth_inputs
    from planetref.scene.manifest import load_manifest

    manifest, r = load_manifest(root / "scene.toml")
    _, dem = open_reference(manifest, r)
    camera, images = strip_cameras(manifest, r, manifest.strips[0])
    truth, _ = truth_inputs(manifest, r)
    true_dem = GridTerrain.from_geotiff(root / "truth" / "dem.tif")
    return camera, images, dem, truth[manifest.strips[0].id], true_dem


def _true_offsets(truth, ties, dem):  # type: ignore[no-untyped-def]
    """Where the true camera puts, in CCD b, the ground CCD a sees at the tie's (line, sample)."""
    out = np.full((len(ties), 2), np.nan)
    for a, b in {tuple(p) for p in ties.ccd}:
        on = (ties.ccd[:, 0] == a) & (ties.ccd[:, 1] == b)
        g = truth.image_to_ground(ties.line[on, 0], ties.sample[on, 0], dem, ccd=a)
        ip = truth.ground_to_image(g, ccd=b)
        out[on] = np.column_stack([ip.line, ip.sample])
    return out


def _detrended_rms(ties, values):  # type: ignore[no-untyped-def]
    """Rms per axis after a cubic in the line per pair is removed (the smooth part)."""
    out = np.zeros_like(values)
    for pair in {tuple(p) for p in ties.ccd}:
        on = np.all(ties.ccd == pair, axis=1)
        x = ties.line[on, 0] / 640.0
        for k in range(2):
            out[on, k] = values[on, k] - np.polyval(np.polyfit(x, values[on, k], 3), x)
    return np.sqrt(np.mean(out**2, axis=0))


def test_overlap_ties_reproduce_the_true_jitter_difference(scenes) -> None:  # type: ignore[no-untyped-def]
    cfg = CcdOverlapConfig(enabled=True, step_lines=4)
    cam, images, dem, truth, true_dem = _load(scenes["jitter"])
    ties = find_overlap_ties(cam, images, dem, cfg, "strip1")
    assert set(ties.pairs) == {"ccd1~ccd2", "ccd2~ccd3"}
    assert min(ties.pairs.values()) > 100  # of ~150 templates per pair
    # The stagger: ccd2 sits 0.2 mm (20 lines) ahead of ccd1 and ccd3.
    assert np.median(np.abs(ties.line_offset)) == pytest.approx(20.0, abs=1.0)
    # Measured positions in b against the true camera's projection of the same ground
    # (seen by a at the tie's line and sample): measured 0.082 and 0.158 px rms (line,
    # sample; 9 x 25 px templates in tiny's 16-sample overlaps).
    want = _true_offsets(truth, ties, true_dem)
    got = np.column_stack([ties.line[:, 1], ties.sample[:, 1]])
    rms = np.sqrt(np.mean((got - want) ** 2, axis=0))
    assert np.all(rms < 0.2), rms
    # The jitter's part of the truth: the difference to the jitter-free true camera of
    # the other scene (same seed: same CCD placement and lens); 0.30 and 0.62 px rms,
    # what 6 urad at 7 Hz (pitch) and 8 urad at 11 Hz (roll) leave through the
    # overlap's transfer |2 sin(pi f dt)|. The ties follow it: correlation 0.96 and
    # 0.97, slope 0.95 and 0.96 (the templates' 25 lines average the 11 Hz a little).
    _, _, _, still, _ = _load(scenes["still"])
    calm = _true_offsets(still, ties, true_dem)
    signal = want - calm
    measured = got - calm
    sig_rms = np.sqrt(np.mean((signal - signal.mean(axis=0)) ** 2, axis=0))
    assert sig_rms[0] > 0.25 and sig_rms[1] > 0.5, sig_rms
    dt = 20.0 * float(np.ravel(cam.line_rates.period(320.0))[0])  # 20 lines of 0.78 ms
    px = 265e3 * 1e-6 / 2.5  # pixels per urad
    amp = np.array([6.0 * overlap_transfer(7.0, dt), 8.0 * overlap_transfer(11.0, dt)]) * px
    np.testing.assert_allclose(sig_rms, amp / np.sqrt(2), rtol=0.15)
    for k in range(2):
        c = np.corrcoef(measured[:, k], signal[:, k])[0, 1]
        slope = np.polyfit(signal[:, k], measured[:, k], 1)[0]
        assert c > 0.9 and 0.85 < slope < 1.15, (k, c, slope)


def test_overlap_ties_vanish_without_jitter(scenes) -> None:  # type: ignore[no-untyped-def]
    cfg = CcdOverlapConfig(enabled=True, step_lines=4)
    cam, images, dem, truth, true_dem = _load(scenes["still"])
    ties = find_overlap_ties(cam, images, dem, cfg, "strip1")
    want = _true_offsets(truth, ties, true_dem)
    got = np.column_stack([ties.line[:, 1], ties.sample[:, 1]])
    # Measured 0.073 and 0.118 px rms against the true camera.
    assert np.all(np.sqrt(np.mean((got - want) ** 2, axis=0)) < 0.15)
    # Without jitter the ties' offsets from the initial camera's prediction are smooth
    # (its errors over 20 lines): what is left after a cubic is noise (measured 0.059,
    # 0.112 px) -- with jitter the same statistic is 0.29 and 0.60 px.
    still = _detrended_rms(ties, ties.offset_from_prediction)
    cam_j, images_j, dem_j, _, _ = _load(scenes["jitter"])
    moving = find_overlap_ties(cam_j, images_j, dem_j, cfg, "strip1")
    shaking = _detrended_rms(moving, moving.offset_from_prediction)
    print("detrended offset rms still", still, "jitter", shaking)
    assert np.all(still < 0.15), still
    assert np.all(shaking > 2.5 * still), (shaking, still)


def test_overlap_transfer_and_stagger_time() -> None:
    from planetref.camera.jitter import (
        overlap_blind_frequencies,
        overlap_unit_gain_hz,
    )

    dt = 0.0063  # HiRIC: 40 lines of 0.157 ms
    f = np.array([0.0, 1.2, 3.3, 8.5, 17.0, 1 / dt, 0.5 / dt])
    np.testing.assert_allclose(
        overlap_transfer(f, dt),
        [0.0, 0.0475, 0.1305, 0.3349, 0.6603, 0.0, 2.0],
        atol=2e-4,
    )
    assert overlap_unit_gain_hz(dt) == pytest.approx(26.455, abs=1e-3)
    assert overlap_transfer(overlap_unit_gain_hz(dt), dt) == pytest.approx(1.0)
    np.testing.assert_allclose(overlap_blind_frequencies(dt, 400.0), [1 / dt, 2 / dt])


def _ties() -> OverlapTies:
    rng = np.random.default_rng(0)
    n = 6
    la = np.arange(n) * 8.0 + 30.5
    pl = la + 20.0
    return OverlapTies(
        strip="s1",
        ccd=np.array([["ccd1", "ccd2"]] * 3 + [["ccd2", "ccd3"]] * 3),
        line=np.column_stack([la, pl + 0.3 + rng.normal(0, 0.05, n)]),
        sample=np.column_stack([np.full(n, 310.5), np.full(n, 6.5) - 0.2]),
        predicted=np.column_stack([pl, np.full(n, 6.5)]),
        xyz=rng.normal(0, 1, (n, 3)) + np.array([3.4e6, 0.0, 0.0]),
        score=np.full(n, 0.9),
        pairs={"ccd1~ccd2": 3, "ccd2~ccd3": 3},
    )


def test_overlap_ties_csv_round_trip(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from planetref.errors import MissingFileError
    from planetref.frontend.overlap import read_overlap_ties, write_overlap_ties

    ties = _ties()
    back = read_overlap_ties(write_overlap_ties(ties, tmp_path / "t.csv"), "s1")
    np.testing.assert_array_equal(back.ccd, ties.ccd)
    np.testing.assert_allclose(back.line, ties.line, atol=1e-4)
    np.testing.assert_allclose(back.sample, ties.sample, atol=1e-4)
    np.testing.assert_allclose(back.predicted, ties.predicted, atol=1e-4)
    np.testing.assert_allclose(back.xyz, ties.xyz, atol=1e-3)
    np.testing.assert_allclose(back.line_offset, ties.line_offset, atol=2e-4)
    assert back.pairs == ties.pairs
    assert back.point_ids == ties.point_ids
    with pytest.raises(MissingFileError, match="not found"):
        read_overlap_ties(tmp_path / "none.csv", "s1")


def test_overlap_ties_enter_a_network_centred() -> None:
    from planetref.control.network import Network
    from planetref.control.networks import OVERLAP_PLANIMETRIC_SIGMA_M, with_overlap_ties
    from planetref.simulate.config import load_config
    from planetref.simulate.orbit import build_strip_cameras

    cfg = load_config("tiny")
    cam = build_strip_cameras(cfg, cfg.strips[0], np.random.default_rng(0)).initial
    ties = _ties()
    net = Network.mcps(
        cam,
        line=[10.5, 20.5],
        sample=[5.5, 6.5],
        xyz=[[3.4e6, 0, 0], [3.4e6, 1, 0]],
        ccd="ccd1",
        camera_id="s1",
    )
    ovl = CcdOverlapConfig(enabled=True, sigma_px=0.3, height_sigma_m=50.0)
    out = with_overlap_ties(net, ties, ovl)
    assert out.n_points == 2 + 6 and out.n_obs == 2 + 12
    np.testing.assert_array_equal(out.point_kind, ["mcp"] * 2 + ["overlap"] * 6)
    np.testing.assert_array_equal(out.obs_line[:2], net.obs_line)  # MCPs first, unchanged
    np.testing.assert_allclose(out.point_sigma_m[2], [OVERLAP_PLANIMETRIC_SIGMA_M] * 2 + [50.0])
    assert out.point_sigma_local[2] and not out.point_sigma_local[0]
    np.testing.assert_allclose(out.obs_sigma_px[2:], 0.3)
    # b's measures lose their pair's median offset from the prediction (0.3 line and
    # -0.2 sample here): what is left is the variation along the strip.
    b_line = out.obs_line[3::2]
    b_sample = out.obs_sample[3::2]
    off = ties.offset_from_prediction
    for pair in (slice(0, 3), slice(3, 6)):
        np.testing.assert_allclose(
            b_line[pair] - ties.predicted[pair, 0], off[pair, 0] - np.median(off[pair, 0])
        )
        np.testing.assert_allclose(b_sample[pair], ties.predicted[pair, 1])
    np.testing.assert_array_equal(out.obs_line[2::2], ties.line[:, 0])
    names = [cam.ccd_names[k] for k in out.obs_ccd[2:]]
    assert names == [c for row in ties.ccd for c in row]


def test_overlap_ties_carry_no_ccd_offset_consider_term() -> None:
    # A constant offset of either CCD leaves the ties unchanged (their pair's median
    # offset is taken off), so the consider analysis must not propagate a CCD offset
    # through them; the MCPs of the same CCDs still carry theirs.
    from planetref.adjust.config import SystematicConfig
    from planetref.adjust.consider import consider_layout
    from planetref.control.network import Network
    from planetref.control.networks import with_overlap_ties
    from planetref.simulate.config import load_config
    from planetref.simulate.orbit import build_strip_cameras

    cfg = load_config("tiny")
    cam = build_strip_cameras(cfg, cfg.strips[0], np.random.default_rng(0)).initial
    net = Network.mcps(
        cam,
        line=[10.5, 20.5],
        sample=[5.5, 6.5],
        xyz=[[3.4e6, 0, 0], [3.4e6, 1, 0]],
        ccd="ccd2",
        camera_id="s1",
    )
    out = with_overlap_ties(net, _ties(), CcdOverlapConfig(enabled=True))
    sys_cfg = SystematicConfig(ccd_offset_sigma_px=0.5)
    weighted = np.zeros(out.n_points, bool)
    lay = consider_layout(out, sys_cfg, weighted, [False])
    ((kind, obs_key, n_keys),) = lay.obs_keys  # no tiles in this network
    # Only ccd2 has MCPs: one key (line and sample offsets), on the two MCP observations.
    assert kind == "ccd" and n_keys == 1
    assert lay.names == ["s1/ccd2 line offset", "s1/ccd2 sample offset"]
    np.testing.assert_array_equal(obs_key, [0, 0] + [-1] * 12)
    np.testing.assert_allclose(lay.sigma, 0.5)


def test_overlap_ties_join_a_campaign_network() -> None:
    from planetref.control.network import Network
    from planetref.control.networks import with_overlap_ties
    from planetref.errors import InputError
    from planetref.simulate.config import load_config
    from planetref.simulate.orbit import build_strip_cameras

    cfg = load_config("tiny")
    cam = build_strip_cameras(cfg, cfg.strips[0], np.random.default_rng(0)).initial
    net = Network.from_records(
        {"s1": cam, "s2": cam},
        obs_camera=["s1", "s2"],
        obs_point=["p", "p"],
        line=[10.5, 12.5],
        sample=[5.5, 6.5],
        point_xyz={"p": [3.4e6, 0.0, 0.0]},
        obs_ccd=["ccd1", "ccd2"],
    )
    ties = _ties()
    ties.strip = "s2"
    out = with_overlap_ties(net, ties, CcdOverlapConfig(enabled=True))
    assert out.n_obs == 2 + 12
    np.testing.assert_array_equal(out.obs_camera[2:], 1)  # the strip's own camera
    assert all(str(p).startswith("s2:ovl:") for p in out.point_ids[1:])
    ties.strip = "s3"
    with pytest.raises(InputError, match="no such camera"):
        with_overlap_ties(net, ties, CcdOverlapConfig(enabled=True))
