"""``compare``: one scene, several matchers, everything else identical.

The same initial cameras and the same fixed-parameter adjustment for every matcher, so
the matcher is the only variable.

Output directory::

    run.json, config.json, planetref.log
    report.json            {"scene", "runs": {matcher: georef report (+ "agreement":
                           its excess error)}, "skipped": {...},
                           "agreement": {"pairs": [...], "excess_m": {...}}}
                           (a run whose matcher ran but failed, e.g. too few MCPs, is
                           in "runs" with "failed": why; "skipped": could not run;
                           "agreement": every pair of matchers' adjusted cameras
                           compared, no truth needed, and each matcher's error
                           beyond its own covariance from them; see _agreement)
    report.md, report.html the report (scene, settings, definitions, tables, figures,
                           warnings); the HTML is one self-contained file
    matching.csv, adjustment.csv, truth.csv, funnel.csv, timing.csv
    tables/*.tex           the same tables as LaTeX booktabs
    figures/headline.png   the headline metrics per matcher
    figures/<matcher>_*.png  copies of each run's figures
    runs/<matcher>/        each georef run directory
"""

from __future__ import annotations

import itertools
import json
import logging
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from planetref.adjust.precision import excess_error
from planetref.errors import (
    InputError,
    MatcherFailedError,
    MatchingError,
    PlanetrefError,
)
from planetref.pipeline.config import GeorefConfig
from planetref.pipeline.rundir import RunDir, config_digest
from planetref.pipeline.systematic import declared_uncertainty
from planetref.scene.inputs import scene_input_files
from planetref.scene.inputs import scene_path as scene_path_of
from planetref.scene.manifest import load_manifest

__all__ = [
    "CompareOutcome",
    "SeedsOutcome",
    "resolve_matchers",
    "run_compare",
    "summarize_compares",
]

log = logging.getLogger(__name__)


@dataclass
class CompareOutcome:
    """What :func:`run_compare` returns.

    Attributes:
        report: The combined report.json content.
        run_dir: The output directory.
        tables_markdown: The Markdown of both tables (as printed by ``demo``).
        files: Paths of the outputs.
    """

    report: dict[str, Any]
    run_dir: Path
    tables_markdown: str
    files: dict[str, Any] = field(default_factory=dict)


@dataclass
class SeedsOutcome:
    """What :func:`summarize_compares` returns.

    Attributes:
        summary: The rankings over the scenes.
        folder: Where the summary was written.
        markdown: The summary as Markdown (what ``demo --seeds`` prints).
        files: Paths of the outputs.
    """

    summary: Any
    folder: Path
    markdown: str
    files: dict[str, str] = field(default_factory=dict)


def summarize_compares(
    compares: dict[str, str | os.PathLike[str]], out: str | os.PathLike[str], *, title: str = ""
) -> SeedsOutcome:
    """Rankings over several comparisons (scenes, e.g. seeds of one preset).

    Reads each comparison's report.json and writes ``seeds.json``, ``seeds.csv``,
    ``pairs.csv``, ``report.md``, ``report.html`` and ``figures/headline_seeds.png``
    into ``out`` (:func:`planetref.report.seeds.write_seeds_report`).

    Args:
        compares: Scene label (e.g. ``"seed0"``) -> its comparison folder.
        out: Output folder.
        title: The report's title.

    Raises:
        MissingFileError: A comparison folder without report.json.
    """
    from planetref.report.seeds import summarize_seeds, write_seeds_report
    from planetref.runtime.jsonfile import read_json

    reports = {
        k: read_json(Path(v) / "report.json", "comparison report") for k, v in compares.items()
    }
    summary = summarize_seeds(reports)
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    paths = write_seeds_report(
        summary, folder, title=title, links={k: str(v) for k, v in compares.items()}
    )
    md = paths.pop("markdown")
    return SeedsOutcome(summary=summary, folder=folder, markdown=md, files=paths)


