"""``planetref matchers`` and ``planetref match`` through click's CliRunner."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner
from rasterio.transform import Affine

from planetref.cli.match import match_command, matchers_command, read_band


@pytest.fixture
def write_tif(write_geotiff):
    """``write_tif(path, array, nodata=None)``: a float32 GeoTIFF of 0.25 m pixels."""

    def write(path, array, nodata=None):
        transform = Affine(0.25, 0.0, 1000.0, 0.0, -0.25, 5000.0)
        return write_geotiff(path, array, dtype="float32", nodata=nodata, transform=transform)

    return write


@pytest.fixture
def pair_tifs(tmp_path, shifted_pair, write_tif):
    a, b = shifted_pair(200, (3.0, -2.0), seed=4)
    a = a.copy()
    a[:20, :] = -9999.0  # nodata strip
    b = b.copy()
    b[-15:, -40:] = -3.4028226e38  # ISIS special pixels, not declared as nodata
    p0, p1 = tmp_path / "a.tif", tmp_path / "b.tif"
    write_tif(p0, a, nodata=-9999.0)
    write_tif(p1, b)
    return p0, p1


def test_read_band_masks_nodata_and_isis_specials(pair_tifs):
    img0, valid0 = read_band(pair_tifs[0])
    _, valid1 = read_band(pair_tifs[1])
    assert img0.dtype == np.float32 and valid0.dtype == bool
    assert not valid0[:20].any() and valid0[20:].all()
    assert not valid1[-15:, -40:].any() and valid1[:-15].all()


def test_read_band_isis_cube(hirise_dir):
    img, valid = read_band(hirise_dir / "no_change_before.cub")
    assert (~valid).sum() == 22322  # ISIS NULL pixels of this cube (top wedge)
    assert img[valid].min() > 0 and not valid[0, 0]


def test_matchers_command(shared_weights):
    runner = CliRunner()
    res = runner.invoke(matchers_command, ["--weights-dir", str(shared_weights), "--json"])
    assert res.exit_code == 0, res.output
    data = json.loads(res.output)
    rows = {r["name"]: r for r in data["matchers"]}
    assert rows["loftr"]["present"] is False and rows["loftr"]["missing"] == ["loftr_outdoor.ckpt"]
    assert rows["disk-lightglue"]["present"] is True
    assert rows["ncc"]["paradigm"] == "area-based"
    res = runner.invoke(matchers_command, ["--weights-dir", str(shared_weights)])
    assert res.exit_code == 0
    assert "missing: loftr_outdoor.ckpt" in res.output


@pytest.mark.parametrize("matcher", ["sift", "ncc"])
def test_match_command_writes_csv_and_figure(matcher, pair_tifs, tmp_path):
    out, fig = tmp_path / "m.csv", tmp_path / "m.png"
    res = CliRunner().invoke(
        match_command,
        [
            str(pair_tifs[0]),
            str(pair_tifs[1]),
            "--matcher",
            matcher,
            "--out",
            str(out),
            "--figure",
            str(fig),
        ],
    )
    assert res.exit_code == 0, res.output
    line = json.loads(res.output.strip().splitlines()[-1])
    assert line["matcher"] == matcher and line["ncp"] > 50 and line["seconds"] >= 0
    rows = np.loadtxt(out, delimiter=",", skiprows=1)
    assert out.read_text().splitlines()[0] == "x0,y0,x1,y1,confidence"
    assert len(rows) == line["ncp"]
    np.testing.assert_allclose(
        np.median(rows[:, 2:4] - rows[:, 0:2], axis=0), [3.0, -2.0], atol=0.1
    )
    assert rows[:, 1].min() >= 20  # nothing on the nodata strip
    assert fig.stat().st_size > 1000
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.tif", "b.tif", "m.csv", "m.png"]


def test_match_command_tiles_large_images(tmp_path, shifted_pair, write_tif):
    a, b = shifted_pair(300, (2.0, 1.0), seed=9)
    write_tif(tmp_path / "a.tif", a)
    write_tif(tmp_path / "b.tif", b)
    res = CliRunner().invoke(
        match_command,
        [
            str(tmp_path / "a.tif"),
            str(tmp_path / "b.tif"),
            "--matcher",
            "ncc",
            "--out",
            str(tmp_path / "m.csv"),
            "--tile-size",
            "128",
            "--overlap",
            "32",
        ],
    )
    assert res.exit_code == 0, res.output
    rows = np.loadtxt(tmp_path / "m.csv", delimiter=",", skiprows=1)
    assert rows[:, 0].max() > 250 and rows[:, 1].max() > 250  # tiles cover the whole image
    pts = np.round(rows[:, :4], 3)
    assert len(np.unique(pts, axis=0)) == len(pts)  # overlaps deduplicated


def test_match_command_errors(pair_tifs, tmp_path, write_tif):
    runner = CliRunner()
    out = str(tmp_path / "x.csv")

    def run(*args):
        res = runner.invoke(match_command, list(args))
        assert res.exit_code != 0
        assert res.output.startswith("Error:") or res.output.startswith("Usage:")
        assert "Traceback" not in res.output
        return res.output

    assert "no such file" in run(str(tmp_path / "nope.tif"), str(pair_tifs[1]), "--out", out)
    notraster = tmp_path / "notes.txt"
    notraster.write_text("hello")
    assert "not a readable raster" in run(str(notraster), str(pair_tifs[1]), "--out", out)
    msg = run(
        str(pair_tifs[0]),
        str(pair_tifs[1]),
        "--matcher",
        "loftr",
        "--weights-dir",
        str(tmp_path),
        "--out",
        out,
    )
    assert "loftr_outdoor.ckpt" in msg and "http" in msg
    blank = tmp_path / "blank.tif"
    write_tif(blank, np.full((64, 64), 5.0))
    # A constant or empty image is named before any matching (was "no verified matches").
    assert f"{blank}: the image is constant (5 at every valid pixel)" in run(
        str(blank), str(pair_tifs[1]), "--out", out
    )
    empty = tmp_path / "nan.tif"
    write_tif(empty, np.full((64, 64), np.nan))
    assert f"{empty}: the image has no valid pixel" in run(
        str(pair_tifs[0]), str(empty), "--out", out
    )
    assert "Invalid value" in run(
        str(pair_tifs[0]), str(pair_tifs[1]), "--matcher", "superglue", "--out", out
    )
    assert "output folder does not exist" in run(
        str(pair_tifs[0]), str(pair_tifs[1]), "--out", str(tmp_path / "no" / "dir" / "m.csv")
    )
    assert not (tmp_path / "x.csv").exists()


def test_match_command_refine_lsm(pair_tifs, tmp_path):
    raw, refined = tmp_path / "raw.csv", tmp_path / "lsm.csv"
    for out, how in ((raw, "none"), (refined, "lsm")):
        args = [str(pair_tifs[0]), str(pair_tifs[1]), "--matcher", "sift", "--out", str(out)]
        res = CliRunner().invoke(match_command, [*args, "--refine", how])
        assert res.exit_code == 0, res.output
        line = json.loads(res.output.strip().splitlines()[-1])
    assert line["refine"].get("lsm", 0) >= 0.9 * line["ncp"]
    a = np.loadtxt(raw, delimiter=",", skiprows=1)
    b = np.loadtxt(refined, delimiter=",", skiprows=1)
    err_raw = np.abs(a[:, 2:4] - a[:, 0:2] - [3.0, -2.0])
    err_lsm = np.abs(b[:, 2:4] - b[:, 0:2] - [3.0, -2.0])
    # refinement keeps image-0 points and brings image-1 points onto the true shift
    assert set(map(tuple, b[:, :2].round(4))) <= set(map(tuple, a[:, :2].round(4)))
    assert np.median(err_lsm) < 0.5 * np.median(err_raw) and np.median(err_lsm) < 0.02
