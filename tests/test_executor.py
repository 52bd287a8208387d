"""Tile-parallel execution: the same MCPs and adjustment on every executor, resume, specs."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pyarrow.parquet as pq
import pytest

from planetref.errors import InputError
from planetref.pipeline.georef import run_georef
from planetref.runtime.execute import (
    DaskExecutor,
    InProcessExecutor,
    LocalPoolExecutor,
    make_executor,
)


@pytest.fixture(scope="module")
def scene(tiny_scene):
    """The session's tiny scene (tests/conftest.py), simulated once for all test files."""
    return tiny_scene


@pytest.fixture(scope="module")
def dask_local():
    pytest.importorskip("distributed")
    ex = make_executor("dask-local:2")
    assert isinstance(ex, DaskExecutor)
    yield ex
    ex.close()


@pytest.fixture
def inprocess_run(tiny_sift_run):
    """The in-process sift run of the tiny scene (``ref_grid``), shared with test_georef."""
    return tiny_sift_run


def _journal(path):
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _assert_close(a, b, path="report"):
    """Nested report blocks equal, floats to 1e-9 relative / 1e-8 absolute."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), path
        for k in a:
            _assert_close(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, list | tuple):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_close(x, y, f"{path}[{i}]")
    elif isinstance(a, float) and isinstance(b, float):
        assert a == pytest.approx(b, rel=1e-9, abs=1e-8, nan_ok=True), path
    else:
        assert a == b, path


def _assert_same_mcps(a, b):
    ta, tb = pq.read_table(a), pq.read_table(b)
    assert ta.column_names == tb.column_names
    assert ta.num_rows == tb.num_rows > 0
    for name in ta.column_names:
        va, vb = ta.column(name).to_pylist(), tb.column(name).to_pylist()
        if va and isinstance(va[0], float):
            # Line searches warm-started from the previous call differ in the last bits
            # (~1e-11 px) with the order tiles run in; nothing planetref reports does.
            np.testing.assert_allclose(va, vb, rtol=0, atol=1e-8, err_msg=name)
        else:
            assert va == vb, name


def test_dask_local_gives_identical_mcps_and_adjustment(
    scene, tmp_path, inprocess_run, dask_local, ref_grid, monkeypatch
):
    import planetref.frontend.tile

    calls = []  # tiles matched in this process (the workers are other processes)
    real = planetref.frontend.tile.match_tile
    monkeypatch.setattr(
        planetref.frontend.tile, "match_tile", lambda *a, **k: calls.append(1) or real(*a, **k)
    )
    out = run_georef(
        scene, "sift", tmp_path / "dask", config=ref_grid, progress=False, executor=dask_local
    )
    a, b = inprocess_run.run_dir, out.run_dir
    # Fig. 2 from the stage images the workers wrote: no tile matched again for it, the
    # same picture as in process, its three tiles kept and recorded as the run's.
    assert calls == []
    fig2 = ("figures", "strip1_tile_matches.png")
    assert a.joinpath(*fig2).read_bytes() == b.joinpath(*fig2).read_bytes()
    panels = sorted(p.name for p in (b / "strip1" / "tile_panels").iterdir())
    assert panels == sorted(p.name for p in (a / "strip1" / "tile_panels").iterdir())
    assert len(panels) == 3
    listed = json.loads((b / "run.json").read_text())["files"]
    assert {f"strip1/tile_panels/{p}" for p in panels} <= set(listed)
    _assert_same_mcps(a / "strip1" / "mcps.parquet", b / "strip1" / "mcps.parquet")
    ra, rb = inprocess_run.report, out.report
    _assert_close(ra["adjustment"], rb["adjustment"])
    _assert_close(ra["check"], rb["check"])
    _assert_close(ra["matching"], rb["matching"])
    # Every tile journalled once, in whatever order the workers finished.
    ja, jb = _journal(a / "strip1" / "tiles.jsonl"), _journal(b / "strip1" / "tiles.jsonl")
    assert sorted(d["result"]["tile"]["tile_id"] for d in ja) == sorted(
        d["result"]["tile"]["tile_id"] for d in jb
    )


def test_killed_run_resumes_without_recomputing(
    scene, tmp_path, inprocess_run, dask_local, ref_grid
):
    # A run "killed" half-way: its journal holds the first half of the tiles.
    run = tmp_path / "resumed"
    shutil.copytree(inprocess_run.run_dir, run)
    jpath = run / "strip1" / "tiles.jsonl"
    docs = _journal(jpath)
    half = docs[: len(docs) // 2]
    for d in half:  # a marker that only survives if these tiles are not matched again
        d["result"]["timings"] = {"total": -1.0}
    jpath.write_text("".join(json.dumps(d) + "\n" for d in half))
    out = run_georef(scene, "sift", run, config=ref_grid, progress=False, executor=dask_local)
    after = _journal(jpath)
    assert after[: len(half)] == half  # kept as they were
    ids = [d["result"]["tile"]["tile_id"] for d in after]
    assert len(ids) == len(set(ids)) == len(docs)  # the rest matched exactly once
    assert all(d["result"]["timings"].get("total", 0) >= 0 for d in after[len(half) :])
    _assert_same_mcps(
        inprocess_run.run_dir / "strip1" / "mcps.parquet", run / "strip1" / "mcps.parquet"
    )
    _assert_close(out.report["adjustment"], inprocess_run.report["adjustment"])


def _fail_on_negative(x: int) -> int:
    if x < 0:
        raise ValueError("negative")
    return x * 2


@pytest.mark.parametrize(
    "executor", [InProcessExecutor(), LocalPoolExecutor(2)], ids=["inprocess", "pool"]
)
def test_executors_stream_results_and_report_failures(executor):
    with executor:
        outs = list(executor.map_unordered(_fail_on_negative, [1, 2, -3, 4]))
    assert sorted(o.index for o in outs) == [0, 1, 2, 3]
    by = {o.index: o for o in outs}
    assert [by[i].result for i in (0, 1, 3)] == [2, 4, 8]
    assert isinstance(by[2].error, ValueError) and by[2].result is None


def test_make_executor_parses_specs():
    assert isinstance(make_executor(None), InProcessExecutor)
    assert isinstance(make_executor("inprocess"), InProcessExecutor)
    pool = make_executor("pool:3")
    assert isinstance(pool, LocalPoolExecutor) and pool.n_workers == 3
    local = make_executor("dask-local:2")
    assert isinstance(local, DaskExecutor) and local.address == "dask-local:2"
    remote = make_executor("tcp://10.0.0.5:8786")
    assert isinstance(remote, DaskExecutor) and remote.address == "tcp://10.0.0.5:8786"
    assert make_executor(pool) is pool
    for bad in ("pool", "pool:0", "dask-local:x", "threads:4", "tcp://host", "http://h:1"):
        with pytest.raises(InputError, match=r"pool:N, dask-local:N, or tcp://HOST:PORT"):
            make_executor(bad)


def test_cli_rejects_a_bad_scheduler(tmp_path):
    from click.testing import CliRunner

    from planetref.cli import main

    r = CliRunner().invoke(
        main,
        [
            "georef",
            str(tmp_path),
            "--matcher",
            "sift",
            "--out",
            str(tmp_path / "o"),
            "--scheduler",
            "threads:2",
        ],
    )
    assert r.exit_code != 0
    assert "pool:N, dask-local:N, or tcp://HOST:PORT" in r.output
