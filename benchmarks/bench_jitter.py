"""Does the jitter stage recover the truth's jitter and lower the true error?

For a simulated scene (default: hiric-strip with the truth's jitter raised to 3-5 urad
at 2-15 Hz, ``--jitter-config``) and each matcher, the script georeferences the scene
once with the default settings (``planetref georef``, jitter stage off; an existing run
folder under ``--runs`` is reused), reads back the run's MCPs and check flags and
adjusts them twice with the run's adjustment settings: the seed's node model alone, and
with ``[adjust.jitter] enabled = true`` (``--set adjust.jitter.KEY=VALUE`` overrides).
It prints per strip:

* per true jitter component (axis, amplitude, frequency, phase from the scene's truth):
  the amplitude and phase recovered by the node model alone and by the jitter stage.
  The recovered pointing is the true jitter plus the adjusted camera's pointing error
  as the image sees it (:func:`planetref.adjust.jitter.line_of_sight_difference` of the
  true and adjusted cameras at the middle CCD's centre pixel; attitude errors that only
  compensate position errors cancel); amplitude and phase come from a joint least-squares
  fit of every component's sinusoid and a quadratic to the pointing error, added to
  the true component (``error_urad_*``: the error's amplitude at that frequency);
  ``below_limit`` says whether the component lies below the reported resolution limit;
* ``true_m``: the RMS ground error against the true camera (the pipeline's true-error
  metric), without and with the jitter stage, and the change in per cent; when the
  stage's check rule rejects the dense solution, also that solution's
  (``true_m_jitter_not_kept``);
* ``formal_urad`` / ``true_urad``: the estimated jitter's formal sigma and its true error
  (the pointing error after the stage, a quadratic removed), roll and pitch;
* ``formal_m_*``: the formal ground precision (check_block's, the true error's formal
  counterpart);
* yaw, which the image barely sees: ``yaw_error_urad_rms_*`` the yaw error of the
  node model and after the stage, ``yaw_stage_urad_rms`` what the stage changed of
  the node model's yaw, and ``true_m_*_yaw_removed`` the true error of the same camera
  with its yaw error taken off (:func:`without_yaw_error`): what yaw costs on the ground.

With ``--ties`` both adjustments also get the strip's CCD-overlap tie points (the run
is made with ``[frontend.ccd_overlap] enabled = true``; an existing run must hold
``<strip>/ccd_overlap_ties.csv``), as georef adds them.

Usage::

    python benchmarks/bench_jitter.py [--runs DIR] [--matchers ncc]
        [--scenes strong nojitter] [--ties] [--json]

Scenes: ``strong`` (hiric-strip with --jitter-config), ``nojitter`` (hiric-strip with
``jitter = []``), or a path to a simulated scene folder.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

STRONG = """# hiric-strip with the truth's jitter raised to 3-5 urad at 2-15 Hz (issue 31)
[[jitter]]
axis = "roll"
amplitude_urad = 4.0
frequency_hz = 2.3
[[jitter]]
axis = "pitch"
amplitude_urad = 3.0
frequency_hz = 6.1
[[jitter]]
axis = "yaw"
amplitude_urad = 5.0
frequency_hz = 3.7
[[jitter]]
axis = "roll"
amplitude_urad = 3.0
frequency_hz = 11.3
[[jitter]]
axis = "pitch"
amplitude_urad = 4.0
frequency_hz = 14.7
"""
NOJITTER = "jitter = []\n"
AXES = ("roll", "pitch", "yaw")


def _scene(runs: Path, spec: str) -> Path:
    if Path(spec).is_dir():
        return Path(spec)
    from planetref.simulate.config import load_config
    from planetref.simulate.scene import simulate_scene

    text = {"strong": STRONG, "nojitter": NOJITTER}[spec]
    out = runs / "scenes" / f"hiric-strip-{spec}"
    if not (out / "scene.toml").is_file():
        runs.mkdir(parents=True, exist_ok=True)
        override = runs / f"{spec}.toml"
        override.write_text(text, encoding="utf-8")
        simulate_scene(load_config("hiric-strip", override), out)
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


def fit_components(t: np.ndarray, y: np.ndarray, freqs: list[float]) -> list[tuple[float, float]]:
    """``(amplitude, phase rad)`` of ``a sin(2 pi f t + phase)`` per frequency (joint fit)."""
    cols = [t**k for k in range(3)]
    for f in freqs:
        cols += [np.sin(2 * np.pi * f * t), np.cos(2 * np.pi * f * t)]
    coef = np.linalg.lstsq(np.stack(cols, 1), y, rcond=None)[0][3:]
    return [
        (float(np.hypot(s, c)), float(np.arctan2(c, s)))
        for s, c in zip(coef[0::2], coef[1::2], strict=True)
    ]


def true_m(camera: Any, truth: Any, terrain: Any) -> float:
    """The pipeline's true error (check_block's): RMS over the CCDs of each CCD's RMS (m)."""
    from planetref.adjust.metrics import geolocation_error

    vals = [
        geolocation_error(camera, truth, ccd=c, terrain=terrain)["rms_m"] for c in truth.ccd_names
    ]
    return float(np.sqrt(np.mean(np.square(vals))))


