"""report.json is one typed model (GeorefReport) whose schema the docs publish."""

from __future__ import annotations

import json
from pathlib import Path

from planetref.report.model import GeorefReport, report_schema
from planetref.runtime.atomic import json_safe

ROOT = Path(__file__).resolve().parents[2]
SCHEMA = ROOT / "docs" / "reference" / "report-schema.json"


def test_the_published_schema_is_the_models():
    published = json.loads(SCHEMA.read_text(encoding="utf-8"))
    assert published == report_schema(), (
        "docs/reference/report-schema.json is stale: regenerate it with\n"
        'python -c "import json; from planetref.report.model import report_schema; '
        'print(json.dumps(report_schema(), indent=2, sort_keys=True))" '
        "> docs/reference/report-schema.json"
    )
    for key in ("matching", "adjustment", "check", "timing_s", "strips"):
        assert key in published["properties"]
    assert set(published["required"]) >= {"matcher", "matching", "adjustment", "strips"}


def test_report_json_is_the_typed_model_and_reads_back(tiny_sift_run):
    written = json.loads((Path(tiny_sift_run.run_dir) / "report.json").read_text())
    # What was written is the model the run built (NaN as null, as the file holds it) ...
    assert json_safe(tiny_sift_run.typed.to_json()) == written
    assert json_safe(tiny_sift_run.report) == written
    # ... and the file reads back into the model with the same keys and values.
    back = GeorefReport.model_validate(written)
    assert json_safe(back.to_json()) == written
    assert back.strips["strip1"].matching.ncp == written["matching"]["ncp"] > 50
    assert back.adjustment is not None and back.adjustment.converged is True
    assert list(written) == list(back.to_json())  # the keys in the file's order


def test_an_unknown_key_is_refused():
    import pytest
    from pydantic import ValidationError

    doc = {
        "matcher": "sift",
        "scene": "s",
        "planetref_version": "0",
        "matching": {"ccds": {}, "ncp": 0, "sdu_pct": 0.0, "surprise": 1},
        "adjustment": None,
        "check": None,
        "timing_s": {},
        "strips": {},
    }
    with pytest.raises(ValidationError, match="surprise"):
        GeorefReport.model_validate(doc)
    del doc["matching"]["surprise"]
    assert GeorefReport.model_validate(doc).to_json() == doc
