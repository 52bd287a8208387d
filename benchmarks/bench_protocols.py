"""OR beside the seed's 4.1-7.3 %: the default and the ``paper`` front-end protocol, with truth.

The adjustment's outlier ratio (OR) counts the MCPs its ``3 x RMSE`` rule rejects. With
planetref's default front end (RANSAC at 1 reference px, a translation consensus) almost
no blunder reaches the adjustment, so OR is ~0 whatever the matcher; the seed (Sec. 3.2)
downsampled the tiles to the reference GSD and left the rejecting to the adjustment.
This script simulates a scene (or takes one), runs ``compare`` once per protocol with
the same matchers, and prints per matcher and protocol: NCP, OR, the true outlier ratio
of the matches after RANSAC (share whose true error exceeds 1 and 3 reference px,
:mod:`planetref.frontend.truth`), and the true geolocation error after the adjustment,
beside the seed's OR range.

Usage::

    python benchmarks/bench_protocols.py OUT [--preset tiny] [--seed 0]
        [--difficulty moderate] [--matchers sift,ncc] [--scene DIR]
        [--protocols default,paper] [--json]

Each protocol's comparison stays in ``OUT/<protocol>`` (report.html); a rerun resumes.
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
import time
from pathlib import Path
from typing import Any

PAPER_OR_PCT = (4.1, 7.3)
"""The seed's OR range over its matchers (Table 2)."""


def run(args: argparse.Namespace) -> dict[str, Any]:
    from planetref.pipeline.compare import run_compare
    from planetref.pipeline.config import config_from_mapping
    from planetref.simulate.config import load_config
    from planetref.simulate.scene import simulate_scene

    out = Path(args.out)
    scene = Path(args.scene) if args.scene else out / f"scene-{args.preset}-seed{args.seed}"
    if not (scene / "scene.toml").is_file():
        level = None if args.difficulty == "moderate" else args.difficulty
        simulate_scene(load_config(args.preset, seed=args.seed, difficulty=level), scene)
    rows = []
    cpu = {}
    for protocol in args.protocols.split(","):
        cfg = config_from_mapping({"frontend": {"protocol": protocol}})
        t0 = time.process_time()
        outcome = run_compare(scene, args.matchers, out / protocol, config=cfg, progress=False)
        cpu[protocol] = time.process_time() - t0
        for name, rep in outcome.report["runs"].items():
            adj = rep.get("adjustment") or {}
            tor = rep["matching"].get("true_outliers") or {}
            rows.append(
                {
                    "protocol": protocol,
                    "matcher": name,
                    "failed": rep.get("failed"),
                    "ncp": rep["matching"]["ncp"],
                    "or_pct": adj.get("outlier_ratio_pct"),
                    "rmse_px": adj.get("rmse_px"),
                    "true_or_1px_pct": tor.get("pct_over_1px"),
                    "true_or_3px_pct": tor.get("pct_over_3px"),
                    "ransac_matches": tor.get("n"),
                    "true_error_m": (rep.get("check") or {}).get("geoloc_rmse_m"),
                }
            )
    return {"scene": str(scene), "rows": rows, "cpu_s": cpu, "paper_or_pct": PAPER_OR_PCT}


def _f(v: Any, d: int = 2) -> str:
    return "-" if v is None else f"{v:.{d}f}" if isinstance(v, float) else str(v)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", help="output folder (scene and one comparison per protocol)")
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--difficulty", default="moderate")
    ap.add_argument("--matchers", default="sift,ncc")
    ap.add_argument("--scene", default=None, help="an existing scene instead of simulating")
    ap.add_argument("--protocols", default="default,paper", help="protocols to run")
    ap.add_argument("--json", action="store_true", help="print JSON (machine, date, command)")
    args = ap.parse_args(argv)
    res = run(args)
    if args.json:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from machine import describe

        res |= {
            "machine": describe(),
            "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "command": " ".join(sys.argv),
        }
        print(json.dumps(res, indent=1))
        return 0
    lo, hi = PAPER_OR_PCT
    print(f"scene {res['scene']}; the seed's OR: {lo}-{hi} %")
    print(
        f"{'protocol':8s} {'matcher':18s} {'NCP':>7s} {'OR %':>6s} {'RMSE px':>8s} "
        f"{'RANSAC n':>8s} {'tOR>1 %':>8s} {'tOR>3 %':>8s} {'true m':>7s}"
    )
    for r in res["rows"]:
        print(
            f"{r['protocol']:8s} {r['matcher']:18s} {r['ncp']:7d} {_f(r['or_pct']):>6s} "
            f"{_f(r['rmse_px']):>8s} {_f(r['ransac_matches']):>8s} "
            f"{_f(r['true_or_1px_pct']):>8s} {_f(r['true_or_3px_pct']):>8s} "
            f"{_f(r['true_error_m']):>7s}" + (f"  FAILED: {r['failed']}" if r["failed"] else "")
        )
    print("CPU s per protocol: " + ", ".join(f"{k} {v:.0f}" for k, v in res["cpu_s"].items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
