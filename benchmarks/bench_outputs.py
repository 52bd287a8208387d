"""Where georef's time goes: wall and CPU seconds per stage, and the outputs' share.

Usage::

    python benchmarks/bench_outputs.py SCENE_DIR OUT_DIR [--matcher sift] [--threads 2]
        [--config FILE] [--profile FILE]

Runs ``georef`` once and prints, as JSON, the wall-clock and CPU seconds of each stage:
matching (tiles and MCPs), adjustment, and the outputs (adjusted cameras/RPC refits/
reports, CSM ISDs, ASP/ISIS exports, orthoimages with mosaic and overviews, residual
figure, matching figures), with the outputs' share of the run's wall time and of its CPU
time.

- Outputs' wall time: the pipeline's own ``timing_s["outputs"]`` (the outputs' parts
  run partly at the same time, so per-stage wall times overlap and do not add up; it
  includes waiting for the figure process at the end).
- Per-stage CPU: ``time.process_time`` (every thread of this process) while the stage
  runs, and ``time.thread_time`` of the thread that runs it (``cpu_thread_s_per_stage``;
  exact for a single-threaded stage even when others run beside it).
- Outputs' CPU: this process's CPU while a strip's outputs are written (the adjustment's
  CPU taken out), plus the matching figures, plus CPU spent in child processes
  (``RUSAGE_CHILDREN``, the figure process).

CPU seconds of a single-threaded stage are what an idle machine would show as wall time;
on a loaded machine wall shares mostly measure the other jobs. ``--config`` reads a
georef configuration (e.g. ``[frontend] fine_upsample = 1``). ``--profile`` also runs
cProfile (which inflates Python-heavy stages such as matplotlib several times).

The run's peak memory is printed too: ``peak_rss_mb`` of this process and of its largest
child (``ru_maxrss``).
"""

from __future__ import annotations

import argparse
import functools
import importlib
import json
import resource
import time
from typing import Any

#: Stage -> functions (``module:attribute``) whose time it is; each is wrapped where the
#: pipeline looks it up (module globals of georef, or the module of a local import).
STAGES = {
    "matching": ("planetref.pipeline.georef:_match", "planetref.control.mcp:mcps_from_tiles"),
    "adjustment": ("planetref.adjust.api:adjust",),
    "adjustment_files": ("planetref.report.adjustment:write_outputs",),
    "isd": ("planetref.pipeline.georef:camera_isds",),
    "exports": ("planetref.pipeline.georef:control_exports",),
    "orthoimages": ("planetref.pipeline.georef:orthoimages",),
    "figure_residuals": ("planetref.pipeline.georef:figure_residuals",),
    "figures_matching": ("planetref.pipeline.georef:figures_matching",),
}
NOT_OUTPUTS = ("matching", "adjustment")
#: A strip's adjustment and outputs (its CPU less the adjustment's is the outputs' CPU).
BLOCK = "planetref.pipeline.georef:_adjust_strip"


def _wrap(stage: str, fn: Any, acc: dict[str, list[float]]) -> Any:
    @functools.wraps(fn)
    def timed(*args: Any, **kwargs: Any) -> Any:
        w0, c0, t0 = time.perf_counter(), time.process_time(), time.thread_time()
        try:
            return fn(*args, **kwargs)
        finally:
            acc[stage][0] += time.perf_counter() - w0
            acc[stage][1] += time.process_time() - c0
            acc[stage][2] += time.thread_time() - t0

    return timed


def _children_cpu() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("out")
    ap.add_argument("--matcher", default="sift")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--config", default=None, help="georef config TOML.")
    ap.add_argument("--profile", default=None, help="Also write cProfile stats here.")
    args = ap.parse_args()

    from planetref.runtime.threads import ThreadBudget, apply_thread_budget

    apply_thread_budget(ThreadBudget.resolve(args.threads))
    from machine import describe

    from planetref.pipeline import georef
    from planetref.pipeline.config import load_config

    cfg = load_config(args.config)
    machine = describe()  # the load before the run

    acc = {stage: [0.0, 0.0, 0.0] for stage in [*STAGES, "block"]}
    for stage, targets in [*STAGES.items(), ("block", (BLOCK,))]:
        for target in targets:
            mod_name, attr = target.split(":")
            mod = importlib.import_module(mod_name)
            setattr(mod, attr, _wrap(stage, getattr(mod, attr), acc))

    prof = None
    if args.profile:
        import cProfile

        prof = cProfile.Profile(time.process_time)
    k0 = _children_cpu()
    w0, c0 = time.perf_counter(), time.process_time()
    if prof is not None:
        prof.enable()
    out = georef.run_georef(
        args.scene, args.matcher, args.out, config=cfg, progress=False, overwrite=True
    )
    if prof is not None:
        prof.disable()
        prof.dump_stats(args.profile)
    wall, cpu_main = time.perf_counter() - w0, time.process_time() - c0
    cpu_children = _children_cpu() - k0
    cpu = cpu_main + cpu_children
    stages = {k: v for k, v in acc.items() if k != "block"}
    wall_out = float(out.report["timing_s"].get("outputs", 0.0))
    cpu_out = acc["block"][1] - acc["adjustment"][1] + acc["figures_matching"][1] + cpu_children
    self_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    child_rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    print(
        json.dumps(
            {
                "machine": machine,
                "fine_upsample": cfg.frontend.fine_upsample,
                "wall_s": round(wall, 2),
                "cpu_s": round(cpu, 2),
                "cpu_children_s": round(cpu_children, 2),
                "timing_s": {k: round(v, 2) for k, v in out.report["timing_s"].items()},
                "wall_s_per_stage": {k: round(v[0], 2) for k, v in stages.items()},
                "cpu_s_per_stage": {k: round(v[1], 2) for k, v in stages.items()},
                "cpu_thread_s_per_stage": {k: round(v[2], 2) for k, v in stages.items()},
                "wall_outputs_s": round(wall_out, 2),
                "cpu_outputs_s": round(cpu_out, 2),
                "wall_outputs_share_pct": round(100.0 * wall_out / wall, 1),
                "cpu_outputs_share_pct": round(100.0 * cpu_out / cpu, 1),
                "peak_rss_mb": round(self_rss, 1),
                "peak_rss_children_mb": round(child_rss, 1),
                "check": out.report.get("check"),
            },
            indent=1,
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
