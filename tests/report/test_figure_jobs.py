"""Figures drawn in a child process, and Fig. 2's tiles kept from the matching pass."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from planetref.frontend.result import StageDebug, TileResult
from planetref.frontend.tile_panels import MatchPanel, PanelStore
from planetref.frontend.tiles import Tile
from planetref.report.figure_jobs import FigureJobs
from planetref.report.figures_matching import figure_tile_matches

PNG = b"\x89PNG\r\n\x1a\n"


def _panel() -> MatchPanel:
    img = np.random.default_rng(0).normal(size=(40, 50)).astype(np.float32)
    return MatchPanel(
        "fine", img, img, np.full((3, 2), 5.5), np.full((3, 2), 6.5), np.array([True, False, True])
    )


@pytest.mark.parametrize("background", [True, False])
def test_figure_jobs_draw_and_never_sink_a_run(tmp_path, caplog, background):
    with caplog.at_level(logging.WARNING, logger="planetref.report"):
        with FigureJobs(background=background) as jobs:
            jobs.submit("good", figure_tile_matches, [_panel()], tmp_path / "good.png")
            jobs.submit("bad", figure_tile_matches, [], tmp_path / "bad.png")  # InputError
            jobs.submit("after", figure_tile_matches, [_panel()], tmp_path / "after.png")
    assert (tmp_path / "good.png").read_bytes()[:8] == PNG
    assert (tmp_path / "after.png").read_bytes()[:8] == PNG
    assert not (tmp_path / "bad.png").exists()
    warned = [r.getMessage() for r in caplog.records]
    assert len(warned) == 1 and warned[0].startswith("no figure bad: ")
    assert "InputError" in warned[0] or "no panel" in warned[0]
    # Drawn in the child or here, the PNG is the same.
    again = figure_tile_matches([_panel()], tmp_path / "here.png")
    assert again.read_bytes() == (tmp_path / "good.png").read_bytes()


def test_panel_store_round_trip_and_cleanup():
    rng = np.random.default_rng(1)
    img0 = rng.normal(size=(30, 20)).astype(np.float32)
    img1 = rng.normal(size=(25, 35)).astype(np.float32)
    v0, v1 = img0 > -1.0, img1 > -1.0
    k0, k1 = rng.random((7, 2)) * 20, rng.random((7, 2)) * 25
    inl = rng.random(7) > 0.5
    stages = [StageDebug(s, img0, v0, img1, v1, k0, k1, inl) for s in ("coarse", "fine")]
    tile = Tile("ccd1:r000c000", "ccd1", 0, 0, 10, 10)
    ok = TileResult(tile=tile, matcher="m", status="ok", debug=stages)
    failed = TileResult(
        tile=Tile("ccd1:r001c000", "ccd1", 10, 0, 10, 10), matcher="m", status="too_few_inliers"
    )
    failed.debug = stages
    with PanelStore() as store:
        store.add(ok)
        store.add(failed)  # only drawable (ok) tiles are kept
        assert "ccd1:r000c000" in store and len(store) == 1
        assert store.panels("ccd1:r001c000") is None
        panels = store.panels("ccd1:r000c000")
        folder = store._dir
        assert folder.is_dir()
    assert not folder.exists()
    assert [p.title for p in panels] == ["coarse", "fine"]
    for p in panels:
        for got, want in (
            (p.image0, img0), (p.valid0, v0), (p.image1, img1), (p.valid1, v1),
            (p.keypoints0, k0), (p.keypoints1, k1), (p.inliers, inl),
        ):  # fmt: skip
            assert got.dtype == want.dtype and np.array_equal(got, want)


def test_panel_store_adopts_and_records_a_worker_file(tmp_path):
    from planetref.frontend.tile_panels import save_panels
    from planetref.runtime.atomic import watch_outputs

    class Recorder:
        def __init__(self):
            self.written = []

        def check_output(self, path):
            pass

        def output_written(self, path):
            self.written.append(path)

    rng = np.random.default_rng(2)
    img = rng.normal(size=(12, 14)).astype(np.float32)
    k = rng.random((4, 2)) * 10
    stages = [StageDebug("fine", img, img > 0, img, img > 0, k, k + 1, np.ones(4, bool))]
    tile = Tile("ccd2:r000c001", "ccd2", 0, 10, 10, 10)
    folder = tmp_path / "tile_panels"
    rec = Recorder()
    store = PanelStore(persistent=folder)  # the run's store, empty
    # A worker (another process, nothing watching there) writes the tile's file under its
    # pending name (never the final one: a run killed before it recorded the file would
    # find an unrecorded file there)...
    res = TileResult(tile=tile, matcher="m", status="ok", debug=stages)
    pending = save_panels(folder, res, pending=True)
    assert pending is not None and pending.parent == folder
    assert pending.name == ".planetref-pending.ccd2_r000c001.npz"
    written = folder / "ccd2_r000c001.npz"
    assert not written.exists()
    with watch_outputs(rec):
        # ...and its result arrives here without stages: the store adopts the file.
        store.add(TileResult(tile=tile, matcher="m", status="ok"))
        store.add(TileResult(Tile("ccd2:r009c009", "ccd2", 90, 90, 10, 10), "m", "ok"))
    assert "ccd2:r000c001" in store and len(store) == 1  # a tile without a file is not
    assert rec.written == [written.resolve()]  # recorded as written for this process
    assert written.is_file() and not pending.exists()  # adopted: renamed to its name
    (panel,) = store.panels("ccd2:r000c001")
    assert np.array_equal(panel.image0, img) and np.array_equal(panel.keypoints1, k + 1)
    store.keep_only([])
    assert not written.exists()
