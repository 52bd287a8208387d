"""Tile-parallel scaling of the matching stage: in process vs dask-local with 1, 2... workers.

For each executor the script runs ``georef`` (matcher ``sift`` by default) on a simulated
scene into a fresh run directory and reports:

* ``match s``: wall seconds of the matching stage (``report.json`` ``timing_s.matching``,
  tiles planned, sent, matched and journalled, MCPs built), the cluster already started;
* ``tiles``: tiles of the scene; ``tiles/h``: tiles per hour of the whole executor;
* ``s/tile``: measured per-tile cost (mean of the journal's ``timings.total``, seconds of
  one worker on one tile) and ``tiles/h/worker`` = 3600 / ``s/tile``;
* ``speed-up`` against the in-process run;
* ``peak MiB/worker``: the largest peak resident memory of a worker process
  (``ru_maxrss``; for the in-process run, of this process).

It also checks that every executor produced the very same MCPs as the in-process run.

Usage::

    python benchmarks/bench_scaling.py [--workers 1 2] [--preset tiny|hiric-strip]
        [--matcher sift] [--scene DIR] [--json]
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path


def _maxrss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _journal_costs(path: Path) -> list[float]:
    out = []
    for line in path.read_text().splitlines():
        if line.strip():
            t = json.loads(line)["result"]["timings"].get("total")
            if t is not None:
                out.append(float(t))
    return out


def run_one(scene: Path, out: Path, matcher: str, executor) -> dict:
    from planetref.pipeline.georef import run_georef

    t0 = time.perf_counter()
    res = run_georef(scene, matcher, out, progress=False, executor=executor)
    wall = time.perf_counter() - t0
    costs = []
    for j in sorted(out.glob("*/tiles.jsonl")):
        costs += _journal_costs(j)
    match_s = float(res.report["timing_s"]["matching"])
    per_tile = statistics.fmean(costs) if costs else float("nan")
    return {
        "match_s": match_s,
        "total_s": wall,
        "tiles": len(costs),
        "tiles_per_h": 3600.0 * len(costs) / match_s if match_s > 0 else float("nan"),
        "s_per_tile": per_tile,
        "tiles_per_h_per_worker": 3600.0 / per_tile,
        "ncp": res.report["matching"]["ncp"],
        "mcps": out / "strip1" / "mcps.parquet",
    }


def _same_mcps(a: Path, b: Path) -> bool:
    import pyarrow.parquet as pq

    ta, tb = pq.read_table(a), pq.read_table(b)
    return ta.column_names == tb.column_names and all(
        ta.column(c).to_pylist() == tb.column(c).to_pylist() for c in ta.column_names
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--preset", default="tiny", help="simulator preset (tiny, hiric-strip)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--matcher", default="sift")
    ap.add_argument("--scene", type=Path, default=None, help="an existing scene folder")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)

    from planetref.runtime.execute import DaskExecutor

    with tempfile.TemporaryDirectory(prefix="bench_scaling_") as tmp:
        tmp_path = Path(tmp)
        scene = args.scene
        if scene is None:
            from planetref.simulate.config import load_config
            from planetref.simulate.scene import simulate_scene

            scene = tmp_path / "scene"
            simulate_scene(load_config(args.preset, seed=args.seed), scene, progress=False)
        rows = []
        base = run_one(scene, tmp_path / "inprocess", args.matcher, None)
        rows.append(
            {"executor": "inprocess", "workers": 1, **base, "peak_mib_per_worker": _maxrss_mib()}
        )
        for n in args.workers:
            ex = DaskExecutor(f"dask-local:{n}")
            try:
                ex.client.wait_for_workers(n)  # cluster start-up is not measured
                r = run_one(scene, tmp_path / f"dask{n}", args.matcher, ex)
                rss = ex.client.run(_maxrss_mib)
            finally:
                ex.close()
            rows.append(
                {
                    "executor": f"dask-local:{n}",
                    "workers": n,
                    **r,
                    "peak_mib_per_worker": max(rss.values()),
                }
            )
        for r in rows:
            r["speedup"] = base["match_s"] / r["match_s"]
            r["same_mcps"] = _same_mcps(base["mcps"], r.pop("mcps"))
    if args.json:
        print(
            json.dumps({"scene": args.scene or args.preset, "matcher": args.matcher, "rows": rows})
        )
        return 0
    head = (
        f"{'executor':<14}{'tiles':>6}{'match s':>9}{'tiles/h':>9}{'s/tile':>8}"
        f"{'tiles/h/worker':>15}{'speed-up':>9}{'peak MiB/worker':>16}{'same MCPs':>10}"
    )
    print(f"scene {args.scene or args.preset}, matcher {args.matcher}")
    print(head)
    for r in rows:
        print(
            f"{r['executor']:<14}{r['tiles']:>6}{r['match_s']:>9.2f}{r['tiles_per_h']:>9.0f}"
            f"{r['s_per_tile']:>8.3f}{r['tiles_per_h_per_worker']:>15.0f}"
            f"{r['speedup']:>9.2f}{r['peak_mib_per_worker']:>16.0f}"
            f"{r['same_mcps']!s:>10}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
