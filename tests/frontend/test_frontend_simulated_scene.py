"""The front end on the simulator's ``tiny`` scene: offsets vs the simulated truth.

The ``tiny`` preset lights the reference ortho and the CCD images with different suns
(as real CTX and HiRIC images are). Shading then moves the apparent position of relief
features by about half a reference pixel, which no matcher can undo, so the offset
accuracy is checked on the same scene with the reference lit like the images; the
preset itself must still run end to end with every tile reported.
"""

from __future__ import annotations

import numpy as np
import pytest

from planetref.frontend.config import FrontendConfig
from planetref.frontend.geometry import image_to_ref_pixel
from planetref.frontend.match_tile import STATUSES, match_strip

# CCDs of 256 x 512 px at 1 m over a 5 m reference: one tile per CCD; the initial error
# is about 107 m (21 reference pixels).
CFG = FrontendConfig(tile_size_ref_px=128, coarse_factor=2, uncertainty_m=150.0)
SAME_SUN = {"photometry": {"reference_sun": {"azimuth_deg": 215.0, "elevation_deg": 40.0}}}


def _load(root):
    from planetref.camera.linescan import LineScanCamera
    from planetref.raster.dem import GridTerrain
    from planetref.raster.ortho import ReferenceOrtho
    from planetref.simulate.manifest import load_manifest

    man, root = load_manifest(root)
    strip = man.strips[0]
    return {
        "man": man,
        "init": LineScanCamera.from_json(man.resolve(root, strip.ccds[0].camera)),
        "true": LineScanCamera.from_json(man.resolve(root, man.truth.cameras[strip.id])),
        "ref": ReferenceOrtho(man.resolve(root, man.reference.ortho)),
        "dem": GridTerrain.from_geotiff(man.resolve(root, man.reference.dem)),
        "truth_dem": GridTerrain.from_geotiff(man.resolve(root, man.truth.dem)),
        "images": {c.name: man.resolve(root, c.image) for c in strip.ccds},
    }


def _simulate(tmp_path_factory, name, overrides=None):
    sim = pytest.importorskip("planetref.simulate")
    try:
        cfg = sim.load_config("tiny", overrides)
    except Exception as exc:  # the simulator is still being written by others
        pytest.skip(f"tiny preset unavailable: {exc}")
    out = tmp_path_factory.mktemp(name)
    sim.simulate_scene(cfg, out / "scene")
    return _load(out / "scene")


@pytest.fixture(scope="module")
def same_sun(tmp_path_factory):
    s = _simulate(tmp_path_factory, "tiny_same_sun", SAME_SUN)
    yield s
    s["ref"].close()


def _truth_offset(s, r):
    """Mean over the tile's MCPs of (true - initially predicted) reference position."""
    ref = s["ref"]
    tc, tr = image_to_ref_pixel(s["true"], r.tile.ccd, r.line, r.sample, ref, s["truth_dem"])
    dx, dy = s["man"].truth.ortho_offset_m
    tc, tr = tc + dx / ref.transform.a, tr + dy / ref.transform.e
    ic, ir = image_to_ref_pixel(s["init"], r.tile.ccd, r.line, r.sample, ref, s["dem"])
    return np.array([np.mean(tc - ic), np.mean(tr - ir)])


@pytest.mark.parametrize("name, min_ok", [
    ("sift", 3), ("ncc", 3),
    pytest.param("disk-lightglue", 2, marks=pytest.mark.shared),
    pytest.param("aliked-lightglue", 2, marks=pytest.mark.shared),
    pytest.param("xfeat-lighterglue", 1, marks=[pytest.mark.shared, pytest.mark.xfail(
        strict=False, reason="XFeat + LighterGlue finds fewer than 8 inliers on the tiny "
        "scene's 51 x 102 reference-pixel CCDs")]),
])
def test_tiny_offsets_agree_with_truth(same_sun, make_matcher, name, min_ok):
    s = same_sun
    # An area-based search must reach the initial error (21 px here).
    options = {"search_radius": 40, "spacing": 8} if name == "ncc" else {}
    matcher = make_matcher(name, **options)
    strip = match_strip(s["init"], s["images"], s["ref"], s["dem"], matcher, CFG,
                        progress=False, raise_errors=True)
    errs = {r.tile_id: float(np.max(np.abs(np.asarray(r.offset_px) - _truth_offset(s, r))))
            for r in strip.tiles if r.status == "ok"}
    print(f"tiny/{name}: {strip.status_counts()}, max |offset - truth| (ref px): "
          f"{ {k: round(v, 3) for k, v in errs.items()} }")
    assert len(errs) >= min_ok, [t.message for t in strip.tiles]
    assert max(errs.values()) < 0.5


def test_tiny_preset_runs_and_reports_every_tile(tmp_path_factory):
    from planetref.matching import get_matcher

    s = _simulate(tmp_path_factory, "tiny")
    try:
        strip = match_strip(s["init"], s["images"], s["ref"], s["dem"], get_matcher("sift"), CFG,
                            progress=False)
    finally:
        s["ref"].close()
    assert len(strip.tiles) == 3
    for t in strip.tiles:
        assert t.status in STATUSES and t.status != "error", t.message
        assert t.status == "ok" or t.message
