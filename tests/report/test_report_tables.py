"""Report tables: paper layout, missing values, CSV/Markdown/LaTeX round trips, the funnel."""

from __future__ import annotations

import csv
import io
import json

import pytest

from planetref.report.tables import (
    adjustment_rows,
    format_csv,
    format_latex_table,
    format_markdown_table,
    funnel_from_journal,
    funnel_from_report,
    funnel_rows,
    matching_rows,
    timing_rows,
    truth_rows,
)


def _run(ncp=(10, 20, 30), rmse=0.5, extra=None, check=True):
    ccds = {f"ccd{i + 1}": {"ncp": n, "sdu_pct": 2.0 * (i + 1)} for i, n in enumerate(ncp)}
    adj = {
        "rmse_px": rmse,
        "mean_px": 0.4,
        "max_x_px": 1.25,
        "max_y_px": 1.5,
        "min_x_px": -1.0,
        "min_y_px": -2.0,
        "outlier_ratio_pct": 3.0,
        "rmse_px_before": 40.0,
        "sigma0": 0.9,
        "n_total": sum(ncp),
        **(extra or {}),
    }
    return {
        "scene": "t",
        "matching": {
            "ccds": ccds,
            "ncp": sum(ncp),
            "sdu_pct": 4.0,
            "tiles_total": 4,
            "tiles_failed": 1,
        },
        "adjustment": adj,
        "strips": {"s1": {"adjustment": adj}},
        "check": {
            "geoloc_rmse_m_before": 100.0,
            "geoloc_rmse_m": 1.5,
            "geoloc_rmse_px": 0.6,
            "geoloc_max_m": 3.0,
            "formal_rmse_m": 1.2,
            "true_over_formal": 1.25,
        }
        if check
        else None,
        "timing_s": {"matching": 8.0, "adjustment": 1.0, "total": 10.0},
    }


def test_table1_and_table2_in_the_paper_layout():
    runs = {"sift": _run(), "ncc": _run((5, 6, 7), rmse=0.75)}
    h, rows = matching_rows(runs)
    assert h[:4] == ["Matcher", "ccd1 NCP", "ccd2 NCP", "ccd3 NCP"]
    assert rows[1][:4] == ["ncc", 5, 6, 7] and rows[0][-1] == "1/4"
    h, rows = adjustment_rows(runs)
    assert h[:9] == [
        "Matcher",
        "Strip",
        "RMSE",
        "Mean",
        "Max X",
        "Max Y",
        "Min X",
        "Min Y",
        "OR (%)",
    ]
    assert "RMSE x" not in h  # no run holds it
    assert rows[1][:3] == ["ncc", "s1", 0.75] and rows[0][8] == 3.0


def test_table1_counts_tiles_placed_by_the_ncc_fallback_only_when_a_matcher_needed_it():
    runs = {"sift": _run(), "ncc": _run((5, 6, 7))}
    # NCC's coarse stage is NCC's own search: it never makes the column appear.
    runs["ncc"]["matching"]["coarse_sources"] = {"ncc": 4}
    h, _ = matching_rows(runs)
    assert h[-1] == "tiles failed"
    runs["sift"]["matching"]["coarse_sources"] = {"matcher": 1, "ncc": 2}
    h, rows = matching_rows(runs)
    assert h[-1] == "tiles placed by NCC fallback"
    assert rows[0][-1] == "2/4" and rows[0][-2] == "1/4"


def test_per_axis_rmse_shown_when_present_and_missing_prints_dash():
    runs = {"a": _run(extra={"rmse_x_px": 0.3, "rmse_y_px": 0.4}), "b": _run()}
    h, rows = adjustment_rows(runs)
    ix, iy = h.index("RMSE x"), h.index("RMSE y")
    assert rows[0][ix] == 0.3 and rows[0][iy] == 0.4 and rows[1][ix] is None
    md = format_markdown_table(h, rows)
    b_line = next(line for line in md.splitlines() if line.startswith("| b "))
    assert [c.strip() for c in b_line.strip("|").split("|")][ix] == "-"


