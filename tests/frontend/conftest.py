"""A tiny synthetic scene with truth for the front-end tests.

A textured ground (a smoothed random field on a 2.5 m map grid, continuous through
bilinear interpolation), a smooth DEM at 50 m, a CTX-like reference ortho at 5 m (the
exact 2 x 2 average of the texture grid), two CCD images at ~0.5 m rendered through the
TRUE line-scan camera, and an initial camera whose orbit is shifted by tens of metres.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from planetref.camera.linescan import LineScanCamera
from planetref.camera.orbit import OrbitGeometry, ccd_row, orbit_camera
from planetref.geometry.geodesy import MARS_IAU2015_SPHERE, lonlat_to_xyz
from planetref.raster.dem import GridTerrain

CRS = "IAU_2015:49910"
R = MARS_IAU2015_SPHERE.semi_major_m
LAT, LON, HEADING = 20.0, 74.0, 30.0
TEX_RES = 2.5
REF_RES = 5.0
DEM_RES = 50.0


@dataclass
class Scene:
    root: Path
    ortho_path: Path
    dem_path: Path
    image_paths: dict[str, Path]
    true_cam: LineScanCamera
    init_cam: LineScanCamera
    dem: GridTerrain
    images: dict[str, np.ndarray]
    shift_m: tuple[float, float]


def _torch_one_thread() -> None:
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:  # pragma: no cover
        pass


def shifted_camera(cam: LineScanCamera, east_m: float, north_m: float) -> LineScanCamera:
    up = lonlat_to_xyz(LON, LAT, 0.0, cam.ellipsoid)
    up = up / np.linalg.norm(up)
    lon = np.radians(LON)
    east = np.array([-np.sin(lon), np.cos(lon), 0.0])
    north = np.cross(up, east)
    nodes = cam.nodes.copy()
    nodes[:, :3] += east_m * east + north_m * north
    return cam.replace(nodes=nodes)


def render(
    cam: LineScanCamera, ccd: str, dem: GridTerrain, tex: np.ndarray, tex_transform, step: int = 16
) -> np.ndarray:
    """Sample the texture through a camera: exact rays on a lattice, bilinear between."""
    n_lines, n_samples = cam.image_size(ccd)
    ll = np.append(np.arange(0.0, n_lines, step), n_lines)
    ss = np.append(np.arange(0.0, n_samples, step), n_samples)
    gl, gs = np.meshgrid(ll, ss, indexing="ij")
    o, d = cam.look_rays(gl.ravel(), gs.ravel(), ccd=ccd)
    hits = dem.intersect_rays(o, d)
    mx = hits.x.reshape(gl.shape)
    my = hits.y.reshape(gl.shape)
    lines = np.arange(n_lines) + 0.5
    samples = np.arange(n_samples) + 0.5
    fi = np.interp(lines, ll, np.arange(len(ll)))
    fj = np.interp(samples, ss, np.arange(len(ss)))
    gi, gj = np.meshgrid(fi, fj, indexing="ij")
    coords = np.vstack([gi.ravel(), gj.ravel()])
    x = ndimage.map_coordinates(mx, coords, order=1).reshape(n_lines, n_samples)
    y = ndimage.map_coordinates(my, coords, order=1).reshape(n_lines, n_samples)
    inv = ~tex_transform
    col = inv.a * x + inv.b * y + inv.c - 0.5
    row = inv.d * x + inv.e * y + inv.f - 0.5
    img = ndimage.map_coordinates(
        tex, np.vstack([row.ravel(), col.ravel()]), order=1, mode="nearest"
    )
    return img.reshape(n_lines, n_samples).astype(np.float32)


def build_scene(
    root: Path,
    write_geotiff,
    *,
    n_lines: int = 1920,
    n_samples: int = 960,
    shift_m: tuple[float, float] = (60.0, -35.0),
    seed: int = 7,
) -> Scene:
    import rasterio
    from affine import Affine

    _torch_one_thread()
    root.mkdir(parents=True, exist_ok=True)
    ccds = ccd_row(2, n_samples, n_lines, 0.010, overlap_px=48)
    cam, _ = orbit_camera(
        OrbitGeometry(LAT, LON, HEADING), focal_length_mm=5300.0, ccds=ccds, n_nodes=6
    )
    cx, cy = R * np.radians(LON), R * np.radians(LAT)
    half = 2000.0  # metres of map around the centre
    x0, y1 = np.floor((cx - half) / DEM_RES) * DEM_RES, np.ceil((cy + half) / DEM_RES) * DEM_RES
    n = int(2 * half / TEX_RES) + 80
    n -= n % 2
    rng = np.random.default_rng(seed)
    tex = ndimage.gaussian_filter(rng.normal(size=(n, n)), 1.2)
    tex += 0.6 * ndimage.gaussian_filter(rng.normal(size=(n, n)), 6.0) * 6.0
    # Craters (a dark bowl and a bright rim, lit from one side) give the texture the
    # distinct blobs and edges that learned detectors look for.
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float32)
    for _ in range(int(n * n * TEX_RES**2 / 60000.0)):
        cy0, cx0 = rng.uniform(0, n, 2)
        r = rng.uniform(4.0, 40.0) / TEX_RES
        sl = (
            slice(max(0, int(cy0 - 2 * r)), int(cy0 + 2 * r) + 1),
            slice(max(0, int(cx0 - 2 * r)), int(cx0 + 2 * r) + 1),
        )
        dy, dx = yy[sl] - cy0, xx[sl] - cx0
        rho = np.hypot(dx, dy) / r
        shade = (dx + dy) / (np.hypot(dx, dy) + 1e-6)
        tex[sl] += 2.5 * (
            np.exp(-(((rho - 1.0) / 0.18) ** 2)) * (0.6 + 0.4 * shade)
            - 0.8 * np.clip(1.0 - rho, 0.0, None) * (0.5 - 0.5 * shade)
        )
    tex = (tex - tex.min()) / (tex.max() - tex.min()) * 2000.0 + 500.0
    tex_t = Affine(TEX_RES, 0, x0, 0, -TEX_RES, y1)
    ref = tex.reshape(n // 2, 2, n // 2, 2).mean(axis=(1, 3)).astype(np.float32)
    ref_t = Affine(REF_RES, 0, x0, 0, -REF_RES, y1)

    nd = int(n * TEX_RES / DEM_RES) + 1
    xs = x0 + (np.arange(nd) + 0.5) * DEM_RES
    ys = y1 - (np.arange(nd) + 0.5) * DEM_RES
    gx, gy = np.meshgrid(xs - cx, ys - cy)
    heights = -1500.0 + 0.05 * gx + 0.03 * gy + 120.0 * np.exp(-(gx**2 + gy**2) / (2 * 600.0**2))
    dem_t = Affine(DEM_RES, 0, x0, 0, -DEM_RES, y1)
    dem = GridTerrain(heights.astype(np.float32), dem_t, CRS)

    crs = rasterio.crs.CRS.from_user_input(CRS)
    ortho_path = root / "ref_ortho.tif"
    write_geotiff(ortho_path, ref, dtype="float32", crs=crs, transform=ref_t, nodata=-9999.0)
    dem_path = root / "ref_dem.tif"
    dem.to_geotiff(dem_path)

    images, paths = {}, {}
    for c in cam.ccd_names:
        img = render(cam, c, dem, tex, tex_t)
        images[c] = img
        paths[c] = root / f"{c}.tif"
        write_geotiff(paths[c], img, dtype="float32")
    init = shifted_camera(cam, *shift_m)
    return Scene(root, ortho_path, dem_path, paths, cam, init, dem, images, shift_m)


@pytest.fixture(scope="session")
def scene(tmp_path_factory, write_geotiff) -> Scene:
    return build_scene(tmp_path_factory.mktemp("scene"), write_geotiff)


@pytest.fixture(scope="session")
def shift_camera():
    """``shifted_camera(cam, east_m, north_m)``: the orbit moved on the ground."""
    return shifted_camera


SHARED_WEIGHTS = Path(__file__).resolve().parents[2].parent / "shared" / "weights"


def build_matcher(name: str, **options):
    """A registry matcher; learned ones from ../shared/weights, or skip with the reason."""
    from planetref.matching import get_matcher
    from planetref.matching.registry import MATCHERS
    from planetref.matching.weights import missing_weights

    if MATCHERS[name].weights:
        if not SHARED_WEIGHTS.is_dir():
            pytest.skip(f"shared weights not found at {SHARED_WEIGHTS}")
        missing = missing_weights(MATCHERS[name].weights, SHARED_WEIGHTS)
        if missing:
            pytest.skip(f"{name}: weights {missing} not present in {SHARED_WEIGHTS}")
        return get_matcher(name, weights_dir=SHARED_WEIGHTS, **options)
    return get_matcher(name, **options)


@pytest.fixture(scope="session")
def make_matcher():
    """``make_matcher(name, **options)``; see :func:`build_matcher`."""
    return build_matcher
