"""Batched vs one-pair-at-a-time matching of the learned sparse matchers, on any device.

For each matcher whose weights are present (DISK, ALIKED and XFeat with LightGlue /
LighterGlue), ``--pairs`` image pairs of one shape (a synthetic multi-scale texture and a
copy shifted by a known sub-pixel amount, with a radiometric change: the matcher tests'
pairs) are matched

* one pair at a time (``Matcher.match``: the front end's way today), and
* with ``Matcher.match_many(pairs, batch_size=B)`` for each ``--batch`` size: the
  detector/descriptor runs on ``B`` same-shaped images in one forward pass; LightGlue still
  matches pair by pair (kornia's LightGlue handles the pairs of a batch one at a time when
  its adaptive pruning is on, planetref's default).

It prints seconds per pair (wall, with the device synchronised), the ratio one-at-a-time /
batched (> 1: batching pays), the extractor+LightGlue share (``forward``), the matches per
pair, and the largest keypoint difference between the batched and the unbatched matches
(float tolerance: the same matches). The model is built and one pair matched before the
clock starts.

``--mode frontend`` times georef's matching instead: every tile of a simulated strip
(bench_frontend's scene: the ``tiny`` preset enlarged to 2 CCDs of 1536^2 px; ``--scene
DIR`` takes any scene folder) through ``planetref.frontend.match_strip`` with the run's
matcher settings, tile by tile (``[frontend] batch_tiles = 1``) and with ``batch_tiles``
= each ``--batch`` size (the tiles' stages advance together, and DISK/ALIKED/XFeat detect
on the images of up to that many tiles in one forward pass). It prints seconds per tile,
the ratio tile-by-tile / batched, the MCPs, and how far the batched MCPs are from the
tile-by-tile ones as sets (image and reference pixels, confidence), with whether every
tile's status and inlier count are the same. A warm-up tile builds the model first.

``--device auto`` (default) runs on the first CUDA GPU when torch sees one, else on the
CPU, where batching mostly saves Python and dispatch overhead; on a GPU it fills the
device.

Usage::

    python benchmarks/bench_gpu.py [--device auto|cpu|cuda] [--matchers ...] [--pairs 16]
        [--size 512] [--batch 1 4 8 16] [--keypoints 2048] [--threads N] [--weights-dir DIR]
        [--clock wall|cpu] [--json]
    python benchmarks/bench_gpu.py --mode frontend [--batch 4 8] [--tile 128]
        [--fine-upsample 2] [--ccds N] [--scene DIR] [--device ...] [--matchers ...]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

DEFAULT_WEIGHTS = Path(__file__).resolve().parents[1].parent / "shared" / "weights"
MATCHERS = ("disk-lightglue", "aliked-lightglue", "xfeat-lighterglue")


def make_pairs(n: int, size: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` pairs of ``size x size`` textures, the second shifted and radiometrically changed."""
    from scipy import ndimage

    from planetref.matching._synthetic import texture

    pairs = []
    pad = 32
    for i in range(n):
        rng = np.random.default_rng(100 + i)
        dx, dy = rng.uniform(-4, 4, 2)
        base = texture(size, seed=i, pad=pad)
        moved = np.real(np.fft.ifft2(ndimage.fourier_shift(np.fft.fft2(base), (dy, dx))))
        a = base[pad : pad + size, pad : pad + size]
        b = moved[pad : pad + size, pad : pad + size]
        b = 50.0 * (0.8 * b - b.min() + 1.0) ** 0.9
        pairs.append((a.astype(np.float32), b.astype(np.float32)))
    return pairs


def _sync(device) -> None:
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _timed(fn, device) -> tuple[float, object]:
    _sync(device)
    t0 = time.perf_counter()
    out = fn()
    _sync(device)
    return time.perf_counter() - t0, out  # perf_counter: process_time under --clock cpu


def _sorted(m) -> np.ndarray:
    """``(N, 5)`` rows ``x0, y0, x1, y1, confidence`` in lexicographic order of the points."""
    a = m.to_array()
    return a[np.lexsort(np.round(a[:, 3::-1], 3).T)]


