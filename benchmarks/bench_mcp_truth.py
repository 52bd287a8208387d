"""True error of every MCP of a georef run on a simulated scene, beside the adjustment's verdict.

The outlier ratio (OR) counts the MCPs that the adjustment's ``3 x RMSE`` rule rejects.
Whether an OR of ~0 means "no blunders reached the adjustment" or "the adjustment missed
them" can only be told with the truth: this script projects each MCP's reference ground
point (``x_m, y_m, z_m`` in ``mcps.parquet``: the reference ortho's position on the
reference DEM) through the scene's TRUE camera and subtracts the observed ``(line,
sample)``. That difference, in image pixels, is the MCP's true error: the matcher's
error plus the reference's own geometric error (mosaic offsets and warps, DEM track
artefacts at ``hard``); through the adjusted camera instead, the same difference is the
MCP's residual in ``residuals.csv`` (checked to its six printed decimals). The true
errors are split by the adjustment's status (``inlier``, ``outlier``, ``check``) and
summarised per tile (the mean vector is the tile's systematic offset, the spread its
random part).

A blunder is an MCP whose true error exceeds ``--k`` (default 3) times the RMS of the
true errors of all MCPs of the strip: the seed's rule applied to the truth. Usage::

    python benchmarks/bench_mcp_truth.py RUN_DIR SCENE_DIR
    python benchmarks/bench_mcp_truth.py COMPARE_DIR/runs/ncc planetref-demo/scene-tiny-seed0

Prints one block per strip; ``--json`` prints the numbers as JSON instead.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
from numpy.typing import NDArray

from planetref.scene.inputs import truth_inputs
from planetref.scene.manifest import load_manifest

F64 = NDArray[np.float64]


def _stats(e: F64) -> dict[str, float]:
    e = e[np.isfinite(e)]
    if not len(e):
        return {"n": 0}
    return {
        "n": len(e),
        "rms_px": float(math.sqrt(np.mean(e**2))),
        "median_px": float(np.median(e)),
        "p90_px": float(np.percentile(e, 90)),
        "max_px": float(e.max()),
    }


def _status(residuals: Path) -> dict[str, tuple[str, float]]:
    """Adjustment status and residual length (px) of each MCP, by point id."""
    out: dict[str, tuple[str, float]] = {}
    with residuals.open(newline="") as f:
        for row in csv.DictReader(f):
            if row["point_kind"] == "mcp":
                out[row["point_id"]] = (row["status"], float(row["residual_px"] or "nan"))
    return out


def strip_truth(strip_dir: Path, camera: Any, k: float) -> dict[str, Any]:
    """True errors of the MCPs of one strip of a run, by adjustment status and by tile."""
    t = pq.read_table(strip_dir / "mcps.parquet").to_pydict()
    xyz = np.column_stack([t["x_m"], t["y_m"], t["z_m"]])
    obs = np.column_stack([t["line"], t["sample"]])
    ccd = np.asarray(t["ccd"])
    err = np.full_like(obs, np.nan)
    for c in np.unique(ccd):
        m = ccd == c
        err[m] = camera.ground_to_image(xyz[m], ccd=str(c)).as_array() - obs[m]
    e = np.hypot(err[:, 0], err[:, 1])
    verdict = _status(strip_dir / "adjustment" / "residuals.csv")
    status = np.array([verdict.get(f"mcp{i}", ("none", math.nan))[0] for i in t["mcp_id"]])
    rms = float(math.sqrt(np.nanmean(e**2)))
    blunder = e > k * rms
    tiles = np.asarray(t["tile_id"])
    per_tile = []
    for tile in np.unique(tiles):
        m = tiles == tile
        mean = np.nanmean(err[m], axis=0)
        per_tile.append(
            {
                "tile": str(tile),
                "n": int(m.sum()),
                "mean_line_px": float(mean[0]),
                "mean_sample_px": float(mean[1]),
                "spread_px": float(np.sqrt(np.nanmean(np.sum((err[m] - mean) ** 2, axis=1)))),
                "rejected": int(np.sum(status[m] == "outlier")),
            }
        )
    return {
        "all": _stats(e),
        "by_status": {str(s): _stats(e[status == s]) for s in np.unique(status)},
        "blunders": {
            "threshold_px": k * rms,
            "n": int(blunder.sum()),
            "rejected_by_adjustment": int(np.sum(blunder & (status == "outlier"))),
            "kept_as_inliers": int(np.sum(blunder & (status == "inlier"))),
        },
        "rejected_not_blunders": int(np.sum(~blunder & (status == "outlier"))),
        "tiles": per_tile,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="georef run folder (holds STRIP/mcps.parquet)")
    ap.add_argument("scene", type=Path, help="simulated scene folder or its scene.toml")
    ap.add_argument("--k", type=float, default=3.0, help="blunder factor on the true RMS")
    ap.add_argument("--json", action="store_true", help="print JSON")
    args = ap.parse_args(argv)
    manifest, root = load_manifest(args.scene)
    cams, _ = truth_inputs(manifest, root)
    if not cams:
        print(f"{args.scene}: not a simulated scene (no [truth])", file=sys.stderr)
        return 2
    out = {
        sid: strip_truth(args.run / sid, cam, args.k)
        for sid, cam in cams.items()
        if (args.run / sid / "mcps.parquet").exists()
    }
    if args.json:
        print(json.dumps(out, indent=1))
        return 0
    for sid, r in out.items():
        a, b = r["all"], r["blunders"]
        print(
            f"{sid}: {a['n']} MCPs, true error (image px) RMS {a['rms_px']:.2f} median "
            f"{a['median_px']:.2f} p90 {a['p90_px']:.2f} max {a['max_px']:.2f}"
        )
        for s, st in r["by_status"].items():
            print(
                f"  {s:8s} n={st['n']:6d} median {st['median_px']:.2f} p90 {st['p90_px']:.2f} "
                f"max {st['max_px']:.2f}"
            )
        print(
            f"  blunders (true error > {args.k:g} x true RMS = {b['threshold_px']:.2f} px): "
            f"{b['n']}, rejected by the adjustment {b['rejected_by_adjustment']}, kept as "
            f"inliers {b['kept_as_inliers']}; rejected but not blunders "
            f"{r['rejected_not_blunders']}"
        )
        for tl in r["tiles"]:
            print(
                f"  tile {tl['tile']:16s} n={tl['n']:6d} mean (line, sample) "
                f"({tl['mean_line_px']:7.2f}, {tl['mean_sample_px']:7.2f}) spread "
                f"{tl['spread_px']:.2f} rejected {tl['rejected']}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
