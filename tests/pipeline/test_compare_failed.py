"""A matcher that ran but failed stays a row; "skipped" only for one that could not run.

The compare-level bookkeeping is tested with a stand-in georef (cheap); the real failure
(SIFT on the tiny ``hard`` scene: every tile fails) end to end is marked slow.
"""

from __future__ import annotations

import csv
import json
from types import SimpleNamespace

import pytest

from planetref.errors import MatcherFailedError, MatchingError, WeightsError
from planetref.frontend.config import FrontendConfig
from planetref.report.blocks import failed_report, frontend_settings


def _matching_all_failed(n_tiles=6):
    """A strip's matching block where every tile failed (as matching_block writes it)."""
    return {
        "ccds": {c: {"ncp": 0, "sdu_pct": 0.0} for c in ("ccd1", "ccd2", "ccd3")},
        "ncp": 0,
        "n_mcps": 0,
        "tiles_total": n_tiles,
        "tiles_failed": n_tiles,
        "tiles_thinned": 0,
        "tile_status": {"ok": 0, "too_few_inliers": n_tiles},
        "tiles_lost": [
            {"tile": f"ccd1_r0_c{i}", "status": "too_few_inliers", "message": "3 inliers of 40"}
            for i in range(n_tiles)
        ],
        "funnel": {"raw": 240, "coarse_gate": 200, "ransac": 60, "consensus": 18},
        "drops": {"ransac:outlier": 140},
        "true_outliers": {
            "n": 60,
            "n_unmeasured": 0,
            "n_over_1px": 50,
            "n_over_3px": 45,
            "pct_over_1px": 100 * 50 / 60,
            "pct_over_3px": 75.0,
            "median_px": 12.0,
        },
    }


def test_failed_report_keeps_the_matching_block():
    rep = failed_report(
        "sift",
        "tiny",
        {"strip1": _matching_all_failed()},
        "strip strip1: only 0 matched control points",
        {"matching": 3.0},
        frontend_settings(FrontendConfig()),
    ).to_json()
    m = rep["matching"]
    assert rep["failed"].startswith("strip strip1") and rep["adjustment"] is None
    assert m["ncp"] == 0 and m["tiles_failed"] == m["tiles_total"] == 6
    assert m["funnel"]["ransac"] == 60 and m["true_outliers"]["pct_over_3px"] == 75.0
    assert set(m["ccds"]) == {"ccd1", "ccd2", "ccd3"}
    assert len(m["tiles_lost"]) == 6 and m["tiles_lost"][0]["strip"] == "strip1"
    assert m["settings"]["protocol"] == "default"
    assert rep["strips"]["strip1"] == {"matching": _matching_all_failed(), "failed": rep["failed"]}


