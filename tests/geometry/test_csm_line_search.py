import numpy as np
import pytest

SHARED = __import__("pathlib").Path(__file__).resolve().parents[2].parent / "shared" / "data"


def test_csm_bracketed_fallback_finds_the_lines_of_a_real_isd():
    isd = SHARED / "ctx_syrtis" / "P15_006844_2009_XN_20N286W.lev1.json"
    if not isd.is_file():
        pytest.skip(f"{isd} not found (real data live in ../shared)")
    from planetref.camera.csm import CsmLineScanCamera

    cam = CsmLineScanCamera.from_file(isd)
    nl, ns = cam.image_size()
    rng = np.random.default_rng(0)
    line, sample = rng.uniform(0, nl, 200), rng.uniform(0, ns, 200)
    xyz = cam.image_to_ground(line, sample, -1500.0)
    found, ok = cam._bracket_lines(xyz)
    assert ok.all()
    off = cam.detector_offset(found, xyz)[0]
    assert np.abs(off).max() < 1e-9
    assert np.abs(found + off - line).max() < 1e-6
