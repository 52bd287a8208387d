"""Camera CLI limits and hostile input files: each a one-line error naming the file."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from reliability_helpers import SHARED, one_line_error, run_cli


@pytest.fixture
def camera(mini_scene: Path) -> Path:
    return mini_scene / "strips" / "strip1" / "camera.json"


def test_far_outside_the_image_needs_extrapolate(camera: Path) -> None:
    # planetref camera image-to-ground camera.json --line -1000000 --sample 10
    r = run_cli("camera", "image-to-ground", camera, "--line", "-1000000", "--sample", "10")
    one_line_error(r, "--line/--sample: line -1e+06", "--extrapolate")
    # Inside the image (and a little outside it) nothing changes.
    for line in ("48", "-5"):
        r = run_cli("camera", "image-to-ground", camera, "--line", line, "--sample", "10")
        assert r.exit_code == 0, r.stderr
        assert abs(json.loads(r.stdout)["height_m"]) < 1e-3


def test_heights_outside_the_physical_range(camera: Path) -> None:
    # planetref camera image-to-ground camera.json --line 10 --sample 10 --height 1e9 / -1e7
    for height in ("1e9", "-1e7"):
        r = run_cli(
            "camera",
            "image-to-ground",
            camera,
            "--line",
            "10",
            "--sample",
            "10",
            "--height",
            height,
        )
        one_line_error(r, "physically meaningful range", "[-33962, 33962] m")
    r = run_cli(
        "camera", "image-to-ground", camera, "--line", "10", "--sample", "10", "--height", "-4000"
    )
    assert r.exit_code == 0, r.stderr
    assert json.loads(r.stdout)["height_m"] == pytest.approx(-4000.0, abs=1e-3)
    # ground-to-image with a height far above the body (an orbit, not terrain)
    r = run_cli("camera", "ground-to-image", camera, "--lat", "0", "--lon", "0", "--height", "1e8")
    one_line_error(r, "physically meaningful range")


def test_image_to_ground_round_trips_within_the_margin(camera: Path) -> None:
    # planetref camera image-to-ground, then ground-to-image: the same pixel back
    r = run_cli(
        "camera",
        "image-to-ground",
        camera,
        "--line",
        "30.5",
        "--sample",
        "20.25",
        "--height",
        "100",
    )
    assert r.exit_code == 0, r.stderr
    p = json.loads(r.stdout)
    r = run_cli("camera", "ground-to-image", camera, "--xyz", p["x_m"], p["y_m"], p["z_m"])
    assert r.exit_code == 0, r.stderr
    back = json.loads(r.stdout)
    assert back["line"] == pytest.approx(30.5, abs=1e-3)
    assert back["sample"] == pytest.approx(20.25, abs=1e-3)


def test_deeply_nested_json_camera(tmp_path: Path) -> None:
    # planetref camera image-to-ground deep.json --line 1 --sample 1 (200 000 nested lists)
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 200_000 + "]" * 200_000)
    r = run_cli("camera", "image-to-ground", deep, "--line", "1", "--sample", "1")
    line = one_line_error(r, str(deep))
    assert "RecursionError" not in line


def test_deeply_nested_toml(tmp_path: Path) -> None:
    # planetref adjust deep.toml --out o; planetref georef deep.toml --matcher sift --out o
    deep = tmp_path / "deep.toml"
    deep.write_text("a = " + "[" * 200_000 + "]" * 200_000 + "\n")
    r = run_cli("adjust", deep, "--out", tmp_path / "o1")
    one_line_error(r, str(deep), "nested too deeply")
    r = run_cli("georef", deep, "--matcher", "sift", "--out", tmp_path / "o2")
    one_line_error(r, str(deep), "nested too deeply")
    assert not (tmp_path / "o1").exists() and not (tmp_path / "o2").exists()


def test_deeply_nested_adjust_config(tmp_path: Path) -> None:
    # planetref adjust network.toml --config deep.json --out out
    net = SHARED / "data" / "ctx_syrtis" / "network.toml"
    if not net.is_file():
        pytest.skip("../shared/data/ctx_syrtis is absent")
    deep = tmp_path / "deep.json"
    deep.write_text('{"a":' * 200_000 + "1" + "}" * 200_000)
    r = run_cli("adjust", net, "--config", deep, "--out", tmp_path / "out")
    one_line_error(r, str(deep), "nested too deeply")
    assert not (tmp_path / "out").exists()


def test_non_utf8_measures_csv(tmp_path: Path) -> None:
    # planetref adjust network.toml --out out, measures.csv saved as Latin-1
    src = SHARED / "data" / "ctx_syrtis"
    if not (src / "network.toml").is_file():
        pytest.skip("../shared/data/ctx_syrtis is absent")
    net = tmp_path / "net"
    shutil.copytree(src, net)
    measures = net / "measures.csv"
    text = measures.read_bytes().splitlines(keepends=True)
    text[5] = text[5].rstrip(b"\r\n") + b"\xe9\n"  # a Latin-1 e-acute in a data row
    measures.write_bytes(b"".join(text))
    r = run_cli("adjust", net / "network.toml", "--out", tmp_path / "out")
    one_line_error(r, str(measures.resolve()), "not UTF-8")
    assert not (tmp_path / "out").exists()


def test_malicious_loftr_checkpoint(image_pair: tuple[Path, Path], tmp_path: Path) -> None:
    # planetref match A.tif B.tif --matcher loftr --weights-dir w (a pickle calling os.system)
    import os

    import torch

    class Evil:
        def __reduce__(self):  # type: ignore[no-untyped-def]
            return (os.system, (f"touch {tmp_path / 'pwned'}",))

    weights = tmp_path / "w"
    weights.mkdir()
    torch.save({"state_dict": Evil()}, weights / "loftr_outdoor.ckpt")
    a, b = image_pair
    r = run_cli(
        "match", a, b, "--matcher", "loftr", "--weights-dir", weights, "--out", tmp_path / "m.csv"
    )
    line = one_line_error(r, "loftr_outdoor.ckpt", "refused", "posix.system")
    assert "weights_only" not in line and len(line) < 400
    assert not (tmp_path / "pwned").exists()


def test_earth_crs_on_the_reference(mini_scene: Path, tmp_path: Path) -> None:
    # planetref georef scene --matcher sift --out run, the reference ortho tagged EPSG:3857
    import rasterio
    from rasterio.crs import CRS

    scene = tmp_path / "scene"
    shutil.copytree(mini_scene, scene, ignore=shutil.ignore_patterns("run.json", ".planetref*"))
    with rasterio.open(scene / "reference" / "ortho.tif", "r+") as ds:
        ds.crs = CRS.from_epsg(3857)
    r = run_cli("-q", "georef", scene, "--matcher", "sift", "--out", tmp_path / "run")
    line = one_line_error(r, "not a Mars CRS (WGS 84 / Pseudo-Mercator", "ortho.tif")
    assert "overlap" not in line
    assert not (tmp_path / "run").exists()  # refused before the run folder is claimed


def test_fit_rpc_prints_valid_json_never_nan(camera: Path, tmp_path: Path) -> None:
    # planetref camera fit-rpc camera.json --out x.RPB --height-range -8000 8000
    r = run_cli("camera", "fit-rpc", camera, "--out", tmp_path / "x.RPB")
    assert r.exit_code == 0, r.stderr
    assert "NaN" not in r.stdout and "Infinity" not in r.stdout
    doc = json.loads(r.stdout)
    assert all(np.isfinite(v) for k, v in doc.items() if k.endswith("_px"))
    # A height range beyond the body is refused before anything is fitted or written.
    r = run_cli(
        "camera", "fit-rpc", camera, "--out", tmp_path / "y.RPB", "--height-range", "0", "1e7"
    )
    one_line_error(r, "physically meaningful range")
    assert not (tmp_path / "y.RPB").exists()
