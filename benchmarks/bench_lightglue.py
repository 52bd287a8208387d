"""LightGlue speed at equal accuracy: adaptive depth/width pruning and keypoint budgets.

For DISK+LightGlue and ALIKED+LightGlue (equal terms: the same settings grid for both),
each real HiRISE pair of ``../shared/data/hirise_pairs`` is matched whole with every
combination of

* LightGlue's adaptive pruning: ``published`` (LightGlue's own defaults, early stopping
  ``depth_confidence = 0.95`` and point pruning ``width_confidence = 0.99``; on the CPU
  kornia prunes at any keypoint count) or ``off`` (``-1 / -1``: all 9 layers, all points);
* the keypoint budget per image: 2048 or 4096,

then verified (MAGSAC++ homography, 3 px) and measured exactly as
``benchmarks/bench_precision.py`` does: distance of every verified match to a robust
affine displacement field (median, share within 2 px), raw and after LSM refinement, NCP
(tentative/verified/kept) and the seconds of the match call (wall, and CPU seconds of
the process, which other jobs on the machine do not inflate: single-threaded torch). The
variants of one pair run back to back, in a rotating order, so that other jobs on the
machine weigh on all of them alike; the model is built before the clock starts.

Usage::

    python benchmarks/bench_lightglue.py [--matchers disk-lightglue aliked-lightglue]
        [--budgets 2048 4096] [--pruning published off] [--repeat 1] [--threads 1] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_precision import HIRISE, PAIRS, stats

PRUNING = {"published": (0.95, 0.99), "off": (-1.0, -1.0)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--matchers", nargs="+", default=["disk-lightglue", "aliked-lightglue"])
    ap.add_argument("--pairs", nargs="+", default=list(PAIRS), choices=list(PAIRS))
    ap.add_argument("--budgets", nargs="+", type=int, default=[2048, 4096])
    ap.add_argument("--pruning", nargs="+", default=list(PRUNING), choices=list(PRUNING))
    ap.add_argument("--repeat", type=int, default=1, help="timed calls per variant (median)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--weights-dir", default=None)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if not HIRISE.is_dir():
        print(f"skipped: {HIRISE} not found", file=sys.stderr)
        return 0
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    import torch

    torch.set_num_threads(args.threads)
    from planetref.cli.match import read_band
    from planetref.matching import get_matcher
    from planetref.matching.ransac import verify_matches
    from planetref.matching.refine import RefineConfig, refine_matches

    rows = []
    variants = [(b, p) for b in args.budgets for p in args.pruning]
    for pair in args.pairs:
        img0, valid0 = read_band(HIRISE / PAIRS[pair][0])
        img1, valid1 = read_band(HIRISE / PAIRS[pair][1])
        for name in args.matchers:
            built = {}
            for budget, prune in variants:
                depth, width = PRUNING[prune]
                m = get_matcher(
                    name,
                    weights_dir=args.weights_dir,
                    max_keypoints=budget,
                    depth_confidence=depth,
                    width_confidence=width,
                )
                m.build()
                built[(budget, prune)] = m
            times: dict[tuple[int, str], list[float]] = {v: [] for v in variants}
            cpu: dict[tuple[int, str], list[float]] = {v: [] for v in variants}
            found = {}
            for rep in range(args.repeat):
                order = variants[rep % len(variants) :] + variants[: rep % len(variants)]
                for v in order:
                    t0, c0 = time.perf_counter(), time.process_time()
                    with torch.inference_mode():
                        found[v] = built[v].match(img0, img1, valid0, valid1)
                    times[v].append(time.perf_counter() - t0)
                    cpu[v].append(time.process_time() - c0)
            for budget, prune in variants:
                f = found[(budget, prune)]
                verified = f.select(verify_matches(f, "homography", threshold=3.0).inliers)
                row = {
                    "pair": pair,
                    "matcher": name,
                    "budget": budget,
                    "pruning": prune,
                    "tentative": len(f),
                    "verified": len(verified),
                    "match_s": float(np.median(times[(budget, prune)])),
                    "match_cpu_s": float(np.median(cpu[(budget, prune)])),
                }
                raw = stats(verified.keypoints0, verified.keypoints1)
                row.update({f"raw_{k}": v for k, v in raw.items()})
                res = refine_matches(
                    img0,
                    img1,
                    verified.keypoints0,
                    verified.keypoints1,
                    RefineConfig(method="lsm"),
                    valid0,
                    valid1,
                )
                lsm = stats(verified.keypoints0[res.ok], res.points1[res.ok])
                row["lsm_ncp"] = int(res.ok.sum())
                row.update({f"lsm_{k}": v for k, v in lsm.items()})
                rows.append(row)
                print(json.dumps(row), file=sys.stderr, flush=True)
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    print(
        "| pair | matcher | keypoints | pruning | NCP (tentative/verified/LSM-kept) "
        "| raw median px | raw <=2 px | LSM median px | LSM <=2 px | match CPU s |"
    )
    print("|---|---|---:|---|---|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['pair']} | {r['matcher']} | {r['budget']} | {r['pruning']} | "
            f"{r['tentative']}/{r['verified']}/{r['lsm_ncp']} | {r['raw_median']:.2f} | "
            f"{100 * r['raw_within2']:.0f} % | {r['lsm_median']:.2f} | "
            f"{100 * r['lsm_within2']:.0f} % | {r['match_cpu_s']:.1f} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
