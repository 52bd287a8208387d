"""Cost of the dense NCC matcher: the compiled shared-sum path, its reference and OpenCV.

NCC's fine stage correlates one template per ``dense_spacing_ref_px`` cell (41 px at the
default 2x fine grid) over a 105 x 105 search. The reference
(:func:`planetref.matching.ncc.correlate_batch`) runs OpenCV's ``matchTemplate`` per
template (an FFT each) and vectorised numpy peak tests; the compiled path
(:func:`planetref.matching.ncc.correlate_shared`) shares the templates' overlap (box
sums of products per displacement) and tests the peaks in numba. The script:

1. simulates the scene of ``bench_frontend.py`` (the ``tiny`` preset enlarged to 2 CCDs
   of 1536 x 1536 pixels; ``--preset hiric-strip`` simulates that preset as it is,
   ``--scene DIR`` takes a scene folder) and runs the front end's NCC with the run's
   own settings on ``--max-tiles`` tiles, each tile twice, interleaved (the order
   alternates): ``old`` with the reference, ``new`` with the compiled path; it prints
   per tile CPU seconds (``time.process_time``: other jobs on the cores do not count),
   MCPs, NCP, the tile offset's error against the simulated truth, and how the two MCP
   sets compare (MCPs paired at the same raw pixel, their largest difference, the
   unpaired ones: a peak at a threshold may go either way within float32 noise);
2. on the fine-stage inputs of the first measured tile, CPU seconds per correlation
   (one template against its search window, with the peak tests and sub-pixel fit) of
   ``old``, ``new`` and a bare OpenCV ``matchTemplate(TM_CCOEFF_NORMED)`` over the same
   windows (masked for the partial templates at the edge of the valid area; no peak
   tests), for whole and partial templates apart, the best of ``--repeat`` runs.

OpenCV runs on one thread (``cv2.setNumThreads(1)``), numpy's BLAS too (set
``OMP_NUM_THREADS=1``). ``--json`` prints the figures as JSON with the machine, the
date and the command; ``--out FILE`` also writes that JSON to FILE.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/bench_ncc.py [--max-tiles 4] [--repeat 3]
        [--preset tiny|hiric-strip] [--scene DIR] [--json] [--out FILE]
"""

from __future__ import annotations

import argparse
import datetime
import functools
import json
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def simulate(preset: str, out: Path) -> Path:
    """The benchmark scene: ``tiny`` as ``bench_frontend.py`` has it, or a preset as is."""
    from bench_frontend import SCENE_OVERRIDES

    from planetref.simulate import load_config, simulate_scene

    overrides = SCENE_OVERRIDES if preset == "tiny" else None
    simulate_scene(load_config(preset, overrides), out)
    return out


def compare_mcps(a, b) -> dict:
    """Pairs of old and new MCPs at the same raw pixel (within 0.05 px), their largest
    difference (raw line/sample and reference column/row, pixels), and those unpaired."""
    from scipy.spatial import cKDTree

    def cols(r) -> np.ndarray:
        if r.line is None:
            return np.empty((0, 4))
        return np.column_stack([np.asarray(c, np.float64) for c in
                                (r.line, r.sample, r.ref_col, r.ref_row)])  # fmt: skip

    pa, pb = cols(a), cols(b)
    if len(pa) == 0 or len(pb) == 0:
        return {"paired": 0, "unpaired": len(pa) + len(pb), "max_mcp_diff": float("nan")}
    dist, idx = cKDTree(pa[:, :2]).query(pb[:, :2], distance_upper_bound=0.05)
    hit = np.isfinite(dist)
    diff = np.abs(pb[hit] - pa[idx[hit]]).max() if hit.any() else float("nan")
    return {
        "paired": int(hit.sum()),
        "unpaired": int(len(pa) + len(pb) - 2 * hit.sum()),
        "max_mcp_diff": float(diff),
    }


