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

``--device auto`` (default) runs on the first CUDA GPU when torch sees one, else on the
CPU, where batching mostly saves Python and dispatch overhead; on a GPU it fills the
device.

Usage::

    python benchmarks/bench_gpu.py [--device auto|cpu|cuda] [--matchers ...] [--pairs 16]
        [--size 512] [--batch 1 4 8 16] [--keypoints 2048] [--threads N] [--weights-dir DIR]
        [--clock wall|cpu] [--json]
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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="auto", help="auto, cpu, cuda, cuda:1...")
    ap.add_argument("--matchers", nargs="+", default=list(MATCHERS), choices=list(MATCHERS))
    ap.add_argument("--pairs", type=int, default=16)
    ap.add_argument("--size", type=int, default=512, help="pair side, pixels")
    ap.add_argument("--batch", nargs="+", type=int, default=[1, 4, 8, 16])
    ap.add_argument("--keypoints", type=int, default=2048, help="max_keypoints per image")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    ap.add_argument("--weights-dir", type=Path, default=None)
    ap.add_argument(
        "--clock",
        default="wall",
        choices=["wall", "cpu"],
        help="cpu: CPU seconds of this process (on a shared CPU-only machine, with --threads 1)",
    )
    ap.add_argument("--json", action="store_true", help="print JSON only")
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