def without_yaw_error(camera: Any, truth: Any, spacing: int = 32) -> Any:
    """``camera`` with its yaw error against ``truth`` taken off (rotated about its z axis).

    The camera is re-sampled on nodes ``spacing`` lines apart (exactly its trajectory,
    :func:`planetref.adjust.jitter.densify`) and each node's attitude turned by minus
    the yaw of :func:`~planetref.adjust.jitter.attitude_difference` at its line: the
    true error of the result is the camera's without what its yaw contributes.
    """
    from planetref.adjust.jitter import attitude_difference, densify
    from planetref.geometry.rotations import rotation_matrix

    if float(np.median(np.diff(camera.node_lines))) > spacing:
        camera = densify(camera, spacing)
    lines = np.asarray(camera.node_lines, np.float64)
    yaw = attitude_difference(truth, camera, lines)[:, 2]
    nodes = np.array(camera.nodes, np.float64)
    base = rotation_matrix(nodes[:, 3], nodes[:, 4], nodes[:, 5])
    jac = np.empty((len(lines), 3, 3))
    h = 1e-7
    for j in range(3):
        ang = nodes[:, 3:].copy()
        ang[:, j] += h
        pert = rotation_matrix(ang[:, 0], ang[:, 1], ang[:, 2])
        d = np.einsum("mji,mjk->mik", base, pert)
        jac[:, :, j] = (
            0.5
            * np.stack(
                [d[:, 2, 1] - d[:, 1, 2], d[:, 0, 2] - d[:, 2, 0], d[:, 1, 0] - d[:, 0, 1]], 1
            )
            / h
        )
    want = np.zeros((len(lines), 3))
    want[:, 2] = -yaw
    nodes[:, 3:] += np.linalg.solve(jac, want[:, :, None])[:, :, 0]
    return camera.replace(nodes=nodes)


