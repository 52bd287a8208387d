"""Time the matching front end per tile and split its overhead from the model time.

For each matcher (whose weights are present), the script matches every tile of a
simulated scene through the whole front end -- footprint, orthorectification (or
downsampling) of the CCD tile, windowed reads of the reference, coarse stage, fine
stage, USAC_MAGSAC verification and mapping back to raw pixels -- with the run's own
matcher settings (``planetref.frontend.matchers``: NCC dense on the fine stage, with a
wide-radius coarse instance), and prints per tile, as means over the tiles:

* ``planetref``: seconds of the whole front end (``TileResult.timings["total"]``);
* ``model``: seconds of the bare model calls on the same arrays
  (``Matcher.timings["forward"]``: the detector, descriptor and matcher networks, or
  OpenCV's detection/correlation);
* ``ratio``: planetref / model (the issue's target: <= 1.3);
* the breakdown: ``prep-c`` / ``prep-f`` preparation of the coarse / fine stage
  (orthorectification of the CCD side, reference reads), ``match`` the two
  ``Matcher.match`` calls (model plus normalisation and bookkeeping), ``verify``
  (gates, USAC_MAGSAC, translation consensus) and ``other`` (footprint, mapping back);
* ``MCPs`` (all tiles) and the largest tile-offset error against the simulated truth
  (reference pixels), so that a faster preparation is seen not to cost matches.

``--prep cached uncached`` runs every matcher twice in the same run: with the per-reader
caches of the tile preparation (planetref's way) and with each window projecting its
own lattice and reading its own raw pixels (the way before), for a before/after ratio.
``--clock cpu`` reads CPU seconds of the process instead of wall seconds (with
``--threads 1`` and ``OMP_NUM_THREADS=1``, the figures other jobs on the machine do not
inflate).

``--save-mcps FILE.npz`` keeps every measured tile's MCPs (raw line, sample, reference
column, row, confidence); ``--compare-mcps FILE.npz`` compares this run's with such a file
(another version's) per matcher and grid: tiles bit-identical and the largest difference.

One warm-up tile is matched first, on its own reader (it builds the model; the measured
tiles build the per-reader caches themselves), and left out of the numbers.

The scene is the simulator's ``tiny`` preset enlarged to 2 CCDs of 1536 x 1536 pixels at
0.5 m with the reference lit like the images (``--scene DIR`` takes any scene folder
instead).

Usage::

    python benchmarks/bench_frontend.py [--matchers sift ncc disk-lightglue ...]
        [--tile 128] [--threads 1] [--prep cached uncached] [--clock cpu]
        [--device cpu|cuda|auto] [--weights-dir DIR] [--scene DIR] [--json]
        [--save-mcps FILE.npz] [--compare-mcps FILE.npz]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

SCENE_OVERRIDES = {
    "photometry": {"reference_sun": {"azimuth_deg": 215.0, "elevation_deg": 40.0}},
    "camera": {
        "n_ccds": 2,
        "n_samples": 1536,
        "n_lines": 1536,
        "gsd_m": 0.5,
        "overlap_samples": 32,
    },
    "albedo": {"texture_gsd_m": 0.5},
}
BREAKDOWN = (
    "footprint",
    "coarse_prepare",
    "fine_prepare",
    "coarse_match",
    "fine_match",
    "verify",
    "backmap",
)
DEFAULT_WEIGHTS = Path(__file__).resolve().parents[1].parent / "shared" / "weights"


def simulate(out: Path) -> Path:
    from planetref.simulate import load_config, simulate_scene

    simulate_scene(load_config("tiny", SCENE_OVERRIDES), out)
    return out


def load(root: Path) -> dict:
    from planetref.camera.linescan import LineScanCamera
    from planetref.raster.dem import GridTerrain
    from planetref.raster.ortho import ReferenceOrtho
    from planetref.scene.manifest import load_manifest

    man, root = load_manifest(root)
    strip = man.strips[0]
    out = {
        "man": man,
        "init": LineScanCamera.from_json(man.resolve(root, strip.ccds[0].camera)),
        "ref": ReferenceOrtho(man.resolve(root, man.reference.ortho)),
        "dem": GridTerrain.from_geotiff(man.resolve(root, man.reference.dem)),
        "images": {c.name: man.resolve(root, c.image) for c in strip.ccds},
        "true": None,
    }
    if man.truth is not None:
        out["true"] = LineScanCamera.from_json(man.resolve(root, man.truth.cameras[strip.id]))
        out["truth_dem"] = GridTerrain.from_geotiff(man.resolve(root, man.truth.dem))
    return out


def truth_error(s: dict, r) -> float:
    from planetref.camera.mapping import image_to_ref_pixel

    if s["true"] is None or r.status != "ok":
        return float("nan")
    ref = s["ref"]
    tc, tr = image_to_ref_pixel(s["true"], r.tile.ccd, r.line, r.sample, ref, s["truth_dem"])
    dx, dy = s["man"].truth.ortho_offset_m
    tc, tr = tc + dx / ref.transform.a, tr + dy / ref.transform.e
    ic, ir = image_to_ref_pixel(s["init"], r.tile.ccd, r.line, r.sample, ref, s["dem"])
    truth = np.array([np.mean(tc - ic), np.mean(tr - ir)])
    return float(np.max(np.abs(np.asarray(r.offset_px) - truth)))


def bench(
    name: str,
    s: dict,
    cfg,
    weights_dir: Path | None,
    prep: str = "cached",
    device: str = "cpu",
    max_tiles: int = 0,
) -> dict:
    import planetref.frontend.tile as tile_module
    from planetref.frontend.matchers import matcher_options
    from planetref.frontend.orthorectify import lattice_cache
    from planetref.frontend.tile import match_tile
    from planetref.frontend.tiles import plan_tiles
    from planetref.matching import get_matcher
    from planetref.matching.registry import MATCHERS
    from planetref.raster.image import CcdImage

    # The run's own matcher settings (NCC: dense fine stage, wide coarse search).
    gsd = float(np.mean(s["ref"].ground_sampling_m()))
    fine_opts, coarse_opts = matcher_options(name, {}, cfg, gsd)
    if device != "cpu" and MATCHERS[name].weights:
        fine_opts = {**fine_opts, "device": device}
        coarse_opts = None if coarse_opts is None else {**coarse_opts, "device": device}
    matcher = get_matcher(name, weights_dir=weights_dir, **fine_opts)
    coarse = None
    if coarse_opts is not None:
        coarse = get_matcher(name, weights_dir=weights_dir, **coarse_opts)
    readers = {c: CcdImage(p) for c, p in s["images"].items()}
    plans = {c: plan_tiles(s["init"], c, s["ref"], s["dem"], cfg) for c in readers}
    tiles = [(t, plans[c].ratio) for c in readers for t in plans[c].tiles]
    if max_tiles > 0:
        # Spread the measured tiles over the strip (every k-th tile).
        tiles = tiles[:: max(1, len(tiles) // max_tiles)][:max_tiles]
    rows = []
    mcps: dict[str, np.ndarray] = {}
    # "uncached": each window projects its own lattice and reads its raw pixels (the
    # preparation before the per-reader caches), for comparison in the same run.
    tile_module.lattice_cache = lattice_cache if prep == "cached" else lambda *a, **k: None
    warm = CcdImage(s["images"][tiles[0][0].ccd])
    for i, (t, ratio) in enumerate([tiles[0], *tiles]):
        # The warm-up tile gets its own reader: the measured tiles pay for the per-reader
        # caches (lattice nodes, raw block means) themselves.
        r = match_tile(
            t,
            image=warm if i == 0 else readers[t.ccd],
            camera=s["init"],
            ref=s["ref"],
            terrain=s["dem"],
            matcher=matcher,
            config=cfg,
            ratio=ratio,
            coarse_matcher=coarse,
        )
        if i == 0:
            continue  # warm-up: builds the model
        tm = r.timings
        if r.line is not None:
            key = f"{name}|{cfg.fine_upsample}|{prep}|{t.ccd}|{t.tile_id}"
            cols = (r.line, r.sample, r.ref_col, r.ref_row, r.confidence)
            mcps[key] = np.column_stack([np.asarray(c, np.float64) for c in cols])
        rows.append(
            {
                "tile": t.tile_id,
                "status": r.status,
                "mcps": r.n_points,
                "ncp": r.ncp,
                "total_s": tm.get("total", 0.0),
                "match_s": tm.get("coarse_match", 0.0) + tm.get("fine_match", 0.0),
                "forward_s": tm.get("forward", 0.0),
                **{f"{k}_s": tm.get(k, 0.0) for k in BREAKDOWN},
                "offset_error_px": truth_error(s, r),
            }
        )
    warm.close()
    for rd in readers.values():
        rd.close()
    tot = statistics.median(r["total_s"] for r in rows)
    mat = statistics.median(r["match_s"] for r in rows)
    fwd = statistics.median(r["forward_s"] for r in rows)
    sum_tot = sum(r["total_s"] for r in rows)
    sum_fwd = sum(r["forward_s"] for r in rows)
    sum_mat = sum(r["match_s"] for r in rows)
    mean = {k: statistics.fmean(r[f"{k}_s"] for r in rows) for k in BREAKDOWN}
    errs = [r["offset_error_px"] for r in rows if np.isfinite(r["offset_error_px"])]
    tile_module.lattice_cache = lattice_cache
    return {
        "matcher": name,
        "prep": prep,
        "tiles": len(rows),
        "ok": sum(r["status"] == "ok" for r in rows),
        "s_per_tile": tot,
        "match_s": mat,
        "forward_s": fwd,
        "overhead_share": (sum_tot - sum_fwd) / sum_fwd if sum_fwd > 0 else float("nan"),
        "frontend_share": (sum_tot - sum_mat) / sum_mat if sum_mat > 0 else float("nan"),
        "ratio": sum_tot / sum_fwd if sum_fwd > 0 else float("nan"),
        "mean_total_s": sum_tot / len(rows),
        "mean_forward_s": sum_fwd / len(rows),
        "breakdown_s": mean,
        "mcps": sum(r["mcps"] for r in rows),
        "ncp": sum(r["ncp"] for r in rows),
        "fine_upsample": cfg.fine_upsample,
        "max_offset_error_px": max(errs) if errs else float("nan"),
        "rows": rows,
        "_mcps": mcps,
    }


def compare_mcps(mcps: dict[str, np.ndarray], path: Path) -> list[str]:
    """Lines comparing this run's MCPs with a saved run's, per matcher and fine grid."""
    with np.load(path) as f:
        old = {k: f[k] for k in f.files}
    groups: dict[tuple[str, str], list] = {}
    for key in sorted(set(mcps) | set(old)):
        name, up = key.split("|")[:2]
        a, b = old.get(key), mcps.get(key)
        g = groups.setdefault((name, up), [0, 0, 0, 0, 0.0])
        g[0] += 1
        g[1] += 0 if a is None else len(a)
        g[2] += 0 if b is None else len(b)
        if a is not None and b is not None and a.shape == b.shape:
            g[3] += int(np.array_equal(a, b))
            if a.size:
                g[4] = max(g[4], float(np.max(np.abs(a[:, :4] - b[:, :4]))))
        else:
            g[4] = float("inf")
    return [
        f"{name:<18} up {up}: {n} tiles, MCPs {na} -> {nb}, bit-identical tiles {same}/{n}, "
        f"largest difference {diff:.3g} px"
        for (name, up), (n, na, nb, same, diff) in groups.items()
    ]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--matchers",
        nargs="+",
        default=["sift", "ncc", "disk-lightglue", "aliked-lightglue", "xfeat-lighterglue"],
    )
    ap.add_argument("--tile", type=int, default=128, help="tile size, reference pixels")
    ap.add_argument("--geometry", default="orthorectify", choices=["orthorectify", "downsample"])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument(
        "--device", default="cpu", help="torch device of the learned matchers (cpu, cuda, auto)"
    )
    ap.add_argument("--weights-dir", type=Path, default=None)
    ap.add_argument("--scene", type=Path, default=None, help="a scene folder (scene.toml)")
    ap.add_argument(
        "--prep",
        nargs="+",
        default=["cached"],
        choices=["cached", "uncached"],
        help="tile preparation: per-reader caches (planetref's), or per window (before)",
    )
    ap.add_argument(
        "--fine-upsample",
        nargs="+",
        type=int,
        default=None,
        help="fine-stage grids to compare in one run (default: the config's)",
    )
    ap.add_argument(
        "--defaults",
        action="store_true",
        help="planetref's default front-end settings (tile size, coarse stage, uncertainty) "
        "instead of the small-scene ones (--tile is then ignored)",
    )
    ap.add_argument("--max-tiles", type=int, default=0, help="measure at most this many tiles")
    ap.add_argument("--json", action="store_true", help="print JSON only")
    ap.add_argument("--save-mcps", type=Path, default=None, help="keep the MCPs in this .npz")
    ap.add_argument(
        "--compare-mcps", type=Path, default=None, help="compare the MCPs with this .npz"
    )
    ap.add_argument(
        "--clock",
        default="wall",
        choices=["wall", "cpu"],
        help="cpu: CPU seconds of this process (steadier when other jobs share the cores; "
        "use with single-threaded libraries)",
    )
    args = ap.parse_args(argv)
    if args.clock == "cpu":
        # Every timer of the front end and the matchers reads time.perf_counter.
        time.perf_counter = time.process_time

    import torch

    torch.set_num_threads(args.threads)
    from planetref.errors import PlanetrefError
    from planetref.matching._torch import resolve_device

    try:
        args.device = str(resolve_device(args.device))
    except PlanetrefError as exc:
        print(f"bench_frontend: {exc}", file=sys.stderr)
        return 2
    from planetref.frontend.config import FrontendConfig
    from planetref.matching.registry import MATCHERS
    from planetref.matching.weights import missing_weights

    weights = args.weights_dir or (DEFAULT_WEIGHTS if DEFAULT_WEIGHTS.is_dir() else None)
    if args.defaults:
        cfg = FrontendConfig(geometry=args.geometry)
        args.tile = cfg.tile_size_ref_px
    else:
        cfg = FrontendConfig(
            tile_size_ref_px=args.tile, coarse_factor=2, uncertainty_m=150.0, geometry=args.geometry
        )
    from machine import describe

    machine = describe()  # the load before this run's own work
    ups = args.fine_upsample or [cfg.fine_upsample]
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        root = args.scene or simulate(Path(tmp) / "scene")
        sim_s = time.perf_counter() - t0
        s = load(root)
        results, skipped = [], {}
        for name in args.matchers:
            spec = MATCHERS.get(name)
            if spec is None:
                skipped[name] = "unknown matcher"
                continue
            missing = missing_weights(spec.weights, weights)
            if missing:
                skipped[name] = f"weights missing: {missing}"
                continue
            for up in ups:
                c = cfg.model_copy(update={"fine_upsample": up})
                for prep in args.prep:
                    results.append(bench(name, s, c, weights, prep, args.device, args.max_tiles))
        s["ref"].close()
    mcps = {k: v for r in results for k, v in r.pop("_mcps").items()}
    if args.save_mcps is not None:
        np.savez(args.save_mcps, **mcps)
    compared = [] if args.compare_mcps is None else compare_mcps(mcps, args.compare_mcps)
    if args.json:
        print(
            json.dumps(
                {
                    "machine": machine,
                    "config": cfg.model_dump(),
                    "threads": args.threads,
                    "results": results,
                    "skipped": skipped,
                    "mcp_comparison": compared,
                },
                indent=2,
            )
        )
        return 0
    print(f"machine: {machine}")
    print(
        f"scene: {'given' if args.scene else f'simulated in {sim_s:.1f} s'}; tile "
        f"{args.tile} ref px; {args.geometry}; torch threads {args.threads}; clock {args.clock}; "
        f"device {args.device}"
    )
    print("per tile, mean seconds (warm-up tile excluded); ratio = planetref / bare model")
    print(
        f"{'matcher':<18}{'up':>3}{'prep':>7}{'tiles':>6}{'ok':>4}{'NCP':>7}{'MCPs':>7}"
        f"{'planetref':>10}{'model':>8}"
        f"{'ratio':>7}{'prep-c':>8}{'prep-f':>8}{'match':>8}{'verify':>8}{'other':>8}"
        f"{'max err px':>11}"
    )
    for r in results:
        b = r["breakdown_s"]
        match = b["coarse_match"] + b["fine_match"]
        other = r["mean_total_s"] - match - b["coarse_prepare"] - b["fine_prepare"] - b["verify"]
        print(
            f"{r['matcher']:<18}{r['fine_upsample']:>3}{r['prep']:>7}{r['tiles']:>6}{r['ok']:>4}"
            f"{r['ncp']:>7}{r['mcps']:>7}"
            f"{r['mean_total_s']:>10.3f}{r['mean_forward_s']:>8.3f}{r['ratio']:>7.2f}"
            f"{b['coarse_prepare']:>8.3f}{b['fine_prepare']:>8.3f}{match:>8.3f}"
            f"{b['verify']:>8.3f}{other:>8.3f}{r['max_offset_error_px']:>11.3f}"
        )
    for name, why in skipped.items():
        print(f"{name:<20} skipped: {why}")
    for line in compared:
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
