"""compare and demo on the tiny scene: both tables, all figures, skipped matchers listed."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from planetref.cli import main
from planetref.errors import InputError
from planetref.pipeline.compare import resolve_matchers, run_compare
from planetref.pipeline.config import config_from_mapping

#: NCC's dense default (one template per 2 reference px) is what the demo and the README
#: measure; the tests use a sparser grid so the default run stays fast on 2 cores.
#: Fine stage on the reference grid (fine_upsample = 1), as in the other pipeline tests.
FAST_NCC = config_from_mapping({"frontend": {"dense_spacing_ref_px": 8, "fine_upsample": 1}})

PNG = b"\x89PNG\r\n\x1a\n"


def test_compare_tables_and_figures(tiny_scene, tmp_path, monkeypatch, no_weight_packages):
    # An empty weights folder: every learned matcher is skipped, with the missing files.
    empty = tmp_path / "no-weights"
    empty.mkdir()
    out = run_compare(
        tiny_scene,
        "sift,ncc,disk-lightglue",
        tmp_path / "cmp",
        config=FAST_NCC,
        weights_dir=empty,
        progress=False,
    )
    rep = json.loads((out.run_dir / "report.json").read_text())
    assert set(rep) == {"scene", "runs", "skipped"}
    assert set(rep["runs"]) == {"sift", "ncc"}
    assert (
        "disk-lightglue" in rep["skipped"] and "depth-save.pth" in rep["skipped"]["disk-lightglue"]
    )
    for name, run in rep["runs"].items():
        assert run["check"]["geoloc_rmse_m"] < 5.0
        # Only actionable warnings: the tiny strip's unobserved nodes all lie in the
        # margin beyond the imaged lines, and its refitted RPCs (~0.2 px) are well below
        # half the adjustment's RMSE.
        warnings = [w for s in run["strips"].values() for w in s["warnings"]]
        assert not any("weak node" in w for w in warnings), warnings
        adj = json.loads(
            (out.run_dir / "runs" / name / "strip1" / "adjustment" / "report.json").read_text()
        )
        assert not any("RPC" in w for w in adj.get("output_warnings", [])), adj
    md = (out.run_dir / "report.md").read_text()
    assert "## Matching" in md and "## Adjustment" in md and "Skipped" in md
    for name in ("RMSE", "Mean", "Max X", "Max Y", "Min X", "Min Y", "OR (%)"):
        assert name in md
    assert "ccd1 NCP" in md and "ccd3 SDU (%)" in md
    header = (out.run_dir / "adjustment.csv").read_text().splitlines()[0]
    assert header.startswith("Matcher,Strip,RMSE,Mean,Max X,Max Y,Min X,Min Y,OR (%)")
    assert len((out.run_dir / "matching.csv").read_text().splitlines()) == 3
    figs = out.run_dir / "figures"
    expected = ["headline.png"] + [
        f"{m}_strip1_{k}.png"
        for m in ("sift", "ncc")
        for k in ("mcp_distribution", "residuals", "tile_matches")
    ]
    for name in expected:
        assert (figs / name).read_bytes()[:8] == PNG, name
    _check_report_html(out.run_dir, expected)


def _check_report_html(run_dir, expected):
    """report.html stands alone: every figure embedded and decodable, every table parses."""
    import csv
    import io

    import matplotlib.image as mpimg

    from planetref.report.document import read_report_html

    page = read_report_html(run_dir / "report.html")
    assert not page.external
    names = [n for n, _ in page.figures]
    assert sorted(names) == sorted(expected)  # every figure once, none missing
    for name, data in page.figures:
        assert data == (run_dir / "figures" / name).read_bytes(), name
        img = mpimg.imread(io.BytesIO(data), format="png")
        assert img.shape[0] > 200 and img.shape[1] > 300, name
    captions = [c for c, _ in page.tables]
    for key in (
        "NCP and SDU",
        "Residuals after adjustment",
        "True geolocation error",
        "funnel",
        "Wall-clock",
        "differ per matcher",
    ):
        assert any(key in c for c in captions), (key, captions)
    for caption, rows in page.tables:
        assert len(rows) >= 2 and all(len(r) == len(rows[0]) for r in rows), caption
    # The HTML tables hold the numbers of the CSVs.
    adj = next(rows for c, rows in page.tables if "Residuals after adjustment" in c)
    with open(run_dir / "adjustment.csv", encoding="utf-8") as fh:
        csv_rows = list(csv.reader(fh))
    assert adj[0] == csv_rows[0]
    for html_row, csv_row in zip(adj[1:], csv_rows[1:], strict=True):
        assert float(html_row[2]) == pytest.approx(float(csv_row[2]), abs=5e-4)
    text = (run_dir / "report.html").read_text()
    for word in ("Metric definitions", "sqrt((1/n)", "lower is better", "simulated"):
        assert word.lower() in text.lower(), word
    md = (run_dir / "report.md").read_text()
    assert "](figures/headline.png)" in md and "## Warnings" in md
    for name in ("matching", "adjustment", "truth", "funnel", "timing"):
        assert (run_dir / f"{name}.csv").is_file()
        tex = (run_dir / "tables" / f"{name}.tex").read_text()
        assert "\\toprule" in tex and "\\bottomrule" in tex


def test_resolve_matchers(tmp_path):
    names, skipped = resolve_matchers("all", tmp_path)
    assert "sift" in names and "ncc" in names
    assert "loftr" in skipped and "loftr_outdoor.ckpt" in skipped["loftr"]
    with pytest.raises(InputError, match="valid: sift"):
        resolve_matchers("sift,nope", tmp_path)


def test_demo_command_prints_both_tables(tmp_path, ref_grid_toml):
    args = ["-q", "demo", "--preset", "tiny", "--matchers", "sift", "--out", str(tmp_path / "demo")]
    args += ["--config", str(ref_grid_toml)]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    assert "## Matching" in r.stdout and "## Adjustment" in r.stdout
    assert "report:" in r.stdout and "figures:" in r.stdout
    # The scene is cached: a second run does not simulate again.
    scene = tmp_path / "demo" / "scene-tiny-seed0" / "scene.toml"
    stamp = scene.stat().st_mtime_ns
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0 and scene.stat().st_mtime_ns == stamp
