"""Sub-pixel bias of the matchers: one texture against copies shifted by known sub-pixel amounts.

Question behind it: on the hiric-strip scenes, XFeat + LighterGlue MCPs carried a bias of
about 0.2 fine-grid pixels common to the tiles, where ALIKED + LightGlue and XFeat* did
not. Is that a coordinate bug of planetref's XFeat wrapper or a property of XFeat's
detector (whole-pixel keypoints from 8 x 8 cells)? This script measures every matcher on
pairs whose true displacement is known exactly, and runs XFeat as its authors' code
decodes it (``xfeat-upstream``, below) on the same pairs.

Pairs (``--modes``), all from one high-resolution texture ``T`` (``--texture``):

* ``phases``: ``K x K`` block means of ``T`` (``K = --block``, 4 by default) from the
  block grid's origin, against the same block means from an origin moved by
  ``(dx, dy)`` texture pixels, ``dx, dy`` in ``0 .. K - 1``: the copy is shifted by
  exactly ``(dx, dy) / K`` pixels (phases 0, 0.25, 0.5, 0.75), with the same blur,
  no interpolation;
* ``sweep``: the same along x only, from -1 to +2 pixels in steps of ``1 / K``: whole-
  pixel shifts too, to tell a bias tied to the pixel phase (periodic in 1 px) from one
  tied to XFeat's 8-pixel cell grid;
* ``frontend``: the two images the front end matches at ``fine_upsample = 2``: the CCD
  side as :func:`planetref.frontend.orthorectify.orthorectify` builds it (2 x 2 texture
  block means, sampled bilinearly every 5 texture pixels) against a 10 x 10 block mean
  (the 5 m reference), rounded to 8 bits and upsampled x2 bicubically as
  :func:`planetref.frontend.grid.read_fine` does; shifts of the reference side in
  steps of one texture pixel (0.2 fine pixel);
* ``tiles`` (with ``--scene``, a simulated scene; made there with the ``hiric-strip``
  moderate seed-0 config when missing): the fine-stage pairs of ``--tile-ids`` as the
  front end builds them (:func:`tile_pairs`), the reference window placed on the true
  offset and then moved by ``d`` fine pixels, so that the arrays are displaced by
  ``D = -d`` (within half a pixel); each match's error is its reference position minus
  the true position of its CCD-side point (through the scene's true camera and DEM), in
  fine pixels. The front end itself places that window on the coarse offset rounded to
  whole reference pixels (2 fine pixels), so ``D`` there is the coarse stage's error.

For each matcher and shift: the matches' error ``kp1 - (kp0 + t)`` (``t`` the true
displacement, pixels of the matched images), its mean and RMS per axis over the matches
within 2 px (3 px for ``tiles``; the others are wrong matches: counted, not averaged);
per matcher and mode, the mean of the per-shift means, their spread (standard deviation
over shifts) and, where opposite shifts were measured, the odd part ``odd_x`` /
``odd_y`` (half the difference of the mean errors at ``+t`` and ``-t``): negative when
the matches measure less than the true displacement, whichever its sign.

``xfeat-upstream`` is planetref's XFeat + LighterGlue with its detector input replaced
by what XFeat's own code does: ``XFeat.detectAndCompute`` on the image as it is (it
resizes to multiples of 32 and scales the integer keypoints back), instead of
planetref's replicate padding to multiples of 32. Its keypoints get the same
``+ 0.5`` (pixel centres at integers -> planetref's corner convention) as every
detector's, which cancels in ``kp1 - kp0``.

Textures: ``sim`` (default) renders a patch of the ``--preset`` scene (``hiric-strip``
at moderate difficulty, seed 0: the terrain of the scene where the bias was seen) at
0.5 m with the simulator's target illumination; ``hirise`` takes the four real HiRISE
images of ``../shared/data/hirise_pairs`` (0.25 m; skipped with a message when absent);
any other value is read as a raster path. A simulated texture is easier than reality:
no noise, no illumination change between the two images, the same surface on both.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/bench_subpixel_bias.py [--texture sim|hirise|PATH]
        [--modes phases sweep frontend tiles] [--scene DIR] [--tile-ids ccd1:r003c000 ...]
        [--matchers xfeat-lighterglue ...] [--size 384] [--json] [--json-out FILE]

``benchmarks/results/bench_subpixel_bias.json`` holds the ``sim`` and ``tiles`` modes,
``bench_subpixel_bias_hirise.json`` the real HiRISE textures (``--texture hirise``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
HIRISE = SHARED / "data" / "hirise_pairs"
MATCHERS = ("xfeat-lighterglue", "xfeat-upstream", "xfeat-star", "aliked-lightglue", "sift")
F32 = NDArray[np.float32]
F64 = NDArray[np.float64]


# --------------------------------------------------------------------------- textures


def sim_texture(preset: str, size_px: int, res_m: float = 0.5) -> NDArray[np.float64]:
    """A ``size_px`` square of the simulated scene's target radiance at ``res_m`` (nadir).

    The patch is centred on the scene's reference grid; the simulator's supersampling is
    lowered to 2 (the texture is averaged further by the pairs' blocks).
    """
    from planetref.simulate.config import load_config
    from planetref.simulate.grid import MapGrid
    from planetref.simulate.reference import ortho_radiance
    from planetref.simulate.scene import build_scene_model

    difficulty = "moderate" if preset != "tiny" else None
    cfg = load_config(preset, seed=0, difficulty=difficulty)
    model = build_scene_model(cfg)
    og = model.ortho_grid
    cx = og.x0 + og.cols * og.res / 2
    cy = og.y0 - og.rows * og.res / 2
    half = size_px * res_m / 2
    grid = MapGrid(cx - half, cy + half, res_m, size_px, size_px)
    sensor = cfg.reference.ortho_sensor.model_copy(update={"supersample": 2})
    ref_cfg = cfg.reference.model_copy(update={"ortho_sensor": sensor})
    out = np.zeros(grid.shape, np.float32)
    ortho_radiance(grid, model.ref, model.local, model.radiance_model("target"), ref_cfg, out)
    return out.astype(np.float64)


def raster_textures(paths: list[Path]) -> list[tuple[str, NDArray[np.float64]]]:
    """Each raster's largest centred square without no-data."""
    import rasterio

    out = []
    for p in paths:
        with rasterio.open(p) as ds:
            a = ds.read(1).astype(np.float64)
            nodata = ds.nodata
        valid = np.isfinite(a) & (a > -1e30)
        if nodata is not None:
            valid &= a != nodata
        h, w = a.shape
        n = min(h, w)
        r0, c0 = (h - n) // 2, (w - n) // 2
        while n > 32 and not valid[r0 : r0 + n, c0 : c0 + n].all():
            n -= 4
            r0, c0 = (h - n) // 2, (w - n) // 2
        out.append((p.name, a[r0 : r0 + n, c0 : c0 + n]))
    return out


# --------------------------------------------------------------------------- pairs


def block_mean(t: NDArray[np.float64], k: int, dy: int, dx: int, n: int) -> F32:
    """``n x n`` means of ``k x k`` blocks of ``t`` from texture pixel ``(dy, dx)``.

    Output pixel ``i`` covers texture pixels ``[k i + d, k i + d + k)``: its content is
    that of the origin's image shifted by ``-d / k`` pixels.
    """
    b = t[dy : dy + n * k, dx : dx + n * k]
    return b.reshape(n, k, n, k).mean(axis=(1, 3)).astype(np.float32)


@dataclass(frozen=True)
class Pair:
    """Two images and the true displacement ``t``: a point at ``p`` in ``image0`` is at
    ``p + t`` in ``image1`` (pixels)."""

    label: str
    image0: F32
    image1: F32
    t: tuple[float, float]


def shift_pairs(
    t: NDArray[np.float64], k: int, shifts: list[tuple[int, int]], size: int
) -> list[Pair]:
    """Block means from origin ``(2k, 2k)`` against origins moved by ``(dx, dy)`` texture px.

    The label is the origin's move in pixels, ``-t``.
    """
    o = 2 * k
    n = min(size, (min(t.shape) - 2 * o) // k)
    base = block_mean(t, k, o, o, n)
    return [
        Pair(
            f"({dx / k:+.2f}, {dy / k:+.2f})",
            base,
            block_mean(t, k, o + dy, o + dx, n),
            (-dx / k, -dy / k),
        )
        for dx, dy in shifts
    ]


def ortho_like(t: NDArray[np.float64], n: int, margin: int) -> F32:
    """The front end's CCD side at 5 texture px per pixel: 2 x 2 block means, bilinear."""
    from scipy import ndimage

    h2, w2 = t.shape[0] // 2, t.shape[1] // 2
    b = t[: 2 * h2, : 2 * w2].reshape(h2, 2, w2, 2).mean(axis=(1, 3))
    c = 5.0 * (np.arange(n) + 0.5) + margin  # texture coordinate of pixel centres
    rr, cc = np.meshgrid(c / 2 - 0.5, c / 2 - 0.5, indexing="ij")
    return ndimage.map_coordinates(b, [rr, cc], order=1).astype(np.float32)


def reference_like(t: NDArray[np.float64], n: int, margin: int, dx: int) -> F32:
    """10 x 10 block means, 8 bits, bicubic x2 (``read_fine``), origin moved by ``dx``.

    Fine pixel ``i`` is centred on texture coordinate ``5 (i + 0.5) + margin + dx``.
    """
    import cv2

    pad = 2  # coarse pixels read around the window, as read_fine does
    o = margin - 10 * pad
    m = n // 2 + 2 * pad
    a = t[o : o + 10 * m, o + dx : o + dx + 10 * m]
    coarse = a.reshape(m, 10, m, 10).mean(axis=(1, 3))
    coarse = np.clip(np.round(coarse / np.median(coarse) * 81.0), 0, 255)  # like the scene's
    fine = cv2.resize(coarse.astype(np.float32), None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC)
    return fine[2 * pad : 2 * pad + n, 2 * pad : 2 * pad + n]


def frontend_pairs(t: NDArray[np.float64], steps: list[int]) -> list[Pair]:
    """CCD side against reference side, the reference moved by ``dx`` texture px (0.2 px)."""
    margin = 40
    n = ((min(t.shape) - 2 * margin) // 10) * 2
    side = ortho_like(t, n, margin)
    return [
        Pair(f"({dx / 5:+.2f}, +0.00)", side, reference_like(t, n, margin, dx), (-dx / 5, 0.0))
        for dx in steps
    ]


def build_pairs(mode: str, t: NDArray[np.float64], k: int, size: int) -> list[Pair]:
    """The pairs of one mode (see the module docstring), images of at most ``size`` px."""
    if mode == "phases":
        return shift_pairs(t, k, [(dx, dy) for dy in range(k) for dx in range(k)], size)
    if mode == "sweep":
        return shift_pairs(t, k, [(d, 0) for d in range(-k, 2 * k + 1)], size)
    if mode == "frontend":
        return frontend_pairs(t, [-5, -3, -1, 0, 1, 3, 5])
    raise SystemExit(f"unknown mode {mode!r}")


@dataclass(frozen=True)
class TilePair:
    """A tile's fine-stage pair of a simulated scene, the reference side moved by ``d`` px."""

    tile_id: str
    d: int
    side: Any  # planetref.frontend.orthorectify.ImageSide
    ref_image: F32
    ref_valid: NDArray[np.bool_]
    window: Any  # planetref.frontend.grid.FineWindow: ref_image's pixel (0, 0) is its crop
    crop: tuple[int, int]  # fine pixels cut off the window's left and top
    truth: Any  # (line, sample) -> true reference (col, row)


def tile_pairs(scene: Path, tile_ids: list[str], steps: list[int]) -> list[list[TilePair]]:
    """The front end's fine-stage pairs of some tiles, with known true displacement.

    Per tile: the CCD side exactly as the fine stage builds it (orthorectified onto the
    footprint window at ``fine_upsample = 2``) and the reference read as the fine stage
    reads it, from a window placed on the TRUE offset (rounded to whole fine pixels, so
    the arrays' residual displacement ``D0`` is within half a fine pixel), then moved by
    ``d`` fine pixels: the two arrays are displaced by ``D = D0 - d`` fine pixels, where
    the front end's own window (placed by the coarse offset, rounded to whole reference
    pixels) leaves whatever the coarse stage's error is.

    Returns:
        One list per ``d`` of ``steps``, one pair per tile.
    """
    from planetref.camera.linescan import LineScanCamera
    from planetref.camera.mapping import image_to_ref_pixel
    from planetref.frontend.config import FrontendConfig
    from planetref.frontend.grid import FineWindow, read_fine
    from planetref.frontend.orthorectify import lattice_cache, orthorectify
    from planetref.frontend.tiles import plan_tiles, tile_footprint
    from planetref.raster.dem import GridTerrain
    from planetref.raster.image import CcdImage
    from planetref.raster.ortho import ReferenceOrtho
    from planetref.scene.manifest import load_manifest

    if not scene.exists():
        from planetref.simulate import load_config, simulate_scene

        print(f"simulating hiric-strip (moderate, seed 0) into {scene}", file=sys.stderr)
        simulate_scene(load_config("hiric-strip", seed=0, difficulty="moderate"), scene)
    man, root = load_manifest(scene)
    if man.truth is None:
        raise SystemExit(f"{scene}: not a simulated scene (no [truth])")
    strip = man.strips[0]
    init = LineScanCamera.from_json(man.resolve(root, strip.ccds[0].camera))
    true = LineScanCamera.from_json(man.resolve(root, man.truth.cameras[strip.id]))
    ref = ReferenceOrtho(man.resolve(root, man.reference.ortho))
    dem = GridTerrain.from_geotiff(man.resolve(root, man.reference.dem))
    truth_dem = GridTerrain.from_geotiff(man.resolve(root, man.truth.dem))
    ox, oy = man.truth.ortho_offset_m
    images = {c.name: man.resolve(root, c.image) for c in strip.ccds}
    cfg = FrontendConfig()
    out: list[list[TilePair]] = [[] for _ in steps]
    for tid in tile_ids:
        ccd = tid.split(":")[0]
        image = CcdImage(images[ccd])
        tile = next(t for t in plan_tiles(init, ccd, ref, dem, cfg).tiles if t.tile_id == tid)
        fp = tile_footprint(init, tile, ref, dem, cfg.footprint_points_per_edge)
        iwin = fp.window.padded(cfg.fine_pad_ref_px)
        cache = lattice_cache(image, init, ccd, ref, dem, cfg.lattice_step_ref_px)
        side = orthorectify(image, init, ccd, ref, dem, FineWindow(iwin, 2), cache=cache, stride=1)

        def truth(line: F64, sample: F64, ccd: str = ccd) -> tuple[F64, F64]:
            c, r = image_to_ref_pixel(true, ccd, line, sample, ref, truth_dem)
            return c + ox / ref.transform.a, r + oy / ref.transform.e

        # the true offset (true minus predicted reference position) over the side
        yy, xx = np.mgrid[8 : side.image.shape[0] : 16, 8 : side.image.shape[1] : 16] + 0.5
        ok = side.valid[yy.astype(int), xx.astype(int)]
        line, sample, _ = side.to_raw(xx[ok], yy[ok])
        tc, tr = truth(line, sample)
        pc, pr = side.predicted_ref_pixel(xx[ok], yy[ok])
        off = 2 * np.array([np.nanmean(tc - pc), np.nanmean(tr - pr)])  # fine px
        whole = np.round(off).astype(int)
        for i, d in enumerate(steps):
            (qx, cx), (qy, cy) = divmod(int(whole[0]) + d, 2), divmod(int(whole[1]) + d, 2)
            window = FineWindow(iwin.shifted(qx, qy), 2)
            data, valid = read_fine(ref, window)
            out[i].append(
                TilePair(tid, d, side, data[cy:, cx:], valid[cy:, cx:], window, (cx, cy), truth)
            )
        print(
            f"tile {tid}: true offset {np.round(off / 2, 3)} ref px, residual displacement "
            f"D0 {np.round(off - whole, 2)} fine px",
            file=sys.stderr,
        )
    return out


def tile_errors(matcher: Any, p: TilePair, reach: float = 3.0) -> tuple[F64, int]:
    """True error (fine px) of the reference side of each match of a tile pair."""
    m = matcher.match(p.side.image, p.ref_image, p.side.valid, p.ref_valid)
    k0 = np.asarray(m.keypoints0, np.float64).reshape(-1, 2)
    k1 = np.asarray(m.keypoints1, np.float64).reshape(-1, 2) + np.asarray(p.crop)
    line, sample, _ = p.side.to_raw(k0[:, 0], k0[:, 1])
    tc, tr = p.truth(line, sample)
    ac, ar = p.window.to_ref_pixel(k1[:, 0], k1[:, 1])
    e = 2.0 * np.column_stack([ac - tc, ar - tr])
    good = np.all(np.abs(e) < reach, axis=1)
    return e[good], int((~good).sum())


# --------------------------------------------------------------------------- matchers


def upstream_xfeat(weights_dir: Path | None) -> Any:
    """planetref's XFeat + LighterGlue with XFeat's own input handling (no padding)."""
    import torch

    from planetref.matching.options import LightGlueSettings
    from planetref.matching.xfeat import XFeatLighterGlueMatcher

    class UpstreamXFeat(XFeatLighterGlueMatcher):
        name = "xfeat-upstream"
        pad_multiple = 0  # batches only images of one shape

        def _extract_batch(self, images: Any) -> list[dict[str, torch.Tensor]]:
            out = []
            for image in images:
                x = torch.from_numpy(np.ascontiguousarray(image, np.float32))[None, None]
                f = self._model["extractor"].detectAndCompute(
                    x.to(self.device), top_k=self.settings.max_keypoints
                )[0]
                out.append({"keypoints": f["keypoints"].float(), "descriptors": f["descriptors"]})
            return out

    return UpstreamXFeat(LightGlueSettings(weights_dir=weights_dir))


def make_matcher(name: str, weights_dir: Path | None) -> Any:
    from planetref.matching.registry import get_matcher

    if name == "xfeat-upstream":
        return upstream_xfeat(weights_dir)
    return get_matcher(name, weights_dir=weights_dir)


def errors(matcher: Any, pair: Pair, reach: float = 2.0) -> tuple[F64, int]:
    """``kp1 - (kp0 + t)`` of the matches within ``reach`` px, and the count of the others."""
    m = matcher.match(pair.image0, pair.image1)
    k0 = np.asarray(m.keypoints0, np.float64).reshape(-1, 2)
    k1 = np.asarray(m.keypoints1, np.float64).reshape(-1, 2)
    e = k1 - (k0 + np.asarray(pair.t))
    good = np.all(np.abs(e) < reach, axis=1)
    return e[good], int((~good).sum())


def stats(label: str, t: tuple[float, float], e: F64, wrong: int) -> dict[str, Any]:
    """Mean and RMS per axis of one shift's errors (``t``: its true displacement)."""
    row: dict[str, Any] = {"shift": label, "t": list(t), "n": len(e), "wrong": wrong}
    if len(e):
        row.update(
            mean_x=float(e[:, 0].mean()),
            mean_y=float(e[:, 1].mean()),
            rms_x=float(np.sqrt(np.mean(e[:, 0] ** 2))),
            rms_y=float(np.sqrt(np.mean(e[:, 1] ** 2))),
        )
    return row


def odd_part(rows: list[dict[str, Any]], axis: int) -> float | None:
    """Half the difference of the mean errors at ``+t`` and ``-t`` along ``axis``, averaged.

    Negative: the matches measure less than the true displacement whatever its sign (they
    are pulled towards the two arrays' own registration). None without opposite shifts.
    """
    key = ("mean_x", "mean_y")[axis]
    by_t = {tuple(r["t"]): r[key] for r in rows if key in r}
    half = [
        (v - by_t[(-a, -b)]) / 2
        for (a, b), v in by_t.items()
        if (a, b)[axis] > 0 and (-a, -b) in by_t
    ]
    return float(np.mean(half)) if half else None


def summary(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Mean over shifts of the per-shift means, their spread, the RMS over shifts, the
    odd part (:func:`odd_part`) where opposite shifts were measured."""
    ok = [r for r in rows if "mean_x" in r]
    mx = np.array([r["mean_x"] for r in ok])
    my = np.array([r["mean_y"] for r in ok])
    odd = {f"odd_{a}": odd_part(ok, i) for i, a in enumerate("xy")}
    return {
        "mean_x": float(mx.mean()),
        "mean_y": float(my.mean()),
        "spread_x": float(mx.std()),
        "spread_y": float(my.std()),
        "max_abs_mean": float(max(np.abs(mx).max(), np.abs(my).max())),
        "rms_x": float(np.sqrt(np.mean([r["rms_x"] ** 2 for r in ok]))),
        "rms_y": float(np.sqrt(np.mean([r["rms_y"] ** 2 for r in ok]))),
        **{k: v for k, v in odd.items() if v is not None},
    }


# --------------------------------------------------------------------------- main


def textures(which: str, preset: str, size: int) -> list[tuple[str, NDArray[np.float64]]]:
    if which == "sim":
        return [(f"sim:{preset}", sim_texture(preset, size))]
    if which == "hirise":
        paths = sorted(HIRISE.glob("*.cub"))
        if not paths:
            print(f"skipped hirise: no {HIRISE}", file=sys.stderr)
            return []
        return [(f"hirise:{n}", a) for n, a in raster_textures(paths)]
    return [(Path(which).name, a) for _, a in raster_textures([Path(which)])]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--texture", default="sim", help="sim, hirise or a raster path")
    ap.add_argument("--preset", default="hiric-strip", help="simulator preset of --texture sim")
    ap.add_argument("--modes", nargs="+", default=["phases", "sweep", "frontend"])
    ap.add_argument("--matchers", nargs="+", default=list(MATCHERS))
    ap.add_argument("--block", type=int, default=4, help="K: texture px per pixel (phases)")
    ap.add_argument("--size", type=int, default=384, help="pixels of the matched images (sim)")
    ap.add_argument("--weights", type=Path, default=None, help="weights directory")
    ap.add_argument(
        "--scene",
        type=Path,
        default=None,
        help="simulated scene folder (mode tiles); simulated there when missing",
    )
    ap.add_argument(
        "--tile-ids", nargs="+", default=["ccd1:r003c000", "ccd2:r001c000", "ccd3:r002c000"]
    )
    ap.add_argument("--json", action="store_true", help="print the result as JSON")
    ap.add_argument("--json-out", type=Path, default=None, help="also write the JSON here")
    args = ap.parse_args(argv)

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from machine import describe, result_record, write_result

    from planetref.matching.registry import MATCHERS as REGISTRY
    from planetref.matching.weights import missing_weights

    machine = describe()
    k = args.block
    # texture pixels the modes need: (n + 4) K for the shifts, 10 (n / 2 + 8) for frontend
    size = max((args.size + 4) * k + 3 * k, 5 * args.size + 120)
    shift_modes = [m for m in args.modes if m != "tiles"]
    texs = textures(args.texture, args.preset, size) if shift_modes else []
    steps = [-2, -1, 0, 1, 2, 3]
    tiles = tile_pairs(args.scene, args.tile_ids, steps) if "tiles" in args.modes else []
    if "tiles" in args.modes and args.scene is None:
        raise SystemExit("mode tiles needs --scene")
    figures: list[dict[str, object]] = []
    details: list[dict[str, Any]] = []
    tname = texs[0][0] if len(texs) == 1 else args.texture
    for name in args.matchers:
        reg = "xfeat-lighterglue" if name == "xfeat-upstream" else name
        if missing_weights(REGISTRY[reg].weights):
            print(f"skipped {name}: no weights", file=sys.stderr)
            continue
        matcher = make_matcher(name, args.weights)
        for mode in args.modes:
            t0 = time.perf_counter()
            if mode == "tiles":
                label = f"tiles:{args.scene.name if args.scene else ''}"
                groups = [
                    (f"D = {-d:+d} px", (-d, -d), [(tile_errors, p) for p in ps])
                    for d, ps in zip(steps, tiles, strict=True)
                ]
            else:
                label = tname
                # the same shifts of every texture, pooled
                per_texture = [build_pairs(mode, tex, k, args.size) for _, tex in texs]
                groups = [
                    (ps[0].label, ps[0].t, [(errors, p) for p in ps])
                    for ps in zip(*per_texture, strict=True)
                ]
            rows = []
            for shift, t, jobs in groups:
                got = [fn(matcher, p) for fn, p in jobs]
                e = np.concatenate([g[0] for g in got])
                row = stats(shift, (float(t[0]), float(t[1])), e, sum(g[1] for g in got))
                rows.append(row)
                if "mean_x" in row:
                    print(
                        f"{label} {mode:8s} {name:18s} shift {row['shift']} "
                        f"n {row['n']:5d} (+{row['wrong']} wrong) mean "
                        f"({row['mean_x']:+.3f}, {row['mean_y']:+.3f}) RMS "
                        f"({row['rms_x']:.3f}, {row['rms_y']:.3f}) px",
                        flush=True,
                    )
            s = summary(rows)
            print(
                f"== {label} {mode} {name}: mean over {len(rows)} shifts "
                f"({s['mean_x']:+.3f}, {s['mean_y']:+.3f}) px, spread "
                f"({s['spread_x']:.3f}, {s['spread_y']:.3f}), max |mean| "
                f"{s['max_abs_mean']:.3f}, RMS ({s['rms_x']:.3f}, {s['rms_y']:.3f})"
                + "".join(f", {k} {s[k]:+.3f}" for k in ("odd_x", "odd_y") if k in s)
                + f" [{time.perf_counter() - t0:.0f} s]",
                flush=True,
            )
            for key, v in s.items():
                figures.append(
                    {"name": f"{label} {mode} {name}: {key}", "value": round(v, 4), "unit": "px"}
                )
            details.append(
                {
                    "texture": args.tile_ids if mode == "tiles" else [t for t, _ in texs],
                    "mode": mode,
                    "matcher": name,
                    "shifts": rows,
                }
            )
    record = result_record(
        "bench_subpixel_bias",
        figures,
        title="Sub-pixel bias of the matchers on known shifts",
        machine=machine,
    )
    record["details"] = details
    if args.json_out:
        write_result(str(args.json_out), record)
    if args.json:
        print(json.dumps(record, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
