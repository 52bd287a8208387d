"""georef with ``[frontend] batch_tiles``: the same MCPs and adjustment, and it resumes.

SIFT matches pair by pair inside ``match_many``, so batching the tiles of a sift run must
give the in-process run's numbers exactly; ``batch_tiles`` is left out of the run's
identity, so a run resumes whatever the batching. (The learned matchers' batched
detectors are compared with tile-by-tile matching in
tests/frontend/test_frontend_batched.py.)
"""

from __future__ import annotations

import json
import shutil

import pyarrow.parquet as pq
import pytest

from planetref.pipeline.config import config_from_mapping
from planetref.pipeline.georef import run_georef

BATCHED = {"frontend": {"fine_upsample": 1, "batch_tiles": 4}}


def _journal(path):
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


@pytest.mark.slow
def test_batched_sift_georef_equals_the_in_process_run_and_resumes_it(
    tiny_scene, tmp_path, tiny_sift_run
):
    # resume a copy of the tile-by-tile run, half of its journal gone, with batched tiles
    run = tmp_path / "resumed"
    shutil.copytree(tiny_sift_run.run_dir, run)
    jpath = run / "strip1" / "tiles.jsonl"
    docs = _journal(jpath)
    half = docs[: len(docs) // 2]
    jpath.write_text("".join(json.dumps(d) + "\n" for d in half))
    cfg = config_from_mapping(BATCHED)
    out = run_georef(tiny_scene, "sift", run, config=cfg, progress=False)
    after = _journal(jpath)
    assert after[: len(half)] == half and len(after) == len(docs)
    a = pq.read_table(tiny_sift_run.run_dir / "strip1" / "mcps.parquet")
    b = pq.read_table(run / "strip1" / "mcps.parquet")
    assert a.num_rows == b.num_rows > 0
    assert a.equals(b)
    assert out.report["adjustment"] == tiny_sift_run.report["adjustment"]
