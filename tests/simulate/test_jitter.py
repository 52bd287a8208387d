"""The truth's jitter: band-limited random part, node-spacing limits, provenance."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from planetref.camera.jitter import interpolation_limit_hz, node_nyquist_hz
from planetref.errors import InputError
from planetref.simulate.config import JitterRandomConfig
from planetref.simulate.orbit import build_strip_cameras, random_jitter

NO_MISMATCH = {
    "ccd_offset_px": 0.0,
    "ccd_rotation_urad": 0.0,
    "ccd_scale_ppm": 0.0,
    "line_rate_error_ppm": 0.0,
    "position_oscillation_m": [0.0, 0.0, 0.0],
    "attitude_oscillation_urad": [0.0, 0.0, 0.0],
    "radial_k1_px": 0.0,
    "radial_k2_px": 0.0,
    "decentering_px": 0.0,
}
SINES = [
    {"axis": "roll", "amplitude_urad": 2.0, "frequency_hz": 7.0},
    {"axis": "pitch", "amplitude_urad": 1.5, "frequency_hz": 11.0},
]


def test_random_jitter_has_the_rms_band_and_slope() -> None:
    cfg = JitterRandomConfig(
        rms_urad=(1.0, 0.0, 0.5), min_frequency_hz=2.0, max_frequency_hz=30.0, psd_slope=-2.0
    )
    terms = random_jitter(cfg, 2.0, np.random.default_rng(3))
    n = max(16, math.ceil(2 * 28.0 * 2.0))  # 112 per axis
    assert len(terms) == 2 * n
    for axis, rms in (("roll", 1.0), ("yaw", 0.5)):
        a = np.array([t[1] for t in terms if t[0] == axis])
        f = np.array([t[2] for t in terms if t[0] == axis])
        assert math.sqrt(np.sum(a**2) / 2) == pytest.approx(rms, rel=1e-12)
        assert f.min() >= 2.0 and f.max() <= 30.0
        # PSD ~ f^-2: the power below 6 Hz against 6-30 Hz is (1/2 - 1/6) / (1/6 - 1/30).
        p_lo, p_hi = np.sum(a[f < 6] ** 2), np.sum(a[f >= 6] ** 2)
        assert p_lo / p_hi == pytest.approx((1 / 2 - 1 / 6) / (1 / 6 - 1 / 30), rel=0.1)
    # Sampled over 20 s the sum's rms is the configured one (a stationary process).
    t = np.linspace(0.0, 20.0, 40001)
    roll = sum(a * np.sin(2 * np.pi * f * t + p) for ax, a, f, p in terms if ax == "roll")
    assert float(np.sqrt(np.mean(roll**2))) == pytest.approx(1.0, rel=0.05)
    # Seeded: the same generator state gives the same terms; pitch (rms 0) draws nothing.
    assert random_jitter(cfg, 2.0, np.random.default_rng(3)) == terms


def _cameras(mini_config, **random):  # type: ignore[no-untyped-def]
    cfg = mini_config(
        jitter=SINES,
        jitter_random=random,
        truth_mismatch=NO_MISMATCH,
        camera={"n_lines": 2000},
    )
    return cfg, build_strip_cameras(cfg, cfg.strips[0], np.random.default_rng(5))


def test_truth_carries_the_random_jitter(mini_config) -> None:  # type: ignore[no-untyped-def]
    band = {"min_frequency_hz": 1.0, "max_frequency_hz": 15.0}
    cfg, off = _cameras(mini_config)
    _, on = _cameras(mini_config, rms_urad=[1.0, 0.8, 0.0], **band)
    # Turning the random part on keeps the sinusoids' phases (drawn first) and the
    # initial camera; the random part is drawn after them.
    assert on.jitter == off.jitter
    np.testing.assert_array_equal(on.initial.nodes, off.initial.nodes)
    assert {t[0] for t in on.jitter_random} == {"roll", "pitch"}
    # Between the nodes, the truth's rotation differs from the random-free truth by the
    # random part: R_off^T R_on = Rx(roll) Ry(pitch) (small angles), at every line.
    lines = np.linspace(10.0, 1990.0, 397) + 0.37
    _, r_on = on.truth.exterior(lines)
    _, r_off = off.truth.exterior(lines)
    rel = np.einsum("mji,mjk->mik", r_off, r_on)
    roll, pitch = rel[:, 2, 1], rel[:, 0, 2]
    t = on.truth.line_rates.time(lines)
    want = np.zeros((len(lines), 2))
    for ax, a, f, p in on.jitter_random:
        want[:, ["roll", "pitch"].index(ax)] += a * 1e-6 * np.sin(2 * np.pi * f * t + p)
    got = np.column_stack([roll, pitch])
    # Within 1 % of the rms (the band is below the nodes' 1 % limit; the sinusoids'
    # cross terms are second order, < 1e-11 rad).
    limit = on.facts["truth_node_1pct_hz"]
    assert limit > 15.0
    err = np.sqrt(np.mean((got - want) ** 2, axis=0))
    assert np.all(err < 0.01e-6), err
    assert np.sqrt(np.mean(want**2, axis=0)) == pytest.approx([1.0e-6, 0.8e-6], rel=0.35)
    # The facts state the limits of the truth's nodes.
    period = on.facts["true_line_period_s"]
    assert on.facts["truth_node_nyquist_hz"] == pytest.approx(
        node_nyquist_hz(period, cfg.orbit.truth_node_spacing_lines)
    )
    assert on.facts["truth_node_1pct_hz"] == pytest.approx(
        interpolation_limit_hz(period, cfg.orbit.truth_node_spacing_lines, 4, 0.01)
    )
    assert on.facts["jitter_max_frequency_hz"] == 15.0
    assert off.facts["jitter_max_frequency_hz"] == 11.0


def test_jitter_above_the_nodes_nyquist_is_refused(mini_config, caplog) -> None:  # type: ignore[no-untyped-def]
    _, sc = _cameras(mini_config)
    nyq = sc.facts["truth_node_nyquist_hz"]  # 1 / (2 * 16 lines * 0.315 ms) = 99 Hz
    assert 90.0 < nyq < 110.0
    with pytest.raises(InputError, match=r"orbit\.truth_node_spacing_lines to at most \d+"):
        _cameras(mini_config, rms_urad=[1.0, 0.0, 0.0], max_frequency_hz=1.05 * nyq)
    # Between the 5 % limit and Nyquist: built, with a warning naming the setting.
    caplog.clear()
    f = 0.5 * (sc.facts["truth_node_5pct_hz"] + nyq)
    # The module logger's own level: a CLI test earlier in the session may have left the
    # "planetref" logger at ERROR (``-q``).
    with caplog.at_level(logging.WARNING, logger="planetref.simulate.orbit"):
        _cameras(mini_config, rms_urad=[1.0, 0.0, 0.0], max_frequency_hz=f)
    assert any("truth_node_spacing_lines" in r.getMessage() for r in caplog.records)


def test_scene_records_the_random_jitter(tmp_path, mini_config) -> None:  # type: ignore[no-untyped-def]
    import json

    from planetref.simulate.scene import simulate_scene

    cfg = mini_config(jitter_random={"rms_urad": [0.5, 0.0, 0.0], "max_frequency_hz": 12.0})
    a = simulate_scene(cfg, tmp_path / "a")
    b = simulate_scene(cfg, tmp_path / "b")
    errors = json.loads((a.root / "truth" / "errors.json").read_text())["strip1"]
    assert len(errors["jitter_random"]) == 16  # n = max(16, 2 * 11 Hz * 0.03 s)
    assert errors["facts"]["jitter_max_frequency_hz"] == 12.0
    assert errors["facts"]["truth_node_nyquist_hz"] > 12.0
    for rel in ("truth/strip1.camera.json", "truth/errors.json", "strips/strip1/ccd2.tif"):
        assert (a.root / rel).read_bytes() == (b.root / rel).read_bytes(), rel