def measure(
    scene: Path,
    run_dir: Path,
    cfg: Any,
    matcher: str,
    figure: Path | None = None,
    ties: bool = False,
) -> list[dict[str, Any]]:
    """Adjust a run's MCPs with and without the jitter stage; compare with the truth.

    ``figure``: also draw the jitter figure (estimate and truth) of each strip there
    (``<figure stem>_<strip>.png``). ``ties``: add the run's CCD-overlap ties
    (``<strip>/ccd_overlap_ties.csv``, a run made with ``[frontend.ccd_overlap]``) to
    both adjustments, as georef does.
    """
    from planetref.adjust.api import adjust
    from planetref.adjust.jitter import line_of_sight_difference
    from planetref.control.ground_sigma import reference_gsd_m
    from planetref.control.mcp import read_mcps
    from planetref.control.networks import (
        McpSet,
        template_overlap,
        template_support_m,
        with_overlap_ties,
    )
    from planetref.frontend.matchers import matcher_options
    from planetref.frontend.overlap import read_overlap_ties
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
    errors = json.loads((root / "truth" / "errors.json").read_text(encoding="utf-8"))
    rows = []
    for strip in manifest.strips:
        camera, _ = strip_cameras(manifest, root, strip)
        truth = truth_cams[strip.id]
        facts = errors[strip.id]
        comps = facts.get("jitter", [])
        table = read_mcps(run_dir / strip.id / "mcps.parquet")
        # The check tiles of the run (georef's rule, McpSet.held_out).
        network = McpSet.held_out(strip.id, table, cfg.mcp).network(camera, cfg.mcp.sigma_px)
        n_ties = 0
        if ties:
            tie_set = read_overlap_ties(run_dir / strip.id / "ccd_overlap_ties.csv", strip.id)
            network = with_overlap_ties(network, tie_set, cfg.frontend.ccd_overlap)
            n_ties = len(tie_set)
        gsd = reference_gsd_m(ref)
        support = template_support_m(
            matcher,
            matcher_options(matcher, cfg.matchers.get(matcher, {}), cfg.frontend, gsd)[0],
            cfg.frontend.fine_upsample,
            gsd,
        )
        overlap = template_overlap(table["ref_x"], table["ref_y"], support)
        adjust_cfg, _ = systematic_settings(cfg.adjust, manifest, [strip.id], gsd, overlap)
        jit = adjust_cfg.jitter.model_copy(update={"enabled": True, "mcp_support_m": support})
        jitter_cfg = adjust_cfg.model_copy(update={"jitter": jit})
        cpu = time.process_time()
        seed = adjust(
            network,
            adjust_cfg.model_copy(update={"jitter": jit.model_copy(update={"enabled": False})}),
        )
        cpu_seed = time.process_time() - cpu
        cpu = time.process_time()
        dense = adjust(network, jitter_cfg)
        cpu_dense = time.process_time() - cpu
        block_seed = check_block(seed, {strip.id: truth}, terrain)
        block_dense = check_block(dense, {strip.id: truth}, terrain)
        true_seed, true_dense = block_seed.geoloc_rmse_m, block_dense.geoloc_rmse_m
        summary = dense.diagnostics.get("jitter", {}).get(strip.id, {})
        series = dense.jitter.get(strip.id)
        row: dict[str, Any] = {
            "strip": strip.id,
            "n_mcps": len(table),
            "n_overlap_ties": n_ties,
            "true_m_nodes": true_seed,
            "true_m_jitter": true_dense,
            "true_change_pct": 100.0 * (true_dense - true_seed) / true_seed,
            "formal_m_nodes": block_seed.formal_rmse_m,
            "formal_m_jitter": block_dense.formal_rmse_m,
            # What the yaw error contributes: the true error with it taken off.
            "true_m_nodes_yaw_removed": true_m(
                without_yaw_error(seed.cameras[strip.id], truth), truth, terrain
            ),
            "true_m_jitter_yaw_removed": true_m(
                without_yaw_error(dense.cameras[strip.id], truth), truth, terrain
            ),
            "check_px_nodes": (seed.metrics.get("check") or {}).get("after", {}).get("rms_px"),
            "check_px_jitter": (dense.metrics.get("check") or {}).get("after", {}).get("rms_px"),
            "kept": summary.get("kept"),
            "resolution": summary.get("resolution"),
            "adjust_cpu_s_nodes": cpu_seed,
            "adjust_cpu_s_jitter": cpu_dense,
            "components": [],
        }
        series_camera = dense.cameras[strip.id]
        if series is None and summary.get("kept") is False:
            # The check rule kept the node model: measure the dense solution anyway.
            forced = adjust(
                network,
                jitter_cfg.model_copy(update={"jitter": jit.model_copy(update={"keep": "always"})}),
            )
            series_camera = forced.cameras[strip.id]
            series = forced.jitter[strip.id]
            row["true_m_jitter_not_kept"] = check_block(
                forced, {strip.id: truth}, terrain
            ).geoloc_rmse_m
            row["true_change_pct_not_kept"] = (
                100.0 * (row["true_m_jitter_not_kept"] - true_seed) / true_seed
            )
        if series is None:
            rows.append(row)
            continue
        lines = series.line
        t_true = truth.line_rates.time(lines)
        j_true = np.zeros((len(lines), 3))
        for c in comps:
            k = AXES.index(c["axis"])
            j_true[:, k] += (
                c["amplitude_urad"]
                * 1e-6
                * np.sin(2 * np.pi * c["frequency_hz"] * t_true + c["phase_rad"])
            )
        if figure is not None:
            from planetref.adjust.jitter import true_jitter
            from planetref.report.figures_adjust import figure_jitter

            figure_jitter(
                series.time_s,
                series.angles_rad * 1e6,
                series.sigma_rad * 1e6,
                figure.with_name(f"{figure.stem}_{strip.id}.png"),
                truth_urad=true_jitter(series, series_camera, truth) * 1e6,
                limit_hz=series.resolution.limit_hz,
                title=f"{scene.name}, {matcher}, {strip.id}: estimated jitter and the truth",
            )
        err_dense = line_of_sight_difference(truth, series_camera, lines)
        err_seed = line_of_sight_difference(truth, seed.cameras[strip.id], lines)
        limit = series.resolution.limit_hz
        for axis in (0, 1, 2):
            mine = [c for c in comps if c["axis"] == AXES[axis]]
            if not mine:
                continue
            freqs = [c["frequency_hz"] for c in mine]
            # The camera's pointing error at each component's frequency (a joint fit of
            # the components' sinusoids and a quadratic), added to the true component:
            # what the adjusted camera holds of it.
            e_d = fit_components(t_true, err_dense[:, axis], freqs)
            e_s = fit_components(t_true, err_seed[:, axis], freqs)
            for i, c in enumerate(mine):
                ph = c["phase_rad"]
                true = c["amplitude_urad"] * 1e-6 * np.exp(1j * ph)
                rec_d = true + e_d[i][0] * np.exp(1j * e_d[i][1])
                rec_s = true + e_s[i][0] * np.exp(1j * e_s[i][1])
                row["components"].append(
                    {
                        "axis": c["axis"],
                        "frequency_hz": c["frequency_hz"],
                        "true_amplitude_urad": c["amplitude_urad"],
                        "true_phase_deg": float(np.degrees(ph)),
                        "amplitude_urad_jitter": float(abs(rec_d)) * 1e6,
                        "phase_deg_jitter": float(np.degrees(np.angle(rec_d))),
                        "phase_error_deg_jitter": _wrap(np.degrees(np.angle(rec_d) - ph)),
                        "amplitude_urad_nodes": float(abs(rec_s)) * 1e6,
                        "phase_error_deg_nodes": _wrap(np.degrees(np.angle(rec_s) - ph)),
                        "error_urad_jitter": e_d[i][0] * 1e6,
                        "error_urad_nodes": e_s[i][0] * 1e6,
                        "below_limit": c["frequency_hz"] < limit,
                        "axis_observable": axis < 2,
                    }
                )
        # Yaw: the node model's error, and what the stage changed of it (its prior holds it).
        row["yaw_error_urad_rms_nodes"] = float(np.sqrt(np.mean(err_seed[:, 2] ** 2)) * 1e6)
        row["yaw_error_urad_rms_jitter"] = float(np.sqrt(np.mean(err_dense[:, 2] ** 2)) * 1e6)
        row["yaw_stage_urad_rms"] = float(np.sqrt(np.mean(series.angles_rad[:, 2] ** 2)) * 1e6)
        base = np.stack([t_true**k for k in range(3)], 1)
        for axis in (0, 1):
            e = err_dense[:, axis]
            e = e - base @ np.linalg.lstsq(base, e, rcond=None)[0]
            row[f"true_urad_{AXES[axis]}"] = float(np.sqrt(np.mean(e**2)) * 1e6)
            row[f"formal_urad_{AXES[axis]}"] = float(
                np.sqrt(np.mean(series.sigma_rad[:, axis] ** 2)) * 1e6
            )
        rows.append(row)
    return rows


