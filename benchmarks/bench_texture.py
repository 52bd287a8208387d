"""Texture statistics of simulated line-scan images against real HiRISE images.

Compares, on the same ground scales (metres, not pixels):

* **PSD slope**: the log-log slope of the radially averaged power spectrum of the
  image's relative radiance (``DN / mean - 1``, Hann-windowed), fitted over wavelengths
  from ``--band`` (default 2.5 to 40 m, well inside both images' Nyquist and above the
  simulated PSF/noise floor);
* **local contrast**: the standard deviation over the mean in 4 m x 4 m windows
  (10th, 50th and 90th percentiles);
* **gradient orientation**: Sobel gradients after a Gaussian of 1 m, the orientation
  histogram (8 bins over 360 degrees, magnitude-weighted) summarised by its normalised
  entropy (1 = isotropic) and its mean resultant length (0 = isotropic, 1 = all
  gradients one way, as when the sun's shading dominates).

Real: the four map-projected HiRISE RED crops in ``../shared/data/hirise_pairs``
(~0.25 m/px; pixels without data are trimmed away). Simulated: the CCD images of a scene
(``--scene DIR``), or of a freshly simulated ``hiric-strip`` scene with ``--lines`` lines
(default 1024; images at 0.5 m/px). Usage::

    python benchmarks/bench_texture.py
    python benchmarks/bench_texture.py --scene planetref-demo/scene-hiric-strip-seed0
    python benchmarks/bench_texture.py --difficulty hard --lines 2048

The table prints both side by side and the ratio of the mean simulated PSD slope to the
mean real one (the simulator is tuned so that it lies within 20 % of 1).
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter, sobel, uniform_filter

F64 = NDArray[np.float64]
HIRISE = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "hirise_pairs"


def psd_slope(img: F64, px_m: float, band_m: tuple[float, float]) -> float:
    """Slope of log P(f) against log f over wavelengths ``band_m`` (metres)."""
    a = img / img.mean() - 1.0
    h = np.outer(np.hanning(a.shape[0]), np.hanning(a.shape[1]))
    p = np.abs(np.fft.fftshift(np.fft.fft2(a * h))) ** 2
    fy = np.fft.fftshift(np.fft.fftfreq(a.shape[0], d=px_m))
    fx = np.fft.fftshift(np.fft.fftfreq(a.shape[1], d=px_m))
    f = np.hypot(*np.meshgrid(fy, fx, indexing="ij"))
    edges = np.geomspace(1.0 / band_m[1], 1.0 / band_m[0], 16)
    idx = np.digitize(f.ravel(), edges)
    pr = p.ravel()
    centres, power = [], []
    for k in range(1, len(edges)):
        sel = idx == k
        if sel.sum() >= 4:
            centres.append(math.sqrt(edges[k - 1] * edges[k]))
            power.append(pr[sel].mean())
    return float(np.polyfit(np.log(centres), np.log(power), 1)[0])


def local_contrast(img: F64, px_m: float, window_m: float = 4.0) -> F64:
    """Percentiles 10, 50, 90 of std/mean in ``window_m`` windows."""
    w = max(2, round(window_m / px_m))
    m = uniform_filter(img, w)
    m2 = uniform_filter(img * img, w)
    c = np.sqrt(np.maximum(m2 - m * m, 0.0)) / np.maximum(m, 1e-12)
    c = c[w:-w, w:-w]
    return np.percentile(c, [10, 50, 90])


def orientation_stats(img: F64, px_m: float, scale_m: float = 1.0) -> tuple[float, float]:
    """(normalised entropy, mean resultant length) of the gradient orientations."""
    s = gaussian_filter(img, scale_m / px_m)
    gx, gy = sobel(s, axis=1), sobel(s, axis=0)
    mag = np.hypot(gx, gy)
    ang = np.arctan2(gy, gx)
    hist, _ = np.histogram(ang, bins=8, range=(-np.pi, np.pi), weights=mag)
    p = hist / hist.sum()
    ent = float(-(p[p > 0] * np.log(p[p > 0])).sum() / math.log(8))
    r = float(np.hypot((mag * np.cos(ang)).sum(), (mag * np.sin(ang)).sum()) / mag.sum())
    return ent, r


def _trim_invalid(a: np.ma.MaskedArray) -> F64:
    """The largest border-trimmed block without masked or non-finite pixels."""
    data = np.asarray(a.filled(np.nan), dtype=np.float64)
    bad = ~np.isfinite(data)
    r0, r1, c0, c1 = 0, data.shape[0], 0, data.shape[1]
    while bad[r0:r1, c0:c1].any():
        sub = bad[r0:r1, c0:c1]
        counts = [sub[0].sum(), sub[-1].sum(), sub[:, 0].sum(), sub[:, -1].sum()]
        k = int(np.argmax(counts))
        if k == 0:
            r0 += 1
        elif k == 1:
            r1 -= 1
        elif k == 2:
            c0 += 1
        else:
            c1 -= 1
    return data[r0:r1, c0:c1]


def real_images() -> list[tuple[str, F64, float]]:
    """``(name, image, pixel size m)`` of the real HiRISE crops (empty when absent)."""
    import rasterio

    out = []
    for p in sorted(HIRISE.glob("*.cub")):
        with rasterio.open(p) as ds:
            img = _trim_invalid(ds.read(1, masked=True))
            out.append((p.stem[:28], img, float(ds.res[0])))
    return out


def simulated_images(scene: Path) -> list[tuple[str, F64, float]]:
    """``(name, image, nadir GSD m)`` of the scene's CCD images (central 512 lines)."""
    import json

    import rasterio
    from rasterio.errors import NotGeoreferencedWarning

    from planetref.runtime.tomlfile import read_toml

    man = read_toml(scene / "scene.toml", "scene manifest")
    errors = json.loads((scene / "truth" / "errors.json").read_text())
    out = []
    for strip in man["strips"]:
        gsd = float(errors[strip["id"]]["facts"]["gsd_m"])
        for ccd in strip["ccds"]:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", NotGeoreferencedWarning)
                with rasterio.open(scene / ccd["image"]) as ds:
                    img = ds.read(1).astype(np.float64)
            n = min(512, img.shape[0])
            a = (img.shape[0] - n) // 2
            out.append((f"sim {strip['id']}/{ccd['name']}", img[a : a + n], gsd))
    return out


