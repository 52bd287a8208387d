"""Matching figures are valid PNGs (and the end-to-end strip -> MCPs -> files path works)."""

from __future__ import annotations

import numpy as np
import pytest

from planetref.control.mcp import mcps_from_tiles, read_mcps, write_mcps
from planetref.errors import InputError
from planetref.frontend.config import FrontendConfig
from planetref.frontend.stats import sdu_per_ccd
from planetref.frontend.strip import match_strip
from planetref.raster.ortho import ReferenceOrtho
from planetref.report.figures_matching import (
    MatchPanel,
    figure_mcp_distribution,
    figure_tile_matches,
    mcp_distribution_sdu,
    panels_from_tile,
)

PNG = b"\x89PNG\r\n\x1a\n"


def _is_png(path, min_w=200, min_h=150):
    import matplotlib.image as mpimg

    assert path.read_bytes()[:8] == PNG
    arr = mpimg.imread(path)
    assert arr.ndim == 3 and arr.shape[0] >= min_h and arr.shape[1] >= min_w
    assert float(arr[..., :3].std()) > 0.01  # not blank


def test_strip_to_mcps_and_figures(scene, tmp_path):
    from planetref.frontend.tile_panels import PanelStore
    from planetref.matching import get_matcher

    # Fine stage on the reference grid, as the other front-end tests (fast).
    cfg = FrontendConfig(tile_size_ref_px=96, uncertainty_m=150.0, coarse_factor=2, fine_upsample=1)
    store = PanelStore()
    with ReferenceOrtho(scene.ortho_path) as ref:
        strip = match_strip(
            scene.init_cam,
            scene.image_paths,
            ref,
            scene.dem_path,
            get_matcher("sift"),
            cfg,
            progress=False,
            debug_tiles=["ccd1:r001c000"],
            debug_sink=store.add,
        )
        table = mcps_from_tiles(strip, ref=ref, dem=scene.dem)
    assert len(table) > 100
    assert table.counts.kept == len(table) and table.counts.nan_dem == 0
    files = write_mcps(table, tmp_path / "mcps.parquet")
    assert len(read_mcps(files[1])) == len(table)

    tile = next(t for t in strip.tiles if t.tile_id == "ccd1:r001c000")
    panels = panels_from_tile(tile)
    assert [p.title.split(":")[0] for p in panels] == ["coarse", "fine"]
    # The sink kept every drawable tile of the pass, with the very arrays a debug tile
    # holds; the other tiles' results let their stage images go.
    with store:
        assert len(store) == sum(t.status == "ok" for t in strip.tiles)
        kept = store.panels(tile.tile_id)
        for a, b in zip(kept, panels, strict=True):
            assert a.title == b.title
            for f in ("image0", "valid0", "image1", "valid1", "keypoints0", "keypoints1"):
                assert np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True)
            assert np.array_equal(a.inliers, b.inliers)
    assert all(not t.debug for t in strip.tiles if t.tile_id != tile.tile_id)
    out = figure_tile_matches(panels, tmp_path / "fig" / "tile.png", title=tile.tile_id)
    _is_png(out)

    sizes = {c: scene.init_cam.image_size(c) for c in scene.init_cam.ccd_names}
    out = figure_mcp_distribution(table, sizes, tmp_path / "dist.png", title="sift")
    _is_png(out)
    sdu = sdu_per_ccd(table, sizes)
    assert all(0 < v <= 100 for v in sdu.values())
    # The SDU handed over by the caller (the figure process then loads no front end) is
    # the strip's own, and gives the same picture.
    grids, given = mcp_distribution_sdu(table, sizes)
    assert given == pytest.approx(sdu, rel=1e-12)
    again = figure_mcp_distribution(
        table, sizes, tmp_path / "dist2.png", title="sift", grids=grids, sdu=given
    )
    assert again.read_bytes() == out.read_bytes()
    assert not [p for p in tmp_path.rglob("*") if ".tmp" in p.name]


def test_figure_inputs_are_checked(tmp_path):
    with pytest.raises(InputError):
        figure_tile_matches([], tmp_path / "x.png")
    img = np.random.default_rng(0).normal(size=(40, 50))
    p = MatchPanel("bad", img, img, np.zeros((3, 2)), np.zeros((2, 2)))
    with pytest.raises(InputError):
        figure_tile_matches([p], tmp_path / "x.png")
    ok = MatchPanel(
        "ok", img, img, np.full((3, 2), 5.5), np.full((3, 2), 6.5), np.array([True, False, True])
    )
    _is_png(figure_tile_matches([ok], tmp_path / "ok.png"))
    with pytest.raises(InputError):
        figure_mcp_distribution(
            {"ccd": [], "line": [], "sample": []},
            {"a": (10, 10)},
            tmp_path / "d.png",
            ccd_order=["b"],
        )
    from planetref.frontend.result import TileResult
    from planetref.frontend.tiles import Tile

    with pytest.raises(InputError, match="debug"):
        panels_from_tile(TileResult(tile=Tile("t", "c", 0, 0, 1, 1), matcher="m", status="ok"))
