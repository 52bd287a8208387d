"""A campaign of two overlapping strips: each strip on its own, or both tied together."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from planetref.pipeline.config import GeorefConfig, config_from_mapping
from planetref.pipeline.georef import run_georef
from planetref.simulate.config import load_config
from planetref.simulate.scene import simulate_scene

#: The fine stage on the reference grid, as the ``ref_grid`` fixture (tests/conftest.py).
REF_GRID = {"frontend": {"fine_upsample": 1}}

#: Two tiny strips 1.4 km apart across track: each is 2.3 km wide, so they share ~0.9 km.
TWO_STRIPS = {
    "strips": [
        {"id": "strip1", "cross_offset_m": -700.0},
        {"id": "strip2", "cross_offset_m": 700.0},
    ]
}


@pytest.fixture(scope="module")
def two_strip_scene(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("scenes") / "two_strips"
    simulate_scene(load_config("tiny", TWO_STRIPS, seed=0), out)
    return out


#: An explicit ``[campaign] adjust_together = false``: the same settings as ``ref_grid``
#: (asserted in test_adjust_separately_is_the_default), so ``separate`` is also the run
#: with the default campaign table.
OFF = {"campaign": {"adjust_together": False}, **REF_GRID}


@pytest.fixture(scope="module")
def separate(two_strip_scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "separate"
    cfg = config_from_mapping(OFF)
    return run_georef(two_strip_scene, "sift", out, config=cfg, progress=False)


def test_adjust_together_ties_the_strips(two_strip_scene, separate, tmp_path):
    cfg = config_from_mapping({"campaign": {"adjust_together": True}, **REF_GRID})
    out = run_georef(two_strip_scene, "sift", tmp_path / "together", config=cfg, progress=False)
    rep = out.report
    camp = rep["campaign"]
    assert camp["n_tie_points"] > 0
    assert camp["tie_points_per_strip_pair"] == {"strip1~strip2": camp["n_tie_points"]}
    assert rep["adjustment"]["n_tie_points"] == camp["n_tie_points"]
    assert rep["adjustment"]["converged"]
    for sid in ("strip1", "strip2"):
        s = rep["strips"][sid]
        assert s["adjustment"]["n_tie_observations"] > 0
        assert s["check"]["geoloc_rmse_m_before"] > 50.0
        assert s["check"]["geoloc_rmse_m"] < 5.0
        # The same MCPs as when each strip is adjusted on its own.
        assert s["matching"] == separate.report["strips"][sid]["matching"]
        assert (out.run_dir / sid / "ortho").is_dir()
    joint = json.loads((out.run_dir / "campaign" / "adjustment" / "report.json").read_text())
    assert joint
    assert set((out.run_dir / "campaign" / "adjustment" / "cameras").iterdir())
    assert (
        json.loads((out.run_dir / "report.json").read_text())["campaign"]["n_tie_points"]
        == camp["n_tie_points"]
    )


def test_adjust_separately_is_the_default(separate, ref_grid):
    # The default campaign table leaves the run's configuration (and its digest) as before.
    default = config_from_mapping({"campaign": {"adjust_together": False}})
    assert default.to_json() == GeorefConfig().to_json()
    assert default == GeorefConfig()
    assert "campaign" not in GeorefConfig().to_json()
    off = config_from_mapping(OFF)
    assert off.to_json() == ref_grid.to_json()
    # Equal settings: ``separate`` (run with ``off``) is the run with ``ref_grid`` too.
    assert off == ref_grid
    assert "campaign" not in separate.report
    assert set(separate.report["strips"]) == {"strip1", "strip2"}
    for sid in ("strip1", "strip2"):
        s = separate.report["strips"][sid]
        assert "n_tie_observations" not in s["adjustment"]
        assert s["check"]["geoloc_rmse_m"] < 5.0
        assert (separate.run_dir / sid / "adjustment" / "report.json").is_file()
    assert not (separate.run_dir / "campaign").exists()
