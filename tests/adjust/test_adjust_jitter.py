"""The jitter stage: dense attitude nodes with a smoothness prior after the seed's nodes.

A synthetic strip (the seed's 6-node camera of ``adjust_synth``) gets sinusoidal
attitude jitter in the truth; MCPs are projected from the jittered truth with 0.3 px
noise. The stage must recover the components the observations see (amplitude, phase),
leave a jitter-free strip as good as the node model, hold a gap with its prior and keep
its formal sigma honest.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from adjust_synth import N_LINES, N_SAMPLES, ground_points, perturb, true_strip

from planetref.adjust import Network
from planetref.adjust.api import adjust
from planetref.adjust.config import JitterConfig, validate_config
from planetref.adjust.jitter import (
    JitterParameterization,
    densify,
    jitter_config,
    line_of_sight_difference,
    smoothness_sigma_rad,
)
from planetref.errors import InputError

NOISE_PX = 0.3


def _strip_setup():
    smooth = true_strip(n_nodes=6)
    t01 = smooth.line_rates.time(np.array([0.0, 1.0]))
    duration = N_LINES * float(t01[1] - t01[0])
    return smooth, duration


def _jittered(smooth, comps):
    """The smooth truth with ``(node angle column, amplitude rad, Hz, phase)`` sinusoids."""
    dense = densify(smooth, 16)
    t = dense.line_rates.time(dense.node_lines)
    nodes = dense.nodes.copy()
    for col, amp, f, ph in comps:
        nodes[:, col] += amp * np.sin(2 * np.pi * f * t + ph)
    return dense.replace(nodes=nodes)


def _network(truth, init, *, n=6000, seed=0, gap=None):
    rng = np.random.default_rng(seed)
    ccd = rng.integers(0, 3, n)
    line = rng.uniform(1.0, N_LINES - 1.0, n)
    if gap is not None:
        keep = (line < gap[0]) | (line > gap[1])
        ccd, line = ccd[keep], line[keep]
        n = len(line)
    sample = rng.uniform(1.0, N_SAMPLES - 1.0, n)
    xyz = ground_points(truth, ccd, line, sample, rng.uniform(-2000.0, 2000.0, n))
    return Network.mcps(
        init,
        line=line + rng.normal(0.0, NOISE_PX, n),
        sample=sample + rng.normal(0.0, NOISE_PX, n),
        xyz=xyz,
        ccd=np.array(init.ccd_names)[ccd],
        sigma_px=NOISE_PX,
    )


def _jitter_settings(duration, **extra):
    # A band of 20 cycles per strip; the strip lasts 0.54 s, so ~37 Hz.
    return {
        "jitter": {
            "enabled": True,
            "node_spacing_lines": 32,
            "amplitude_rad": "5 urad",
            "max_frequency_hz": 20.0 / duration,
            **extra,
        }
    }


def _fit(t, y, freqs, deg=2):
    """Amplitude and phase (deg) of ``sin(2 pi f t + phase)`` per frequency, jointly."""
    cols = [t**k for k in range(deg + 1)]
    for f in freqs:
        cols += [np.sin(2 * np.pi * f * t), np.cos(2 * np.pi * f * t)]
    coef = np.linalg.lstsq(np.stack(cols, 1), y, rcond=None)[0][deg + 1 :]
    s, c = coef[0::2], coef[1::2]
    return np.hypot(s, c), np.degrees(np.arctan2(c, s))


def _ground_error(truth, cam, n=41):
    """RMS ground distance (m) of a pixel grid of every CCD through both cameras."""
    err = []
    for c in truth.ccds:
        ln, sm = np.meshgrid(np.linspace(1, N_LINES - 1, n), np.linspace(1, N_SAMPLES - 1, 5))
        a = truth.image_to_ground(ln.ravel(), sm.ravel(), 0.0, ccd=c.name)
        b = cam.image_to_ground(ln.ravel(), sm.ravel(), 0.0, ccd=c.name)
        err.append(np.linalg.norm(a - b, axis=1))
    return float(np.sqrt(np.mean(np.concatenate(err) ** 2)))


@pytest.fixture(scope="module")
def jittered_case():
    smooth, duration = _strip_setup()
    # Node-angle columns 4 (omega) and 3 (phi) are the camera's roll and pitch here
    # (nadir strip; the test checks the truth series); column 5 (yaw about the
    # boresight) barely moves a 1536-sample swath: the prior must hold it.
    comps = [
        (4, 3e-6, 12.0 / duration, 2.0),
        (3, 4e-6, 5.0 / duration, 0.7),
        (3, 2e-6, 15.0 / duration, -1.0),
        (5, 3e-6, 8.0 / duration, -1.0),
    ]
    truth = _jittered(smooth, comps)
    init = perturb(smooth)
    net = _network(truth, init)
    seed = adjust(net)
    res = adjust(net, _jitter_settings(duration))
    return smooth, truth, comps, seed, res


def test_recovers_sinusoidal_jitter(jittered_case):
    smooth, truth, comps, seed, res = jittered_case
    series = res.jitter["strip"]
    lines = series.line
    t = series.time_s
    freqs = [c[2] for c in comps]
    true_los = line_of_sight_difference(smooth, truth, lines)
    dense_los = line_of_sight_difference(smooth, res.cameras["strip"], lines)
    seed_los = line_of_sight_difference(smooth, seed.cameras["strip"], lines)
    for axis, idx in ((0, [0]), (1, [1, 2])):
        a_true, p_true = _fit(t, true_los[:, axis], freqs)
        a_est, p_est = _fit(t, dense_los[:, axis], freqs)
        a_seed, _ = _fit(t, seed_los[:, axis], freqs)
        for i in idx:
            assert a_true[i] == pytest.approx(comps[i][1], rel=0.02)  # the truth is what it says
            assert a_est[i] == pytest.approx(a_true[i], rel=0.10)
            dphi = (p_est[i] - p_true[i] + 180.0) % 360.0 - 180.0
            assert abs(dphi) < 10.0
        # The seed's nodes (600 lines apart) cannot follow the 12 and 15 cycle ones.
        hi = [i for i in idx if comps[i][2] * (t[-1] - t[0]) > 10]
        assert all(a_seed[i] < 0.5 * a_true[i] for i in hi)
    # Estimated jitter (dense minus seed) is what the dense camera adds to the seed.
    est = series.angles_rad
    assert np.sqrt(np.mean(est[:, :2] ** 2)) * 1e6 > 1.5
    # Yaw about the boresight is not observable: the prior holds it near 0 and says so.
    assert np.sqrt(np.mean(est[:, 2] ** 2)) < 1e-6
    assert np.median(series.sigma_rad[:, 2]) > 1e-6
    # The true ground error drops by far more than 40 % with the jitter solved.
    e_seed = _ground_error(truth, seed.cameras["strip"])
    e_dense = _ground_error(truth, res.cameras["strip"])
    assert e_dense < 0.4 * e_seed


def test_formal_sigma_matches_true_error(jittered_case):
    _, truth, _, _, res = jittered_case
    series = res.jitter["strip"]
    # True error of the estimated jitter: the dense pointing minus the true one, as the
    # image sees it, for the observable axes; a quadratic (the seed's share) removed.
    err = line_of_sight_difference(truth, res.cameras["strip"], series.line)
    t = series.time_s
    base = np.stack([t**k for k in range(3)], 1)
    for axis in (0, 1):
        e = err[:, axis] - base @ np.linalg.lstsq(base, err[:, axis], rcond=None)[0]
        true_rms = float(np.sqrt(np.mean(e**2)))
        formal = float(np.sqrt(np.mean(series.sigma_rad[:, axis] ** 2)))
        assert 0.5 < true_rms / formal < 2.0, (axis, true_rms, formal)


def test_jitter_free_strip_not_degraded():
    smooth, duration = _strip_setup()
    init = perturb(smooth)
    net = _network(smooth, init, seed=3)
    seed = adjust(net)
    res = adjust(net, _jitter_settings(duration))
    e_seed = _ground_error(smooth, seed.cameras["strip"])
    e_dense = _ground_error(smooth, res.cameras["strip"])
    s = res.jitter["strip"]
    # Nothing invented: the estimated jitter is at its formal precision (noise), and the
    # ground error grows by no more than that precision on the ground (2 sigma).
    rms = np.sqrt(np.mean(s.angles_rad[:, :2] ** 2))
    formal = np.sqrt(np.mean(s.sigma_rad[:, :2] ** 2))
    assert rms < 2.0 * formal
    range_m = float(np.linalg.norm(smooth.exterior(np.array([1500.0]))[0][0])) - 3396190.0
    assert e_dense**2 < e_seed**2 + (2.0 * formal * range_m) ** 2
    assert e_dense < 0.1 * 0.65  # a tenth of a pixel


def test_jitter_kept_only_if_check_improves():
    smooth, duration = _strip_setup()
    init = perturb(smooth)
    comps = [(4, 3e-6, 12.0 / duration, 2.0)]
    for truth, kept in ((smooth, False), (_jitted := _jittered(smooth, comps), True)):
        net = _network(truth, init, seed=4)
        rng = np.random.default_rng(9)
        check = rng.random(net.n_obs) < 0.2
        net = dataclasses.replace(net, obs_check=check)
        res = adjust(net, _jitter_settings(duration))
        assert res.diagnostics["jitter"]["strip"]["kept"] is kept
        assert (res.cameras["strip"].n_nodes > 6) is kept
    del _jitted


def test_prior_holds_a_gap():
    smooth, duration = _strip_setup()
    init = perturb(smooth)
    net = _network(smooth, init, seed=5, gap=(1200.0, 1800.0))
    res = adjust(net, _jitter_settings(duration))
    s = res.jitter["strip"]
    in_gap = (s.line > 1300) & (s.line < 1700)
    out = (s.line < 1100) | (s.line > 1900)
    # Not invented: no more jitter in the gap than where it is observed...
    assert np.max(np.abs(s.angles_rad[in_gap, :2])) < 3 * np.max(np.abs(s.angles_rad[out, :2]))
    # ... and the formal sigma says the gap is weak.
    assert np.median(s.sigma_rad[in_gap, :2]) > 3 * np.median(s.sigma_rad[out, :2])
    # The resolution limit sees the gap (600 lines out of 3000).
    assert s.resolution.max_gap_lines > 550


def test_smoothness_prior_from_amplitude_and_band():
    cfg = JitterConfig(amplitude_rad="5 urad", max_frequency_hz=10.0)
    expect = 5e-6 * 4.0 * math.sin(math.pi * 10.0 * 0.01) ** 2
    assert smoothness_sigma_rad(cfg, 0.01) == pytest.approx(expect, rel=1e-12)
    # The band is capped at the nodes' Nyquist frequency (4 * amplitude at most).
    assert smoothness_sigma_rad(cfg, 0.1) == pytest.approx(20e-6, rel=1e-12)
    over = JitterConfig(smoothness_sigma_rad="0.2 urad")
    assert smoothness_sigma_rad(over, 0.01) == pytest.approx(2e-7)


def test_dense_stage_counts_overlapping_mcps_once():
    # Dense templates sharing their pixels (measurement overlap 80) beside CCD-overlap
    # ties: the dense stage adjusts the MCPs with 1/80 of their weight and no
    # covariance sandwich; MCPs alone (mcp_overlap 1) keep the seed's settings.
    from planetref.adjust.jitter import jitter_config

    cfg = validate_config({"systematic": {"measurement_overlap": 80.0}})
    dense = jitter_config(cfg, 80.0)
    assert dense.systematic.measurement_overlap == 1.0
    assert dense.variance.mcp_weight_share == pytest.approx(1.0 / 80.0)
    assert dense.linescan.position.mode == "fixed"
    plain = jitter_config(cfg)
    assert plain.variance.mcp_weight_share == 1.0
    assert plain.systematic == cfg.systematic


def test_jitter_settings_validated():
    cfg = validate_config({})
    assert cfg.jitter.enabled is False
    with pytest.raises(InputError, match="amplitude_rad"):
        validate_config({"jitter": {"amplitude_rad": -1.0}})
    with pytest.raises(InputError, match="node_spacing_lines"):
        validate_config({"jitter": {"node_spacing_lines": 1}})


def test_dense_parameterization_partials_and_prior():
    smooth, duration = _strip_setup()
    cam = densify(perturb(smooth), 32)
    cfg = jitter_config(validate_config(_jitter_settings(duration)))
    model = JitterParameterization("s", cam, cfg.linescan, cfg.jitter)
    model.compiled_partials = False
    # Dense nodes reproduce the sparse trajectory.
    lines = np.linspace(0, N_LINES, 50)
    d = line_of_sight_difference(perturb(smooth), cam, lines)
    assert np.max(np.abs(d[:, :2])) < 1e-9
    # Positions fixed, attitudes weighted by the amplitude, second differences weighted.
    n = cam.n_nodes
    assert np.all(model.mode[: 6 * n].reshape(n, 6)[:, :3] == 2)
    assert np.all(model.sigma[: 6 * n].reshape(n, 6)[:, 3:] == pytest.approx(5e-6))
    a, w = model.constraints
    assert a.shape == (3 * (n - 2), len(model.x0))
    assert np.allclose(a.sum(axis=1), 0.0)
    assert np.allclose(w, 1.0 / model.smooth_sigma_rad**2)
    # Partials of (line, sample) w.r.t. the dense attitude nodes: exact vs differences.
    rng = np.random.default_rng(1)
    m = 40
    ccd = 1
    line = rng.uniform(100, N_LINES - 100, m)
    sample = rng.uniform(10, N_SAMPLES - 10, m)
    xyz = ground_points(cam, np.full(m, ccd), line, sample, np.zeros(m))
    ev = model.evaluate(model.x0, xyz, ccd, line)
    h = 1e-7  # rad: 0.05 px, far above the projection's 1e-9 px precision
    scale = np.max(np.abs(ev.d_params))  # the differences' noise is ~1e-9 px / h
    for i in rng.choice(len(model.pattern_columns), 3, replace=False):
        cols = model.pattern_columns[i]
        rows = np.flatnonzero(ev.pattern == i)
        if rows.size == 0:
            continue
        for q in np.flatnonzero(cols >= 0)[:24]:
            j = cols[q]
            if j % 6 < 3:
                continue
            xp, xm = model.x0.copy(), model.x0.copy()
            xp[j] += h
            xm[j] -= h
            ep = model.evaluate(xp, xyz, ccd, line, partials=False)
            em = model.evaluate(xm, xyz, ccd, line, partials=False)
            fd = np.stack([(ep.line - em.line) / (2 * h), (ep.sample - em.sample) / (2 * h)], 1)
            exact = ev.d_params[rows, :, q]
            assert np.max(np.abs(exact - fd[rows])) < 1e-5 * scale


def test_jitter_outputs(jittered_case, tmp_path):
    import csv

    from planetref.report.adjustment import write_jitter_csv
    from planetref.report.figures_adjust import figure_jitter

    _, truth, _, _, res = jittered_case
    s = res.jitter["strip"]
    path = write_jitter_csv(res, tmp_path / "jitter.csv", {"strip": truth})
    rows = list(csv.DictReader(path.open()))
    assert len(rows) == len(s.line)
    roll = np.array([float(r["roll_urad"]) for r in rows])
    true_roll = np.array([float(r["true_roll_urad"]) for r in rows])
    assert np.allclose(roll, s.angles_rad[:, 0] * 1e6, atol=1e-4)
    assert float(rows[3]["sigma_pitch_urad"]) == pytest.approx(s.sigma_rad[3, 1] * 1e6, abs=1e-4)
    # The truth column is the truth's pointing relative to the seed: the estimate follows it.
    assert np.corrcoef(roll, true_roll)[0, 1] > 0.95
    png = figure_jitter(
        s.time_s,
        s.angles_rad * 1e6,
        s.sigma_rad * 1e6,
        tmp_path / "jitter.png",
        truth_urad=true_roll[:, None] * np.array([1.0, 0.0, 0.0]),
        limit_hz=s.resolution.limit_hz,
    )
    assert png.stat().st_size > 10_000
    summary = res.diagnostics["jitter"]["strip"]
    assert summary["kept"] is True
    assert summary["resolution"]["limit_hz"] == pytest.approx(s.resolution.limit_hz)


def test_template_support_bounds_the_resolution_limit():
    from planetref.adjust.jitter import resolution_limit

    smooth, _ = _strip_setup()
    cam = densify(smooth, 32)
    lines = np.arange(0.0, N_LINES, 2.0)
    free = resolution_limit(cam, lines, JitterConfig(max_frequency_hz=1e4))
    assert free.support_limit_hz == math.inf
    t01 = cam.line_rates.time(np.array([0.0, 1.0]))
    period = float(t01[1] - t01[0])
    assert free.limit_hz == pytest.approx(1.0 / (4 * 32 * period))  # the nodes limit
    # Square pixels at nadir: the along-track metres per line are the across-track GSD.
    mid = cam.ccds[1]
    g = cam.image_to_ground(np.full(2, 1500.0), np.array([700.0, 800.0]), 0.0, ccd=mid.name)
    gsd = float(np.linalg.norm(g[1] - g[0])) / 100.0
    res = resolution_limit(cam, lines, JitterConfig(max_frequency_hz=1e4, mcp_support_m=50.0))
    assert res.support_lines == pytest.approx(50.0 / gsd, rel=0.01)
    assert res.support_limit_hz == pytest.approx(0.360 / (50.0 / gsd * period), rel=0.01)
    # sinc(pi f T) at that limit is 0.8
    x = math.pi * res.support_limit_hz * res.support_lines * period
    assert math.sin(x) / x == pytest.approx(0.8, abs=2e-3)
    assert res.limit_hz == pytest.approx(min(res.support_limit_hz, res.node_limit_hz))
    assert free.mcp_gap_lines < 4.0