def resolve_matchers(
    spec: str | Sequence[str], weights_dir: str | os.PathLike[str] | None
) -> tuple[list[str], dict[str, str]]:
    """Matcher names from ``"a,b,c"``, ``"all"`` or a list; and those skipped, with why.

    ``all`` means every registered matcher; those whose weights are missing are listed
    as skipped with the missing files, never silently left out.

    Raises:
        InputError: An unknown matcher name (the message lists the valid ones).
    """
    from planetref.matching.registry import available_matchers

    avail = {name: (present, missing) for name, present, missing in available_matchers(weights_dir)}
    names = (
        list(avail)
        if spec == "all" or spec == ["all"]
        else (
            [s.strip() for s in spec.split(",") if s.strip()]
            if isinstance(spec, str)
            else list(spec)
        )
    )
    unknown = [n for n in names if n not in avail]
    if unknown or not names:
        raise InputError(
            f"unknown matcher(s) {unknown or names}; valid: {', '.join(avail)} or 'all'"
        )
    run, skipped = [], {}
    for n in names:
        present, missing = avail[n]
        if present:
            run.append(n)
        else:
            fix = f"planetref weights download {n}" + (" --unverified" if n == "loftr" else "")
            skipped[n] = "weights missing: " + ", ".join(str(m) for m in missing) + f" (run: {fix})"
    return run, skipped


def run_compare(
    scene: str | os.PathLike[str],
    matchers: str | Sequence[str],
    out: str | os.PathLike[str],
    *,
    config: GeorefConfig | None = None,
    weights_dir: str | os.PathLike[str] | None = None,
    overwrite: bool = False,
    progress: bool = True,
    executor: Any = None,
    device: str = "cpu",
) -> CompareOutcome:
    """Run georef once per matcher with identical settings and tabulate the results.

    A matcher that could not run (missing weights, a matcher that cannot be built) is
    listed under ``skipped`` with the reason. A matcher that ran but whose run failed
    (too few MCPs, a degenerate adjustment) stays in ``runs``: its report has ``failed``
    (why), NCP and SDU as matched, its failed tiles and its funnel, and no adjustment;
    the tables keep its rows. The others go on.

    Args:
        scene: ``scene.toml`` or its folder.
        matchers: ``"a,b,c"``, ``"all"`` or a list of matcher names.
        out: Output directory.
        config: Settings (defaults when ``None``).
        weights_dir: Folder of pretrained weights.
        overwrite: Replace a different previous run in ``out``.
        progress: Show progress bars.
        executor: Where the tiles are matched (see :func:`~planetref.pipeline.georef.
            run_georef`); a spec string starts one executor (e.g. one Dask cluster) that
            serves every matcher and is closed at the end.
        device: Torch device of the learned matchers (see :func:`~planetref.pipeline.
            georef.run_georef`).

    Raises:
        InputError: Unknown matcher names, a bad scene, or an output directory holding
            another run.
    """
    from planetref.runtime.execute import Executor, make_executor

    owned = executor is not None and not isinstance(executor, Executor)
    ex = make_executor(executor)
    try:
        return _run_compare(
            scene, matchers, out, config, weights_dir, overwrite, progress, ex, device
        )
    finally:
        if owned:
            ex.close()


