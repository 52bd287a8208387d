"""Is the adjustment's reported precision calibrated? True vs formal ground error per matcher.

For each simulated scene and matcher, the script georeferences the scene once with the
default settings (``planetref georef``; an existing run folder under ``--runs`` is
reused), reads back the run's MCPs and check flags, and adjusts them again with the run's
adjustment settings (optionally overridden with ``--set adjust.KEY=VALUE``). It then
prints, per strip:

* ``true_m``: the RMS ground error of the adjusted camera against the true camera over the
  21 x 21 pixel grid of every CCD at the true terrain (the pipeline's true-error metric,
  :func:`planetref.report.blocks.check_block`);
* ``formal_m``: the RMS ground precision propagated from the adjustment's own parameter
  covariance to the same grid points (:func:`planetref.adjust.precision.
  formal_ground_precision`), with every covariance term the adjustment reports
  (``formal_meas_m``: the measurement term alone, the covariance without the reference's
  correlated error);
* ``ratio``: ``true_m / formal_m`` (calibrated: within 0.5-2), with sigma0 before VCE;
* ``check_z``: the held-out tiles' mean misfits over their predicted SD, RMS over tiles
  and axes (:func:`planetref.adjust.precision.check_tile_misfit`: ~1 when calibrated;
  the truth-free counterpart of ``ratio``, from one or two tiles a rough one);
* with three matchers or more of one scene and seed, ``excess_m``: the matcher's ground
  error beyond its own covariance, from the matchers' adjusted cameras compared with each
  other and no truth (:func:`planetref.adjust.precision.excess_error`, the three-cornered
  hat that ``planetref compare`` reports), and ``ratio_with_excess``: true over the
  formal precision with the excess added.

Usage::

    python benchmarks/bench_calibration.py [--scenes tiny:moderate tiny:hard]
        [--matchers sift ncc] [--seeds 0 1] [--runs DIR] [--set adjust.reference.sigma_m=0]
        [--json]

A scene ``tiny:hard`` is simulated (each of ``--seeds``, default 0) into ``--runs`` when it
is not there yet. With several seeds the figures add, per scene and matcher, the RMS of
true and formal over the seeds, their ratio and the spread of the per-seed ratios.
Weights: ``PLANETREF_WEIGHTS`` (or ``--weights-dir``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np


def _scene(runs: Path, spec: str, seed: int) -> Path:
    from planetref.simulate.config import load_config
    from planetref.simulate.scene import simulate_scene

    preset, _, difficulty = spec.partition(":")
    out = runs / "scenes" / f"{preset}-{difficulty or 'moderate'}-s{seed}"
    if not (out / "scene.toml").is_file():
        simulate_scene(load_config(preset, seed=seed, difficulty=difficulty or None), out)
    return out


def _override(cfg: Any, sets: list[str]) -> Any:
    from planetref.pipeline.config import config_from_mapping

    data: dict[str, Any] = cfg.to_json()
    for item in sets:
        key, _, value = item.partition("=")
        node = data
        parts = key.split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = json.loads(value) if value not in ("", "None") else None
    return config_from_mapping(data)


def measure(scene: Path, run_dir: Path, cfg: Any, matcher: str) -> list[dict[str, Any]]:
    """Re-adjust a run's MCPs and compare formal and true ground errors per strip."""
    from planetref.adjust.api import adjust
    from planetref.adjust.precision import formal_ground_precision
    from planetref.control.ground_sigma import reference_gsd_m
    from planetref.control.mcp import read_mcps
    from planetref.control.networks import (
        McpSet,
        template_overlap,
        template_support_m,
    )
    from planetref.errors import MatchingError
    from planetref.frontend.matchers import matcher_options
    from planetref.pipeline.systematic import systematic_settings
    from planetref.report.blocks import check_block
    from planetref.scene.inputs import (
        open_reference,
        scene_path,
        strip_cameras,
        truth_inputs,
        truth_terrain,
    )
    from planetref.scene.manifest import load_manifest

    manifest, root = load_manifest(scene_path(scene))
    ref, dem = open_reference(manifest, root)
    truth_cams, truth_dem = truth_inputs(manifest, root)
    terrain = truth_terrain(truth_dem, dem)
    rows = []
    for strip in manifest.strips:
        camera, _ = strip_cameras(manifest, root, strip)
        table = read_mcps(run_dir / strip.id / "mcps.parquet")
        n = len(table)
        if n < cfg.mcp.min_mcps:
            # The run failed (its report keeps the matcher as a row); say why, as it did.
            raise MatchingError(
                f"strip {strip.id}: only {n} matched control points with matcher {matcher} "
                f"(at least {cfg.mcp.min_mcps} needed)"
            )
        mcps = McpSet.held_out(strip.id, table, cfg.mcp)
        network = mcps.network(camera, cfg.mcp.sigma_px)
        gsd = reference_gsd_m(ref)
        support = template_support_m(
            matcher,
            matcher_options(matcher, cfg.matchers.get(matcher, {}), cfg.frontend, gsd)[0],
            cfg.frontend.fine_upsample,
            gsd,
        )
        overlap = template_overlap(table["ref_x"], table["ref_y"], support)
        adjust_cfg, _ = systematic_settings(cfg.adjust, manifest, [strip.id], gsd, overlap)
        cpu = time.process_time()
        result = adjust(network, adjust_cfg)
        cpu = time.process_time() - cpu
        true = check_block(result, {strip.id: truth_cams[strip.id]}, terrain).to_json()
        cpu_formal = time.process_time()
        formal = formal_ground_precision(result, strip.id, terrain=terrain)
        cpu_formal = time.process_time() - cpu_formal
        cov_meas = getattr(result, "covariance_measurement", None)
        meas = (
            formal_ground_precision(result, strip.id, terrain=terrain, covariance=cov_meas)
            if cov_meas is not None
            else formal
        )
        groups = result.variance.get("groups") or []
        rows.append(
            {
                "strip": strip.id,
                "n_mcps": int(n),
                "true_m": true["geoloc_rmse_m"],
                "formal_m": formal["rms_m"],
                "formal_meas_m": meas["rms_m"],
                "ratio": true["geoloc_rmse_m"] / formal["rms_m"],
                "ratio_meas": true["geoloc_rmse_m"] / meas["rms_m"],
                "sigma0": result.sigma0,
                "sigma0_before_vce": result.variance.get("sigma0_before"),
                "measurement_overlap": result.variance.get("measurement_overlap"),
                "vce_factors": {
                    g["group"]: round(float(g["sigma_scale"]), 4)
                    for g in groups
                    if g.get("estimated")
                },
                "rmse_px": result.metrics["all"]["after"]["rmse_px"],
                "check_px": (result.metrics.get("check") or {}).get("after", {}).get("rms_px"),
                "check_m": (result.metrics.get("check") or {}).get("after", {}).get("rms_m"),
                "check_tiles": (result.metrics.get("check") or {}).get("tiles"),
                "warnings": list(result.warnings),
                "self_calibration_check": result.diagnostics.get("self_calibration_check"),
                "systematic": None if result.consider is None else result.consider.summary(),
                "adjust_cpu_s": cpu,
                "formal_cpu_s": cpu_formal,
                "_result": result,
                "_dem": dem,
            }
        )
    return rows


