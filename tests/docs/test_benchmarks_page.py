"""The benchmarks page is made from the JSON results the benchmark scripts write."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import benchmarks_page

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))
import machine  # noqa: E402  (benchmarks/machine.py: the scripts' own helper)


def test_a_written_result_shows_its_figures_machine_date_and_command(tmp_path):
    record = machine.result_record(
        "bench_terrain",
        [{"name": "nadir: CPU time per batch", "value": 0.1437, "unit": "CPU-s"}],
        title="Ray/DEM intersection",
    )
    machine.write_result(str(tmp_path / "bench_terrain.json"), record)
    page = benchmarks_page.page(tmp_path)
    assert "## Ray/DEM intersection" in page
    assert "| nadir: CPU time per batch | 0.1437 | CPU-s |" in page
    assert record["date"] in page
    assert f"`{record['command']}`" in page
    assert str(record["machine"]["cpu"]) in page
    # The description is the script's own docstring, not typed into the JSON.
    assert "Ray/DEM intersection speed and precision" in page


def test_latest_result_of_each_benchmark_wins_and_loose_json_shows(tmp_path):
    old = {"benchmark": "bench_x", "date": "2026-01-01T00:00:00Z", "figures": {"speedup": 2.0}}
    new = {"benchmark": "bench_x", "date": "2026-02-01T00:00:00Z", "figures": {"speedup": 3.5}}
    flat = {"machine": {"cpu": "Test CPU", "cores": 2}, "planetref_s": 1.25, "nested": {"a": 1}}
    (tmp_path / "a.json").write_text(json.dumps(old))
    (tmp_path / "b.json").write_text(json.dumps(new))
    (tmp_path / "bench_adjust_ceres.json").write_text(json.dumps(flat))
    page = benchmarks_page.page(tmp_path)
    assert "| speedup | 3.5 |" in page
    assert "| speedup | 2 |" not in page
    assert "| planetref_s | 1.25 |" in page
    assert "| nested.a | 1 |" in page
    assert "Test CPU, 2 cores available" in page


def test_the_seeded_results_load():
    results = benchmarks_page.latest()
    assert results, "benchmarks/results/ holds no result"
    for r in results:
        assert r.figures and r.date and r.command.startswith("python benchmarks/")
        assert r.machine.get("cpu")