def _run_compare(
    scene: str | os.PathLike[str],
    matchers: str | Sequence[str],
    out: str | os.PathLike[str],
    config: GeorefConfig | None,
    weights_dir: str | os.PathLike[str] | None,
    overwrite: bool,
    progress: bool,
    executor: Any,
    device: str = "cpu",
) -> CompareOutcome:
    from planetref.pipeline.georef import run_georef
    from planetref.report.georef import (
        excess_block,
        figure_headline_bars,
        write_compare_report,
    )

    cfg = config or GeorefConfig()
    names, skipped = resolve_matchers(matchers, weights_dir)
    scene_path = scene_path_of(scene)
    if not scene_path.is_file():
        raise InputError("scene manifest not found", path=scene_path)

    manifest, root = load_manifest(scene_path)
    identity = {"scene": str(scene_path), "config": config_digest(cfg.identity_json())}
    if device != "cpu":  # a CPU run's identity stays what it was
        identity["device"] = device
    run = RunDir(
        out,
        "compare",
        identity,
        overwrite=overwrite,
        inputs=[scene_path, *scene_input_files(manifest, root)],
    )
    runs: dict[str, Any] = {}
    with run.logging_to_file():
        run.write_json(
            "config.json",
            {"scene": str(scene_path), "matchers": names, "skipped": skipped, **cfg.to_json()},
        )
        for name in names:
            log.info("compare: running %s", name)
            try:
                outcome = run_georef(
                    scene_path,
                    name,
                    run.path / "runs" / name,
                    config=cfg,
                    weights_dir=weights_dir,
                    overwrite=overwrite,
                    progress=progress,
                    executor=executor,
                    device=device,
                )
            except MatcherFailedError as exc:
                log.warning("compare: %s failed: %s", name, exc)
                runs[name] = exc.report or {
                    "matcher": name,
                    "failed": str(exc),
                    "matching": {"ccds": {}, "ncp": 0, "sdu_pct": 0.0},
                    "adjustment": None,
                    "check": None,
                }
                _collect_figures(run.path / "runs" / name, run, name)
                continue
            except PlanetrefError as exc:  # missing weights and the like: it did not run
                log.warning("compare: %s skipped: %s", name, exc)
                skipped[name] = str(exc)
                continue
            runs[name] = outcome.report
            adj = outcome.report.get("adjustment") or {}
            log.info(
                "compare: %s done in %.0f s: NCP %s, RMSE %.3g px",
                name,
                (outcome.report.get("timing_s") or {}).get("total", float("nan")),
                outcome.report["matching"].get("ncp"),
                adj.get("rmse_px", float("nan")),
            )
            _collect_figures(outcome.run_dir, run, name)
        scene_name = next(
            (r["scene"] for r in runs.values() if "scene" in r), scene_path.parent.name
        )
        agreement = _agreement(scene_path, run.path, runs)
        excess = excess_error(agreement)
        for name, ex in excess.items():
            runs[name]["agreement"] = excess_block(runs[name], ex)
        report = {
            "scene": scene_name,
            "runs": runs,
            "skipped": skipped,
            "agreement": {
                "pairs": [_agreement_json(a) for a in agreement],
                "excess_m": excess,
            },
        }
        run.write_json("report.json", report)
        headline = None
        if runs:
            headline = figure_headline_bars(
                runs, run.file("figures", "headline.png"), scene=scene_name
            )
        context = _context(scene_path, scene_name, cfg, runs, run.path, headline)
        context.agreement = agreement
        tables = write_compare_report(runs, skipped, run.path, context)
        files = {k: v for k, v in tables.items() if k != "markdown"}
        if headline is not None:
            files["headline"] = str(headline)
        ok = [n for n, r in runs.items() if not r.get("failed")]
        if not ok:  # the report keeps every failed row and why; the command fails in one line
            why = {**{n: r["failed"] for n, r in runs.items()}, **skipped}
            first = next(iter(why.items()), ("", "no matcher to run"))
            raise MatchingError(
                f"every matcher failed ({len(why)}); the first, {first[0]}: "
                f"{' '.join(str(first[1]).split())} (see {run.path / 'report.md'})"
            )
    return CompareOutcome(
        report=report, run_dir=run.path, tables_markdown=tables["markdown"], files=files
    )


_FIGURE_CAPTIONS = {
    "tile_matches": "Fig. 2 (matches of one tile, coarse and fine stage side by side) for "
    "the tiles with the most, the median and the fewest verified matches; green: kept, "
    "red: rejected",
    "mcp_distribution": "Fig. 3 (MCP distribution) per CCD in image coordinates, with the "
    "coarsest SDU grid (occupied cells shaded)",
    "residuals": "Fig. 4 (residual vectors after the adjustment) per CCD; black: check "
    "points; the title says whether neighbouring residuals correlate",
}


