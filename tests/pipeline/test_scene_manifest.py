from __future__ import annotations

from pathlib import Path

import pytest

from planetref.errors import InputError, MissingFileError
from planetref.scene.manifest import (
    CcdSpec,
    ReferenceSpec,
    SceneManifest,
    StripSpec,
    TruthSpec,
    load_manifest,
    write_manifest,
)


def _manifest() -> SceneManifest:
    return SceneManifest(
        name="x",
        reference=ReferenceSpec(ortho="ref/o.tif", dem="/abs/d.tif"),
        strips=(
            StripSpec(
                id="s1",
                ccds=(
                    CcdSpec(name="ccd1", image="s1/1.tif", camera="s1/cam.json", camera_ccd="ccd1"),
                    CcdSpec(name="ccd2", image="s1/2.tif", camera="s1/2.RPB"),
                ),
            ),
        ),
        truth=TruthSpec(dem="t/dem.tif", cameras={"s1": "t/s1.json"}, ortho_offset_m=(1.5, 2)),
    )


def test_round_trip(tmp_path: Path) -> None:
    m = _manifest()
    p = write_manifest(m, tmp_path / "scene.toml")
    back, root = load_manifest(tmp_path, check_files=False)
    assert back == m and root == tmp_path
    assert back.resolve(root, "ref/o.tif") == tmp_path / "ref/o.tif"
    assert back.resolve(root, "/abs/d.tif") == Path("/abs/d.tif")
    assert "rpc" not in p.read_text()  # None values are left out
    # Same manifest, same bytes.
    q = write_manifest(m, tmp_path / "again.toml")
    assert p.read_bytes() == q.read_bytes()
    with pytest.raises(MissingFileError, match=r"ref/o\.tif"):
        load_manifest(p)


def test_unknown_keys_and_bad_values_are_rejected(tmp_path: Path) -> None:
    p = write_manifest(_manifest(), tmp_path / "scene.toml")
    text = p.read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace('ortho = "ref/o.tif"', 'orto = "ref/o.tif"'))
    with pytest.raises(InputError) as err:
        load_manifest(bad, check_files=False)
    msg = str(err.value)
    assert "reference.orto" in msg and "ortho" in msg and "dem_band" in msg
    bad.write_text(text.replace('name = "ccd2"', 'name = "ccd1"'))
    with pytest.raises(InputError, match="unique"):
        load_manifest(bad, check_files=False)
    bad.write_text(text.replace('format = "planetref-scene"', 'format = "other"'))
    with pytest.raises(InputError, match="format"):
        load_manifest(bad, check_files=False)
    bad.write_text(text.replace('s1 = "t/s1.json"', 's2 = "t/s1.json"'))
    with pytest.raises(InputError, match=r"truth\.cameras"):
        load_manifest(bad, check_files=False)
    with pytest.raises(MissingFileError):
        load_manifest(tmp_path / "nowhere")