def _with_excess(rows: list[dict[str, Any]]) -> None:
    """Add each matcher's excess error (the three-cornered hat) to the rows of one scene."""
    import itertools

    from planetref.adjust.precision import camera_agreement, excess_error

    by_strip: dict[str, dict[str, dict[str, Any]]] = {}
    for r in rows:
        if "_result" in r:
            by_strip.setdefault(r["strip"], {})[r["matcher"]] = r
    for strip, by_matcher in by_strip.items():
        pairs = [
            camera_agreement(
                by_matcher[a]["_result"],
                by_matcher[b]["_result"],
                strip,
                matchers=(a, b),
                terrain=by_matcher[a]["_dem"],
            )
            for a, b in itertools.combinations(by_matcher, 2)
        ]
        excess = excess_error(pairs)
        for name, r in by_matcher.items():
            r["agreement"] = [
                {"other": p.matchers[1 - p.matchers.index(name)], "ratio": p.ratio}
                for p in pairs
                if name in p.matchers
            ]
            if name in excess:
                r["excess_m"] = excess[name]
                r["formal_with_excess_m"] = float(np.hypot(r["formal_m"], excess[name]))
                r["ratio_with_excess"] = r["true_m"] / r["formal_with_excess_m"]
    for r in rows:
        r.pop("_result", None)
        r.pop("_dem", None)