def _agreement(scene_path: Path, out: Path, runs: dict[str, Any]) -> list[Any]:
    """Every pair of matchers' adjustments of each strip, compared with no truth.

    :func:`planetref.adjust.precision.camera_agreement` on the adjustments the runs saved
    (``runs/<matcher>/<strip>/adjustment``), over the true error's image grid at the
    reference DEM. Strips adjusted jointly (``[campaign] adjust_together``), failed runs
    and runs without a saved adjustment are left out; an empty list when fewer than two
    matchers have one.
    """
    from planetref.adjust.precision import camera_agreement
    from planetref.pipeline.artefacts import load_result
    from planetref.scene.inputs import open_reference

    ok = [n for n, r in runs.items() if not r.get("failed")]
    strips = sorted({s for n in ok for s in (runs[n].get("strips") or {})})
    results: dict[str, dict[str, Any]] = {}
    for sid in strips:
        for n in ok:
            res = load_result(out / "runs" / n / sid / "adjustment")
            if res is not None and sid in getattr(res, "cameras", {}):
                results.setdefault(sid, {})[n] = res
    if not any(len(v) > 1 for v in results.values()):
        return []
    manifest, root = load_manifest(scene_path)
    _, dem = open_reference(manifest, root, warnings=[])
    out_list = []
    for sid, by_matcher in results.items():
        for a, b in itertools.combinations(by_matcher, 2):
            out_list.append(
                camera_agreement(by_matcher[a], by_matcher[b], sid, matchers=(a, b), terrain=dem)
            )
    log.info("compare: agreement of %d pair(s) of adjustments", len(out_list))
    return out_list


def _agreement_json(a: Any) -> dict[str, Any]:
    return {
        "strip": a.camera_id,
        "matchers": list(a.matchers),
        "diff_m": a.diff_m,
        "own_m": list(a.own_m),
        "predicted_m": a.predicted_m,
        "ratio": a.ratio,
        "n": a.n,
    }


def _raster_fact(path: Path) -> str:
    import rasterio

    try:
        with rasterio.open(path) as ds:
            crs = ds.crs.to_string() if ds.crs else "no CRS"
            if len(crs) > 60:
                crs = (ds.crs.to_dict() or {}).get("proj", "") or crs[:57] + "..."
            return (
                f"`{path.name}`, {ds.width} x {ds.height} px, "
                f"{abs(ds.res[0]):.4g} x {abs(ds.res[1]):.4g} m/px, {crs}"
            )
    except Exception as exc:
        return f"`{path}` (not readable: {exc})"


def _context(
    scene_path: Path,
    scene_name: str,
    cfg: GeorefConfig,
    runs: dict[str, Any],
    out: Path,
    headline: Path | None,
) -> Any:
    """What the comparison report says about the scene, the settings and the figures."""
    from planetref.report.georef import CompareContext, paper_departures
    from planetref.report.tables import funnel_from_journal, funnel_from_report

    ctx = CompareContext(scene=scene_name, scene_path=str(scene_path), headline=headline)
    ctx.scene_facts.append(("manifest", f"`{scene_path}`"))
    try:
        manifest, root = load_manifest(scene_path)
    except PlanetrefError as exc:
        ctx.scene_facts.append(("scene", f"not readable again: {exc}"))
        manifest = None
    if manifest is not None:
        ref = manifest.reference
        ctx.scene_facts += [
            ("body", manifest.body.name),
            ("reference ortho", _raster_fact(Path(manifest.resolve(root, ref.ortho)))),
            ("reference DEM", _raster_fact(Path(manifest.resolve(root, ref.dem)))),
        ]
        for strip in manifest.strips:
            ctx.scene_facts.append(
                (f"strip {strip.id}", ", ".join(c.name for c in strip.ccds) + " (left to right)")
            )
        ctx.simulated = manifest.truth is not None
        if manifest.truth is not None and manifest.truth.config:
            from planetref.scene.realism import read_realism

            try:
                realism = read_realism(manifest.resolve(root, manifest.truth.config))
            except PlanetrefError as exc:
                ctx.scene_facts.append(("simulation config", f"not readable: {exc}"))
            else:
                ctx.realism_level = realism.level
                ctx.realism_sources = [tuple(v) for v in realism.values]
                ctx.easier_than_real = list(realism.easier_than_real)
    conf = cfg.to_json()
    fe, mcp = conf.get("frontend", {}), conf.get("mcp", {})
    ctx.common_settings += [
        ("front-end protocol", _protocol_line(fe)),
        ("front end", ", ".join(f"{k} = {v}" for k, v in fe.items() if not isinstance(v, dict))),
        ("MCPs", ", ".join(f"{k} = {v}" for k, v in mcp.items() if not isinstance(v, dict))),
        ("adjustment", "see `runs/<matcher>/<strip>/adjustment/config.json`"),
        *(("departs from the seed paper", d) for d in paper_departures(conf)),
        *(
            [
                (
                    "per-tile cap",
                    f"`max_mcps_per_tile = {fe['max_mcps_per_tile']}`: NCP counts the "
                    "verified MCPs before this cap (less the MCP stage's duplicates), SDU the "
                    "MCPs kept after it; the funnel table shows both",
                )
            ]
            if fe.get("max_mcps_per_tile")
            else []
        ),
        ("full configuration", "`config.json` (and `runs/<matcher>/config.json`)"),
    ]
    for name, rep in runs.items():
        run_dir = out / "runs" / name
        ctx.matcher_settings[name] = _matcher_settings(name, cfg, run_dir)
        journals = [run_dir / sid / "tiles.jsonl" for sid in rep.get("strips") or {}]
        for sid in rep.get("strips") or {}:
            try:
                adj = json.loads((run_dir / sid / "adjustment" / "report.json").read_text())
            except (OSError, ValueError):
                continue
            ctx.output_warnings.setdefault(name, []).extend(adj.get("output_warnings") or [])
        ctx.funnels[name] = funnel_from_report(rep) or funnel_from_journal(journals)
        figs = []
        for kind in ("tile_matches", "mcp_distribution", "residuals"):
            for png in sorted((out / "figures").glob(f"{name}_*_{kind}.png")):
                strip = png.stem[len(name) + 1 : -len(kind) - 1]
                figs.append((png, f"{name}, {strip}: {_FIGURE_CAPTIONS[kind]}"))
        ctx.figures[name] = figs
    ctx.funnels = {k: v for k, v in ctx.funnels.items() if v}
    return ctx