def main() -> None:
    """Print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", type=Path, default=None, help="An existing simulated scene.")
    ap.add_argument("--preset", default="hiric-strip")
    ap.add_argument("--difficulty", default=None)
    ap.add_argument("--lines", type=int, default=1024)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--band", type=float, nargs=2, default=(2.5, 40.0), metavar=("MIN_M", "MAX_M"))
    args = ap.parse_args()
    real = real_images()
    if not real:
        print(f"no real HiRISE images in {HIRISE}; nothing to compare", file=sys.stderr)
        sys.exit(0)
    with tempfile.TemporaryDirectory() as tmp:
        scene = args.scene
        if scene is None:
            from planetref.simulate.config import load_config
            from planetref.simulate.scene import simulate_scene

            cfg = load_config(
                args.preset,
                {"camera": {"n_lines": args.lines}, "render": {"write_rpc": False}},
                seed=args.seed,
                difficulty=args.difficulty,
            )
            scene = Path(tmp) / "scene"
            simulate_scene(cfg, scene)
        sim = simulated_images(scene)
    band = tuple(args.band)
    print(
        f"{'image':32s} {'px m':>5s} {'PSD slope':>9s}  {'contrast p10/p50/p90':>22s}"
        f"  {'orient. entropy':>15s} {'resultant':>9s}"
    )
    slopes: dict[str, list[float]] = {"real": [], "sim": []}
    for kind, items in (("real", real), ("sim", sim)):
        for name, img, px in items:
            s = psd_slope(img, px, band)  # type: ignore[arg-type]
            c = local_contrast(img, px)
            e, r = orientation_stats(img, px)
            slopes[kind].append(s)
            print(
                f"{name:32s} {px:5.2f} {s:9.2f}  {c[0]:6.3f} {c[1]:6.3f} {c[2]:6.3f}"
                f"     {e:15.3f} {r:9.3f}"
            )
    mr, ms = float(np.mean(slopes["real"])), float(np.mean(slopes["sim"]))
    print(
        f"mean PSD slope over {band[0]:g}-{band[1]:g} m: real {mr:.2f}, simulated {ms:.2f}, "
        f"ratio {ms / mr:.2f} (target 0.8-1.2)"
    )


if __name__ == "__main__":
    main()
