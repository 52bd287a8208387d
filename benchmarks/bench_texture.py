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
(``--scene DIR``, in blocks of 512 lines), or of a freshly simulated ``hiric-strip`` scene
at the ``realistic`` level with ``--lines`` lines (default 2048; images at 0.5 m/px); the
reference: the central 1.2 km of the scene's reference ortho in four quarters, compared
with the real crops block-averaged to the reference's pixel size (``--ref-band``,
default 11-60 m; contrast windows of 4 reference pixels, orientations at 1 pixel).
Usage::

    python benchmarks/bench_texture.py
    python benchmarks/bench_texture.py --scene planetref-demo/scene-hiric-strip-seed0
    python benchmarks/bench_texture.py --difficulty hard --lines 1024 --json

The tables print every image and, per statistic, the real mean (and range), the
simulated mean and their ratio; the ``realistic`` level is tuned so that the ratios of
PSD slope, local contrast p50 and orientation entropy lie within 0.8-1.25 for the CCD
images and the reference.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import warnings
from pathlib import Path
from typing import NamedTuple

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


def block_mean(img: F64, factor: int) -> F64:
    """``img`` averaged over ``factor x factor`` blocks (the area sampling of a coarser sensor)."""
    r, c = img.shape[0] // factor, img.shape[1] // factor
    return img[: r * factor, : c * factor].reshape(r, factor, c, factor).mean(axis=(1, 3))


def real_references(gsd_m: float) -> list[tuple[str, F64, float]]:
    """The real crops block-averaged to about ``gsd_m`` (the reference's scale)."""
    out = []
    for name, img, px in real_images():
        k = max(1, round(gsd_m / px))
        out.append((f"{name[:22]} /{k}", block_mean(img, k), px * k))
    return out


def simulated_images(scene: Path, block: int = 512) -> list[tuple[str, F64, float]]:
    """``(name, image, nadir GSD m)``: the scene's CCD images in blocks of ``block`` lines.

    Every full block of every CCD is one sample, so the simulated figures average over
    the whole strip rather than one patch of ground.
    """
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
            n = min(block, img.shape[0])
            for a in range(0, img.shape[0] - n + 1, n):
                out.append((f"sim {strip['id']}/{ccd['name']} l{a}", img[a : a + n], gsd))
    return out


def simulated_reference(scene: Path, size_m: float = 1200.0) -> list[tuple[str, F64, float]]:
    """The central ``size_m`` square of the scene's reference ortho, split in four quarters.

    Quarters of about the real crops' ground size (times 3-4) keep the statistics on
    comparable areas, so that the spread between them reads like the real crops' spread.
    """
    import rasterio

    from planetref.runtime.tomlfile import read_toml

    man = read_toml(scene / "scene.toml", "scene manifest")
    with rasterio.open(scene / man["reference"]["ortho"]) as ds:
        img = ds.read(1).astype(np.float64)
        px = float(ds.res[0])
    n = min(round(size_m / px), *img.shape)
    r0, c0 = (img.shape[0] - n) // 2, (img.shape[1] - n) // 2
    img = img[r0 : r0 + n, c0 : c0 + n]
    h = n // 2
    return [
        (f"sim reference q{k}", img[a : a + h, b : b + h], px)
        for k, (a, b) in enumerate(((0, 0), (0, h), (h, 0), (h, h)))
    ]


class Stats(NamedTuple):
    """Texture statistics of one image (see the module docstring)."""

    psd_slope: float
    contrast_p10: float
    contrast_p50: float
    contrast_p90: float
    orientation_entropy: float
    resultant: float
    dark_floor: float
    column_striping: float


def measure(
    img: F64, px: float, band_m: tuple[float, float], window_m: float, scale_m: float
) -> Stats:
    """The statistics of ``img`` (pixel ``px`` metres) on the given ground scales."""
    c = local_contrast(img, px, window_m)
    e, r = orientation_stats(img, px, scale_m)
    floor = float(np.percentile(img, 0.1) / img.mean())
    return Stats(
        psd_slope(img, px, band_m),
        float(c[0]),
        float(c[1]),
        float(c[2]),
        e,
        r,
        floor,
        column_striping(img),
    )


def column_striping(img: F64, width: int = 9) -> float:
    """Relative RMS of the column means' fine structure in excess of the rows'.

    The profile of column means (and of row means) relative to the image mean is
    high-passed (minus a ``width``-column running mean); scene texture and noise give
    both profiles alike, a fixed per-column gain only the columns' (detector columns run
    along the image's columns: in the real crops, map-projected from nearly N-S orbits,
    too). Returns ``sqrt(max(0, std_col^2 - std_row^2))``.
    """
    from scipy.ndimage import uniform_filter1d

    rel = img / img.mean()
    hp = []
    for axis in (0, 1):
        prof = rel.mean(axis=axis)
        hp.append(float(np.std(prof - uniform_filter1d(prof, width))))
    return math.sqrt(max(0.0, hp[0] ** 2 - hp[1] ** 2))


COMPARED = (
    "psd_slope",
    "contrast_p50",
    "orientation_entropy",
    "dark_floor",
    "column_striping",
)
"""The statistics whose sim/real ratio is printed; the first three are the calibration
target (0.8-1.25); ``dark_floor`` (the 0.1th percentile over the mean: how dark the
darkest pixels are, which bounds the additive haze and skylight) supports the haze;
``column_striping`` (:func:`column_striping`) sets ``sensor.column_gain_rms``."""


