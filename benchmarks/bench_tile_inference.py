"""Where a learned matcher's tile time goes: feature extraction, LightGlue, the rest.

For each learned matcher and a few tiles of a simulated scene (spread over the strip),
the script runs the front end's own steps of each tile (:func:`planetref.frontend.tile.
tile_steps`: footprint, orthorectification, coarse stage, fine stage(s), verification,
mapping back) at planetref's default settings (``FrontendConfig()``: 256 reference-pixel
tiles, fine stage on the 2x grid) and splits the CPU seconds of the process
(``time.process_time``, which other jobs on the machine do not inflate; torch with one
thread unless ``--threads``) per tile into:

* ``extract``: the detector/descriptor network and its keypoint selection
  (``_extract_batch``; for XFeat* the cell extraction at both scales, ``_cells``);
* ``glue``: LightGlue's forward pass (for XFeat*: the mutual nearest neighbours of the
  cells and the refinement head);
* ``match other``: the rest of the ``Matcher.match`` calls (normalisation, masks,
  resizing, coordinate conversion, copies to and from torch);
* ``tile other``: everything of the tile outside the matcher calls (orthorectification,
  reference reads, verification, mapping back);

with the number of matcher calls per tile (2: coarse and fine; 3 when the coarse stage
finds no consensus and a second fine pass runs), LightGlue's layers run (early stopping)
and keypoints per image, and the tile's status, matches and inliers.

``--variants NAME=JSON ...`` runs each matcher once per option set (registry options
merged over the run's own, e.g. ``k2048='{"max_keypoints": 2048}'``) on the same tiles in
the same run, so that their CPU seconds compare as ratios. The option ``"_kornia_cross":
true`` puts kornia's own LightGlue cross-attention back (planetref fuses its two
directions, :func:`planetref.matching._torch.fused_cross_block`): the way before, e.g.
``--variants kornia='{"_kornia_cross": true}' fused='{}'``.

Usage::

    python benchmarks/bench_tile_inference.py --scene DIR [--matchers ...] [--tiles 3]
        [--threads 1] [--variants base='{}' ...] [--json-out benchmarks/results/X.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

LEARNED = ["disk-lightglue", "aliked-lightglue", "xfeat-lighterglue", "xfeat-star"]
clock = time.process_time


def _instrument(m: Any, acc: dict[str, float], layers: list[tuple[int, int, int]]) -> None:
    """Wrap the matcher's extraction and matching calls to add their CPU seconds to ``acc``."""

    def wrap(owner: Any, attr: str, key: str, target: dict[str, Any]) -> None:
        f = getattr(owner, attr)

        def timed(*a: Any, **k: Any) -> Any:
            t0 = clock()
            try:
                return f(*a, **k)
            finally:
                acc[key] = acc.get(key, 0.0) + clock() - t0

        target[attr] = timed

    if hasattr(m, "_extract_batch"):
        wrap(m, "_extract_batch", "extract", m.__dict__)
        glue = m._model["matcher"]
        inner = glue._forward

        def counted(data: dict[str, Any]) -> Any:
            out = inner(data)
            n0 = int(data["image0"]["keypoints"].shape[1])
            n1 = int(data["image1"]["keypoints"].shape[1])
            layers.append((int(out["stop"]), n0, n1))
            return out

        glue.__dict__["_forward"] = counted
        wrap(glue, "forward", "glue", glue.__dict__)
    else:  # XFeat*: cells at all scales, then matching + refinement head
        wrap(m, "_cells", "extract", m.__dict__)
        cells = m.__dict__["_cells"]
        run = type(m)._run

        def matched(pair: Any) -> Any:
            t0 = clock()
            e0 = acc.get("extract", 0.0)
            try:
                return run(m, pair)
            finally:
                acc["glue"] = acc.get("glue", 0.0) + clock() - t0 - (acc.get("extract", 0.0) - e0)

        m.__dict__["_run"] = matched
        m.__dict__["_cells"] = cells


