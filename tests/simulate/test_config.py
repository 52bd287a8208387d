from __future__ import annotations

from pathlib import Path

import pytest

from planetref.errors import InputError, MissingFileError
from planetref.simulate.config import (
    SimulationConfig,
    available_presets,
    load_config,
    merge_overrides,
)


def test_presets_are_valid_typed_and_frozen() -> None:
    assert {"tiny", "hiric-strip"} <= set(available_presets())
    for name in available_presets():
        cfg = load_config(name)
        assert isinstance(cfg, SimulationConfig)
        assert cfg.name == name
    cfg = load_config("hiric-strip")
    assert cfg.camera.n_ccds == 3 and cfg.camera.n_samples == 2048
    assert cfg.camera.overlap_samples == 64 and cfg.camera.gsd_m == 0.5
    with pytest.raises(Exception):  # noqa: B017 - pydantic's frozen error
        cfg.seed = 3  # type: ignore[misc]


def test_tiny_preset_is_matchable_against_its_reference() -> None:
    """``tiny`` is the front end's end-to-end fixture: each CCD must span several tiles of
    the 5 m reference, and the reference sun must differ from the images' moderately."""
    cfg = load_config("tiny")
    cam, ratio = cfg.camera, cfg.camera.gsd_m / cfg.reference.ortho_gsd_m
    assert cam.n_ccds == 3 and 0 < cam.overlap_samples < cam.n_samples // 10
    assert cam.n_samples * ratio >= 150 and cam.n_lines * ratio >= 300  # reference px
    assert cam.n_ccds * cam.n_samples * cam.n_lines <= 1_000_000  # stays quick to render
    assert cfg.terrain.dem_gsd_m < cam.gsd_m and cfg.albedo.texture_gsd_m < cam.gsd_m
    tgt, ref = cfg.photometry.target_sun, cfg.photometry.reference_sun
    d_az = abs((ref.azimuth_deg - tgt.azimuth_deg + 180.0) % 360.0 - 180.0)
    assert 20.0 <= d_az <= 35.0
    assert 0.0 < abs(ref.elevation_deg - tgt.elevation_deg) <= 10.0


def test_unknown_preset_lists_valid_names() -> None:
    with pytest.raises(InputError) as err:
        load_config("hirise")
    msg = str(err.value)
    assert "hirise" in msg and "tiny" in msg and "hiric-strip" in msg


def test_override_file_merges_tables_and_replaces_arrays(tmp_path: Path) -> None:
    f = tmp_path / "o.toml"
    f.write_text(
        'seed = 5\n[camera]\nn_lines = 64\n[[jitter]]\naxis = "yaw"\n'
        "amplitude_urad = 1.0\nfrequency_hz = 2.0\n"
    )
    cfg = load_config("tiny", f)
    base = load_config("tiny")
    assert cfg.seed == 5 and cfg.camera.n_lines == 64
    assert cfg.camera.n_samples == base.camera.n_samples  # untouched key kept
    assert len(cfg.jitter) == 1 and cfg.jitter[0].axis == "yaw"
    assert load_config("tiny", f, seed=9).seed == 9


def test_unknown_key_lists_valid_keys(tmp_path: Path) -> None:
    f = tmp_path / "bad.toml"
    f.write_text("[camera]\nn_line = 64\n")
    with pytest.raises(InputError) as err:
        load_config("tiny", f)
    msg = str(err.value)
    assert str(f) in msg and "camera.n_line" in msg
    for key in ("n_lines", "n_samples", "overlap_samples", "gsd_m"):
        assert key in msg
    with pytest.raises(InputError) as err:
        load_config("tiny", {"terrain": {"craters": {"densty": 1}}})
    assert "density_per_km2" in str(err.value) and "sfd_slope" in str(err.value)
    with pytest.raises(InputError) as err:
        load_config("tiny", {"colour": 1})
    assert "valid keys: " in str(err.value) and "photometry" in str(err.value)


def test_bad_values_and_files(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="gsd_m"):
        load_config("tiny", {"camera": {"gsd_m": -1.0}})
    with pytest.raises(InputError, match="overlap_samples"):
        load_config("tiny", {"camera": {"overlap_samples": 4096}})
    with pytest.raises(InputError, match="d_max_m"):
        load_config("tiny", {"terrain": {"craters": {"d_min_m": 50.0, "d_max_m": 10.0}}})
    with pytest.raises(InputError, match="unique"):
        load_config("tiny", {"strips": [{"id": "a"}, {"id": "a"}]})
    bad = tmp_path / "bad.toml"
    bad.write_text("[camera\n")
    with pytest.raises(InputError, match="TOML"):
        load_config("tiny", bad)
    with pytest.raises(MissingFileError):
        load_config("tiny", tmp_path / "missing.toml")


def test_merge_overrides_does_not_mutate() -> None:
    base = {"a": {"b": 1, "c": 2}, "d": [1]}
    out = merge_overrides(base, {"a": {"b": 5}, "d": [2, 3]})
    assert out == {"a": {"b": 5, "c": 2}, "d": [2, 3]}
    assert base == {"a": {"b": 1, "c": 2}, "d": [1]}
