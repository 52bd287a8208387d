"""Benchmark of the scene simulator: wall time, CPU time and peak memory per preset.

Each preset runs in its own child process, so the peak resident set size
(``getrusage(RUSAGE_SELF).ru_maxrss``) is that preset's alone. Usage::

    python benchmarks/bench_simulate.py                    # tiny and hiric-strip
    python benchmarks/bench_simulate.py --presets tiny --repeat 3
    python benchmarks/bench_simulate.py --json results.json

On a shared machine, CPU time is the steadier figure; wall time includes waiting for
the CPU.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

CHILD = r"""
import json, resource, sys, time
from planetref.simulate.config import load_config
from planetref.simulate.scene import simulate_scene

preset, out = sys.argv[1], sys.argv[2]
cfg = load_config(preset)
t0, c0 = time.perf_counter(), time.process_time()
res = simulate_scene(cfg, out, overwrite=True)
wall, cpu = time.perf_counter() - t0, time.process_time() - c0
peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
strip = next(iter(cfg.strips)).id
e = res.errors[strip]
pixels = cfg.camera.n_ccds * cfg.camera.n_samples * cfg.camera.n_lines * len(cfg.strips)
print(json.dumps({
    "preset": preset, "wall_s": wall, "cpu_s": cpu, "peak_rss_mb": peak_mb,
    "pixels": pixels, "stages_s": res.timings_s,
    "initial_error_rms_m": e["initial_errors"]["ground_m"]["horizontal"]["rms"],
    "initial_error_max_m": e["initial_errors"]["ground_m"]["horizontal"]["max"],
    "initial_error_rms_px": e["initial_errors"]["image_px"]["distance"]["rms"],
    "roundtrip_max_px": e["consistency"]["roundtrip_max_px"],
    "render_ray_max_m": e["consistency"]["render_ray_max_m"],
    "truth_dem_cells": res.errors["truth_dem"]["rows"] * res.errors["truth_dem"]["cols"],
}))
"""


def run(preset: str, out: Path) -> dict[str, object]:
    """Simulate ``preset`` into ``out`` in a child process and return its measurements."""
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, preset, str(out)], check=True, capture_output=True, text=True
    )
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    """Run the benchmark and print a table (and optionally JSON)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--presets", nargs="+", default=["tiny", "hiric-strip"])
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--json", type=Path, default=None, help="Also write the results here.")
    ap.add_argument("--keep", type=Path, default=None, help="Keep the scenes in this folder.")
    args = ap.parse_args()
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        base = args.keep or Path(tmp)
        for preset in args.presets:
            for i in range(args.repeat):
                r = run(preset, base / f"{preset}-{i}")
                results.append(r)
                print(
                    f"{preset:12s} wall {r['wall_s']:7.1f} s  cpu {r['cpu_s']:7.1f} s  "
                    f"peak RSS {r['peak_rss_mb']:7.0f} MB  "
                    f"{r['pixels'] / 1e6:6.1f} Mpx  "
                    f"initial error {r['initial_error_rms_m']:6.1f} m RMS "
                    f"({r['initial_error_rms_px']:.0f} px)  "
                    f"roundtrip {r['roundtrip_max_px']:.1e} px",
                    flush=True,
                )
                stages = ", ".join(f"{k} {v:.1f}" for k, v in r["stages_s"].items())  # type: ignore[union-attr]
                print(f"{'':12s} stages: {stages}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