def run_tiles(s: dict, max_tiles: int) -> tuple[list[dict], tuple | None]:
    """Each tile matched with the reference and the compiled NCC, interleaved."""
    from bench_frontend import truth_error

    import planetref.matching.ncc as ncc
    from planetref.frontend.config import FrontendConfig
    from planetref.frontend.matchers import matcher_options
    from planetref.frontend.tile import match_tile
    from planetref.frontend.tiles import plan_tiles
    from planetref.matching import get_matcher
    from planetref.raster.image import CcdImage

    cfg = FrontendConfig()
    gsd = float(np.mean(s["ref"].ground_sampling_m()))
    fine_opts, coarse_opts = matcher_options("ncc", {}, cfg, gsd)
    fine = get_matcher("ncc", **fine_opts)
    coarse = get_matcher("ncc", **(coarse_opts or {}))
    readers = {c: CcdImage(p) for c, p in s["images"].items()}
    plans = {c: plan_tiles(s["init"], c, s["ref"], s["dem"], cfg) for c in readers}
    tiles = [(t, plans[c].ratio) for c in readers for t in plans[c].tiles]
    if max_tiles > 0:
        tiles = tiles[:: max(1, len(tiles) // max_tiles)][:max_tiles]
    shared = ncc.correlate_shared
    captured: list[tuple] = []

    def capture(*args, **kwargs):
        if not captured:
            captured.append((args, kwargs))
        return shared(*args, **kwargs)

    variants = {"old": functools.partial(shared, compiled=False), "new": capture}
    rows = []
    try:
        # warm-up: compiles (or loads) the kernels, builds the caches; not measured
        ncc.correlate_shared = shared
        t0, ratio0 = tiles[0]
        match_tile(t0, image=readers[t0.ccd], camera=s["init"], ref=s["ref"],
                   terrain=s["dem"], matcher=fine, config=cfg, ratio=ratio0,
                   coarse_matcher=coarse)  # fmt: skip
        for n, (t, ratio) in enumerate(tiles):
            out = {"tile": f"{t.ccd}/{t.tile_id}"}
            got = {}
            for name in ("old", "new") if n % 2 == 0 else ("new", "old"):
                ncc.correlate_shared = variants[name]
                c0 = time.process_time()
                r = match_tile(t, image=readers[t.ccd], camera=s["init"], ref=s["ref"],
                               terrain=s["dem"], matcher=fine, config=cfg, ratio=ratio,
                               coarse_matcher=coarse)  # fmt: skip
                cpu = time.process_time() - c0
                got[name] = r
                out[name] = {
                    "cpu_s": cpu,
                    "status": r.status,
                    "mcps": r.n_points,
                    "ncp": r.ncp,
                    "offset_error_px": truth_error(s, r),
                }
            out.update(compare_mcps(got["old"], got["new"]))
            rows.append(out)
    finally:
        ncc.correlate_shared = shared
        for rd in readers.values():
            rd.close()
    return rows, captured[0] if captured else None


def per_correlation(captured: tuple, repeat: int) -> dict:
    """CPU seconds per template of old, new and bare OpenCV on one fine stage's inputs."""
    import cv2

    import planetref.matching.ncc as ncc

    args, kwargs = captured
    image0, image1, bad1, r0, c0, r1, c1, settings = args[:8]
    valid0 = args[8] if len(args) > 8 else kwargs.get("valid0")
    t, radius = settings.template_radius, settings.search_radius
    side = 2 * t + 1
    if valid0 is None:
        partial = np.zeros(len(r0), bool)
    else:
        holes = cv2.boxFilter((~valid0).astype(np.float64), -1, (side, side), normalize=False,
                              borderType=cv2.BORDER_CONSTANT)  # fmt: skip
        partial = holes[r0, c0] > 0.5
    m = t + radius
    img1 = np.pad(image1.astype(np.float32), m, mode="edge")
    h1, w1 = image1.shape

    def opencv(sel: np.ndarray, masked: bool) -> None:
        rr, cc = np.clip(r1[sel], 0, h1 - 1), np.clip(c1[sel], 0, w1 - 1)
        out = np.empty((2 * radius + 1, 2 * radius + 1), np.float32)
        for k, a, b in zip(sel, rr, cc, strict=True):
            templ = image0[r0[k] - t : r0[k] + t + 1, c0[k] - t : c0[k] + t + 1]
            win = img1[a : a + 2 * m + 1, b : b + 2 * m + 1]
            if masked:
                mask = valid0[r0[k] - t : r0[k] + t + 1, c0[k] - t : c0[k] + t + 1]
                cv2.matchTemplate(win, templ, cv2.TM_CCOEFF_NORMED, mask=mask.astype(np.float32))
            else:
                cv2.matchTemplate(win, templ, cv2.TM_CCOEFF_NORMED, result=out)

    result: dict[str, dict] = {}
    for kind, sel in (("whole", np.flatnonzero(~partial)), ("partial", np.flatnonzero(partial))):
        if len(sel) == 0:
            continue
        v0 = valid0 if kind == "partial" else None
        sub = (image0, image1, bad1, r0[sel], c0[sel], r1[sel], c1[sel], settings, v0)
        runs = {
            "old": lambda sub=sub: ncc.correlate_batch(*sub),
            "new": lambda sub=sub: ncc.correlate_shared(*sub),
            "opencv": lambda sel=sel, kind=kind: opencv(sel, kind == "partial"),
        }
        best = {name: float("inf") for name in runs}
        for _ in range(repeat):
            for name, fn in runs.items():
                c = time.process_time()
                fn()
                best[name] = min(best[name], time.process_time() - c)
        result[kind] = {
            "templates": len(sel),
            **{f"{name}_cpu_s_per_correlation": v / len(sel) for name, v in best.items()},
        }
    result["search"] = {"template_px": side, "surface_px": 2 * radius + 1}
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="tiny", choices=["tiny", "hiric-strip"])
    ap.add_argument("--scene", type=Path, default=None, help="a scene folder (scene.toml)")
    ap.add_argument("--max-tiles", type=int, default=4, help="tiles measured (0: all)")
    ap.add_argument("--repeat", type=int, default=3, help="runs of the per-correlation test")
    ap.add_argument("--json", action="store_true", help="print JSON only")
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = ap.parse_args(argv)
    import cv2

    cv2.setNumThreads(1)
    from bench_frontend import load
    from machine import describe

    machine = describe()
    with tempfile.TemporaryDirectory() as tmp:
        root = args.scene or simulate(args.preset, Path(tmp) / "scene")
        s = load(root)
        rows, captured = run_tiles(s, args.max_tiles)
        s["ref"].close()
    corr = per_correlation(captured, args.repeat) if captured is not None else {}
    tot = {k: sum(r[k]["cpu_s"] for r in rows) for k in ("old", "new")}
    report = {
        "machine": machine,
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "command": "python " + shlex.join(["benchmarks/bench_ncc.py", *(argv or sys.argv[1:])]),
        "scene": str(args.scene) if args.scene else f"simulated {args.preset}",
        "tiles": rows,
        "tile_cpu_s": tot,
        "tile_cpu_ratio_old_over_new": tot["old"] / tot["new"] if tot["new"] else None,
        "per_correlation": corr,
    }
    text = json.dumps(report, indent=2)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n", encoding="utf-8")
    if args.json:
        print(text)
        return 0
    print(f"machine: {machine}")
    print(f"scene: {report['scene']}; front end NCC, the run's settings; CPU seconds")
    print(f"{'tile':<14}{'old s':>8}{'new s':>8}{'ratio':>7}{'MCPs':>12}{'NCP':>12}"
          f"{'err old/new px':>18}{'paired':>8}{'unpaired':>9}{'max diff px':>12}")  # fmt: skip
    for r in rows:
        o, n = r["old"], r["new"]
        print(
            f"{r['tile']:<14}{o['cpu_s']:>8.2f}{n['cpu_s']:>8.2f}{o['cpu_s'] / n['cpu_s']:>7.2f}"
            f"{o['mcps']:>6}/{n['mcps']:<5}{o['ncp']:>6}/{n['ncp']:<5}"
            f"{o['offset_error_px']:>9.4f}/{n['offset_error_px']:<8.4f}"
            f"{r['paired']:>8}{r['unpaired']:>9}{r['max_mcp_diff']:>12.2e}"
        )
    ratio = report["tile_cpu_ratio_old_over_new"]
    print(f"all tiles: old {tot['old']:.2f} s, new {tot['new']:.2f} s, ratio {ratio:.2f}")
    if corr:
        g = corr["search"]
        print(f"per correlation ({g['template_px']} px template, {g['surface_px']} px surface):")
        for kind in ("whole", "partial"):
            if kind in corr:
                c = corr[kind]
                print(
                    f"  {kind:<8}{c['templates']:>6} templates: "
                    f"old {c['old_cpu_s_per_correlation'] * 1e3:.3f} ms, "
                    f"new {c['new_cpu_s_per_correlation'] * 1e3:.3f} ms, "
                    f"bare OpenCV {c['opencv_cpu_s_per_correlation'] * 1e3:.3f} ms"
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
