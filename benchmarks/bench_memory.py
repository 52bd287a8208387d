"""Peak memory of georef against strip length: MB per 1000 lines.

Usage::

    planetref simulate S2000 --preset hiric-strip --config lines2000.toml  # n_lines = 2000
    planetref simulate S4000 --preset hiric-strip --config lines4000.toml
    planetref simulate S8000 --preset hiric-strip
    python benchmarks/bench_memory.py S2000 S4000 S8000 --out /tmp/mem [--matcher sift]

Each scene is georeferenced in its own process (``bench_outputs.py``, so that each peak
is that run's own) and the peak resident memory of the georef process (``ru_maxrss``) is
fitted linearly against the strip's lines (its first CCD's): the slope is what grows with
the strip. The figure process is not counted: its ``ru_maxrss`` starts from the parent's
size at ``fork`` (before its ``exec``), and it draws the same three figures whatever the
length. Printed as JSON.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np


def _lines(scene: str) -> int:
    from planetref.scene.inputs import scene_path, strip_cameras
    from planetref.scene.manifest import load_manifest

    manifest, root = load_manifest(scene_path(scene))
    camera, images = strip_cameras(manifest, root, manifest.strips[0])
    return int(camera.image_size(next(iter(images)))[0])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--out", required=True, help="Folder for the runs (one sub-folder each).")
    ap.add_argument("--matcher", default="sift")
    args = ap.parse_args()
    bench = Path(__file__).with_name("bench_outputs.py")
    rows = []
    for scene in args.scenes:
        out = Path(args.out) / Path(scene).resolve().name
        done = subprocess.run(
            [sys.executable, str(bench), scene, str(out), "--matcher", args.matcher],
            check=True,
            capture_output=True,
            text=True,
        )
        doc = json.loads(done.stdout)
        rows.append({"scene": scene, "lines": _lines(scene), "peak_rss_mb": doc["peak_rss_mb"]})
    x = np.array([r["lines"] for r in rows], float)
    y = np.array([r["peak_rss_mb"] for r in rows], float)
    slope = float(np.polyfit(x, y, 1)[0]) * 1000.0 if len(rows) > 1 else float("nan")
    print(json.dumps({"runs": rows, "mb_per_1000_lines": round(slope, 1)}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