def test_compare_keeps_a_failed_matcher_as_a_row(tiny_scene, tmp_path, monkeypatch):
    """sift ran and failed (a row with NCP 0, 6/6 tiles failed, funnel, reason); ncc could
    not run (skipped)."""
    import planetref.pipeline.georef as georef
    from planetref.pipeline.compare import run_compare
    from planetref.report.document import read_report_html

    def fake_run_georef(scene, name, out, **kw):
        if name == "ncc":
            raise WeightsError("weights missing: ncc.pth")
        rep = failed_report(
            name, "tiny", {"strip1": _matching_all_failed()}, "only 0 MCPs", {"total": 1.0}
        ).to_json()
        raise MatcherFailedError("only 0 MCPs", report=rep)

    monkeypatch.setattr(georef, "run_georef", fake_run_georef)
    # No matcher finished: the report is written with every row, then the command fails
    # in one line (issue 35).
    with pytest.raises(MatchingError, match=r"every matcher failed \(2\)"):
        run_compare(tiny_scene, "sift,ncc", tmp_path / "cmp", progress=False)
    outcome = SimpleNamespace(
        run_dir=tmp_path / "cmp", tables_markdown=(tmp_path / "cmp" / "report.md").read_text()
    )
    rep = json.loads((outcome.run_dir / "report.json").read_text())
    assert list(rep["runs"]) == ["sift"] and rep["runs"]["sift"]["failed"] == "only 0 MCPs"
    assert list(rep["skipped"]) == ["ncc"] and "ncc.pth" in rep["skipped"]["ncc"]
    with open(outcome.run_dir / "matching.csv", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 1 and rows[0]["Matcher"] == "sift"
    assert rows[0]["NCP"] == "0" and float(rows[0]["SDU (%)"]) == 0.0
    assert rows[0]["tiles failed"] == "6/6"
    with open(outcome.run_dir / "adjustment.csv", encoding="utf-8") as fh:
        adj = list(csv.DictReader(fh))
    assert adj[0]["Matcher"] == "sift" and adj[0]["status"] == "failed" and adj[0]["RMSE"] == ""
    with open(outcome.run_dir / "funnel.csv", encoding="utf-8") as fh:
        fun = list(csv.DictReader(fh))
    assert fun[0]["Matcher"] == "sift" and fun[0]["ransac"] == "60"
    with open(outcome.run_dir / "truth.csv", encoding="utf-8") as fh:
        truth = list(csv.DictReader(fh))
    assert truth[0]["Matcher"] == "sift" and float(truth[0]["true OR >3 px (%)"]) == 75.0
    md = outcome.tables_markdown
    assert "Failed matchers" in md and "only 0 MCPs" in md and "## Skipped matchers" in md
    page = read_report_html(outcome.run_dir / "report.html")
    text = (outcome.run_dir / "report.html").read_text()
    assert "Failed matchers" in text and "Skipped matchers" in text
    assert "front-end protocol" in text and "`default`" not in text  # rendered as <code>
    table1 = next(rows for c, rows in page.tables if "NCP and SDU" in c)
    assert table1[1][0] == "sift" and table1[1][-1] == "6/6"


@pytest.mark.slow
def test_sift_fails_on_tiny_hard_and_stays_a_row(tmp_path):
    """SIFT at tiny ``hard`` (default settings): every tile fails; the run is a row."""
    from planetref.pipeline.compare import run_compare
    from planetref.simulate.config import load_config
    from planetref.simulate.scene import simulate_scene

    scene = tmp_path / "scene"
    simulate_scene(load_config("tiny", seed=0, difficulty="hard"), scene)
    # Its only matcher failed: the report keeps the row, then compare fails in one line.
    with pytest.raises(MatchingError, match=r"every matcher failed \(1\)"):
        run_compare(scene, "sift", tmp_path / "cmp", progress=False)
    report = json.loads((tmp_path / "cmp" / "report.json").read_text())
    markdown = (tmp_path / "cmp" / "report.md").read_text()
    run = report["runs"]["sift"]
    m = run["matching"]
    assert run["failed"] and not report["skipped"]
    assert m["ncp"] == 0 and m["tiles_failed"] == m["tiles_total"] == 6
    assert m["funnel"]["raw"] > 0
    # SIFT's own coarse stage finds no consensus on any tile, so NCC's bounded coarse
    # search places every fine window (frontend.coarse_fallback), and Table 1 says so.
    assert m["coarse_sources"] == {"ncc": 6}
    assert "tiles placed by NCC fallback" in markdown
    # Around the right window, what RANSAC keeps is still mostly wrong (measured: 16 of 20
    # matches beyond 1 reference px, 7 beyond 3, median 2.2 px): the true OR sees the
    # matcher's outliers that no adjustment could.
    assert m["true_outliers"]["n"] == m["funnel"]["ransac"] > 0
    assert m["true_outliers"]["pct_over_1px"] > 50.0
    assert m["true_outliers"]["pct_over_3px"] > 20.0
    assert "| sift" in markdown and "6/6" in markdown


def test_ncp_counts_the_unique_mcps_and_the_funnel_shows_the_mcp_stage():
    """NCP per CCD = verified less what the MCP stage dropped; funnel ends at mcp_unique."""
    import numpy as np

    from planetref.control.mcp import McpCounts, McpTable
    from planetref.frontend.config import FrontendConfig
    from planetref.frontend.result import StripMatches, TileResult
    from planetref.frontend.tiles import Tile
    from planetref.report.blocks import matching_block

    def tile(tid, ccd, status, n, raw):
        t = TileResult(Tile(tid, ccd, 0, 0, 100, 100), "ncc", status)
        t.line = t.sample = np.arange(n, dtype=float) + 0.5
        for name in ("ref_col", "ref_row", "ref_x", "ref_y", "confidence"):
            setattr(t, name, np.zeros(n))
        for stage, count in (("raw", raw), ("ransac", n + 1), ("backprojection", n), ("mcp", n)):
            t.record(stage, count)
        return t

    tiles = [
        tile("ccd1:r0c0", "ccd1", "ok", 5, 10),
        tile("ccd1:r1c0", "ccd1", "too_few_inliers", 3, 8),  # failed after its mcp stage
        tile("ccd2:r0c0", "ccd2", "ok", 4, 9),
    ]
    matches = StripMatches("ncc", FrontendConfig(), {}, tiles)
    # The MCP stage kept 3 of ccd1's 5 (2 duplicates) and ccd2's 4.
    ccd = ["ccd1"] * 3 + ["ccd2"] * 4
    cols = {
        "mcp_id": np.arange(7),
        "ccd": ccd,
        "tile_id": ["t"] * 7,
        "line": np.arange(7) * 10.0 + 5,
        "sample": np.arange(7) * 10.0 + 5,
    }
    from planetref.control.mcp import MCP_COLUMNS

    cols |= {c: np.zeros(7) for c in MCP_COLUMNS if c not in cols}
    cols["matcher"] = ["ncc"] * 7
    table = McpTable(cols, None, McpCounts(candidates=9, duplicates=2, kept=7))
    m = matching_block(matches, table, {"ccd1": (100, 100), "ccd2": (100, 100)}).to_json()
    assert m["ccds"]["ccd1"]["ncp"] == 3 and m["ccds"]["ccd2"]["ncp"] == 4
    assert m["ncp"] == m["n_mcps"] == 7
    assert m["funnel"]["mcp"] == 12 and m["funnel"]["mcp_unique"] == 7
    assert m["drops"]["mcp_unique:duplicates"] == 2
    assert m["drops"]["mcp_unique:tile_failed"] == 3
    assert "mcp_unique:nan_dem" not in m["drops"]
