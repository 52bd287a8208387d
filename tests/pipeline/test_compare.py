"""compare and demo on the tiny scene: both tables, all figures, skipped matchers listed."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from planetref.cli import main
from planetref.errors import InputError
from planetref.pipeline.compare import resolve_matchers, run_compare

PNG = b"\x89PNG\r\n\x1a\n"


def test_compare_tables_and_figures(tiny_scene, tmp_path, monkeypatch):
    # An empty weights folder: every learned matcher is skipped, with the missing files.
    empty = tmp_path / "no-weights"
    empty.mkdir()
    out = run_compare(
        tiny_scene, "sift,ncc,disk-lightglue", tmp_path / "cmp", weights_dir=empty, progress=False
    )
    rep = json.loads((out.run_dir / "report.json").read_text())
    assert set(rep) == {"scene", "runs", "skipped"}
    assert set(rep["runs"]) == {"sift", "ncc"}
    assert (
        "disk-lightglue" in rep["skipped"] and "depth-save.pth" in rep["skipped"]["disk-lightglue"]
    )
    for run in rep["runs"].values():
        assert run["check"]["geoloc_rmse_m"] < 5.0
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


def test_resolve_matchers(tmp_path):
    names, skipped = resolve_matchers("all", tmp_path)
    assert "sift" in names and "ncc" in names
    assert "loftr" in skipped and "loftr_outdoor.ckpt" in skipped["loftr"]
    with pytest.raises(InputError, match="valid: sift"):
        resolve_matchers("sift,nope", tmp_path)


def test_demo_command_prints_both_tables(tmp_path):
    r = CliRunner().invoke(
        main,
        ["-q", "demo", "--preset", "tiny", "--matchers", "sift", "--out", str(tmp_path / "demo")],
    )
    assert r.exit_code == 0, r.output
    assert "## Matching" in r.stdout and "## Adjustment" in r.stdout
    assert "report:" in r.stdout and "figures:" in r.stdout
    # The scene is cached: a second run does not simulate again.
    scene = tmp_path / "demo" / "scene-tiny-seed0" / "scene.toml"
    stamp = scene.stat().st_mtime_ns
    r = CliRunner().invoke(
        main,
        ["-q", "demo", "--preset", "tiny", "--matchers", "sift", "--out", str(tmp_path / "demo")],
    )
    assert r.exit_code == 0 and scene.stat().st_mtime_ns == stamp
