"""A quick-look figure of a scene: reference ortho, DEM hillshade and the CCD images.

Uses matplotlib's object API with the Agg canvas, so it never touches pyplot's global
state or the interactive backend.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

__all__ = ["hillshade", "write_preview"]


def hillshade(
    height: NDArray[np.floating],
    res_m: float,
    azimuth_deg: float = 315.0,
    elevation_deg: float = 45.0,
) -> NDArray[np.float32]:
    """Lambertian hillshade in [0, 1] of a north-up height grid (square cells of ``res_m``).

    Args:
        height: Heights (m); NaN gives NaN.
        res_m: Cell size (m).
        azimuth_deg: Sun azimuth, degrees clockwise from north.
        elevation_deg: Sun elevation, degrees.
    """
    h = np.asarray(height, dtype=np.float32)
    gy, gx = np.gradient(h, res_m)
    gy = -gy  # rows run south
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    s = np.array([np.sin(az) * np.cos(el), np.cos(az) * np.cos(el), np.sin(el)])
    norm = np.sqrt(gx * gx + gy * gy + 1.0)
    return np.clip((-gx * s[0] - gy * s[1] + s[2]) / norm, 0.0, 1.0).astype(np.float32)


def _read(path: Path, max_size: int) -> tuple[NDArray[np.float32], float]:
    """Band 1 decimated to at most ``max_size`` pixels per side, and the decimation step."""
    import warnings

    import rasterio
    from rasterio.errors import NotGeoreferencedWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(path) as ds:
            step = max(1, int(np.ceil(max(ds.height, ds.width) / max_size)))
            out = ds.read(1, out_shape=(max(1, ds.height // step), max(1, ds.width // step)))
            res = abs(ds.transform.a) * step
    return out.astype(np.float32), res


def _stretch(img: NDArray[np.float32]) -> NDArray[np.float32]:
    finite = img[np.isfinite(img)]
    if finite.size == 0:
        return img
    lo, hi = np.percentile(finite, [0.5, 99.5])
    return np.clip((img - lo) / max(hi - lo, 1e-6), 0.0, 1.0)


def write_preview(
    scene: str | os.PathLike[str], out_png: str | os.PathLike[str], *, max_size: int = 1200
) -> Path:
    """Save a PNG with the ortho, the truth (or reference) DEM hillshade and all CCD images.

    Args:
        scene: The scene directory (or its ``scene.toml``).
        out_png: Output PNG path.
        max_size: Largest side (pixels) each raster is decimated to.

    Returns:
        The PNG path.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from planetref.scene.manifest import load_manifest

    manifest, root = load_manifest(scene, check_files=False)
    ortho, _ = _read(manifest.resolve(root, manifest.reference.ortho), max_size)
    dem_rel = manifest.truth.dem if manifest.truth else manifest.reference.dem
    dem, dem_res = _read(manifest.resolve(root, dem_rel), max_size)
    ccds = [
        (f"{s.id}/{c.name}", manifest.resolve(root, c.image))
        for s in manifest.strips
        for c in s.ccds
    ]
    n = 2 + len(ccds)
    fig = Figure(figsize=(3.2 * n, 6.0))
    FigureCanvasAgg(fig)
    ax = fig.subplots(1, n, squeeze=False)[0]
    ax[0].imshow(_stretch(ortho), cmap="gray", interpolation="nearest")
    ax[0].set_title("reference ortho")
    ax[1].imshow(hillshade(dem, dem_res), cmap="gray", interpolation="nearest")
    ax[1].set_title("truth DEM (hillshade)" if manifest.truth else "reference DEM (hillshade)")
    for a, (name, path) in zip(ax[2:], ccds, strict=True):
        img, _ = _read(path, max_size)
        a.imshow(_stretch(img), cmap="gray", interpolation="nearest", aspect="equal")
        a.set_title(name)
    for a in ax:
        a.set_xticks([])
        a.set_yticks([])
    fig.suptitle(f"planetref scene '{manifest.name}'")
    fig.tight_layout()
    out = Path(out_png)
    fig.savefig(out, dpi=100, metadata={"Software": None})
    return out
