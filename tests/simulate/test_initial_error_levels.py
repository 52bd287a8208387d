"""Named initial-error levels: physical terms, each with a source, ground magnitude."""

from __future__ import annotations

import numpy as np
import pytest

from planetref.errors import InputError
from planetref.simulate.config import (
    INITIAL_ERROR_LEVELS,
    InitialErrorConfig,
    load_config,
    load_initial_errors_dict,
)

H = 265_000.0  # HiRIC's altitude in the presets (m)


@pytest.mark.parametrize("level", INITIAL_ERROR_LEVELS)
def test_every_term_of_a_level_is_set_and_sourced(level: str) -> None:
    table = load_initial_errors_dict(level)
    values = table["initial_errors"]
    assert set(values) == set(InitialErrorConfig.model_fields)  # every term, none left default
    sources = table["sources"]
    assert sorted(sources) == sorted(f"initial_errors.{k}" for k in values)
    assert all(len(s) > 20 for s in sources.values())
    cfg = load_config("tiny", initial_errors=level)
    assert cfg.name == f"tiny-ie{level}"
    assert cfg.sources == sources
    assert cfg.initial_errors.declared_uncertainty_m == values["declared_uncertainty_m"]


def _ground_m(e: InitialErrorConfig) -> float:
    """First-order horizontal ground error at nadir: position bias + H * (roll, pitch)."""
    along = e.position_bias_m[0] - H * e.attitude_bias_urad[1] * 1e-6
    cross = e.position_bias_m[1] + H * e.attitude_bias_urad[0] * 1e-6
    return float(np.hypot(along, cross))


def test_levels_have_their_magnitude_and_declare_a_bound_above_it() -> None:
    for level, size in (("100m", 100.0), ("1km", 1000.0), ("2km", 2000.0)):
        e = load_config("tiny", initial_errors=level).initial_errors
        g = _ground_m(e)
        assert 0.9 * size < g < 1.2 * size
        assert e.declared_uncertainty_m is not None
        assert g < e.declared_uncertainty_m < 1.4 * g
        assert e.attitude_bias_urad[2] >= 200.0  # yaw about the boresight
        assert e.position_bias_m[2] > 0.0  # an altitude (scale) error
    # The 100m level is the presets' errors, declared.
    preset = load_config("tiny").initial_errors
    e = load_config("tiny", initial_errors="100m").initial_errors
    assert e.model_copy(update={"declared_uncertainty_m": None}) == preset
    assert preset.declared_uncertainty_m is None


def test_unknown_level_names_the_valid_ones() -> None:
    with pytest.raises(InputError, match="valid levels: 100m, 1km, 2km"):
        load_config("tiny", initial_errors="5km")