def _protocol_line(fe: dict[str, Any]) -> str:
    """Which front-end protocol ran, and what that means for OR."""
    if fe.get("protocol") == "paper":
        return (
            "`paper` (the seed's Sec. 3.2: tiles downsampled to the reference GSD, "
            f"RANSAC at {fe.get('ransac_threshold_ref_px')} reference px, so the "
            "adjustment's 3 x RMSE rule does the rejecting): OR compares with the seed's "
            "4.1-7.3 %"
        )
    return (
        "`default` (planetref's: RANSAC at "
        f"{fe.get('ransac_threshold_ref_px')} reference px keeps only matches far inside the "
        "adjustment's 3 x RMSE, so OR sees few blunders; the true OR column measures them; "
        '`frontend.protocol = "paper"` for an OR comparable with the seed\'s)'
    )


def _matcher_settings(name: str, cfg: GeorefConfig, run_dir: Path) -> dict[str, Any]:
    """The options a matcher ran with beyond the shared settings.

    Its entry of the configuration's ``matchers`` table, and what the pipeline derives
    for it from the matcher's declarations (e.g. NCC's template spacing and search radii).
    """
    out: dict[str, Any] = {}
    try:
        conf = json.loads((run_dir / "config.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        conf = {}
    out.update({f"option {k}": v for k, v in (conf.get("matchers") or {}).get(name, {}).items()})
    # The options the front end derives (pixel lengths on the fine grid, search radii),
    # read from the matcher's own declarations: shown where they add to the user's.
    from planetref.frontend.matchers import matcher_options

    try:
        manifest, root = load_manifest(Path(conf.get("scene", "")))
        import rasterio

        with rasterio.open(manifest.resolve(root, manifest.reference.ortho)) as ds:
            gsd = float(abs(ds.res[0]))
        fe, _ = declared_uncertainty(cfg.frontend, manifest)
        fine, coarse = matcher_options(name, cfg.matchers.get(name, {}), fe, gsd)
        user = (conf.get("matchers") or {}).get(name, {})
        out.update({f"fine {k}": v for k, v in fine.items() if user.get(k) != v})
        out.update({f"coarse {k}": v for k, v in (coarse or {}).items()})
    except (PlanetrefError, OSError, ValueError) as exc:
        out["derived options"] = f"not available ({exc})"
    return out


def _collect_figures(run_dir: Path, run: RunDir, matcher: str) -> None:
    for png in sorted((run_dir / "figures").glob("*.png")):
        shutil.copyfile(png, run.file("figures", f"{matcher}_{png.name}"))
