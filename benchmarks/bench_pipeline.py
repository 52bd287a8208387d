"""End-to-end georef per matcher on a simulated scene: time per stage, per km^2, memory.

Usage::

    python benchmarks/bench_pipeline.py [--preset hiric-strip] [--matchers all] [--json]
        [--scene-dir DIR] [--weights-dir DIR]

The scene is simulated once (cached in ``--scene-dir``). Each matcher's georef runs in
its own Python process so that its peak resident memory is its own. Printed per matcher:
seconds of matching, adjustment, outputs and total; seconds per km^2 of imaged ground;
the share of each stage in the total (matching, adjustment, outputs); peak RSS; and the
true geolocation error before/after, so a speed-up can never hide a loss of accuracy.

Then, in the same run, the orthoimage of every CCD of the first strip (truth camera) is
computed by the previous implementation (``--old-rev``, read with ``git show``) and by the
current one: seconds of each, the speed-up, and their largest pixel difference.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import types
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
OLD_REV = "3663937"  # main before the lattice/streaming rewrite of pipeline/orthoimage.py

CHILD = r"""
import json, resource, sys
from planetref.runtime.threads import ThreadBudget, apply_thread_budget
apply_thread_budget(ThreadBudget.resolve(int(sys.argv[5])))
from planetref.pipeline.georef import run_georef
out = run_georef(sys.argv[1], sys.argv[2], sys.argv[3], weights_dir=sys.argv[4] or None,
                 progress=False, overwrite=True)
