"""Time every matcher on synthetic tile pairs and split pipeline overhead from model time.

For each matcher whose weights are present (and, with ``--random-weights``, LoFTR and
DoG+HardNet+LightGlue with random weights saved in their official formats: their timings
do not depend on the weight values), and for each tile size, the script runs the full
pipeline of ``planetref match`` on one tile pair -- robust normalisation, matching,
conversion, masking, MAGSAC++ verification -- once to warm up (this builds the model), then
``--repeat`` times, and reports the median seconds per tile pair, the median time spent in
the model calls themselves (``Matcher.timings["forward"]``: detector, descriptor and
matcher networks, or the OpenCV detection/correlation for SIFT and NCC), and the share of
the pipeline spent outside them.

Usage::

    python benchmarks/bench_matchers.py [--sizes 512 1024] [--repeat 3] [--threads 1]
        [--weights-dir DIR] [--matchers sift ncc ...] [--random-weights] [--json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import ndimage


def texture_pair(size: int, shift=(5.0, -3.0), seed: int = 0):
    """Multi-scale noise + blobs, and a copy shifted by ``shift`` with a radiometric change."""
    from planetref.matching._synthetic import texture

    pad = 32
    img = texture(size, seed, pad)
    moved = np.real(np.fft.ifft2(ndimage.fourier_shift(np.fft.fft2(img), (shift[1], shift[0]))))
    a = img[pad:-pad, pad:-pad]
    b = 0.8 * moved[pad:-pad, pad:-pad] + 0.3
    return a.astype(np.float32), b.astype(np.float32)


def random_weights_dir(root: Path) -> Path:
    """Write random LoFTR / HardNet / LightGlue("doghardnet") checkpoints (official formats)."""
    import kornia.feature as KF
    import torch

    ckpt = root / "hub" / "checkpoints"
    ckpt.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(0)
    torch.save(
        {"state_dict": {f"matcher.{k}": v for k, v in KF.LoFTR(None).state_dict().items()}},
        ckpt / "loftr_outdoor.ckpt",
    )
    torch.save(
        {"state_dict": KF.HardNet(False).state_dict()}, ckpt / "checkpoint_liberty_with_aug.pth"
    )
    conf = {k: v for k, v in KF.LightGlue.features["doghardnet"].items() if k != "weights"}
    torch.save(KF.LightGlue(None, **conf).state_dict(), ckpt / "doghardnet_v0-1_arxiv-pth")
    return root


def bench(name: str, factory, sizes, repeat: int) -> list[dict]:
    from planetref.matching.ransac import verify_matches
    from planetref.matching.tiling import match_tiled

    matcher = factory()
    rows = []
    for size in sizes:
        a, b = texture_pair(size)
        totals, forwards, ransacs, ncps = [], [], [], []
        for i in range(repeat + 1):
            start = time.perf_counter()
            found = match_tiled(matcher, a, b, tile_size=max(size, 1024))
            t_ransac = time.perf_counter()
            ver = verify_matches(found, "homography", threshold=3.0)
            end = time.perf_counter()
            if i == 0:
                continue  # warm-up: builds the model, fills caches
            totals.append(end - start)
            forwards.append(matcher.timings.get("forward", 0.0))
            ransacs.append(end - t_ransac)
            ncps.append(ver.n_inliers)
        total = statistics.median(totals)
        forward = statistics.median(forwards)
        rows.append(
            {
                "matcher": name,
                "size": size,
                "seconds": round(total, 4),
                "forward_seconds": round(forward, 4),
                "ransac_seconds": round(statistics.median(ransacs), 4),
                "overhead_share": round(max(0.0, total - forward) / total, 4) if total > 0 else 0.0,
                "ncp": int(statistics.median(ncps)),
            }
        )
    return rows


def ncc_batch_speedup(size: int, spacing: int, repeat: int) -> dict:
    """NCC correlation: the per-template loop (``ncc._correlate``, the former implementation,
    kept for ``refine_matches_ncc``) against the batched :func:`ncc.correlate_batch`, on the
    same normalised synthetic pair and the same template centres; also checks they agree."""
    from planetref.matching import ncc
    from planetref.matching.base import prepare_image, robust_normalise

    a, b = texture_pair(size)
    m = ncc.NccMatcher(spacing=spacing)
    n0, _ = robust_normalise(*prepare_image(a))
    n1, _ = robust_normalise(*prepare_image(b))
    valid = np.ones(n0.shape, bool)
    t, radius = m.template_radius, m.search_radius
    _, bad1 = ncc._box_stats(n1, valid, t)
    rows, cols = m._grid(n0.shape)

    def loop():
        return [
            ncc._correlate(n0, n1, bad1, r, c, r, c, t, radius, m.min_ncc, 0.9, "quadratic")
            for r, c in zip(rows.tolist(), cols.tolist(), strict=True)
        ]

    def batch():
        return ncc.correlate_batch(n0, n1, bad1, rows, cols, rows, cols, m)

    times = {}
    for name, fn in (("loop", loop), ("batch", batch)):
        fn()
        runs = []
        for _ in range(repeat):
            start = time.perf_counter()
            out = fn()
            runs.append(time.perf_counter() - start)
        times[name] = statistics.median(runs)
        if name == "loop":
            ref = out
        else:
            x1, y1, _, ok = out
    agree = sum(
        1
        for k, hit in enumerate(ref)
        if hit is not None and ok[k] and abs(hit[0] - x1[k]) < 5e-3 and abs(hit[1] - y1[k]) < 5e-3
    )
    return {
        "templates": len(rows),
        "loop_s": times["loop"],
        "batch_s": times["batch"],
        "speedup": times["loop"] / times["batch"],
        "agree": agree,
        "loop_matches": sum(h is not None for h in ref),
        "batch_matches": int(ok.sum()),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--ncc-batch",
        action="store_true",
        help="only time the NCC per-template loop against the batched correlation",
    )
    parser.add_argument("--sizes", type=int, nargs="+", default=[512, 1024])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--weights-dir", default=None)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--matchers", nargs="+", default=None)
    parser.add_argument(
        "--random-weights",
        action="store_true",
        help="also time LoFTR and DoG+HardNet+LightGlue with random weights",
    )
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    args = parser.parse_args(argv)
    if args.ncc_batch:
        for size in args.sizes:
            for spacing in (16, 8):
                r = ncc_batch_speedup(size, spacing, args.repeat)
                print(
                    f"ncc {size}px spacing {spacing}: {r['templates']} templates, loop "
                    f"{r['loop_s']:.3f} s, batch {r['batch_s']:.3f} s, speed-up "
                    f"{r['speedup']:.2f}x; matches {r['loop_matches']} / {r['batch_matches']}, "
                    f"{r['agree']} agree within 0.005 px"
                )
        return 0

    import torch

    torch.set_num_threads(args.threads)
    from planetref.matching import MATCHERS, available_matchers, get_matcher

    tmp = tempfile.TemporaryDirectory()
    random_dir = random_weights_dir(Path(tmp.name)) if args.random_weights else None
    wanted = args.matchers or list(MATCHERS)
    rows: list[dict] = []
    for avail in available_matchers(args.weights_dir):
        if avail.name not in wanted:
            continue
        learned = bool(MATCHERS[avail.name].weights)
        if avail.present:
            kwargs = {"weights_dir": args.weights_dir, "device": args.device} if learned else {}
            note = ""
        elif random_dir is not None and avail.name in ("loftr", "doghardnet-lightglue"):
            kwargs = {"weights_dir": random_dir, "device": args.device, "verify_weights": False}
            note = " (random weights)"
        else:
            print(f"skip {avail.name}: missing {', '.join(avail.missing)}", file=sys.stderr)
            continue
        for row in bench(
            avail.name,
            lambda n=avail.name, kw=kwargs: get_matcher(n, **kw),
            args.sizes,
            args.repeat,
        ):
            row["note"] = note.strip(" ()")
            rows.append(row)
            if not args.json:
                print(f"  {row['matcher']} {row['size']}: {row['seconds']:.3f} s", file=sys.stderr)
    tmp.cleanup()
    if args.json:
        print(
            json.dumps({"threads": args.threads, "device": args.device, "results": rows}, indent=2)
        )
        return 0
    header = (
        f"{'matcher':20s} {'tile':>5s} {'s/pair':>8s} {'model s':>8s} {'ransac s':>8s} "
        f"{'overhead':>8s} {'NCP':>6s}"
    )
    print(header)
    print("-" * len(header))
    for r in rows:
        print(
            f"{r['matcher']:20s} {r['size']:5d} {r['seconds']:8.3f} {r['forward_seconds']:8.3f} "
            f"{r['ransac_seconds']:8.4f} {100 * r['overhead_share']:7.1f}% {r['ncp']:6d}"
            + (f"  {r['note']}" if r["note"] else "")
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
