"""Re-running georef reloads the adjustment when its inputs are unchanged; the tiles resume
from their journal. (A deleted adjustment is solved again: tests/pipeline/test_georef.py.)"""

from __future__ import annotations

import hashlib
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


def test_a_result_file_not_the_recorded_one_is_solved_again(rerun):
    """An edited result file is never unpickled: its digest differs from the stamp's."""
    run_dir, solved, go = rerun
    adj = run_dir / "strip1" / "adjustment"
    data = (adj / RESULT_NAME).read_bytes()
    (adj / RESULT_NAME).write_bytes(data[:-1] + bytes([data[-1] ^ 1]))  # one bit changed
    go()
    assert solved == [1]  # solved again, not loaded
    # and written again, its new content recorded in the stamp
    new = (adj / RESULT_NAME).read_bytes()
    assert (adj / RESULT_STAMP).read_text().split()[1] == hashlib.sha256(new).hexdigest()


def test_the_fingerprint_follows_the_adjustments_inputs(tiny_sift_run):
    import dataclasses
    import pickle

    from planetref.pipeline.artefacts import adjustment_fingerprint

    adj = Path(tiny_sift_run.run_dir) / "strip1" / "adjustment"
    with (adj / RESULT_NAME).open("rb") as fh:
        result = pickle.load(fh)
    net, cfg = result.network, result.config
    digest = adjustment_fingerprint(net, cfg)
    assert digest == (adj / RESULT_STAMP).read_text().split()[0]  # what the run stamped
    assert adjustment_fingerprint(dataclasses.replace(net), cfg) == digest
    # one observation moved by 0.01 px, one check flag, the settings, the initial camera
    line = net.obs_line.copy()
    line[0] += 0.01
    check = net.obs_check.copy()
    check[0] = not check[0]
    cam = net.cameras[0]

    class Moved:  # the initial camera, described otherwise
        def __getattr__(self, name):
            return getattr(cam, name)

        def to_dict(self):
            return {**cam.to_dict(), "moved": True}

    class Opaque:  # the initial camera, without a description
        def __getattr__(self, name):
            if name == "to_dict":
                raise AttributeError(name)
            return getattr(cam, name)

    others = [
        dataclasses.replace(net, obs_line=line),
        dataclasses.replace(net, obs_check=check),
        dataclasses.replace(net, cameras=(Moved(),)),
    ]
    for other in others:
        assert adjustment_fingerprint(other, cfg) not in (digest, None)
    assert (
        adjustment_fingerprint(net, cfg.model_copy(update={"fixed_cameras": ["strip1"]})) != digest
    )
    # a camera that cannot describe itself: never reloaded
    assert adjustment_fingerprint(dataclasses.replace(net, cameras=(Opaque(),)), cfg) is None