r = out.report
print(json.dumps({"timing_s": r["timing_s"], "ncp": r["matching"]["ncp"],
                  "rmse_px": r["adjustment"]["rmse_px"], "check": r["check"],
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def scene_area_km2(scene: Path) -> float:
    """Imaged ground area (km^2): every CCD's pixels times its GSD squared."""
    from planetref.camera.io import load_camera
    from planetref.camera.mapping import image_gsd_m
    from planetref.raster.dem import GridTerrain
    from planetref.scene.manifest import load_manifest

    manifest, root = load_manifest(scene)
    dem = GridTerrain.from_geotiff(manifest.resolve(root, manifest.reference.dem))
    area = 0.0
    for strip in manifest.strips:
        cam = load_camera(manifest.resolve(root, strip.ccds[0].camera))
        for c in strip.ccds:
            ccd = c.camera_ccd or c.name
            n_lines, n_samples = cam.image_size(ccd)
            area += n_lines * n_samples * image_gsd_m(cam, ccd, dem) ** 2
    return area / 1e6


def _old_orthorectify(rev: str) -> Any:
    """``orthorectify_ccd`` of the previous implementation, loaded from git."""
    src = subprocess.run(
        ["git", "show", f"{rev}:src/planetref/products/orthoimage.py"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    # Modules moved since: the old code's maths is unchanged, only its imports follow.
    for old, new in (("planetref.camera.geodesy", "planetref.geometry.geodesy"),):
        src = src.replace(old, new)
    mod = types.ModuleType("old_orthoimage")
    exec(compile(src, f"{rev}:orthoimage.py", "exec"), mod.__dict__)
    return mod.orthorectify_ccd


def ortho_old_vs_new(scene: Path, rev: str, out: Path) -> dict[str, Any]:
    """Orthoimages of the first strip (truth camera): old vs new seconds and max difference."""
    import numpy as np
    import rasterio

    from planetref.camera.io import load_camera
    from planetref.camera.mapping import image_gsd_m
    from planetref.products.ortho_strip import orthorectify_ccd
    from planetref.raster.dem import GridTerrain
    from planetref.raster.image import CcdImage
    from planetref.raster.ortho import ReferenceOrtho
    from planetref.scene.manifest import load_manifest

    old_fn = _old_orthorectify(rev)
    manifest, root = load_manifest(scene)
    dem = GridTerrain.from_geotiff(manifest.resolve(root, manifest.reference.dem))
    crs = ReferenceOrtho(manifest.resolve(root, manifest.reference.ortho)).crs
    strip = manifest.strips[0]
    t_old = t_new = 0.0
    max_diff = 0.0
    dn_range = 0.0
    lines = 0
    for c in strip.ccds:
        cam = load_camera(manifest.resolve(root, c.camera))
        ccd = c.camera_ccd or c.name
        image = CcdImage(manifest.resolve(root, c.image))
        gsd = image_gsd_m(cam, ccd, dem)
        lines += cam.image_size(ccd)[0]
        t0 = time.perf_counter()
        p_old = old_fn(image, cam, ccd, dem, crs, out / f"old-{ccd}.tif", gsd_m=gsd)
        t_old += time.perf_counter() - t0
        t0 = time.perf_counter()
        p_new = orthorectify_ccd(
            image, cam, ccd, dem, crs, out / f"new-{ccd}.tif", gsd_m=gsd, resume=False
        )
        t_new += time.perf_counter() - t0
        with rasterio.open(p_old) as a, rasterio.open(p_new) as b:
            va, vb = (ds.read(1, masked=True).astype(float).filled(np.nan) for ds in (a, b))
            same_grid = a.transform == b.transform and a.shape == b.shape
        lo, hi = np.nanpercentile(va, [1, 99])
        dn_range = max(dn_range, float(hi - lo))
        if not same_grid:  # the new grid is aligned to multiples of the pixel size
            max_diff = float("nan")
            continue
        both = np.isfinite(va) & np.isfinite(vb)
        max_diff = max(max_diff, float(np.abs(va - vb)[both].max()))
    return {
        "ccds": len(strip.ccds),
        "lines": lines,
        "old_s": t_old,
        "new_s": t_new,
        "speedup": t_old / t_new,
        "max_diff_dn": max_diff,
        "dn_range_1_99": dn_range,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="hiric-strip")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--matchers", default="all")
    ap.add_argument("--scene-dir", default=None)
    ap.add_argument("--weights-dir", default=os.environ.get("PLANETREF_WEIGHTS", ""))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--scene", default=None, help="Use this simulated scene (scene.toml folder).")
    ap.add_argument("--old-rev", default=OLD_REV, help="Git revision of the old orthoimage code.")
    ap.add_argument("--no-ortho", action="store_true", help="Skip the old vs new orthoimages.")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    from planetref.pipeline.compare import resolve_matchers
    from planetref.simulate.config import load_config
    from planetref.simulate.scene import simulate_scene

    base = Path(args.scene_dir or Path(tempfile.gettempdir()) / "planetref-bench")
    scene = Path(args.scene) if args.scene else base / f"scene-{args.preset}-seed{args.seed}"
    if not (scene / "scene.toml").is_file():
        print(f"simulating {args.preset} into {scene} ...", file=sys.stderr)
        simulate_scene(load_config(args.preset, seed=args.seed), scene)
    area = scene_area_km2(scene)
    names, skipped = resolve_matchers(args.matchers, args.weights_dir or None)
    rows = {}
    for name in names:
        run_dir = base / f"run-{args.preset}-{name}"
        proc = subprocess.run(
            [
                sys.executable,
                "-c",
                CHILD,
                str(scene),
                name,
                str(run_dir),
                args.weights_dir,
                str(args.threads),
            ],
            capture_output=True,
            text=True,
            check=False,
        )
        if proc.returncode != 0:
            skipped[name] = proc.stderr.strip().splitlines()[-1] if proc.stderr else "failed"
            continue
        doc = json.loads(proc.stdout.strip().splitlines()[-1])
        t = doc["timing_s"]
        rows[name] = {
            **{f"{k}_s": v for k, v in t.items()},
            "s_per_km2": t["total"] / area,
            "matching_share_pct": 100.0 * t["matching"] / t["total"],
            "adjustment_share_pct": 100.0 * t["adjustment"] / t["total"],
            "outputs_share_pct": 100.0 * t["outputs"] / t["total"],
            "peak_rss_mb": doc["peak_rss_mb"],
            "ncp": doc["ncp"],
            "rmse_px": doc["rmse_px"],
            "geoloc_m_before": (doc["check"] or {}).get("geoloc_rmse_m_before"),
            "geoloc_m_after": (doc["check"] or {}).get("geoloc_rmse_m"),
        }
    ortho = None
    if not args.no_ortho:
        from planetref.runtime.threads import ThreadBudget, apply_thread_budget

        apply_thread_budget(ThreadBudget.resolve(args.threads))
        with tempfile.TemporaryDirectory(dir=base) as tmp:
            ortho = ortho_old_vs_new(scene, args.old_rev, Path(tmp))
    result = {
        "ortho_old_vs_new": ortho,
        "preset": args.preset,
        "area_km2": area,
        "threads": args.threads,
        "runs": rows,
        "skipped": skipped,
    }
    if args.json:
        print(json.dumps(result, indent=1))
        return 0
    print(f"{args.preset}: {area:.2f} km^2 imaged, {args.threads} threads")
    cols = [
        "matching_s",
        "adjustment_s",
        "outputs_s",
        "total_s",
        "s_per_km2",
        "matching_share_pct",
        "adjustment_share_pct",
        "outputs_share_pct",
        "peak_rss_mb",
        "ncp",
        "geoloc_m_after",
    ]
    print(f"{'matcher':<20}" + "".join(f"{c:>20}" for c in cols))
    for name, r in rows.items():
        print(
            f"{name:<20}"
            + "".join(
                f"{r[c]:>20.2f}" if isinstance(r[c], float) else f"{r[c]!s:>20}" for c in cols
            )
        )
    for name, why in skipped.items():
        print(f"skipped {name}: {why}")
    if ortho:
        print(
            f"orthoimages of strip 1 ({ortho['ccds']} CCDs, {ortho['lines']} lines, truth "
            f"camera): old ({args.old_rev}) {ortho['old_s']:.2f} s, new {ortho['new_s']:.2f} s, "
            f"speed-up {ortho['speedup']:.2f}x; max |old - new| {ortho['max_diff_dn']:.2f} DN "
            f"(1-99 % range {ortho['dn_range_1_99']:.0f} DN)"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
