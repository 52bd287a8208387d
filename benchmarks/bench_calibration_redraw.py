"""Is one scene's true / formal a fair draw? The same MCP layout with redrawn reference errors.

``bench_calibration.py`` compares the true ground error of one simulated scene with the
formal precision, but the true error is one draw of the scene's reference errors (a few
mosaic sources, each an offset and a warp): where the adjustment's error rests on one or
two random quantities (MCPs on part of the strip only, the rest extrapolated), one draw
says little. This script keeps a run's MCP layout, image positions, check flags and
matching errors and redraws the reference's error, then re-adjusts and compares per draw:

* every MCP's ground point is put at the true camera's ground point of its pixel plus its
  own matching error as measured on the scene (its ground error minus the scene's mosaic
  displacement there, ``truth/reference.json``) plus a new reference displacement;
* ``--field mosaic`` draws a new mosaic with the scene's own mosaic settings
  (:func:`planetref.simulate.mosaic.draw_mosaic`: per source an offset and a warp), the
  simulator's error; ``--field patch`` draws the adjustment's own model (an offset
  ``N(0, accuracy_m)`` per ``accuracy_length_m`` square of the MCPs).

The CCDs' placement errors stay the scene's (not redrawn). Printed per draw: true and
formal RMS ground error and their ratio; then the RMS over the draws and the ratio range.

Usage::

    python benchmarks/bench_calibration_redraw.py --runs DIR --scene tiny:hard
        --matcher xfeat-star [--field mosaic|patch] [--draws 12] [--json]

``DIR`` is a ``bench_calibration.py`` runs folder holding the scene and the run.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np


def _mosaic(root: Path, gsd: float) -> tuple[Any, Any, Any]:
    """The scene's mosaic sources and seams (``truth/reference.json``) and settings."""
    import tomllib

    from planetref.simulate.config import validate_config
    from planetref.simulate.mosaic import MosaicSource, Seams

    doc = json.loads((root / "truth" / "reference.json").read_text())["mosaic"]
    sources = [
        MosaicSource(
            index=s["index"],
            sun=None,  # type: ignore[arg-type]
            haze=s["haze"],
            gain=s["gain"],
            offset_m=tuple(s["offset_m"]),  # type: ignore[arg-type]
            waves=np.array(
                [[w["kx"], w["ky"], w["amp_x_m"], w["amp_y_m"], w["phase"]] for w in s["waves"]]
            ).reshape(-1, 5),
        )
        for s in doc["sources"]
    ]
    seams = Seams(
        base=np.array([s["base_x_m"] for s in doc["seams"]]),
        amplitude=np.array([s["amplitude_m"] for s in doc["seams"]]),
        wavelength=np.array([s["wavelength_m"] for s in doc["seams"]]),
        phase=np.array([s["phase"] for s in doc["seams"]]),
    )
    cfg = validate_config(tomllib.loads((root / "truth" / "config.toml").read_text()))
    return sources, seams, cfg


