from __future__ import annotations

import math

import numpy as np
import pytest

from planetref.simulate.config import AlbedoConfig, PhotometryConfig, SunConfig
from planetref.simulate.grid import MapGrid
from planetref.simulate.photometry import (
    RadianceModel,
    ShadingFields,
    TextureTiles,
    cast_shadow,
    lambert,
    lunar_lambert,
    mcewen_l,
    sun_vector,
)


def _flat_model(
    sun: SunConfig, model: str = "lambert", height: np.ndarray | None = None, sky: float = 0.0
) -> RadianceModel:
    grid = MapGrid(0.0, 200.0, 1.0, 200, 200)
    h = np.zeros(grid.shape, np.float32) if height is None else height
    shadow = cast_shadow(h, 1.0, sun)
    fields = ShadingFields(grid, h, np.full(grid.shape, 0.25), np.zeros(grid.shape), shadow)
    albedo = AlbedoConfig(mean=0.25)
    tiles = TextureTiles(albedo, 1.0, np.random.default_rng(0))
    phot = PhotometryConfig(model=model, sky_fraction=sky)
    return RadianceModel(fields, tiles, sun, phot, albedo, haze=0.0)


def test_lambert_radiance_is_proportional_to_cos_incidence() -> None:
    x = np.full(5, 100.0)
    y = np.full(5, 100.0)
    nadir = np.array([0.0, 0.0, 1.0])
    vals = []
    for el in (10.0, 25.0, 40.0, 60.0, 85.0):
        model = _flat_model(SunConfig(azimuth_deg=120.0, elevation_deg=el))
        vals.append(float(model.evaluate(x, y, nadir)[0]) / math.sin(math.radians(el)))
    np.testing.assert_allclose(vals, 0.25, rtol=1e-3)


def test_reflectance_functions() -> None:
    ci = np.array([0.0, 0.3, 0.8, -0.2])
    np.testing.assert_allclose(lambert(ci), [0.0, 0.3, 0.8, 0.0])
    # At zero phase L = 1: F = 2 cos i / (cos i + cos e).
    np.testing.assert_allclose(lunar_lambert(np.array([0.5]), np.array([0.5]), 0.0), [1.0])
    assert mcewen_l(0.0) == 1.0 and 0.0 < float(mcewen_l(60.0)) < 1.0
    s = sun_vector(SunConfig(azimuth_deg=90.0, elevation_deg=30.0))
    np.testing.assert_allclose(s, [math.cos(math.radians(30)), 0.0, 0.5], atol=1e-12)


def test_cast_shadow_of_a_wall_has_the_right_length() -> None:
    # A 10 m high north-south wall; the sun in the east at 30 degrees: the shadow reaches
    # 10 / tan(30) = 17.3 m to the west of the wall, nothing to the east.
    h = np.zeros((50, 200), np.float32)
    h[:, 100:103] = 10.0
    s = cast_shadow(h, 1.0, SunConfig(azimuth_deg=90.0, elevation_deg=30.0))
    row = s[25]
    shadow_cols = np.flatnonzero(row > 0.5)
    assert shadow_cols.min() >= 100 - 19 and shadow_cols.max() < 100
    assert len(shadow_cols) == pytest.approx(10 / math.tan(math.radians(30)), abs=1.5)
    assert row[103:].max() == 0.0
    high = cast_shadow(h, 1.0, SunConfig(azimuth_deg=90.0, elevation_deg=89.0))
    assert (high[25] > 0.5).sum() == 0


@pytest.mark.parametrize("azimuth", [0.0, 45.0, 200.0, 300.0])
def test_low_sun_casts_shadows_behind_a_hill(azimuth: float) -> None:
    grid = MapGrid(0.0, 200.0, 1.0, 200, 200)
    x = grid.x_centres()[None, :] - 100
    y = grid.y_centres()[:, None] - 100
    h = (20.0 * np.exp(-(x**2 + y**2) / 15.0**2)).astype(np.float32)
    sun = SunConfig(azimuth_deg=azimuth, elevation_deg=10.0)
    s = cast_shadow(h, 1.0, sun)
    sv = sun_vector(sun)
    # A point 30 m from the top away from the sun is in shadow; towards the sun, lit.
    nadir = np.array([0.0, 0.0, 1.0])
    model = _flat_model(sun, height=h, sky=0.05)
    for sign, shadowed in ((-1.0, True), (1.0, False)):
        mx, my = 100.0 + sign * 30.0 * sv[0], 100.0 + sign * 30.0 * sv[1]
        row, col = round(200.0 - my - 0.5), round(mx - 0.5)
        assert s[row, col] == (1.0 if shadowed else 0.0)
    dark = model.evaluate(np.array([100.0 - 30 * sv[0]]), np.array([100.0 - 30 * sv[1]]), nadir)
    lit = model.evaluate(np.array([100.0 + 30 * sv[0]]), np.array([100.0 + 30 * sv[1]]), nadir)
    assert float(dark[0]) < 0.5 * float(lit[0])
