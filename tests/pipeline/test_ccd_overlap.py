"""``[frontend.ccd_overlap]``: the strip's CCD-overlap ties in the same adjustment as its MCPs."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from planetref.pipeline.config import GeorefConfig, config_from_mapping
from planetref.pipeline.georef import run_georef

ON = {"frontend": {"fine_upsample": 1, "ccd_overlap": {"enabled": True}}}


def test_overlap_ties_off_keep_the_run_identity() -> None:
    # Off (the default), the table is left out of the configuration digest: runs made
    # before it existed resume; on, it is part of it.
    assert "ccd_overlap" not in GeorefConfig().identity_json()["frontend"]
    assert config_from_mapping(ON).identity_json()["frontend"]["ccd_overlap"]["enabled"]
    assert "ccd_overlap" not in config_from_mapping(ON).frontend.identity()


def test_overlap_ties_join_the_strip_adjustment(tiny_scene, tiny_sift_run, tmp_path) -> None:  # type: ignore[no-untyped-def]
    out = run_georef(
        tiny_scene, "sift", tmp_path / "ovl", config=config_from_mapping(ON), progress=False
    )
    rep = out.report
    block = rep["strips"]["strip1"]["ccd_overlap"]
    facts = json.loads((tiny_scene / "truth" / "errors.json").read_text())["strip1"]["facts"]
    period = facts["line_period_s"]  # 0.78 ms
    # tiny: 640 lines, a template every 8 lines in each of the two overlaps.
    assert block["n_ties"] > 100
    assert set(block["pairs"]) == {"ccd1~ccd2", "ccd2~ccd3"}
    for pair in block["pairs"].values():
        # The middle CCD sits 0.2 mm (20 lines) ahead of its neighbours (the truth's CCD
        # placement errors move it by up to a line).
        assert abs(pair["stagger_lines"]) == pytest.approx(20.0, abs=1.5)
        assert pair["stagger_s"] == pytest.approx(abs(pair["stagger_lines"]) * period)
        assert pair["unit_gain_hz"] == pytest.approx(1.0 / (6.0 * pair["stagger_s"]))
    # The ties are adjusted: their residuals after are at the level of the matching and
    # of what the node model cannot follow (tiny's jitter, 2 and 1.5 urad at 7 and 11
    # Hz, and its attitude oscillation at 6 Hz); measured 0.15 px before, 0.10 after.
    assert block["rmse_px"] < 0.3
    assert block["n_inlier_observations"] > 1.8 * block["n_ties"]
    # ... and they do not hurt the node model's true error (tiny's default run: the same
    # MCPs, without the ties): measured 1.81 m with them, 1.95 m without.
    base = tiny_sift_run.report["check"]["geoloc_rmse_m"]
    assert rep["check"]["geoloc_rmse_m"] < 1.0 * base, (rep["check"], base)
    # The formal precision stays calibrated with the ties: they carry no CCD-offset
    # consider term (their pair's median offset is taken off, and a CCD's constant
    # offset with it). Measured true 1.68 m, formal 1.33 m (true / formal 1.27); when
    # the ties propagated the CCD offsets, formal 6.6 m (0.26).
    assert 0.5 < rep["check"]["true_over_formal"] < 2.0, rep["check"]
    # The reprojection metrics are the MCPs' alone, as without the ties, and the ties
    # (judged by the outlier rule apart) reject none of them.
    for key in ("n_total", "n_inliers"):
        assert rep["adjustment"][key] == tiny_sift_run.report["adjustment"][key]
    with open(out.files["strip1"]["ccd_overlap"], newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == block["n_ties"]
    off = np.array([float(r["line_offset"]) for r in rows])
    assert np.median(np.abs(off)) == pytest.approx(20.0, abs=1.0)
    assert (out.run_dir / "strip1" / "ccd_overlap_ties.csv").is_file()
    assert rep["timing_s"]["ccd_overlap"] > 0
