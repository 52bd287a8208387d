from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from planetref.simulate.config import load_config
from planetref.simulate.grid import MapGrid, cubic_resample
from planetref.simulate.terrain import (
    crater_profile,
    fractal_field,
    generate_terrain,
    sample_crater_population,
    soft_mask,
)

STREAMS = ("regional", "fractal", "plains", "dunes", "craters", "ridges", "albedo")


def _streams(seed: int = 0) -> dict[str, np.random.Generator]:
    return {k: np.random.default_rng([seed, i]) for i, k in enumerate(STREAMS)}


def test_fractal_field_is_unit_rms_and_red() -> None:
    f = fractal_field((256, 256), 1.0, np.random.default_rng(0), hurst=0.8)
    assert f.dtype == np.float32
    assert abs(float(f.mean())) < 1e-5 and float(f.std()) == pytest.approx(1.0, rel=1e-4)
    # A red spectrum: neighbouring cells are strongly correlated.
    assert np.corrcoef(f[:, :-1].ravel(), f[:, 1:].ravel())[0, 1] > 0.9
    g = fractal_field((256, 256), 1.0, np.random.default_rng(0), hurst=0.8)
    np.testing.assert_array_equal(f, g)


def test_crater_sfd_follows_the_power_law() -> None:
    cfg = load_config(
        "tiny",
        {
            "terrain": {
                "craters": {
                    "density_per_km2": 3000.0,
                    "d_min_m": 5.0,
                    "d_max_m": 500.0,
                    "sfd_slope": 2.0,
                }
            }
        },
    )
    bounds = (0.0, 0.0, 3000.0, 3000.0)
    pop = sample_crater_population(cfg.terrain, bounds, np.random.default_rng(3))
    pad = 0.75 * 500.0
    area = (3000 + 2 * pad) ** 2 / 1e6
    assert len(pop) == pytest.approx(3000.0 * area, rel=0.05)
    d = np.sort(pop.diameter_m)[::-1]
    assert d.min() >= 5.0 and d.max() <= 500.0
    # Cumulative counts N(>=D) ~ D^-2: fit the log-log slope between 5 and 50 m.
    edges = np.array([5.0, 10.0, 20.0, 40.0])
    counts = np.array([np.count_nonzero(d >= e) for e in edges])
    slope = np.polyfit(np.log(edges), np.log(counts), 1)[0]
    assert slope == pytest.approx(-2.0, abs=0.1)
    fresh = pop.fresh.mean()
    assert fresh == pytest.approx(cfg.terrain.craters.fresh_fraction, abs=0.03)


def test_crater_profiles_fresh_and_degraded() -> None:
    rho = np.linspace(0.0, 3.5, 351)
    fresh = crater_profile(rho, depth_ratio=0.2, rim_ratio=0.04, diameter_m=100.0, degradation=0.0)
    old = crater_profile(rho, depth_ratio=0.2, rim_ratio=0.04, diameter_m=100.0, degradation=0.8)
    # Fresh: rim-to-floor depth 20 m, rim 4 m high at rho = 1, nothing beyond 3 R.
    assert fresh.max() - fresh.min() == pytest.approx(20.0, rel=1e-3)
    assert fresh[100] == pytest.approx(4.0, rel=1e-3)
    assert np.all(fresh[rho >= 3.0] == 0.0)
    # Degraded: shallower, lower and smoother rim.
    assert old.max() - old.min() < 0.5 * (fresh.max() - fresh.min())
    assert old.max() < 0.5 * fresh.max()
    assert np.abs(np.diff(old, 2)).max() < np.abs(np.diff(fresh, 2)).max()


def test_terrain_statistics_plains_are_smooth_and_reference_lacks_relief() -> None:
    cfg = load_config(
        "tiny", {"terrain": {"plains": {"fraction": 0.4}, "dunes": {"enabled": False}}}
    )
    grid = MapGrid.covering(-600, -600, 600, 600, 2.0, align=64.0)
    coarse = MapGrid.covering(-3000, -3000, 3000, 3000, 64.0, align=64.0)
    t = generate_terrain(cfg, grid, coarse, _streams())
    assert t.height.shape == grid.shape and np.isfinite(t.height).all()
    plains = t.plains.astype(np.float32)
    # Small-scale relief (height minus its 10 m smoothing) is much weaker on plains.
    h = t.height.astype(np.float64)
    detail = h - gaussian_filter(h, 5.0)
    in_plains = plains > 0.99
    rough = plains < 0.01
    assert in_plains.mean() > 0.2 and rough.mean() > 0.2
    assert detail[in_plains].std() < 0.6 * detail[rough].std()
    assert t.texture_amplitude[in_plains].astype(float).mean() < 0.3
    # The regional composite holds the truth's block means: smooth compared with it.
    fine_on_coarse = cubic_resample(t.regional_composite, coarse, grid)
    resid = h - fine_on_coarse
    assert resid.std() > 0.5  # small relief exists in the truth ...
    assert abs(resid.mean()) < 0.5  # ... and averages out at the coarse scale
    assert 0.02 <= float(t.albedo.min()) and float(t.albedo.max()) <= 0.9


def test_soft_mask_covers_the_requested_fraction() -> None:
    noise = fractal_field((300, 300), 1.0, np.random.default_rng(2), hurst=0.9)
    m = soft_mask(noise, 0.3)
    assert (m > 0.5).mean() == pytest.approx(0.3, abs=0.03)
    assert soft_mask(noise, 0.0).max() == 0.0
