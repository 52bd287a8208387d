"""Re-running georef reloads the adjustment when its inputs are unchanged, redoes it when
its output was deleted; the tiles resume from their journal either way."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from planetref.pipeline.artefacts import RESULT_NAME, RESULT_STAMP


def _without_timings(report: dict) -> dict:
    return {k: v for k, v in report.items() if k not in ("timing_s", "resumed")}


@pytest.fixture
def rerun(tiny_sift_run, tiny_scene, ref_grid, tmp_path, monkeypatch):
    """A copy of the session's tiny sift run, and a re-run of it counting adjustments."""
    import planetref.adjust.api as api
    from planetref.pipeline.georef import run_georef

    run_dir = tmp_path / "run"
    shutil.copytree(tiny_sift_run.run_dir, run_dir)
    solved = []
    real = api.adjust

    def counting(*args, **kwargs):
        solved.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(api, "adjust", counting)

    def go():
        journal = (run_dir / "strip1" / "tiles.jsonl").read_bytes()
        out = run_georef(tiny_scene, "sift", run_dir, config=ref_grid, progress=False)
        # no tile matched again: the journal is as it was
        assert (run_dir / "strip1" / "tiles.jsonl").read_bytes() == journal
        return out

    return run_dir, solved, go


def test_unchanged_inputs_reload_the_adjustment(rerun, tiny_sift_run):
    run_dir, solved, go = rerun
    adj = run_dir / "strip1" / "adjustment"
    assert (adj / RESULT_NAME).is_file() and (adj / RESULT_STAMP).is_file()
    (adj / "residuals.csv").unlink()  # what follows the adjustment is written again
    out = go()
    assert solved == []  # reloaded, not solved
    assert out.report["resumed"] is True
    assert (adj / "residuals.csv").is_file()
    written = json.loads((run_dir / "report.json").read_text())
    original = json.loads((Path(tiny_sift_run.run_dir) / "report.json").read_text())
    assert _without_timings(written) == _without_timings(original)


def test_a_deleted_adjustment_is_solved_again(rerun, tiny_sift_run):
    run_dir, solved, go = rerun
    adj = run_dir / "strip1" / "adjustment"
    shutil.rmtree(adj)
    out = go()
    assert solved == [1]  # the adjustment, and only it, solved again
    assert (adj / RESULT_NAME).is_file() and (adj / "report.json").is_file()
    written = json.loads((run_dir / "report.json").read_text())
    original = json.loads((Path(tiny_sift_run.run_dir) / "report.json").read_text())
    assert _without_timings(written) == _without_timings(original)
    assert written["adjustment"]["n_inliers"] > 50 and written["check"]["geoloc_rmse_m"] > 0
    assert out.files["strip1"]["adjustment"]["report_json"] == str(adj / "report.json")