def max_difference(a: list, b: list) -> float:
    """Largest keypoint difference (px) between two lists of matches; inf if counts differ.

    Compared as sets (sorted): keypoints whose scores differ by float rounding may come
    in another order.
    """
    worst = 0.0
    for x, y in zip(a, b, strict=True):
        if len(x) != len(y):
            return float("inf")
        if len(x):
            worst = max(worst, float(np.abs(_sorted(x)[:, :4] - _sorted(y)[:, :4]).max()))
    return worst


def bench(name: str, args, weights: Path, pairs: list) -> dict:
    from planetref.matching import get_matcher

    m = get_matcher(name, weights_dir=weights, device=args.device, max_keypoints=args.keypoints)
    m.build()
    m.match(*pairs[0])  # warm-up: kernels, allocator
    dev = m.device
    fwd = []

    def each() -> list:
        out = []
        for p in pairs:
            out.append(m.match(*p))
            fwd.append(m.timings.get("forward", 0.0))
        return out

    t_one, one = _timed(each, dev)
    fwd_one = sum(fwd) / len(pairs)
    rows = []
    for b in args.batch:
        t_b, many = _timed(lambda b=b: m.match_many(pairs, batch_size=b), dev)
        rows.append(
            {
                "batch": b,
                "s_per_pair": t_b / len(pairs),
                "speedup": t_one / t_b if t_b > 0 else float("nan"),
                "forward_s_per_pair": m.timings.get("forward", 0.0) / len(pairs),
                "max_keypoint_diff_px": max_difference(one, many),
            }
        )
    return {
        "matcher": name,
        "device": str(dev),
        "pairs": len(pairs),
        "size": args.size,
        "one_at_a_time_s_per_pair": t_one / len(pairs),
        "one_forward_s_per_pair": fwd_one,
        "matches_per_pair": float(np.mean([len(x) for x in one])),
        "batched": rows,
    }


def _mcps(strip) -> np.ndarray:
    """``line, sample, ref_col, ref_row, confidence`` of every MCP, sorted as a set."""
    rows = [
        np.column_stack([r.line, r.sample, r.ref_col, r.ref_row, r.confidence])
        for r in strip.tiles
        if r.status == "ok"
    ]
    a = np.concatenate(rows) if rows else np.empty((0, 5))
    return a[np.lexsort(np.round(a[:, 3::-1], 3).T)]