def compare(
    real: list[tuple[str, F64, float]],
    sim: list[tuple[str, F64, float]],
    band_m: tuple[float, float],
    window_m: float,
    scale_m: float,
) -> dict[str, object]:
    """Per-image rows and, per compared statistic, the real and simulated means and ratio."""
    rows = []
    means: dict[str, dict[str, float]] = {}
    for kind, items in (("real", real), ("sim", sim)):
        values = []
        for name, img, px in items:
            st = measure(img, px, band_m, window_m, scale_m)
            values.append(st)
            rows.append({"kind": kind, "image": name, "px_m": px, **st._asdict()})
        means[kind] = {k: float(np.mean([getattr(v, k) for v in values])) for k in Stats._fields}
    ratios = {
        k: {
            "real": means["real"][k],
            "sim": means["sim"][k],
            "ratio": means["sim"][k] / means["real"][k],
            "real_range": [
                float(min(r[k] for r in rows if r["kind"] == "real")),
                float(max(r[k] for r in rows if r["kind"] == "real")),
            ],
        }
        for k in COMPARED
    }
    return {
        "band_m": list(band_m),
        "window_m": window_m,
        "scale_m": scale_m,
        "rows": rows,
        "statistics": ratios,
    }


def _print(title: str, result: dict[str, object]) -> None:
    band = result["band_m"]
    print(
        f"\n{title}: PSD slope over {band[0]:g}-{band[1]:g} m, contrast in "  # type: ignore[index]
        f"{result['window_m']:g} m windows, orientations at {result['scale_m']:g} m"
    )
    print(
        f"{'image':32s} {'px m':>5s} {'PSD slope':>9s}  {'contrast p10/p50/p90':>22s}"
        f"  {'orient. entropy':>15s} {'resultant':>9s} {'dark floor':>10s} {'stripes':>8s}"
    )
    for r in result["rows"]:  # type: ignore[attr-defined]
        print(
            f"{r['image']:32s} {r['px_m']:5.2f} {r['psd_slope']:9.2f}  {r['contrast_p10']:6.3f} "
            f"{r['contrast_p50']:6.3f} {r['contrast_p90']:6.3f}     "
            f"{r['orientation_entropy']:15.3f} {r['resultant']:9.3f} {r['dark_floor']:10.3f}"
            f" {r['column_striping']:8.5f}"
        )
    for k, v in result["statistics"].items():  # type: ignore[attr-defined]
        lo, hi = v["real_range"]
        flag = "" if 0.8 <= v["ratio"] <= 1.25 else "   <-- outside 0.8-1.25"
        print(
            f"  {k:20s} real {v['real']:7.3f} ({lo:.3f} to {hi:.3f})  sim {v['sim']:7.3f}  "
            f"sim/real {v['ratio']:5.2f}{flag}"
        )


def main() -> None:
    """Print the tables (or one JSON object with ``--json``)."""
    import json
    import time

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", type=Path, default=None, help="An existing simulated scene.")
    ap.add_argument("--preset", default="hiric-strip")
    ap.add_argument("--difficulty", default="realistic")
    ap.add_argument("--lines", type=int, default=2048)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--overrides", type=Path, default=None, help="A TOML override file.")
    ap.add_argument("--band", type=float, nargs=2, default=(2.5, 40.0), metavar=("MIN_M", "MAX_M"))
    ap.add_argument(
        "--ref-band", type=float, nargs=2, default=(11.0, 60.0), metavar=("MIN_M", "MAX_M")
    )
    ap.add_argument("--json", action="store_true", help="Print one JSON object.")
    args = ap.parse_args()
    real = real_images()
    if not real:
        print(f"no real HiRISE images in {HIRISE}; nothing to compare", file=sys.stderr)
        sys.exit(0)
    t0 = time.process_time()
    with tempfile.TemporaryDirectory() as tmp:
        scene = args.scene
        if scene is None:
            from planetref.runtime.tomlfile import read_toml
            from planetref.simulate.config import load_config, merge_overrides

            table: dict[str, object] = {
                "camera": {"n_lines": args.lines},
                "render": {"write_rpc": False},
            }
            if args.overrides is not None:
                table = merge_overrides(read_toml(args.overrides, "override file"), table)
            cfg = load_config(args.preset, table, seed=args.seed, difficulty=args.difficulty)
            scene = Path(tmp) / "scene"
            from planetref.simulate.scene import simulate_scene

            simulate_scene(cfg, scene)
        sim = simulated_images(scene)
        sim_ref = simulated_reference(scene)
    ref_gsd = sim_ref[0][2]
    image = compare(real, sim, tuple(args.band), 4.0, 1.0)
    reference = compare(
        real_references(ref_gsd), sim_ref, tuple(args.ref_band), 4.0 * ref_gsd, ref_gsd
    )
    if args.json:
        from machine import describe

        print(
            json.dumps(
                {
                    "machine": describe(),
                    "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                    "command": " ".join(sys.argv),
                    "scene": str(args.scene) if args.scene else None,
                    "preset": args.preset,
                    "difficulty": args.difficulty,
                    "seed": args.seed,
                    "cpu_s": time.process_time() - t0,
                    "image": image,
                    "reference": reference,
                },
                indent=1,
            )
        )
        return
    _print("CCD images vs real HiRISE", image)
    _print(f"reference vs real HiRISE averaged to {ref_gsd:g} m", reference)


if __name__ == "__main__":
    main()