def test_csv_markdown_latex_agree():
    h, rows = adjustment_rows({"sift": _run()})
    back = list(csv.reader(io.StringIO(format_csv(h, rows))))
    assert back[0] == h and float(back[1][2]) == 0.5 and float(back[1][7]) == -2.0
    tex = format_latex_table(h, rows, caption="Table 2 (50% of x_y)", label="tab:adj")
    assert r"\toprule" in tex and r"\midrule" in tex and r"\bottomrule" in tex
    assert r"50\% of x\_y" in tex and r"OR (\%)" in tex
    body = [line for line in tex.splitlines() if line.endswith(r"\\")]
    assert len(body) == 2 and all(line.count("&") == len(h) - 1 for line in body)
    assert body[1].split(" & ")[2] == "0.500"
    # Text columns left, numbers right.
    assert tex.splitlines()[4].startswith(r"\begin{tabular}{ll" + "r" * 7)


def test_adjustment_rows_with_check_points():
    run = _run()
    run["adjustment"]["check_mcps"] = {
        "after": {"rms_px": 1.2, "rms_m": 3.0, "n": 40},
        "tiles": {"n_tiles": 2, "rms_normalised": 1.3},
    }
    h, rows = adjustment_rows({"sift": run, "ncc": _run()})
    i = h.index("Check (px)")
    assert h[i + 1 : i + 3] == ["Check (m)", "Check / predicted"]
    assert rows[0][i : i + 3] == [1.2, 3.0, 1.3]
    assert rows[1][i : i + 3] == [None, None, None]


def test_truth_and_timing_rows():
    runs = {"a": _run(), "b": _run(check=False)}
    h, rows = truth_rows(runs)
    assert [r[0] for r in rows] == ["a"] and rows[0][1:3] == [100.0, 1.5]
    i = h.index("formal (m)")
    assert h[i + 1] == "true/formal" and rows[0][i : i + 2] == [1.2, 1.25]
    assert h[i + 2 :] == [
        "tile offset (px)",
        "RANSAC matches",
        "true OR >1 px (%)",
        "true OR >3 px (%)",
    ]
    assert rows[0][i + 2] is None  # no tile term in this run's adjustment
    runs["a"]["adjustment"] = {"systematic": {"tile_offset_sigma_px": [1.234, 0.5]}}
    assert truth_rows(runs)[1][0][i + 2] == "1.23/0.50"
    runs["a"]["adjustment"] = {"systematic": {"tile_offset_sigma_px": [0.5, 0.5]}}
    assert truth_rows(runs)[1][0][i + 2] == 0.5
    h, rows = timing_rows(runs)
    assert h[-1] == "matching per tile (s)" and rows[0][-1] == pytest.approx(2.0)


def test_funnel_from_journal_and_rows(tmp_path):
    j = tmp_path / "tiles.jsonl"
    lines = [
        {
            "result": {
                "n_coarse_matches": 9,
                "n_coarse_inliers": 7,
                "n_matches": 50,
                "n_inliers": 40,
            }
        },
        {"result": {"n_coarse_matches": 3, "n_coarse_inliers": 0, "n_matches": 0, "n_inliers": 0}},
        {"result": {"funnel": {"raw": 100, "ransac": 80, "consensus": 70}}},
    ]
    j.write_text("\n".join(json.dumps(x) for x in lines) + "\nnot json\n")
    f = funnel_from_journal([j, tmp_path / "missing.jsonl"])
    assert f == {"coarse_raw": 12, "coarse_kept": 7, "raw": 150, "ransac": 120, "consensus": 70}
    h, rows = funnel_rows({"sift": f}, {"sift": 60})
    assert h == [
        "Matcher",
        "coarse_raw",
        "coarse_kept",
        "raw",
        "ransac",
        "consensus",
        "mcp",
        "kept of raw (%)",
    ]
    assert rows[0][-2] == 60 and rows[0][-1] == pytest.approx(40.0)