def bench_frontend(name: str, args, weights: Path | None, s: dict) -> dict:
    """Match every tile of the scene's strip tile by tile, then batched (``--batch``)."""
    from planetref.frontend.config import FrontendConfig
    from planetref.frontend.matchers import matcher_options
    from planetref.frontend.strip import match_strip
    from planetref.frontend.tile import match_tile
    from planetref.frontend.tiles import plan_tiles
    from planetref.matching import get_matcher
    from planetref.raster.image import CcdImage

    cfg = FrontendConfig(
        tile_size_ref_px=args.tile,
        coarse_factor=2,
        uncertainty_m=150.0,
        fine_upsample=args.fine_upsample,
    )
    gsd = float(np.mean(s["ref"].ground_sampling_m()))
    fine_opts, coarse_opts = matcher_options(name, {}, cfg, gsd)
    extra: dict = {"device": args.device}
    if args.keypoints is not None:  # else the run's own budget
        extra["max_keypoints"] = args.keypoints
    matcher = get_matcher(name, weights_dir=weights, **fine_opts, **extra)
    coarse = None
    if coarse_opts is not None:
        coarse = get_matcher(name, weights_dir=weights, **coarse_opts, **extra)
    ccds = list(s["images"])[: args.ccds or None]
    plan = plan_tiles(s["init"], ccds[0], s["ref"], s["dem"], cfg)
    with CcdImage(s["images"][ccds[0]]) as warm:  # builds the model, compiles the kernels
        match_tile(
            plan.tiles[0],
            image=warm,
            camera=s["init"],
            ref=s["ref"],
            terrain=s["dem"],
            matcher=matcher,
            config=cfg,
            ratio=plan.ratio,
            coarse_matcher=coarse,
        )
    dev = getattr(matcher, "device", None)

    def run(batch: int):
        return _timed(
            lambda: match_strip(
                s["init"],
                {c: s["images"][c] for c in ccds},
                s["ref"],
                s["dem"],
                matcher,
                cfg.model_copy(update={"batch_tiles": batch}),
                progress=False,
                raise_errors=True,
                coarse_matcher=coarse,
            ),
            dev,
        )

    t_one, one = run(1)
    base = _mcps(one)
    n = len(one.tiles)
    rows = []
    for b in args.batch:
        if b <= 1:
            continue
        t_b, many = run(b)
        got = _mcps(many)
        same_tiles = [(r.status, r.n_inliers) for r in one.tiles] == [
            (r.status, r.n_inliers) for r in many.tiles
        ]
        if len(got) == len(base):
            d_px = float(np.abs(got[:, :4] - base[:, :4]).max()) if len(got) else 0.0
            d_conf = float(np.abs(got[:, 4] - base[:, 4]).max()) if len(got) else 0.0
        else:
            d_px = d_conf = float("inf")
        rows.append(
            {
                "batch_tiles": b,
                "s_per_tile": t_b / n,
                "speedup": t_one / t_b if t_b > 0 else float("nan"),
                "mcps": len(got),
                "max_mcp_diff_px": d_px,
                "max_confidence_diff": d_conf,
                "same_status_and_inliers": same_tiles,
            }
        )
    return {
        "matcher": name,
        "device": str(dev or "cpu"),
        "tiles": n,
        "fine_upsample": args.fine_upsample,
        "tile_by_tile_s_per_tile": t_one / n,
        "mcps": len(base),
        "batched": rows,
    }


