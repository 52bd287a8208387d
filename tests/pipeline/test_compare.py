"""compare and demo on the tiny scene: both tables, all figures, skipped matchers listed."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import pytest
from click.testing import CliRunner, Result

from planetref.cli import main
from planetref.errors import InputError
from planetref.matching.weights import NO_PACKAGES_ENV_VAR
from planetref.pipeline.compare import resolve_matchers
from planetref.pipeline.config import config_from_mapping, load_config

#: NCC's dense default (one template per 2 reference px) is what the demo and the README
#: measure; the tests use a sparser grid so the default run stays fast on 2 cores.
#: Fine stage on the reference grid (fine_upsample = 1), as in the other pipeline tests.
FAST_NCC = config_from_mapping({"frontend": {"dense_spacing_ref_px": 8, "fine_upsample": 1}})
FAST_NCC_TOML = "[frontend]\ndense_spacing_ref_px = 8\nfine_upsample = 1\n"

PNG = b"\x89PNG\r\n\x1a\n"


@dataclass(frozen=True)
class DemoRuns:
    """``planetref demo`` run twice into one folder (the second finds the cached scene)."""

    base: Path
    first: Result
    second: Result
    scene_mtime_ns: tuple[int, int]  # scene.toml after the first and after the second run

    @property
    def compare_dir(self) -> Path:
        return self.base / "compare-tiny-seed0"


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> DemoRuns:
    """``planetref demo`` on the tiny preset, run twice; both runs done before any test reads.

    One compare of sift, ncc and disk-lightglue with an empty weights folder (every learned
    matcher is skipped, with the missing files) and only that folder counting
    (``PLANETREF_NO_WEIGHT_PACKAGES``), NCC on the sparser grid: what
    ``test_compare_tables_and_figures`` checks, through the command a user types (which
    calls ``run_compare``), so that the tiny compare runs once instead of twice.
    """
    root = tmp_path_factory.mktemp("demo")
    config = root / "fast_ncc.toml"
    config.write_text(FAST_NCC_TOML)
    assert load_config(config) == FAST_NCC
    empty = root / "no-weights"
    empty.mkdir()
    base = root / "demo"
    args = ["-q", "demo", "--preset", "tiny", "--matchers", "sift,ncc,disk-lightglue"]
    args += ["--out", str(base), "--config", str(config), "--weights-dir", str(empty)]
    runner = CliRunner(env={NO_PACKAGES_ENV_VAR: "1"})
    first = runner.invoke(main, args)
    scene = base / "scene-tiny-seed0" / "scene.toml"
    stamp = scene.stat().st_mtime_ns if scene.is_file() else -1
    second = runner.invoke(main, args)
    again = scene.stat().st_mtime_ns if scene.is_file() else -2
    return DemoRuns(base, first, second, (stamp, again))


def test_compare_tables_and_figures(demo):
    assert demo.first.exit_code == 0, demo.first.output
    run_dir = demo.compare_dir
    rep = json.loads((run_dir / "report.json").read_text())
    assert set(rep) == {"scene", "runs", "skipped", "agreement"}
    # two matchers: no split of the excess (one equation, two unknowns)
    assert rep["agreement"]["excess_m"] == {}
    assert set(rep["runs"]) == {"sift", "ncc"}
    # The two matchers' adjusted cameras compared, with no truth: one pair on one strip,
    # over the same 3 x 21 x 21 grid as the true error.
    (pair,) = rep["agreement"]["pairs"]
    assert pair["strip"] == "strip1" and sorted(pair["matchers"]) == ["ncc", "sift"]
    assert pair["n"] == 3 * 21 * 21 and 0 < pair["diff_m"] < 10.0
    assert abs(pair["predicted_m"] ** 2 - sum(v * v for v in pair["own_m"])) < 1e-9
    assert abs(pair["ratio"] - pair["diff_m"] / pair["predicted_m"]) < 1e-9
    assert (
        "disk-lightglue" in rep["skipped"] and "depth-save.pth" in rep["skipped"]["disk-lightglue"]
    )
    for name, run in rep["runs"].items():
        assert run["check"]["geoloc_rmse_m"] < 5.0
        m = run["matching"]
        # NCP = the unique MCPs delivered to the adjustment (no thinning here), and the
        # funnel ends with them; what the MCP stage dropped is in its drops.
        (strip,) = run["strips"].values()
        assert m["ncp"] == strip["matching"]["n_mcps"] == m["funnel"]["mcp_unique"]
        n_check = run["adjustment"]["check_mcps"]["after"]["n"]  # held out as check points
        assert m["ncp"] == run["adjustment"]["n_total"] + n_check
        dropped = sum(v for k, v in m["drops"].items() if k.startswith("mcp_unique:"))
        assert m["funnel"]["mcp"] - m["funnel"]["mcp_unique"] == dropped
        # The true outlier ratio of the matches after RANSAC (a simulated scene).
        t = m["true_outliers"]
        assert t["n"] + t["n_unmeasured"] == m["funnel"]["ransac"] and t["n"] > 0
        assert 0.0 <= t["pct_over_3px"] <= t["pct_over_1px"] <= 100.0
        assert m["settings"]["protocol"] == "default"
        # Only actionable warnings: the tiny strip's unobserved nodes all lie in the
        # margin beyond the imaged lines, and its refitted RPCs (~0.2 px) are well below
        # half the adjustment's RMSE.
        warnings = [w for s in run["strips"].values() for w in s["warnings"]]
        assert not any("weak node" in w for w in warnings), warnings
        adj = json.loads(
            (run_dir / "runs" / name / "strip1" / "adjustment" / "report.json").read_text()
        )
        assert not any("RPC" in w for w in adj.get("output_warnings", [])), adj
    md = (run_dir / "report.md").read_text()
    assert "## Matching" in md and "## Adjustment" in md and "Skipped" in md
    assert "## Matcher agreement (no truth needed)" in md and "median diff / predicted" in md
    for name in ("RMSE", "Mean", "Max X", "Max Y", "Min X", "Min Y", "OR (%)"):
        assert name in md
    assert "ccd1 NCP" in md and "ccd3 SDU (%)" in md
    header = (run_dir / "adjustment.csv").read_text().splitlines()[0]
    assert header.startswith("Matcher,Strip,RMSE,Mean,Max X,Max Y,Min X,Min Y,OR (%)")
    assert len((run_dir / "matching.csv").read_text().splitlines()) == 3
    figs = run_dir / "figures"
    expected = ["headline.png"] + [
        f"{m}_strip1_{k}.png"
        for m in ("sift", "ncc")
        for k in ("mcp_distribution", "residuals", "tile_matches")
    ]
    for name in expected:
        assert (figs / name).read_bytes()[:8] == PNG, name
    _check_report_html(run_dir, expected)


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
    for word in (
        "Metric definitions",
        "sqrt((1/n)",
        "lower is better",
        "simulated",
        "front-end protocol",
        "true OR &gt;3 px",
    ):
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


def test_demo_command_prints_both_tables(demo):
    r = demo.first
    assert r.exit_code == 0, r.output
    assert "## Matching" in r.stdout and "## Adjustment" in r.stdout
    assert "report:" in r.stdout and "figures:" in r.stdout
    # The scene is cached: a second run does not simulate again.
    stamp, again = demo.scene_mtime_ns
    assert stamp > 0
    assert demo.second.exit_code == 0, demo.second.output
    assert again == stamp


def test_seeds_summary_of_real_comparisons(demo, tmp_path):
    """The rankings read real comparison reports (the same scene twice: no spread, and
    every paired gap the same on both, its standard error 0)."""
    from planetref.pipeline.compare import summarize_compares

    assert demo.first.exit_code == 0, demo.first.output
    out = summarize_compares({"a": demo.compare_dir, "b": demo.compare_dir}, tmp_path / "s")
    rep = json.loads((demo.compare_dir / "report.json").read_text())
    s = out.summary
    assert s.matchers == ["sift", "ncc"] and "disk-lightglue" in s.skipped
    for name, run in rep["runs"].items():
        true = s.metrics["geoloc_rmse_m"][name]
        assert true.mean == pytest.approx(run["check"]["geoloc_rmse_m"]) and true.std == 0.0
        assert s.metrics["ncp"][name].mean == run["matching"]["ncp"]
        assert s.metrics["true_or_3px_pct"][name].n == 2
    ncp = {n: r["matching"]["ncp"] for n, r in rep["runs"].items()}
    pair = s.pair("ncp", "sift", "ncc")
    assert pair.mean == ncp["sift"] - ncp["ncc"] and pair.se == 0.0 and pair.n == 2
    assert pair.beyond_noise == (ncp["sift"] != ncp["ncc"])
    assert any("over 2 seeds" in r for r in s.ranking)
    assert (tmp_path / "s" / "report.html").is_file() and (tmp_path / "s" / "seeds.json").is_file()


def test_demo_seeds_runs_one_comparison_per_seed_and_ranks(tmp_path, monkeypatch):
    """``demo --seeds 2``: seeds 3 and 4 simulated and compared, then the rankings (the
    simulation and the comparisons are stand-ins; the real ones are tested above)."""
    import planetref.cli.simulate as sim
    import planetref.pipeline.compare as compare

    calls = []

    def fake_simulate(config, out, **kw):
        calls.append(("simulate", config.seed, Path(out).name))
        Path(out).mkdir(parents=True)
        (Path(out) / "scene.toml").write_text("")

    def fake_compare(scene, matchers, out, **kw):
        seed = int(str(scene).rsplit("seed", 1)[1])
        calls.append(("compare", seed, matchers))
        out = Path(out)
        out.mkdir(parents=True)
        runs = {
            m: {
                "matching": {"ncp": 100 * (i + 1) + seed, "sdu_pct": 5.0},
                "adjustment": {"rmse_px": 0.5},
                "check": {"geoloc_rmse_m": 1.0 + i + 0.1 * seed},
            }
            for i, m in enumerate(matchers.split(","))
        }
        (out / "report.json").write_text(json.dumps({"runs": runs, "skipped": {}}))
        return compare.CompareOutcome(report={}, run_dir=out, tables_markdown="")

    monkeypatch.setattr(sim, "simulate_run", fake_simulate)
    monkeypatch.setattr(compare, "run_compare", fake_compare)
    args = ["-q", "demo", "--preset", "tiny", "--seed", "3", "--seeds", "2"]
    args += ["--matchers", "sift,ncc", "--out", str(tmp_path)]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    assert [c for c in calls if c[0] == "simulate"] == [
        ("simulate", 3, "scene-tiny-seed3"),
        ("simulate", 4, "scene-tiny-seed4"),
    ]
    assert [c[1] for c in calls if c[0] == "compare"] == [3, 4]
    folder = tmp_path / "seeds-tiny-seed3-4"
    doc = json.loads((folder / "seeds.json").read_text())
    assert doc["n_seeds"] == 2 and doc["seeds"] == ["seed3", "seed4"]
    assert doc["metrics"]["geoloc_rmse_m"]["ncc"]["mean"] == pytest.approx(2.35)
    # sift is 1 m better on both seeds: a constant gap, beyond noise.
    (pair,) = [p for p in doc["pairs"] if p["metric"] == "geoloc_rmse_m"]
    assert pair["beyond_noise"] and pair["better"] == "sift"
    assert "over 2 seeds" in r.stdout and "sift 1.35 +- 0.0707 >> ncc" in r.stdout, r.stdout
