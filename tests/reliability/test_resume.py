"""Resume verifies what it keeps (issue 35, group 2).

A finished run whose orthoimage was truncated afterwards resumed with rc 0 and kept the
unreadable file: only its digest file was looked at. A kept output is now opened and
decoded, and its size compared with the one recorded when it was written.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import rasterio

from planetref.camera.mapping import image_gsd_m
from planetref.products.ortho_strip import orthorectify_strip, round_gsd


@pytest.fixture(scope="module")
def strip(mini_scene: Path):
    from planetref.camera.io import load_camera
    from planetref.raster.image import CcdImage
    from planetref.scene.inputs import open_reference
    from planetref.scene.manifest import load_manifest

    m, root = load_manifest(mini_scene)
    ref, dem = open_reference(m, root)
    s = m.strips[0]
    cam = load_camera(m.resolve(root, s.ccds[0].camera))
    c = s.ccds[0]
    images = {c.camera_ccd or c.name: CcdImage(m.resolve(root, c.image))}
    return cam, images, dem, ref.crs


def _ortho(strip, out: Path):
    cam, images, dem, crs = strip
    ccd = next(iter(images))
    gsd = round_gsd(image_gsd_m(cam, ccd, dem))
    return orthorectify_strip(images, cam, dem, crs, {ccd: out}, gsd_m=gsd, overviews=False)


def _pixels(path: Path) -> np.ndarray:
    with rasterio.open(path) as ds:
        return ds.read()


@pytest.mark.parametrize("damage", ["truncated", "grown"])
def test_a_damaged_kept_orthoimage_is_written_again(
    strip, tmp_path: Path, damage: str, caplog: pytest.LogCaptureFixture
) -> None:
    # planetref georef ... --out run (finished), then ccd1_ortho.tif cut to half its size
    # (a full disk, a copy interrupted) or grown, then the same command again
    out = tmp_path / "ccd1_ortho.tif"
    first = _ortho(strip, out)
    assert not first.resumed
    good = _pixels(out)
    assert _ortho(strip, out).resumed  # untouched: kept
    data = out.read_bytes()
    out.write_bytes(data[: len(data) // 2] if damage == "truncated" else data + b"\0" * 4096)
    with caplog.at_level(logging.WARNING, logger="planetref.products.ortho_strip"):
        again = _ortho(strip, out)
    assert not again.resumed
    assert any(str(out) in r.getMessage() for r in caplog.records)
    assert np.array_equal(_pixels(out), good)
    assert _ortho(strip, out).resumed