def main_frontend(args, weights: Path | None) -> int:
    """``--mode frontend``: georef's matching of a strip, tile by tile against batched."""
    import tempfile

    import torch

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_frontend import load, simulate

    from planetref.matching.registry import MATCHERS as REGISTRY
    from planetref.matching.weights import missing_weights

    results, skipped = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        root = args.scene or simulate(Path(tmp) / "scene")
        s = load(root)
        try:
            for name in args.matchers:
                missing = missing_weights(REGISTRY[name].weights, weights)
                if missing:
                    skipped[name] = f"weights missing: {missing}"
                    continue
                results.append(bench_frontend(name, args, weights, s))
        finally:
            s["ref"].close()
    gpu = torch.cuda.get_device_name(0) if args.device.startswith("cuda") else "none"
    if args.json:
        doc = {"mode": "frontend", "device": args.device, "gpu": gpu, "results": results}
        print(json.dumps({**doc, "skipped": skipped}))
        return 0
    print(
        f"frontend: device {args.device} (GPU: {gpu}); tile {args.tile} ref px; fine_upsample "
        f"{args.fine_upsample}; keypoints {args.keypoints or 'default'}; torch threads "
        f"{torch.get_num_threads()}; clock {args.clock}"
    )
    print(
        f"{'matcher':<19}{'batch':>6}{'tiles':>6}{'s/tile':>9}{'speedup':>9}{'MCPs':>7}"
        f"{'max diff px':>13}{'conf diff':>11}{'same tiles':>11}"
    )
    for r in results:
        print(
            f"{r['matcher']:<19}{1:>6}{r['tiles']:>6}{r['tile_by_tile_s_per_tile']:>9.3f}"
            f"{1.0:>9.2f}{r['mcps']:>7}"
        )
        for b in r["batched"]:
            print(
                f"{'':<19}{b['batch_tiles']:>6}{'':>6}{b['s_per_tile']:>9.3f}{b['speedup']:>9.2f}"
                f"{b['mcps']:>7}{b['max_mcp_diff_px']:>13.1e}{b['max_confidence_diff']:>11.1e}"
                f"{b['same_status_and_inliers']!s:>11}"
            )
    for name, why in skipped.items():
        print(f"{name:<19} skipped: {why}")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="auto", help="auto, cpu, cuda, cuda:1...")
    ap.add_argument("--matchers", nargs="+", default=list(MATCHERS), choices=list(MATCHERS))
    ap.add_argument("--pairs", type=int, default=16)
    ap.add_argument("--size", type=int, default=512, help="pair side, pixels")
    ap.add_argument("--batch", nargs="+", type=int, default=[1, 4, 8, 16])
    ap.add_argument(
        "--keypoints",
        type=int,
        default=None,
        help="max_keypoints per image (default: 2048 for pairs, the matcher's own in frontend)",
    )
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    ap.add_argument("--weights-dir", type=Path, default=None)
    ap.add_argument(
        "--clock",
        default="wall",
        choices=["wall", "cpu"],
        help="cpu: CPU seconds of this process (on a shared CPU-only machine, with --threads 1)",
    )
    ap.add_argument("--json", action="store_true", help="print JSON only")
    ap.add_argument(
        "--mode",
        default="pairs",
        choices=["pairs", "frontend"],
        help="pairs: synthetic pairs through match_many; frontend: a strip's tiles through "
        "match_strip with [frontend] batch_tiles",
    )
    ap.add_argument("--scene", type=Path, default=None, help="frontend: a scene folder")
    ap.add_argument("--tile", type=int, default=128, help="frontend: tile size, reference px")
    ap.add_argument("--fine-upsample", type=int, default=2, help="frontend: fine-stage grid")
    ap.add_argument("--ccds", type=int, default=0, help="frontend: the first N CCDs (0: all)")
    args = ap.parse_args(argv)
    if args.clock == "cpu":
        # Every timer here and in the matchers reads time.perf_counter.
        time.perf_counter = time.process_time

    import torch

    from planetref.errors import PlanetrefError
    from planetref.matching._torch import resolve_device
    from planetref.matching.registry import MATCHERS as REGISTRY
    from planetref.matching.weights import missing_weights

    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        args.device = str(resolve_device(args.device))
    except PlanetrefError as exc:
        print(f"bench_gpu: {exc}", file=sys.stderr)
        return 2
    weights = args.weights_dir or (DEFAULT_WEIGHTS if DEFAULT_WEIGHTS.is_dir() else None)
    if args.mode == "frontend":
        with torch.inference_mode():
            return main_frontend(args, weights)
    if args.keypoints is None:
        args.keypoints = 2048
    pairs = make_pairs(args.pairs, args.size)
    results, skipped = [], {}
    with torch.inference_mode():
        for name in args.matchers:
            missing = missing_weights(REGISTRY[name].weights, weights)
            if missing:
                skipped[name] = f"weights missing: {missing}"
                continue
            results.append(bench(name, args, weights, pairs))
    gpu = torch.cuda.get_device_name(0) if args.device.startswith("cuda") else "none"
    if args.json:
        print(
            json.dumps({"device": args.device, "gpu": gpu, "results": results, "skipped": skipped})
        )
        return 0
    print(
        f"device {args.device} (GPU: {gpu}); {args.pairs} pairs of {args.size}^2 px; "
        f"{args.keypoints} keypoints; torch threads {torch.get_num_threads()}; clock {args.clock}"
    )
    print(
        f"{'matcher':<19}{'batch':>9}{'s/pair':>9}{'forward':>9}{'speedup':>9}"
        f"{'matches':>9}{'max diff px':>13}"
    )
    for r in results:
        print(
            f"{r['matcher']:<19}{'1 (match)':>9}{r['one_at_a_time_s_per_pair']:>9.3f}"
            f"{r['one_forward_s_per_pair']:>9.3f}{1.0:>9.2f}{r['matches_per_pair']:>9.0f}"
            f"{0.0:>13.1e}"
        )
        for b in r["batched"]:
            print(
                f"{'':<19}{b['batch']:>9}{b['s_per_pair']:>9.3f}{b['forward_s_per_pair']:>9.3f}"
                f"{b['speedup']:>9.2f}{'':>9}{b['max_keypoint_diff_px']:>13.1e}"
            )
    for name, why in skipped.items():
        print(f"{name:<19} skipped: {why}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
