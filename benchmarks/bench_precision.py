"""Real-data localisation precision of every matcher, raw and sub-pixel refined.

Data: the two real HiRISE pairs of ``../shared/data/hirise_pairs`` (two dates of the same
ground, map-projected onto one ~0.25 m grid, so the true displacement field between the
dates is smooth: a mis-registration of a few pixels that varies slowly across the scene).

For each matcher whose weights are present, each pair is matched whole (one tile) with the
matcher's default settings, then verified exactly as ``planetref match`` does (MAGSAC++
homography, 3 px). The verified set is then refined with :func:`planetref.matching.refine.
refine_matches` (same settings for every matcher). For the raw and each refined set the
script fits a robust affine displacement field ``d(x0, y0)`` to that set (iteratively
reweighted least squares, Tukey biweight at 4.685 x 1.4826 x MAD, floor 0.25 px) and prints
the distance of every match to it: median, 90th percentile, share within 1 and 2 px,
together with NCP (tentative -> verified -> kept by refinement) and seconds.

What this measures and what it does not: the smooth field stands in for the unknown truth,
so the distances include true non-affine motion (small for these pairs) and favour sets
whose errors are smooth; the 3 px verification removes gross outliers before the statistics
(the same filter for every matcher); the dates differ in illumination, which moves
shadow-edge features (a real effect any matcher faces).

Usage::

    python benchmarks/bench_precision.py [--matchers sift ncc ...] [--refine none lsm ncc]
        [--threads 1] [--weights-dir DIR] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
HIRISE = ROOT.parent / "shared" / "data" / "hirise_pairs"
PAIRS = {
    "no_change": ("no_change_before.cub", "no_change_after.cub"),
    "esp": (
        "ESP_014038_1415_RED0.30421_33069.boulder_shift.before.cub",
        "ESP_031022_1415_after.cub",
    ),
}


def robust_affine_distances(points0: np.ndarray, disp: np.ndarray) -> np.ndarray:
    """Distance of each displacement to a robustly fitted affine field ``d(x0, y0)``."""
    a = np.column_stack([np.ones(len(points0)), points0 - points0.mean(axis=0)])
    w = np.ones(len(points0))
    resid = np.zeros(len(points0))
    for _ in range(10):
        sw = np.sqrt(w)[:, None]
        coef = np.linalg.lstsq(a * sw, disp * sw, rcond=None)[0]
        resid = np.linalg.norm(disp - a @ coef, axis=1)
        scale = max(0.25, 1.4826 * float(np.median(np.abs(resid))))
        u = resid / (4.685 * scale)
        w = np.where(u < 1, (1 - u * u) ** 2, 0.0)
    return resid


def stats(points0: np.ndarray, points1: np.ndarray) -> dict[str, float]:
    if len(points0) < 6:
        return {"median": float("nan"), "p90": float("nan"), "within1": 0.0, "within2": 0.0}
    d = robust_affine_distances(points0, points1 - points0)
    return {
        "median": float(np.median(d)),
        "p90": float(np.percentile(d, 90)),
        "within1": float(np.mean(d <= 1.0)),
        "within2": float(np.mean(d <= 2.0)),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--matchers", nargs="*", default=None)
    parser.add_argument("--pairs", nargs="*", default=list(PAIRS), choices=list(PAIRS))
    parser.add_argument("--refine", nargs="*", default=["none", "lsm"])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--weights-dir", default=None)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    if not HIRISE.is_dir():
        print(f"skipped: {HIRISE} not found", file=sys.stderr)
        return 0
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    import torch

    torch.set_num_threads(args.threads)
    from planetref.cli.match import read_band
    from planetref.matching import available_matchers, get_matcher
    from planetref.matching.ransac import verify_matches
    from planetref.matching.refine import RefineConfig, refine_matches

    ready = [a.name for a in available_matchers(args.weights_dir) if a.present]
    names = [n for n in (args.matchers or ready) if n in ready]
    rows = []
    for pair in args.pairs:
        img0, valid0 = read_band(HIRISE / PAIRS[pair][0])
        img1, valid1 = read_band(HIRISE / PAIRS[pair][1])
        for name in names:
            matcher = get_matcher(name, weights_dir=args.weights_dir)
            if hasattr(matcher, "build"):
                matcher.build()  # weights load is not matching time
            start = time.perf_counter()
            found = matcher.match(img0, img1, valid0, valid1)
            verified = found.select(verify_matches(found, "homography", threshold=3.0).inliers)
            seconds = time.perf_counter() - start
            for method in args.refine:
                t0 = time.perf_counter()
                res = refine_matches(
                    img0,
                    img1,
                    verified.keypoints0,
                    verified.keypoints1,
                    RefineConfig(method=method),
                    valid0,
                    valid1,
                )
                t_ref = time.perf_counter() - t0
                p0, p1 = verified.keypoints0[res.ok], res.points1[res.ok]
                frac = np.abs(p1 - np.round(p1 - 0.5) - 0.5)
                row = {
                    "pair": pair,
                    "matcher": name,
                    "refine": method,
                    "tentative": len(found),
                    "verified": len(verified),
                    "ncp": int(res.ok.sum()),
                    **stats(p0, p1),
                    "whole_pixel_share": float(np.mean(np.all(frac < 1e-6, axis=1)))
                    if len(p1)
                    else 0.0,
                    "sigma_px_median": float(np.nanmedian(res.sigma_px))
                    if np.isfinite(res.sigma_px).any()
                    else float("nan"),
                    "match_s": round(seconds, 2),
                    "refine_s": round(t_ref, 2),
                    "refine_counts": res.counts(),
                }
                rows.append(row)
                print(json.dumps(row), file=sys.stderr, flush=True)
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    print(
        "| pair | matcher | refine | NCP (tentative/verified/kept) | median px | p90 px "
        "| <=1 px | <=2 px | whole-px | sigma_px | match s | refine s |"
    )
    print("|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['pair']} | {r['matcher']} | {r['refine']} | {r['tentative']}/{r['verified']}/"
            f"{r['ncp']} | {r['median']:.2f} | {r['p90']:.2f} | {100 * r['within1']:.0f} % | "
            f"{100 * r['within2']:.0f} % | {100 * r['whole_pixel_share']:.0f} % | "
            f"{r['sigma_px_median']:.3f} | {r['match_s']:.1f} | {r['refine_s']:.2f} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