def _displacement(sources: list[Any], seams: Any, x: Any, y: Any) -> Any:
    """``d(p)`` of a mosaic at map points (m), ``(n, 2)``."""
    label = seams.label(x, y)
    d = np.zeros((len(x), 2))
    for s in sources:
        on = label == s.index
        if np.any(on):
            dx, dy = s.displacement(x[on], y[on])
            d[on, 0], d[on, 1] = dx, dy
    return d


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", required=True)
    parser.add_argument("--scene", default="tiny:hard")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--matcher", default="xfeat-star")
    parser.add_argument("--field", choices=["mosaic", "patch"], default="mosaic")
    parser.add_argument("--draws", type=int, default=12)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)

    import logging

    from planetref.adjust.api import adjust
    from planetref.adjust.precision import formal_ground_precision
    from planetref.control.ground_sigma import reference_gsd_m
    from planetref.control.mcp import read_mcps
    from planetref.control.network import enu_rotation
    from planetref.control.networks import McpSet
    from planetref.pipeline.config import GeorefConfig
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
    from planetref.simulate.grid import MapGrid
    from planetref.simulate.mosaic import draw_mosaic

    logging.disable(logging.WARNING)
    preset, _, difficulty = args.scene.partition(":")
    runs = Path(args.runs)
    scene = runs / "scenes" / f"{preset}-{difficulty or 'moderate'}-s{args.seed}"
    run_dir = runs / f"{scene.name}-{args.matcher}"
    cfg = GeorefConfig()
    manifest, root = load_manifest(scene_path(scene))
    ref, dem = open_reference(manifest, root)
    truth_cams, truth_dem = truth_inputs(manifest, root)
    terrain = truth_terrain(truth_dem, dem)
    strip = manifest.strips[0]
    camera, _ = strip_cameras(manifest, root, strip)
    true_cam = truth_cams[strip.id]
    table = read_mcps(run_dir / strip.id / "mcps.parquet")
    line = np.asarray(table["line"], np.float64)
    sample = np.asarray(table["sample"], np.float64)
    ccd = np.asarray(table["ccd"]).astype(str)
    mcps = McpSet.held_out(strip.id, table, cfg.mcp)  # georef's check tiles
    gsd = reference_gsd_m(ref)
    # Feature matchers only: the template overlap of area-based ones is the run's.
    adjust_cfg, _ = systematic_settings(cfg.adjust, manifest, [strip.id], gsd, 1.0)
    xyz = table.xyz()
    ground = np.zeros_like(xyz)
    for c in np.unique(ccd):
        on = ccd == c
        ground[on] = true_cam.image_to_ground(line[on], sample[on], terrain, ccd=c)
    enu = enu_rotation(ground)
    # Map coordinates of the MCPs' reference pixels, the mosaic's frame.
    mx, my = ref.pixel_to_map(table["ref_x"], table["ref_y"])
    sources, seams, sim = _mosaic(root, gsd)
    d_scene = _displacement(sources, seams, mx, my)
    err = np.einsum("nij,nj->ni", enu[:, :2, :], xyz - ground)  # east, north (m)
    own = err - d_scene  # the matching error (and DEM's): kept in every draw
    xmin, _, _, ymax = ref.bounds
    grid = MapGrid(x0=xmin, y0=ymax, res=gsd, rows=ref.shape[0], cols=ref.shape[1])
    acc = manifest.reference.accuracy_m or gsd
    patch_m = manifest.reference.accuracy_length_m or 1000.0
    centre = ground.mean(axis=0)
    en = (ground - centre) @ enu_rotation(centre[None])[0][:2].T
    rows = []
    for k in range(args.draws):
        rng = np.random.default_rng(1000 + k)
        if args.field == "mosaic":
            srcs, sms = draw_mosaic(sim.reference.mosaic, sim.photometry, grid, rng)
            d = _displacement(srcs, sms, mx, my)
        else:
            cell = np.floor(en / patch_m).astype(np.int64)
            inv = np.unique(cell, axis=0, return_inverse=True)[1].ravel()
            d = rng.normal(0.0, acc, (inv.max() + 1, 2))[inv]
        move = own + d
        pts = ground + move[:, :1] * enu[:, 0] + move[:, 1:] * enu[:, 1]
        net = mcps.network(camera, cfg.mcp.sigma_px, xyz=pts)
        res = adjust(net, adjust_cfg)
        true = check_block(res, {strip.id: true_cam}, terrain).geoloc_rmse_m
        formal = formal_ground_precision(res, strip.id, terrain=terrain)["rms_m"]
        rows.append({"draw": k, "true_m": true, "formal_m": formal, "ratio": true / formal})
        if not args.json:
            print(f"draw {k:3d}: true {true:7.2f} m, formal {formal:7.2f} m, {true / formal:5.2f}")
    t = np.array([r["true_m"] for r in rows])
    f = np.array([r["formal_m"] for r in rows])
    summary = {
        "true_rms_m": float(np.sqrt(np.mean(t**2))),
        "formal_rms_m": float(np.sqrt(np.mean(f**2))),
        "ratio": float(np.sqrt(np.mean(t**2) / np.mean(f**2))),
        "ratio_min": float(np.min(t / f)),
        "ratio_max": float(np.max(t / f)),
        "scene_matching_error_rms_m": float(np.sqrt(np.mean(own**2))),
        "n_mcps": len(line),
        "n_check": int(np.count_nonzero(mcps.check)),
    }
    key = f"{args.scene} {args.matcher} {args.field} field, {args.draws} draws"
    if args.json:
        from machine import describe

        print(
            json.dumps(
                {
                    "benchmark": "bench_calibration_redraw",
                    "title": "Calibration over redrawn reference errors (one MCP layout)",
                    "date": datetime.now(UTC).isoformat(timespec="seconds"),
                    "machine": {**describe(), "platform": platform.platform()},
                    "command": "python benchmarks/bench_calibration_redraw.py "
                    + " ".join(sys.argv[1:]),
                    "figures": {
                        f"{key}: RMS true error": {"value": summary["true_rms_m"], "unit": "m"},
                        f"{key}: RMS formal precision": {
                            "value": summary["formal_rms_m"],
                            "unit": "m",
                        },
                        f"{key}: true / formal": {
                            "value": summary["ratio"],
                            "note": f"per draw {summary['ratio_min']:.2f}-"
                            f"{summary['ratio_max']:.2f}",
                        },
                    },
                    "summary": summary,
                    "details": rows,
                },
                indent=1,
            )
        )
        return 0
    print(
        f"{key}: RMS true {summary['true_rms_m']:.2f} m, RMS formal "
        f"{summary['formal_rms_m']:.2f} m, ratio {summary['ratio']:.2f} (per draw "
        f"{summary['ratio_min']:.2f}-{summary['ratio_max']:.2f}); matching error kept "
        f"{summary['scene_matching_error_rms_m']:.2f} m RMS; {summary['n_check']} of "
        f"{summary['n_mcps']} MCPs held out"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
