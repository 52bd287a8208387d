"""Report figures and the residual-pattern statistic."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from planetref.report.document import Document, read_report_html
from planetref.report.figures_adjust import (
    figure_headline,
    figure_residual_vectors,
    residual_pattern,
)
from planetref.report.figures_matching import (
    MatchPanel,
    TileRow,
    figure_pair_matches,
    figure_tile_grid,
    select_tiles,
)

PNG = b"\x89PNG\r\n\x1a\n"


def _png_ok(path, min_w=300, min_h=200):
    import matplotlib.image as mpimg

    assert path.read_bytes()[:8] == PNG
    arr = mpimg.imread(path)
    assert arr.shape[0] >= min_h and arr.shape[1] >= min_w
    assert float(arr[..., :3].std()) > 0.01


def _points(n, seed):
    rng = np.random.default_rng(seed)
    return rng.uniform(0, 600, n), rng.uniform(0, 300, n), rng


def test_pattern_flags_a_smooth_field_and_not_white_noise():
    line, sample, rng = _points(300, 1)
    # A smooth field (an uncorrected rotation-like error) plus a little noise.
    dl = 0.002 * (sample - 150) + rng.normal(0, 0.05, 300)
    ds = -0.002 * (line - 300) + rng.normal(0, 0.05, 300)
    p = residual_pattern(line, sample, dl, ds)
    assert p.systematic and p.c > 0.8 and p.p_value <= 0.01
    assert "SYSTEMATIC" in p.note()
    noise = residual_pattern(line, sample, rng.normal(0, 1, 300), rng.normal(0, 1, 300))
    assert not noise.systematic and abs(noise.c) < 0.2 and noise.p_value > 0.01
    few = residual_pattern(line[:5], sample[:5], dl[:5], ds[:5])
    assert np.isnan(few.c) and not few.systematic


def test_pattern_neighbours_stay_within_their_ccd():
    line, sample, rng = _points(200, 2)
    # Each CCD has its own constant offset: neighbours across CCDs would dilute it.
    grp = np.repeat(["a", "b"], 100)
    off = np.where(grp == "a", 1.0, -1.0)
    p = residual_pattern(line, sample, off + rng.normal(0, 0.1, 200), 0 * off, group=grp)
    assert p.c > 0.9 and p.systematic


def _result(n=240, seed=3):
    line, sample, rng = _points(n, seed)
    ccd = np.repeat([0, 1, 2], n // 3)
    status = np.array(["inlier"] * n, dtype=object)
    status[:12] = "check"
    status[12:15] = "outlier"
    net = SimpleNamespace(camera_ids=["s"], obs_ccd=ccd, obs_line=line, obs_sample=sample)
    return SimpleNamespace(
        network=net,
        cameras={"s": SimpleNamespace(ccd_names=("ccd1", "ccd2", "ccd3"))},
        residual=rng.normal(0, 0.7, (n, 2)),
        status=status.astype(str),
    )


def test_residual_and_headline_figures(tmp_path):
    sizes = {"ccd1": (600, 300), "ccd2": (600, 300), "ccd3": (600, 300)}
    out = figure_residual_vectors(_result(), sizes, tmp_path / "res.png", title="t")
    _png_ok(out)
    run = {
        "matching": {"ncp": 100, "sdu_pct": 5.0, "ccds": {"c": {"ncp": 100, "sdu_pct": 5.0}}},
        "adjustment": {"rmse_px": 0.5, "rmse_px_before": 40.0, "outlier_ratio_pct": 0.0},
        "check": None,
    }
    _png_ok(figure_headline({"a": run, "b": run}, tmp_path / "h.png", scene="x"))
    with_truth = {
        **run,
        "check": {"geoloc_rmse_m_before": 100.0, "geoloc_rmse_m": 1.0, "geoloc_max_m": 3.0},
    }
    _png_ok(figure_headline({"a": with_truth, "b": run}, tmp_path / "h2.png"))


def test_select_tiles_rule():
    tiles = [
        SimpleNamespace(tile_id=f"t{i}", status="ok", n_points=n)
        for i, n in enumerate([5, 50, 20, 30, 10])
    ]
    tiles.append(SimpleNamespace(tile_id="bad", status="too_few_inliers", n_points=0))
    picked = select_tiles(tiles)
    assert [(r, t.tile_id) for r, t in picked] == [
        ("best", "t1"),
        ("median", "t2"),
        ("worst", "t0"),
    ]
    assert [t.tile_id for _, t in select_tiles(tiles[:1])] == ["t0"]
    assert select_tiles(tiles[-1:]) == []
    # A cap may equalise the MCPs: the rule ranks by verified matches (the funnel's last
    # stage before thinning, else n_inliers).
    capped = [
        SimpleNamespace(tile_id="a", status="ok", n_points=200, n_inliers=250),
        SimpleNamespace(tile_id="b", status="ok", n_points=200, n_inliers=400),
        SimpleNamespace(
            tile_id="c",
            status="ok",
            n_points=200,
            n_inliers=300,
            funnel={"raw": 900, "ransac": 700, "mcp": 200},
        ),
    ]
    assert [t.tile_id for _, t in select_tiles(capped)] == ["c", "b", "a"]


def test_tile_grid_pair_figure_and_html_embedding(tmp_path):
    rng = np.random.default_rng(4)
    img = rng.random((120, 100)).astype(np.float32)
    k0 = rng.uniform(5, 95, (300, 2))
    inl = rng.random(300) > 0.2
    pnl = MatchPanel("fine", img, img, k0, k0 + 1.0, inl)
    grid = figure_tile_grid(
        [TileRow("best: t1", [pnl, pnl]), TileRow("worst: t2", [pnl])],
        tmp_path / "grid.png",
        title="g",
    )
    _png_ok(grid)
    pair = figure_pair_matches(
        tmp_path / "pair.png", img, None, img, None, k0, k0, "sift", inliers=inl
    )
    _png_ok(pair)
    doc = Document("r")
    doc.figure(grid, "grid")
    doc.figure(tmp_path / "absent.png", "never added")
    doc.table("t", ["a", "b"], [[1, "x"], [2.5, None]])
    paths = doc.write(tmp_path / "rep")
    found = read_report_html(paths["report_html"])
    assert [n for n, _ in found.figures] == ["grid.png"] and not found.external
    assert found.figures[0][1] == grid.read_bytes()
    assert found.tables == [("t", [["a", "b"], ["1", "x"], ["2.500", "-"]])]
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "](../grid.png)" in md


@pytest.mark.parametrize("bad", ["data:image/png;base64,@@@"])
def test_read_report_html_rejects_bad_base64(tmp_path, bad):
    from planetref.errors import InputError

    page = tmp_path / "p.html"
    page.write_text(f'<html><body><img src="{bad}" data-file="x.png"></body></html>')
    with pytest.raises(InputError, match=r"x\.png"):
        read_report_html(page)


def test_save_draws_once_with_the_pixels_of_savefig(tmp_path, monkeypatch):
    """``save`` (one draw, layout inside it) writes the pixels ``savefig`` (two draws) does."""
    import matplotlib.image as mpimg
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from planetref.report.figures_matching import save

    def figure():
        fig = Figure(figsize=(6.0, 3.0), layout="constrained")
        axes = fig.subplots(1, 2, sharey=True)
        x, y, _ = _points(200, 3)
        axes[0].scatter(x, y, s=4)
        axes[1].imshow(np.arange(600.0).reshape(20, 30), extent=(0, 600, 300, 0))
        axes[0].set_ylabel("line (px)")
        fig.suptitle("two panels\nand a second title line")
        return fig

    ref = figure()
    FigureCanvasAgg(ref)
    ref.savefig(tmp_path / "ref.png", dpi=90, format="png")
    draws = []
    fig = figure()
    orig = Figure.draw

    def counted(self, renderer):
        draws.append(1)
        return orig(self, renderer)

    monkeypatch.setattr(Figure, "draw", counted)
    save(fig, tmp_path / "one.png", 90)
    assert len(draws) == 1
    a, b = mpimg.imread(tmp_path / "ref.png"), mpimg.imread(tmp_path / "one.png")
    assert a.shape == b.shape == (270, 540, 4)
    assert np.array_equal(a, b)


def test_headline_axes_are_linear_and_the_outlier_ratio_is_on_a_fixed_scale(tmp_path, monkeypatch):
    import planetref.report.figures_adjust as fa

    figs = []
    save = fa.save
    monkeypatch.setattr(fa, "save", lambda fig, path, dpi: figs.append(fig) or save(fig, path, dpi))

    def run(rmse_before, rmse, outliers, true_before, true_after):
        return {
            "matching": {"ncp": 100, "sdu_pct": 5.0, "ccds": {"c": {"ncp": 100, "sdu_pct": 5.0}}},
            "adjustment": {
                "rmse_px": rmse,
                "rmse_px_before": rmse_before,
                "outlier_ratio_pct": outliers,
            },
            "check": {
                "geoloc_rmse_m_before": true_before,
                "geoloc_rmse_m": true_after,
                "geoloc_max_m": 2 * true_after,
            },
        }

    # One matcher with 0.07 % outliers, the others none: on a fitted axis it would fill
    # the panel. RMSE before (41 px) is far above after (<= 0.9 px): cut, with its value.
    runs = {"a": run(41.2, 0.62, 0.07, 108.0, 1.4), "b": run(41.2, 0.9, 0.0, 108.0, 1.1)}
    _png_ok(figure_headline(runs, tmp_path / "h.png"))
    axes = {ax.get_title().split("\n")[0]: ax for ax in figs[-1].axes}
    assert all(ax.get_yscale() == "linear" for ax in axes.values())
    assert axes["OR (outlier ratio)"].get_ylim() == (0.0, fa.OR_AXIS_TOP_PCT)
    rmse = axes["RMSE of image residuals"]
    assert rmse.get_ylim()[0] == 0.0 and 0.9 < rmse.get_ylim()[1] < 2.0
    texts = [t.get_text() for t in rmse.texts]
    assert texts.count("\u219141.2") == 2 and "0.62" in texts and "0.9" in texts
    # An OR above the fixed scale widens it; a before within 3x is drawn whole.
    runs = {"a": run(2.0, 0.8, 14.0, 3.0, 1.5)}
    figure_headline(runs, tmp_path / "h2.png")
    axes = {ax.get_title().split("\n")[0]: ax for ax in figs[-1].axes}
    assert axes["OR (outlier ratio)"].get_ylim()[1] > 14.0
    rmse = axes["RMSE of image residuals"]
    assert rmse.get_ylim()[1] > 2.0 and "2" in [t.get_text() for t in rmse.texts]
