"""Benchmark of the scene simulator: wall time, CPU time and peak memory per preset.

Each preset runs in its own child process, so the peak resident set size
(``getrusage(RUSAGE_SELF).ru_maxrss``) is that preset's alone. With render worker
processes (``render.processes``, 2 in ``hiric``), the memory of the whole process tree
is sampled every 0.2 s as the sum of the proportional set sizes (``Pss`` of
``/proc/PID/smaps_rollup``: pages shared copy-on-write between the parent and its
workers are counted once), and its peak is printed as ``tree PSS``. Usage::

    python benchmarks/bench_simulate.py                    # tiny and hiric-strip
    python benchmarks/bench_simulate.py --presets tiny --repeat 3
    python benchmarks/bench_simulate.py --presets hiric --lines 2000 4000
    python benchmarks/bench_simulate.py --json results.json

``--lines`` runs the presets at those line counts (the slope per 1000 lines of wall
time and memory is printed), for measuring long strips on a loaded machine.

On a shared machine, CPU time is the steadier figure; wall time includes waiting for
the CPU. ``cpu`` is the main process's, ``workers`` the render workers' (children).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

CHILD = r"""
import json, os, resource, sys, threading, time
from planetref.simulate.config import load_config
from planetref.simulate.scene import simulate_scene

preset, out, lines, difficulty = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
over = {"camera": {"n_lines": lines}} if lines > 0 else None
cfg = load_config(preset, over, difficulty=None if difficulty == "-" else difficulty)
peak = [0.0]
stop = threading.Event()

def tree_pss_mb():
    pids = [os.getpid()]
    try:
        with open(f"/proc/{os.getpid()}/task/{os.getpid()}/children") as fh:
            pids += [int(p) for p in fh.read().split()]
    except OSError:
        pass
    total = 0.0
    for pid in pids:
        try:
            with open(f"/proc/{pid}/smaps_rollup") as fh:
                for row in fh:
                    if row.startswith("Pss:"):
                        total += float(row.split()[1]) / 1024.0
        except OSError:
            pass
    return total

def watch():
    while not stop.is_set():
        peak[0] = max(peak[0], tree_pss_mb())
        stop.wait(0.2)

th = threading.Thread(target=watch, daemon=True)
th.start()
t0, c0 = time.perf_counter(), time.process_time()
res = simulate_scene(cfg, out, overwrite=True)
wall, cpu = time.perf_counter() - t0, time.process_time() - c0
stop.set()
th.join()
peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
kids = resource.getrusage(resource.RUSAGE_CHILDREN)
child_mb = kids.ru_maxrss / 1024.0
cpu_workers = kids.ru_utime + kids.ru_stime
strip = next(iter(cfg.strips)).id
e = res.errors[strip]
pixels = cfg.camera.n_ccds * cfg.camera.n_samples * cfg.camera.n_lines * len(cfg.strips)
print(json.dumps({
    "preset": preset, "wall_s": wall, "cpu_s": cpu, "peak_rss_mb": peak_mb,
    "worker_peak_rss_mb": child_mb, "tree_peak_pss_mb": peak[0], "cpu_workers_s": cpu_workers,
    "n_lines": cfg.camera.n_lines, "processes": cfg.render.processes,
    "n_ccds": cfg.camera.n_ccds, "n_strips": len(cfg.strips),
    "lines_per_s": cfg.camera.n_lines * cfg.camera.n_ccds * len(cfg.strips) / wall,
    "render_lines_per_s": (
        cfg.camera.n_lines * cfg.camera.n_ccds * len(cfg.strips) / res.timings_s["render"]
    ),
    "pixels": pixels, "stages_s": res.timings_s,
    "initial_error_rms_m": e["initial_errors"]["ground_m"]["horizontal"]["rms"],
    "initial_error_max_m": e["initial_errors"]["ground_m"]["horizontal"]["max"],
    "initial_error_rms_px": e["initial_errors"]["image_px"]["distance"]["rms"],
    "roundtrip_max_px": e["consistency"]["roundtrip_max_px"],
    "render_ray_max_m": e["consistency"]["render_ray_max_m"],
    "truth_dem_cells": res.errors["truth_dem"]["rows"] * res.errors["truth_dem"]["cols"],
}))
"""


def run(preset: str, out: Path, lines: int = 0, difficulty: str = "-") -> dict[str, object]:
    """Simulate ``preset`` into ``out`` in a child process and return its measurements.

    Args:
        preset: Preset name.
        out: Scene folder.
        lines: Lines per strip (0: the preset's).
        difficulty: Difficulty level (``-``: the preset as is).
    """
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, preset, str(out), str(lines), difficulty],
        check=True,
        capture_output=True,
        text=True,
    )
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    """Run the benchmark and print a table (and optionally JSON)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--presets", nargs="+", default=["tiny", "hiric-strip"])
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--lines", type=int, nargs="+", default=[0], help="Line counts (0: preset's).")
    ap.add_argument("--difficulty", default="-", help="Difficulty level (default: preset's).")
    ap.add_argument("--json", type=Path, default=None, help="Also write the results here.")
    ap.add_argument("--keep", type=Path, default=None, help="Keep the scenes in this folder.")
    args = ap.parse_args()
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        base = args.keep or Path(tmp)
        for preset in args.presets:
            mine = []
            for lines in args.lines:
                for i in range(args.repeat):
                    r = run(preset, base / f"{preset}-{lines}-{i}", lines, args.difficulty)
                    results.append(r)
                    mine.append(r)
                    _print(preset, r)
            if len({r["n_lines"] for r in mine}) > 1:
                n = [float(r["n_lines"]) for r in mine]  # type: ignore[arg-type]
                for key in ("wall_s", "cpu_s", "cpu_workers_s", "tree_peak_pss_mb"):
                    y = [float(r[key]) for r in mine]  # type: ignore[arg-type]
                    slope = _slope(n, y) * 1000.0
                    print(f"{preset:12s} {key}: {slope:.1f} per 1000 lines", flush=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1) + "\n")


def _slope(x: list[float], y: list[float]) -> float:
    """Least-squares slope of ``y`` against ``x``."""
    mx, my = sum(x) / len(x), sum(y) / len(y)
    sxx = sum((a - mx) ** 2 for a in x)
    return sum((a - mx) * (b - my) for a, b in zip(x, y, strict=True)) / sxx


def _print(preset: str, r: dict[str, object]) -> None:
    print(
        f"{preset:12s} {r['n_lines']} lines, {r['processes']} process(es): "
        f"wall {r['wall_s']:7.1f} s  cpu {r['cpu_s']:7.1f} s "
        f"({r['lines_per_s']:.1f} CCD lines/s overall, {r['render_lines_per_s']:.1f} rendering) "
        f"(+ workers {r['cpu_workers_s']:.1f} s)  "
        f"peak RSS {r['peak_rss_mb']:7.0f} MB (workers {r['worker_peak_rss_mb']:.0f}), "
        f"tree PSS {r['tree_peak_pss_mb']:7.0f} MB  "
        f"{r['pixels'] / 1e6:6.1f} Mpx  "
        f"initial error {r['initial_error_rms_m']:6.1f} m RMS "
        f"({r['initial_error_rms_px']:.0f} px)  "
        f"roundtrip {r['roundtrip_max_px']:.1e} px",
        flush=True,
    )
    stages = ", ".join(f"{k} {v:.1f}" for k, v in r["stages_s"].items())  # type: ignore[union-attr]
    print(f"{'':12s} stages: {stages}", flush=True)


if __name__ == "__main__":
    main()