def profile(
    name: str, options: dict[str, Any], scene: dict[str, Any], cfg: Any, tiles: list, threads: int
) -> dict[str, Any]:
    """Run the tiles with one matcher configuration; the CPU-second split per tile."""
    from planetref.frontend.batched import StageAnswer, inference_mode
    from planetref.frontend.matchers import matcher_options
    from planetref.frontend.tile import TileInputs, tile_steps
    from planetref.matching import get_matcher

    gsd = float(np.mean(scene["ref"].ground_sampling_m()))
    fine_opts, _ = matcher_options(name, {}, cfg, gsd)
    opts = dict(options)
    kornia_cross = bool(opts.pop("_kornia_cross", False))
    m = get_matcher(name, **{**fine_opts, **opts})
    m.build()
    if kornia_cross and hasattr(m, "_extract_batch"):
        # the way before: kornia's own CrossBlock (the M x N matrix on the CPU)
        for layer in m._model["matcher"].transformers:
            layer.cross_attn.__class__ = type(layer.cross_attn).__mro__[1]
    acc: dict[str, float] = {}
    layers: list[tuple[int, int, int]] = []
    _instrument(m, acc, layers)
    rows = []
    for t, ratio, reader in tiles:
        before = dict(acc)
        steps = tile_steps(
            t,
            TileInputs(
                image=reader,
                camera=scene["init"],
                ref=scene["ref"],
                terrain=scene["dem"],
                matcher=m,
                config=cfg,
                ratio=ratio,
            ),
        )
        c0 = clock()
        calls, match_s = 0, 0.0
        try:
            req = next(steps)
            while True:
                a0 = clock()
                with inference_mode():
                    got = req.matcher.match(*req.pair())
                match_s += clock() - a0
                calls += 1
                req = steps.send(StageAnswer(got, 0.0, 0.0))
        except StopIteration as stop:
            res = stop.value
        tile_s = clock() - c0
        ext = acc.get("extract", 0.0) - before.get("extract", 0.0)
        glue = acc.get("glue", 0.0) - before.get("glue", 0.0)
        rows.append(
            {
                "tile": f"{t.ccd}/{t.tile_id}",
                "status": res.status,
                "matches": res.n_matches,
                "inliers": res.n_inliers,
                "ncp": res.ncp,
                "calls": calls,
                "cpu_s": tile_s,
                "extract_s": ext,
                "glue_s": glue,
                "match_other_s": match_s - ext - glue,
                "tile_other_s": tile_s - match_s,
            }
        )
    n = len(rows)
    mean = {
        k: sum(r[k] for r in rows) / n
        for k in ("cpu_s", "extract_s", "glue_s", "match_other_s", "tile_other_s", "calls")
    }
    return {
        "matcher": name,
        "options": options,
        "threads": threads,
        "per_tile": mean,
        "ncp": sum(r["ncp"] for r in rows),
        "inliers": sum(r["inliers"] for r in rows),
        "lightglue_layers_keypoints": layers,
        "tiles": rows,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", type=Path, required=True, help="a simulated scene folder")
    ap.add_argument("--matchers", nargs="+", default=LEARNED)
    ap.add_argument("--tiles", type=int, default=3, help="tiles measured, spread over the strip")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--variants", nargs="+", default=["default={}"], help="NAME=JSON options")
    ap.add_argument("--json-out", default=None)
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    from bench_frontend import load
    from machine import describe, result_record, write_result

    from planetref.errors import PlanetrefError
    from planetref.frontend.config import FrontendConfig
    from planetref.frontend.tiles import plan_tiles
    from planetref.matching.registry import MATCHERS
    from planetref.matching.weights import missing_weights
    from planetref.raster.image import CcdImage

    machine = describe()
    variants = {}
    for v in args.variants:
        key, _, text = v.partition("=")
        variants[key] = json.loads(text or "{}")
    scene = load(args.scene)
    cfg = FrontendConfig()
    readers = {c: CcdImage(p) for c, p in scene["images"].items()}
    plans = {c: plan_tiles(scene["init"], c, scene["ref"], scene["dem"], cfg) for c in readers}
    every = [(t, plans[c].ratio, readers[c]) for c in readers for t in plans[c].tiles]
    tiles = every[:: max(1, len(every) // args.tiles)][: args.tiles]
    results, figures = [], []
    print(f"scene {args.scene}: {len(every)} tiles, measuring {len(tiles)}; CPU-s per tile")
    print("| matcher | variant | CPU-s | extract | glue | match other | tile other | calls | NCP |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for name in args.matchers:
        if missing_weights(MATCHERS[name].weights):
            print(f"skipped {name}: no weights", file=sys.stderr)
            continue
        for vname, opts in variants.items():
            try:
                r = profile(name, opts, scene, cfg, tiles, args.threads)
            except PlanetrefError as exc:  # e.g. max_keypoints for XFeat*
                print(f"skipped {name} {vname}: {exc}", file=sys.stderr)
                continue
            r["variant"] = vname
            results.append(r)
            p = r["per_tile"]
            print(
                f"| {name} | {vname} | {p['cpu_s']:.2f} | {p['extract_s']:.2f} | "
                f"{p['glue_s']:.2f} | {p['match_other_s']:.2f} | {p['tile_other_s']:.2f} | "
                f"{p['calls']:.1f} | {r['ncp']} |",
                flush=True,
            )
            for k in ("cpu_s", "extract_s", "glue_s", "match_other_s", "tile_other_s"):
                figures.append(
                    {
                        "name": f"{args.scene.name} {name} {vname} {k[:-2]} per tile",
                        "value": round(p[k], 2),
                        "unit": "CPU-s",
                    }
                )
    if args.json_out:
        record = result_record(
            Path(args.json_out).stem,
            figures,
            title=f"Learned matchers: where a tile's CPU time goes ({args.scene.name})",
            machine=machine,
        )
        record["details"] = results
        write_result(args.json_out, record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
