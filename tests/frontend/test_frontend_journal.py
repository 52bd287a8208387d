"""The tile journal: torn lines cut off before appending, errored tiles retried to a bound."""

from __future__ import annotations

import json

import numpy as np
import pytest

from planetref.errors import InputError
from planetref.frontend.journal import TileJournal, journal_digest
from planetref.frontend.result import TileResult
from planetref.frontend.tiles import Tile

DIGEST = journal_digest("sift", {"a": 1})


def _ok(i: int, n: int = 3) -> TileResult:
    r = TileResult(
        tile=Tile(f"ccd1:r{i:03d}c000", "ccd1", 100 * i, 0, 100, 50), matcher="sift", status="ok"
    )
    r.line = np.arange(n, dtype=float) + 0.5
    r.sample = r.line + 1.0
    r.ref_col, r.ref_row, r.ref_x, r.ref_y = r.line * 2, r.line * 3, r.line * 4, r.line * 5
    r.confidence = np.full(n, 0.9)
    r.sigma_px = np.full(n, np.nan)
    r.record("raw", 10)
    r.record("ransac", n, {"outlier": 10 - n})
    return r


def _err(i: int) -> TileResult:
    return TileResult(
        tile=Tile(f"ccd1:r{i:03d}c000", "ccd1", 100 * i, 0, 100, 50),
        matcher="sift",
        status="error",
        message="OSError: truncated reference",
    )


def test_torn_last_line_is_cut_before_appending(tmp_path):
    path = tmp_path / "j" / "tiles.jsonl"
    with TileJournal(path, DIGEST) as j:
        assert j.finished == {}
        j.append(_ok(0))
        j.append(_ok(1))
    whole = path.read_bytes()
    # kill -9 in the middle of writing tile 2: half a line, no newline.
    line2 = json.dumps({"digest": DIGEST, "attempt": 1, "result": _ok(2).to_dict()})
    path.write_bytes(whole + line2[: len(line2) // 2].encode())
    with TileJournal(path, DIGEST) as j:
        assert sorted(j.finished) == ["ccd1:r000c000", "ccd1:r001c000"]
        assert path.read_bytes() == whole  # the torn tail is gone before anything is appended
        j.append(_ok(2))
    # ... so every later run reads the journal (the bug: "line 3 is not JSON" forever).
    for _ in range(2):
        with TileJournal(path, DIGEST) as j:
            assert len(j.finished) == 3
    lines = path.read_text().splitlines()
    assert len(lines) == 3 and all(json.loads(x)["digest"] == DIGEST for x in lines)


def test_whole_record_without_newline_is_kept_and_terminated(tmp_path):
    path = tmp_path / "tiles.jsonl"
    rec = json.dumps({"digest": DIGEST, "attempt": 1, "result": _ok(0).to_dict()})
    path.write_text(rec)  # the newline never reached the disk
    with TileJournal(path, DIGEST) as j:
        assert list(j.finished) == ["ccd1:r000c000"]
        j.append(_ok(1))
    assert [json.loads(x)["result"]["tile"]["tile_id"] for x in path.read_text().splitlines()] == [
        "ccd1:r000c000",
        "ccd1:r001c000",
    ]


def test_corruption_before_the_last_line_is_refused(tmp_path):
    path = tmp_path / "tiles.jsonl"
    rec = json.dumps({"digest": DIGEST, "result": _ok(0).to_dict()})
    path.write_text(rec + "\nnot json\n" + rec + "\n")
    with pytest.raises(InputError, match="line 2"):
        TileJournal(path, DIGEST).open()
    path.write_text(rec + "\n")
    with pytest.raises(InputError, match="another matcher or config"):
        TileJournal(path, journal_digest("ncc", {"a": 1})).open()


def test_errored_tiles_are_retried_up_to_a_bound(tmp_path):
    path = tmp_path / "tiles.jsonl"
    with TileJournal(path, DIGEST, max_attempts=2) as j:
        j.append(_ok(0))
        j.append(_err(1))
    with TileJournal(path, DIGEST, max_attempts=2) as j:
        assert list(j.finished) == ["ccd1:r000c000"]  # tile 1 is tried again
        assert j.attempts == {"ccd1:r001c000": 1}
        j.append(_err(1))  # fails again: second attempt
    with TileJournal(path, DIGEST, max_attempts=2) as j:
        assert j.finished["ccd1:r001c000"].status == "error"  # bound reached: kept
        assert j.attempts == {"ccd1:r001c000": 2}
    attempts = [json.loads(x)["attempt"] for x in path.read_text().splitlines()]
    assert attempts == [1, 1, 2]
    # A retry that succeeds replaces the error.
    with TileJournal(path, DIGEST, max_attempts=3) as j:
        assert "ccd1:r001c000" not in j.finished
        j.append(_ok(1))
    with TileJournal(path, DIGEST, max_attempts=3) as j:
        assert j.finished["ccd1:r001c000"].status == "ok"


def test_result_round_trip_keeps_funnel_and_nan_sigmas():
    r = _ok(0)
    r.sigma_px[1] = 0.12
    r.thinned = True
    back = TileResult.from_dict(json.loads(json.dumps(r.to_dict(), allow_nan=False)))
    assert back.funnel == {"raw": 10, "ransac": 3} and back.drops == {"ransac:outlier": 7}
    assert back.thinned is True
    np.testing.assert_array_equal(np.isnan(back.sigma_px), [True, False, True])
    assert back.sigma_px[1] == 0.12
    # Documents written before the funnel existed still load.
    doc = r.to_dict()
    for key in ("funnel", "drops", "thinned", "sigma_px"):
        doc.pop(key)
    old = TileResult.from_dict(doc)
    assert old.funnel == {} and len(old.sigma_px) == 3 and np.isnan(old.sigma_px).all()
