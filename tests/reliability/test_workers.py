"""Workers belong to their run; interrupted runs never wedge their folder (issue 35, group 4).

Ctrl-C, SIGTERM or kill -9 of a ``--scheduler pool:N`` run left tile panels that workers
wrote but the parent never recorded, and every rerun (even ``--overwrite``) refused them
as foreign files; the workers kept running as orphans for minutes and wrote files after
the parent died. Workers now write pending names the parent adopts, and die with it.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from reliability_helpers import REPO

from planetref.pipeline.rundir import MARKER, RunDir


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie waiting to be reaped does not)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _children(pid: int) -> list[int]:
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as fh:
                    if int(fh.read().rsplit(")", 1)[1].split()[1]) == pid:
                        out.append(int(entry))
            except (OSError, ValueError, IndexError):
                pass
    return out


def _digests(root: Path) -> dict[str, str]:
    return {
        str(p): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file() and not p.is_symlink()
    }


def _panel_result(tile_id: str):  # a TileResult with one stage image, as a worker has
    from planetref.frontend.result import StageDebug, TileResult
    from planetref.frontend.tiles import Tile

    img = np.random.default_rng(0).normal(size=(8, 9)).astype(np.float32)
    k = np.zeros((3, 2))
    stages = [StageDebug("fine", img, img > 0, img, img > 0, k, k, np.ones(3, bool))]
    ccd = tile_id.split(":")[0]
    return TileResult(tile=Tile(tile_id, ccd, 0, 0, 8, 9), matcher="m", status="ok", debug=stages)


@pytest.mark.parametrize("overwrite", [False, True])
def test_unrecorded_worker_panels_never_block_a_rerun(tmp_path: Path, overwrite: bool) -> None:
    # planetref georef scene --scheduler pool:2 --out run, killed after a worker wrote a
    # tile panel the parent never recorded; then the same command (resume) or another
    # matcher with --overwrite
    from planetref.frontend.tile_panels import PanelStore, save_panels

    out = tmp_path / "run"
    run = RunDir(out, "georef", {"matcher": "sift"})
    panels = run.file("strip1", "tile_panels")
    panels.mkdir()
    save_panels(panels, _panel_result("ccd1:r000c000"), pending=True)  # the worker's write
    run.close()  # killed: no finish(), the panel is not in run.json
    (out / "NOTES.txt").write_text("mine")
    before = {k: v for k, v in _digests(out).items() if k.endswith("NOTES.txt")}
    identity = {"matcher": "ncc" if overwrite else "sift"}
    run = RunDir(out, "georef", identity, overwrite=overwrite)
    with run.logging_to_file():
        store = PanelStore(persistent=out / "strip1" / "tile_panels")
        # The tile matched again by a worker of this run, its result recorded.
        save_panels(store.folder, _panel_result("ccd1:r000c000"), pending=True)
        from planetref.frontend.result import TileResult

        store.add(TileResult(tile=_panel_result("ccd1:r000c000").tile, matcher="m", status="ok"))
        assert store.panels("ccd1:r000c000") is not None
    files = json.loads((out / MARKER).read_text())["files"]
    assert "strip1/tile_panels/ccd1_r000c000.npz" in files
    assert not [p for p in out.rglob(".planetref-*") if p.name != ".planetref.lock"]
    assert {k: v for k, v in _digests(out).items() if k.endswith("NOTES.txt")} == before


def test_a_pending_panel_of_a_killed_run_is_adopted_on_resume(tmp_path: Path) -> None:
    from planetref.frontend.tile_panels import PanelStore, save_panels

    out = tmp_path / "run"
    run = RunDir(out, "georef", {"matcher": "sift"})
    panels = run.file("strip1", "tile_panels")
    panels.mkdir()
    save_panels(panels, _panel_result("ccd2:r001c000"), pending=True)
    (panels / ".planetref-pending.ccd2_r002c000.npz").write_bytes(b"torn")  # cut short
    run.close()
    run = RunDir(out, "georef", {"matcher": "sift"})
    with run.logging_to_file():
        store = PanelStore(persistent=panels)
    assert "ccd2:r001c000" in store and len(store) == 1
    assert sorted(p.name for p in panels.iterdir()) == ["ccd2_r001c000.npz"]
    assert "strip1/tile_panels/ccd2_r001c000.npz" in json.loads((out / MARKER).read_text())["files"]


_POOL = textwrap.dedent(
    """
    import time
    from planetref.runtime.execute import LocalPoolExecutor
    ex = LocalPoolExecutor(2)
    list(ex.map_unordered(time.sleep, [0.01, 0.01]))  # both workers started
    print(" ".join(str(p) for p in ex._pool._processes), flush=True)
    for _ in range(2):
        ex._pool.submit(time.sleep, 600)  # busy workers, as in a long tile
    time.sleep(600)
    """
)


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM])
def test_pool_workers_die_with_their_parent(sig: int) -> None:
    # kill -9 / kill of a `--scheduler pool:2` run: no worker alive 10 s later
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    parent = subprocess.Popen(
        [sys.executable, "-c", _POOL], stdout=subprocess.PIPE, text=True, env=env
    )
    try:
        assert parent.stdout is not None
        workers = [int(p) for p in parent.stdout.readline().split()]
        assert len(workers) == 2 and all(_alive(p) for p in workers)
        assert set(workers) <= set(_children(parent.pid))
    finally:
        parent.send_signal(sig)
        parent.wait(timeout=60)
    deadline = time.monotonic() + 10.0
    while any(_alive(p) for p in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    alive = [p for p in workers if _alive(p)]
    for p in alive:  # do not leave them behind if the test fails
        os.kill(p, signal.SIGKILL)
    assert alive == []


def _reached(out: Path, moment: str) -> bool:
    """Whether a georef into ``out`` has reached ``moment`` (where it is killed)."""
    if moment == "claimed":
        return (out / MARKER).is_file()
    if moment == "tiles":
        journal = out / "strip1" / "tiles.jsonl"
        return journal.is_file() and journal.read_bytes().count(b"\n") >= 1
    return (out / "strip1" / "ortho").is_dir()  # "outputs": the orthoimages are written


@pytest.mark.slow
@pytest.mark.parametrize(
    ("sig", "moment"),
    [
        (signal.SIGKILL, "claimed"),
        (signal.SIGKILL, "tiles"),
        (signal.SIGTERM, "tiles"),
        (signal.SIGINT, "tiles"),
        (signal.SIGKILL, "outputs"),
    ],
)
def test_kill_a_pool_georef_then_resume(
    tiny_scene: Path, tmp_path: Path, ref_grid_toml, tiny_sift_run, sig: int, moment: str
) -> None:
    # planetref georef tiny --matcher sift --scheduler pool:2 --out run; kill -9 (kill,
    # Ctrl-C) once the folder is claimed, the first tiles are journalled, or the outputs
    # are being written; the same command again resumes to a finished run, no worker of
    # the killed run alive 10 s later, no file of the scene changed, and the same tables
    # as the uninterrupted run (in-process: the results do not depend on the executor)
    out = tmp_path / "run"
    scene_before = _digests(tiny_scene)
    env = {**os.environ, "PYTHONPATH": str(REPO / "src"), "OMP_NUM_THREADS": "1"}
    cmd = [
        sys.executable,
        "-W",
        "ignore",
        "-m",
        "planetref",
        "-q",
        "georef",
        str(tiny_scene),
        "--matcher",
        "sift",
        "--config",
        str(ref_grid_toml),
        "--scheduler",
        "pool:2",
        "--out",
        str(out),
    ]
    parent = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    workers: set[int] = set()
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and parent.poll() is None:
            workers |= set(_children(parent.pid))
            if _reached(out, moment):
                break
            time.sleep(0.02)
        assert parent.poll() is None, "the run ended before it could be killed"
        workers |= set(_children(parent.pid))
    finally:
        parent.send_signal(sig)
        _, err = parent.communicate(timeout=120)
    assert b"Traceback" not in err, err.decode()[-3000:]
    deadline = time.monotonic() + 10.0
    while any(_alive(p) for p in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    alive = [p for p in workers if _alive(p)]
    for p in alive:
        os.kill(p, signal.SIGKILL)
    assert alive == []
    snapshot = _digests(out)
    time.sleep(1.0)
    assert _digests(out) == snapshot  # nothing wrote after the parent died
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900, check=False)
    assert r.returncode == 0, r.stderr[-3000:]
    report = json.loads((out / "report.json").read_text())
    expected = tiny_sift_run.report
    assert report["matching"]["ncp"] == expected["matching"]["ncp"] >= 12
    assert report["adjustment"]["rmse_px"] == pytest.approx(
        expected["adjustment"]["rmse_px"], rel=1e-6
    )
    assert not [p for p in out.rglob(".planetref-*") if p.name != ".planetref.lock"]
    assert _digests(tiny_scene) == scene_before
