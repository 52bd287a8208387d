from __future__ import annotations

from pathlib import Path

from click.testing import CliRunner

from planetref.cli import main

MINI_TOML = """
[site]
margin_m = 150.0
[camera]
n_samples = 48
overlap_samples = 8
n_lines = 64
[terrain]
dem_gsd_m = 2.0
[reference]
dem_pad_m = 500.0
[render]
write_rpc = false
n_checkpoints = 2
measure_grid = 3
"""


def test_simulate_command(tmp_path: Path) -> None:
    cfg = tmp_path / "mini.toml"
    cfg.write_text(MINI_TOML)
    out = tmp_path / "scene"
    runner = CliRunner()
    res = runner.invoke(
        main,
        [
            "simulate",
            str(out),
            "--preset",
            "tiny",
            "--config",
            str(cfg),
            "--seed",
            "3",
            "--preview",
        ],
    )
    assert res.exit_code == 0, res.output
    assert (out / "scene.toml").is_file() and (out / "preview.png").stat().st_size > 1000
    assert "initial geolocation error" in res.output
    # A second run into the same, now non-empty, folder is refused ...
    res = runner.invoke(main, ["simulate", str(out), "--preset", "tiny", "--config", str(cfg)])
    assert res.exit_code == 1 and "--overwrite" in res.output
    # ... unless --overwrite.
    res = runner.invoke(
        main, ["-q", "simulate", str(out), "--preset", "tiny", "--config", str(cfg), "--overwrite"]
    )
    assert res.exit_code == 0, res.output


def test_bad_preset_and_override(tmp_path: Path) -> None:
    runner = CliRunner()
    res = runner.invoke(main, ["simulate", str(tmp_path / "x"), "--preset", "nope"])
    assert res.exit_code == 1
    assert "tiny" in res.output and "hiric-strip" in res.output
    bad = tmp_path / "bad.toml"
    bad.write_text("[sensor]\nbits = 12\n")
    res = runner.invoke(main, ["simulate", str(tmp_path / "x"), "--config", str(bad)])
    assert res.exit_code == 1
    assert "sensor.bits" in res.output and "bit_depth" in res.output
    assert not (tmp_path / "x").exists()


def test_difficulty_option(tmp_path: Path) -> None:
    cfg = tmp_path / "mini.toml"
    cfg.write_text(MINI_TOML)
    out = tmp_path / "scene"
    r = CliRunner().invoke(
        main,
        [
            "-q",
            "simulate",
            str(out),
            "--preset",
            "tiny",
            "--difficulty",
            "hard",
            "--config",
            str(cfg),
        ],
    )
    assert r.exit_code == 0, r.output
    text = (out / "truth" / "config.toml").read_text()
    assert 'name = "tiny-hard"' in text and "n_sources = 3" in text
    for cmd in (["simulate", str(tmp_path / "x")], ["demo", "--out", str(tmp_path / "d")]):
        r = CliRunner().invoke(main, ["-q", *cmd, "--difficulty", "brutal"])
        assert r.exit_code == 2 and "brutal" in r.output


def test_initial_errors_option_declares_the_uncertainty(tmp_path: Path) -> None:
    import json

    cfg = tmp_path / "mini.toml"
    cfg.write_text(MINI_TOML)
    out = tmp_path / "scene"
    cmd = ["-q", "simulate", str(out), "--preset", "tiny", "--config", str(cfg)]
    r = CliRunner().invoke(main, [*cmd, "--initial-errors", "1km"])
    assert r.exit_code == 0, r.output
    assert "initial_uncertainty_m = 1300.0" in (out / "scene.toml").read_text()
    assert 'name = "tiny-ie1km"' in (out / "truth" / "config.toml").read_text()
    errors = json.loads((out / "truth" / "errors.json").read_text())
    ground = errors["strip1"]["initial_errors"]["ground_m"]["horizontal"]
    assert 1000.0 < ground["rms"] < 1100.0
    r = CliRunner().invoke(main, [*cmd, "--initial-errors", "9km"])
    assert r.exit_code == 2 and "9km" in r.output
