"""Outputs never overwrite an input, and replace an existing file only with --overwrite."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from reliability_helpers import one_line_error, run_cli


def _strict_json(text: str) -> dict:
    def no_constant(name: str) -> None:
        raise ValueError(f"invalid JSON constant {name}")

    return json.loads(text, parse_constant=no_constant)


def test_match_out_is_an_input(image_pair: tuple[Path, Path]) -> None:
    # planetref match A.tif B.tif --out A.tif
    a, b = image_pair
    before = a.read_bytes()
    one_line_error(run_cli("match", a, b, "--out", a), str(a), "is an input")
    assert a.read_bytes() == before


def test_match_out_is_an_input_through_a_hard_link(image_pair: tuple[Path, Path]) -> None:
    # planetref match A.tif B.tif --out alias.tif (alias.tif a hard link of B.tif)
    a, b = image_pair
    alias = b.parent / "alias.tif"
    os.link(b, alias)
    before = b.read_bytes()
    one_line_error(run_cli("match", a, b, "--out", alias, "--overwrite"), "is an input")
    assert b.read_bytes() == before


def test_match_figure_is_an_input(image_pair: tuple[Path, Path], tmp_path: Path) -> None:
    # planetref match A.tif B.tif --out m.csv --figure A.tif
    a, b = image_pair
    before = a.read_bytes()
    r = run_cli("match", a, b, "--out", tmp_path / "m.csv", "--figure", a, "--overwrite")
    one_line_error(r, "--figure", "is an input")
    assert a.read_bytes() == before and not (tmp_path / "m.csv").exists()


def test_match_replaces_its_output_only_with_overwrite(
    image_pair: tuple[Path, Path], tmp_path: Path
) -> None:
    # planetref match A.tif B.tif --out m.csv, twice
    a, b = image_pair
    out = tmp_path / "m.csv"
    out.write_text("my matches\n")
    one_line_error(run_cli("match", a, b, "--out", out), str(out), "--overwrite")
    assert out.read_text() == "my matches\n"
    r = run_cli("match", a, b, "--out", out, "--overwrite", "--model", "affine")
    assert r.exit_code == 0, r.stderr
    assert _strict_json(r.stdout.strip())["ncp"] > 10
    assert out.read_text().startswith("x0,y0,x1,y1,confidence\n")


@pytest.fixture
def camera(mini_scene: Path) -> Path:
    return mini_scene / "strips" / "strip1" / "camera.json"


def test_fit_rpc_does_not_replace_an_rpb_silently(camera: Path, tmp_path: Path) -> None:
    # planetref camera fit-rpc camera.json --out ccd1.RPB (ccd1.RPB exists)
    out = tmp_path / "ccd1.RPB"
    r = run_cli("camera", "fit-rpc", camera, "--out", out)
    assert r.exit_code == 0, r.stderr
    doc = _strict_json(r.stdout)
    assert doc["fit_rms_px"] < 0.05 and doc["out"] == str(out)
    first = out.read_bytes()
    out.write_text("the user's edited RPB\n")
    one_line_error(run_cli("camera", "fit-rpc", camera, "--out", out), str(out), "--overwrite")
    assert out.read_text() == "the user's edited RPB\n"
    r = run_cli("camera", "fit-rpc", camera, "--out", out, "--overwrite")
    assert r.exit_code == 0, r.stderr
    assert out.read_bytes() == first


def test_fit_rpc_out_is_the_camera(camera: Path, tmp_path: Path) -> None:
    # planetref camera fit-rpc cam.RPB --out cam.RPB
    rpb = tmp_path / "cam.RPB"
    assert run_cli("camera", "fit-rpc", camera, "--out", rpb).exit_code == 0
    before = rpb.read_bytes()
    r = run_cli("camera", "fit-rpc", rpb, "--out", rpb, "--overwrite")
    one_line_error(r, str(rpb), "is an input")
    assert rpb.read_bytes() == before


def test_full_disk_names_the_file(camera: Path, tmp_path: Path) -> None:
    # planetref camera fit-rpc camera.json --out x.RPB with no room left for the file.
    # RLIMIT_FSIZE makes every write past 200 bytes fail with EFBIG, the same OSError
    # path as ENOSPC (a real full disk needs a dedicated file system).
    import resource
    import signal

    from reliability_helpers import run_subprocess

    def limit() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (200, 200))

    out = tmp_path / "x.RPB"
    r = run_subprocess("camera", "fit-rpc", camera, "--out", out, preexec_fn=limit)
    assert r.returncode == 1, (r.stdout, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and str(out) in lines[0] and "cannot write" in lines[0], lines
    assert not out.exists() and not list(tmp_path.glob(".x.*"))