def _wrap(deg: float) -> float:
    return float((deg + 180.0) % 360.0 - 180.0)


def figures(rows: list[dict[str, Any]]) -> dict[str, dict[str, object]]:
    """The benchmarks page's figures: true error with and without the stage, components."""
    out: dict[str, dict[str, object]] = {}
    for r in rows:
        key = f"{r['scene']} {r['matcher']} {r.get('strip', '')}".strip()
        if r.get("n_overlap_ties"):
            key += " +ties"
        if "failed" in r:
            out[f"{key}: failed"] = {"value": str(r["failed"])[:120]}
            continue
        out[f"{key}: true error, node model"] = {"value": r["true_m_nodes"], "unit": "m"}
        out[f"{key}: true error, jitter stage"] = {"value": r["true_m_jitter"], "unit": "m"}
        out[f"{key}: true error change"] = {"value": r["true_change_pct"], "unit": "%"}
        out[f"{key}: formal error, jitter stage"] = {"value": r["formal_m_jitter"], "unit": "m"}
        out[f"{key}: true error, jitter stage, yaw error removed"] = {
            "value": r["true_m_jitter_yaw_removed"],
            "unit": "m",
        }
        if "yaw_stage_urad_rms" in r:
            out[f"{key}: yaw changed by the stage (RMS)"] = {
                "value": r["yaw_stage_urad_rms"],
                "unit": "urad",
            }
        for c in r["components"]:
            if not c["axis_observable"]:
                # Yaw: the image barely sees it, and the camera's yaw against the truth is
                # mostly the node model's (hundreds of urad that only trade with its
                # position); a sinusoid fitted to it is no recovered amplitude.
                continue
            name = f"{key}: {c['axis']} {c['frequency_hz']:g} Hz"
            out[f"{name} amplitude (true {c['true_amplitude_urad']:g})"] = {
                "value": c["amplitude_urad_jitter"],
                "unit": "urad",
            }
            out[f"{name} phase error"] = {"value": c["phase_error_deg_jitter"], "unit": "deg"}
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="*", default=["strong"])
    parser.add_argument("--matchers", nargs="*", default=["ncc"])
    parser.add_argument("--runs", default="bench_jitter_runs")
    parser.add_argument("--set", dest="sets", action="append", default=[])
    parser.add_argument("--weights-dir", default=os.environ.get("PLANETREF_WEIGHTS"))
    parser.add_argument("--figure", help="draw each run's jitter figure (PNG path stem)")
    parser.add_argument(
        "--ties",
        action="store_true",
        help="add the CCD-overlap ties to both adjustments (a new run is made with them)",
    )
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    from planetref.errors import PlanetrefError
    from planetref.pipeline.config import GeorefConfig
    from planetref.pipeline.georef import run_georef

    runs = Path(args.runs).resolve()
    runs.mkdir(parents=True, exist_ok=True)
    sets = list(args.sets)
    if args.ties:
        sets.append("frontend.ccd_overlap.enabled=true")
    cfg = _override(GeorefConfig(), sets)
    out: list[dict[str, Any]] = []
    for spec in args.scenes:
        scene = _scene(runs, spec)
        for matcher in args.matchers:
            run_dir = runs / f"{scene.name}-{matcher}"
            row: dict[str, Any] = {"scene": scene.name, "matcher": matcher}
            try:
                if not (run_dir / "report.json").is_file():
                    # Defaults (jitter stage off); with --ties, the ties matched too.
                    run_georef(
                        scene,
                        matcher,
                        run_dir,
                        config=_override(GeorefConfig(), sets[len(args.sets) :]),
                        weights_dir=args.weights_dir,
                        progress=False,
                        overwrite=True,
                    )
                fig = (
                    Path(args.figure).with_name(
                        f"{Path(args.figure).stem}_{scene.name}_{matcher}.png"
                    )
                    if args.figure
                    else None
                )
                strips = measure(scene, run_dir, cfg, matcher, fig, ties=args.ties)
            except PlanetrefError as exc:
                out.append(row | {"failed": str(exc)})
                continue
            out.extend(row | s for s in strips)
    if args.json:
        from machine import describe

        print(
            json.dumps(
                {
                    "benchmark": "bench_jitter",
                    "title": "Jitter: recovered components and true error with the jitter stage",
                    "date": datetime.now(UTC).isoformat(timespec="seconds"),
                    "machine": {**describe(), "platform": platform.platform()},
                    "command": "python benchmarks/bench_jitter.py " + " ".join(sys.argv[1:]),
                    "figures": figures(out),
                    "rows": out,
                },
                indent=1,
            )
        )
        return 0
    for r in out:
        if "failed" in r:
            print(f"{r['scene']:10} {r['matcher']:8} failed: {r['failed'][:80]}")
            continue
        print(
            f"{r['scene']:10} {r['matcher']:8} {r['strip']:8} true error {r['true_m_nodes']:.3f} m"
            f" -> {r['true_m_jitter']:.3f} m ({r['true_change_pct']:+.1f} %), kept {r['kept']}, "
            f"limit {((r.get('resolution') or {}).get('limit_hz') or float('nan')):.1f} Hz"
        )
        print(
            f"    formal {r['formal_m_nodes']:.3f} -> {r['formal_m_jitter']:.3f} m; yaw error "
            f"removed: {r['true_m_nodes_yaw_removed']:.3f} -> "
            f"{r['true_m_jitter_yaw_removed']:.3f} m; yaw error RMS "
            f"{r.get('yaw_error_urad_rms_nodes', float('nan')):.1f} -> "
            f"{r.get('yaw_error_urad_rms_jitter', float('nan')):.1f} urad (stage "
            f"{r.get('yaw_stage_urad_rms', float('nan')):.2f}); {r['n_overlap_ties']} ties"
        )
        for c in r["components"]:
            print(
                f"    {c['axis']:5} {c['frequency_hz']:5.1f} Hz true "
                f"{c['true_amplitude_urad']:4.1f} urad | nodes "
                f"{c['amplitude_urad_nodes']:5.2f} urad "
                f"{c['phase_error_deg_nodes']:+6.1f} deg | jitter {c['amplitude_urad_jitter']:5.2f}"
                f" urad {c['phase_error_deg_jitter']:+6.1f} deg"
                + ("" if c["below_limit"] else " (above the limit)")
                + ("" if c["axis_observable"] else " (not observable: the node model's yaw)")
            )
        for a in ("roll", "pitch"):
            if f"true_urad_{a}" in r:
                print(
                    f"    {a}: jitter true error {r[f'true_urad_{a}']:.3f} urad, formal "
                    f"{r[f'formal_urad_{a}']:.3f} urad"
                )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
