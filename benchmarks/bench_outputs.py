"""Where georef's time goes, in CPU seconds per stage (robust to a shared machine).

Usage::

    python benchmarks/bench_outputs.py SCENE_DIR OUT_DIR [--matcher sift] [--threads 2]

Runs ``georef`` once under cProfile with a process-time clock and prints, as JSON, the
wall-clock stage timings of report.json and the CPU seconds of each stage: matching,
adjustment, and the outputs (adjusted cameras/RPC refits/reports, CSM ISDs, ASP/ISIS
exports, orthoimages with mosaic and overviews, residual figure, matching figures), with
the outputs' share of the total. CPU seconds of a single-threaded stage are what an idle
machine would show as wall time; on a loaded machine wall shares mostly measure the
other jobs. The orthoimages' threads make their wall time smaller than their CPU time.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import time

#: Stage -> profiled functions (``module path:function``) whose cumulative CPU it is.
STAGES = {
    "matching": ("pipeline/georef.py:_match", "control.py:mcps_from_tiles"),
    "adjustment": ("adjust/api.py:adjust",),
    "adjustment_files": ("adjust/report.py:write_outputs",),
    "isd": ("georef_outputs.py:camera_isds",),
    "exports": ("georef_outputs.py:control_exports",),
    "orthoimages": ("georef_outputs.py:orthoimages",),
    "figure_residuals": ("georef_outputs.py:figure_residuals",),
    "figures_matching": ("georef_outputs.py:figures_matching",),
}
NOT_OUTPUTS = ("matching", "adjustment")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("out")
    ap.add_argument("--matcher", default="sift")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--profile", default=None, help="Also write the cProfile stats here.")
    args = ap.parse_args()

    from planetref.threads import ThreadBudget, apply_thread_budget

    apply_thread_budget(ThreadBudget.resolve(args.threads))
    from planetref.pipeline.georef import run_georef

    prof = cProfile.Profile(time.process_time)
    w0, c0 = time.perf_counter(), time.process_time()
    prof.enable()
    out = run_georef(args.scene, args.matcher, args.out, progress=False, overwrite=True)
    prof.disable()
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    if args.profile:
        prof.dump_stats(args.profile)
    cum: dict[str, float] = {}
    for (path, _line, name), (_cc, _nc, _tt, ct, _callers) in pstats.Stats(prof).stats.items():
        key = f"{path.split('/planetref/')[-1]}:{name}"
        cum[key] = max(cum.get(key, 0.0), ct)
    parts = {
        stage: sum(v for k, v in cum.items() for f in funcs if k.endswith(f))
        for stage, funcs in STAGES.items()
    }
    outputs = sum(v for k, v in parts.items() if k not in NOT_OUTPUTS)
    print(
        json.dumps(
            {
                "wall_s": wall,
                "cpu_s": cpu,
                "timing_s": out.report["timing_s"],
                "cpu_s_per_stage": parts,
                "cpu_outputs_s": outputs,
                "cpu_outputs_share_pct": 100.0 * outputs / cpu,
                "cpu_outputs_share_without_matching_figures_pct": 100.0
                * (outputs - parts["figures_matching"])
                / cpu,
                "check": out.report.get("check"),
            },
            indent=1,
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
