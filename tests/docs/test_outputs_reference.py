"""Every file a georef run writes is in the outputs reference."""

from __future__ import annotations

import fnmatch
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _documented_patterns() -> list[str]:
    """Glob patterns of the first column of the georef run folder's table."""
    text = (ROOT / "docs" / "reference" / "outputs.md").read_text(encoding="utf-8")
    section = text.split("## A `georef` run folder", 1)[1].split("\n## ", 1)[0]
    patterns = []
    for line in section.splitlines():
        if line.startswith("| `"):
            first = line.split(" | ", 1)[0]
            for path in re.findall(r"`([^`]+)`", first):
                patterns.append(re.sub(r"<[a-z]+>", "*", path))
    return patterns


def test_every_file_of_a_georef_run_is_documented(tiny_sift_run):
    patterns = _documented_patterns()
    assert "*/adjustment/residuals.csv" in patterns
    run_dir = Path(tiny_sift_run.run_dir)
    files = sorted(p.relative_to(run_dir).as_posix() for p in run_dir.rglob("*") if p.is_file())
    assert len(files) > 20  # a whole run folder, not a stub
    undocumented = [f for f in files if not any(fnmatch.fnmatch(f, p) for p in patterns)]
    assert not undocumented, (
        f"files of a georef run missing from docs/reference/outputs.md: {undocumented}"
    )


def test_every_column_of_the_mcp_table_is_documented(tiny_sift_run):
    import pyarrow.parquet as pq

    text = (ROOT / "docs" / "reference" / "outputs.md").read_text(encoding="utf-8")
    section = text.split("**The MCP table**", 1)[1].split("**Orthoimages**", 1)[0]
    documented = set(re.findall(r"`([a-z_]+)`", section))
    columns = pq.read_schema(Path(tiny_sift_run.run_dir) / "strip1" / "mcps.parquet").names
    assert len(columns) > 10
    assert not set(columns) - documented, sorted(set(columns) - documented)


def test_every_key_of_a_georef_report_is_documented(tiny_sift_run):
    import json

    text = (ROOT / "docs" / "reference" / "outputs.md").read_text(encoding="utf-8")
    section = text.split("## `report.json` of a georef run", 1)[1].split("\n## ", 1)[0]
    documented = set(re.findall(r"`([A-Za-z_0-9]+)", section))
    report = json.loads((Path(tiny_sift_run.run_dir) / "report.json").read_text())
    missing = {k for k in report if k not in documented}
    for block in ("matching", "adjustment", "check", "timing_s"):
        missing |= {f"{block}.{k}" for k in report.get(block) or {} if k not in documented}
    assert not missing, sorted(missing)