def test_funnel_from_report_sums_strips_or_takes_the_runs_own():
    rep = _run()
    assert funnel_from_report(rep) == {}
    rep["strips"] = {
        "s1": {"matching": {"funnel": {"raw": 10, "ransac": 8, "mcp": 8}}},
        "s2": {"matching": {"funnel": {"raw": 5, "ransac": 4, "mcp": 3}}},
    }
    assert funnel_from_report(rep) == {"raw": 15, "ransac": 12, "mcp": 11}
    rep["matching"]["funnel"] = {"raw": 1, "mcp": 1}
    assert funnel_from_report(rep) == {"raw": 1, "mcp": 1}


def test_simulated_scene_report_says_the_truth_camera_is_not_the_adjustments(tmp_path):
    """The camera that made a simulated scene's images departs from the adjustment's model
    (lens distortion, CCD placement, jitter): the report must not say they are the same."""
    from planetref.report.georef import CompareContext, write_compare_report
    from planetref.simulate.config import SimulationConfig

    ctx = CompareContext(scene="tiny", simulated=True)
    paths = write_compare_report({"sift": _run()}, {}, tmp_path, ctx)
    md = " ".join(paths["markdown"].split()) + " ".join(
        (tmp_path / "report.md").read_text().split()
    )
    assert "the one that made the images" not in md
    assert "is not the adjustment's model" in md and "lens distortion" in md
    # The settings the sentence names are the simulator's.
    assert {"truth_mismatch", "jitter"} <= set(SimulationConfig.model_fields)


def test_report_timing_header_wraps_and_the_csv_keeps_the_names(tmp_path):
    from planetref.report.georef import CompareContext, write_compare_report

    run = _run()
    run["timing_s"] = {"matching": 8.0, "outputs_adjustment_files": 1.5, "total": 10.0}
    write_compare_report({"sift": run}, {}, tmp_path, CompareContext(scene="x"))
    html = (tmp_path / "report.html").read_text()
    assert "<th>outputs adjustment files</th>" in html and "outputs_adjustment_files" not in html
    with open(tmp_path / "timing.csv") as fh:
        assert "outputs_adjustment_files (s)" in next(csv.reader(fh))


def test_agreement_rows_split_the_excess_and_calibrate_with_it():
    """The compare report's agreement table: per matcher its pairs' diff / predicted, the
    three-cornered hat's excess, and true over the formal precision with and without it."""
    import math

    from planetref.adjust.precision import CameraAgreement, excess_error
    from planetref.report.georef import agreement_rows, excess_block

    own = {"a": 0.3, "b": 0.4, "c": 0.5}
    ex = {"a": 0.0, "b": 0.0, "c": 1.2}
    pairs = [
        CameraAgreement(
            "s1",
            (x, y),
            math.sqrt(own[x] ** 2 + own[y] ** 2 + ex[x] ** 2 + ex[y] ** 2),
            (own[x], own[y]),
            441,
        )
        for x, y in (("a", "b"), ("a", "c"), ("b", "c"))
    ]
    runs = {
        n: {"check": {"geoloc_rmse_m": 1.3 if n == "c" else 0.5, "formal_rmse_m": 0.5}} for n in own
    }
    # what compare writes into each run: its excess from the three-cornered hat
    for name, excess in excess_error(pairs).items():
        runs[name]["agreement"] = excess_block(runs[name], excess)
    header, rows = agreement_rows(pairs, runs)
    assert header[-2:] == ["true / formal", "true / formal with excess"]
    by = {r[0]: dict(zip(header, r, strict=True)) for r in rows}
    # a's pairs: 1 (with b) and sqrt(1.78 / 0.34) = 2.29 (with c): their median
    assert by["a"]["median diff / predicted"] == f"{(1.0 + math.sqrt(1.78 / 0.34)) / 2:.2f}"
    assert by["c"]["excess (m)"] == "1.200" and by["a"]["excess (m)"] == "0.000"
    assert by["c"]["formal with excess (m)"] == f"{math.hypot(0.5, 1.2):.3f}"
    assert by["c"]["true / formal"] == "2.60"
    assert by["c"]["true / formal with excess"] == f"{1.3 / math.hypot(0.5, 1.2):.2f}"
    # no truth: no truth columns
    header, _ = agreement_rows(pairs, {n: {"check": {"formal_rmse_m": 0.5}} for n in own})
    assert "true / formal" not in header