def _scene_rows(
    runs: Path, spec: str, seed: int, matchers: list[str], weights: str | None, cfg: Any
) -> list[dict[str, Any]]:
    """The rows of one scene and seed: each matcher's run (made if missing), measured."""
    from planetref.errors import PlanetrefError
    from planetref.pipeline.georef import run_georef

    scene = _scene(runs, spec, seed)
    out: list[dict[str, Any]] = []
    for matcher in matchers:
        run_dir = runs / f"{scene.name}-{matcher}"
        row: dict[str, Any] = {"scene": spec, "seed": seed, "matcher": matcher}
        try:
            if not (run_dir / "report.json").is_file():
                run_georef(
                    scene, matcher, run_dir, weights_dir=weights, progress=False, overwrite=True
                )
            strips = measure(scene, run_dir, cfg, matcher)
        except PlanetrefError as exc:
            out.append(row | {"failed": str(exc)})
            continue
        out.extend(row | s for s in strips)
    _with_excess(out)
    return out


def over_seeds(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per scene, matcher and strip over the seeds that did not fail: RMS true and formal
    error, their ratio, and the smallest and largest per-seed ratio."""
    groups: dict[tuple[str, str, str], list[dict[str, Any]]] = {}
    for r in rows:
        if "failed" not in r:
            groups.setdefault((r["scene"], r["matcher"], r.get("strip", "")), []).append(r)
    out = []
    for (scene, matcher, strip), items in groups.items():
        true = np.array([i["true_m"] for i in items])
        formal = np.array([i["formal_m"] for i in items])
        ratio = true / formal
        both = [i.get("formal_with_excess_m") for i in items]
        with_excess = (
            {}
            if any(b is None for b in both)
            else {
                "ratio_with_excess": float(
                    np.sqrt(np.mean(true**2) / np.mean(np.square(np.array(both, float))))
                ),
                "ratio_with_excess_min": float(np.min(true / np.array(both, float))),
                "ratio_with_excess_max": float(np.max(true / np.array(both, float))),
            }
        )
        out.append(
            {
                "scene": scene,
                "matcher": matcher,
                "strip": strip,
                "seeds": [i["seed"] for i in items],
                "true_rms_m": float(np.sqrt(np.mean(true**2))),
                "formal_rms_m": float(np.sqrt(np.mean(formal**2))),
                "ratio": float(np.sqrt(np.mean(true**2) / np.mean(formal**2))),
                "ratio_min": float(ratio.min()),
                "ratio_max": float(ratio.max()),
                **with_excess,
            }
        )
    return out


def verdict(ratio: float) -> str:
    """What a true / formal ratio says: calibrated within 0.5-2, else which way it is off."""
    if not np.isfinite(ratio):
        return "not measured"
    if ratio > 2.0:
        return "NOT calibrated: the formal precision is optimistic (goal 0.5-2)"
    if ratio < 0.5:
        return "NOT calibrated: the formal precision is pessimistic (goal 0.5-2)"
    return "calibrated (0.5-2)"


def figures(rows: list[dict[str, Any]]) -> dict[str, dict[str, object]]:
    """The benchmarks page's figures: per scene, matcher and strip, true, formal, ratio."""
    out: dict[str, dict[str, object]] = {}
    seeds = {r["seed"] for r in rows}
    for r in rows:
        key = f"{r['scene']} {r['matcher']}" + (f" {r['strip']}" if r.get("strip") else "")
        if len(seeds) > 1:
            key = f"{key} seed {r['seed']}"
        if "failed" in r:
            out[f"{key}: failed"] = {"value": str(r["failed"])[:120]}
            continue
        out[f"{key}: true error"] = {"value": r["true_m"], "unit": "m"}
        out[f"{key}: formal precision"] = {"value": r["formal_m"], "unit": "m"}
        out[f"{key}: true / formal"] = {"value": r["ratio"], "note": verdict(r["ratio"])}
        if "ratio_with_excess" in r:
            out[f"{key}: excess error (three-cornered hat)"] = {
                "value": r["excess_m"],
                "unit": "m",
            }
            out[f"{key}: true / formal with excess"] = {
                "value": r["ratio_with_excess"],
                "note": verdict(r["ratio_with_excess"]),
            }
    if len(seeds) > 1:
        for g in over_seeds(rows):
            key = f"{g['scene']} {g['matcher']}" + (f" {g['strip']}" if g["strip"] else "")
            out[f"{key}: true / formal over {len(g['seeds'])} seeds"] = {
                "value": g["ratio"],
                "note": (
                    f"RMS true {g['true_rms_m']:.2f} m / RMS formal {g['formal_rms_m']:.2f} m; "
                    f"per seed {g['ratio_min']:.2f}-{g['ratio_max']:.2f}"
                ),
            }
            if "ratio_with_excess" in g:
                out[f"{key}: true / formal with excess over {len(g['seeds'])} seeds"] = {
                    "value": g["ratio_with_excess"],
                    "note": (
                        f"per seed {g['ratio_with_excess_min']:.2f}-"
                        f"{g['ratio_with_excess_max']:.2f}"
                    ),
                }
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="*", default=["tiny:moderate", "tiny:hard"])
    parser.add_argument("--matchers", nargs="*", default=["sift", "ncc"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--seeds", type=int, nargs="*", default=None)
    parser.add_argument("--runs", default="bench_calibration_runs")
    parser.add_argument("--set", dest="sets", action="append", default=[])
    parser.add_argument("--weights-dir", default=os.environ.get("PLANETREF_WEIGHTS"))
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    from planetref.pipeline.config import GeorefConfig

    runs = Path(args.runs).resolve()
    runs.mkdir(parents=True, exist_ok=True)
    cfg = _override(GeorefConfig(), args.sets)
    out: list[dict[str, Any]] = []
    seeds = args.seeds or [args.seed]
    for seed in seeds:
        for spec in args.scenes:
            out.extend(_scene_rows(runs, spec, seed, args.matchers, args.weights_dir, cfg))
    if args.json:
        from machine import describe

        print(
            json.dumps(
                {
                    "benchmark": "bench_calibration",
                    "title": "Calibration: true vs formal ground error",
                    "date": datetime.now(UTC).isoformat(timespec="seconds"),
                    "machine": {**describe(), "platform": platform.platform()},
                    "command": "python benchmarks/bench_calibration.py " + " ".join(sys.argv[1:]),
                    "figures": figures(out),
                    "rows": out,
                    "over_seeds": over_seeds(out) if len(seeds) > 1 else [],
                },
                indent=1,
            )
        )
        return 0
    print(
        f"{'scene':16} {'matcher':8} {'strip':8} {'true_m':>7} {'formal_m':>8} {'ratio':>6} "
        f"{'meas_m':>7} {'r_meas':>6} {'check_z':>7} {'s0_pre':>6} {'excess':>6} "
        f"{'r_exc':>6}  vce factors"
    )
    for r in out:
        if "failed" in r:
            print(f"{r['scene']:16} {r['matcher']:8} failed: {r['failed'][:80]}")
            continue
        s0 = r["sigma0_before_vce"]
        cz = (r.get("check_tiles") or {}).get("rms_normalised")
        print(
            f"{r['scene']:16} {r['matcher']:8} {r['strip']:8} {r['true_m']:7.2f} "
            f"{r['formal_m']:8.2f} {r['ratio']:6.2f} {r['formal_meas_m']:7.2f} "
            f"{r['ratio_meas']:6.2f} {'   none' if cz is None else f'{cz:7.2f}'} "
            f"{s0 if s0 is None else f'{s0:6.2f}'} "
            f"{r.get('excess_m', math.nan):6.2f} {r.get('ratio_with_excess', math.nan):6.2f}  "
            + ", ".join(f"{k} x{v:.3g}" for k, v in r["vce_factors"].items())
        )
    if len(seeds) > 1:
        print(f"over seeds {seeds}: RMS true, RMS formal, their ratio, per-seed ratio range")
        for g in over_seeds(out):
            print(
                f"{g['scene']:16} {g['matcher']:8} {g['strip']:8} {g['true_rms_m']:7.2f} "
                f"{g['formal_rms_m']:8.2f} {g['ratio']:6.2f}  "
                f"{g['ratio_min']:.2f}-{g['ratio_max']:.2f} ({len(g['seeds'])} seeds)"
                + (
                    f"; with excess {g['ratio_with_excess']:.2f} "
                    f"({g['ratio_with_excess_min']:.2f}-{g['ratio_with_excess_max']:.2f})"
                    if "ratio_with_excess" in g
                    else ""
                )
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
