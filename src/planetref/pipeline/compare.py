"""``compare``: one scene, several matchers, everything else identical.

The same initial cameras and the same fixed-parameter adjustment for every matcher, so
the matcher is the only variable.

Output directory::

    run.json, config.json, planetref.log
    report.json            {"scene", "runs": {matcher: georef report}, "skipped": {...}}
    report.md              both tables (and the true error where known)
    matching.csv, adjustment.csv, truth.csv
    figures/headline.png   bar chart of the headline metrics
    figures/<matcher>_*.png  copies of each run's figures
    runs/<matcher>/        each georef run directory
"""

from __future__ import annotations

import logging
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from planetref.errors import InputError, PlanetrefError, WeightsError
from planetref.pipeline.config import GeorefConfig
from planetref.pipeline.rundir import RunDir, config_digest

__all__ = ["CompareOutcome", "resolve_matchers", "run_compare"]

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
            skipped[n] = "weights missing: " + ", ".join(str(m) for m in missing)
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
) -> CompareOutcome:
    """Run georef once per matcher with identical settings and tabulate the results.

    A matcher whose run fails (missing weights, too few matches, a degenerate
    adjustment) is listed under ``skipped`` with the reason; the others go on.

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

    Raises:
        InputError: Unknown matcher names, a bad scene, or an output directory holding
            another run.
    """
    from planetref.execute import Executor, make_executor

    owned = executor is not None and not isinstance(executor, Executor)
    ex = make_executor(executor)
    try:
        return _run_compare(scene, matchers, out, config, weights_dir, overwrite, progress, ex)
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
) -> CompareOutcome:
    from planetref.pipeline.georef import _scene_path, run_georef
    from planetref.report.georef import figure_headline_bars, write_compare_tables

    cfg = config or GeorefConfig()
    names, skipped = resolve_matchers(matchers, weights_dir)
    scene_path = _scene_path(scene)
    if not scene_path.is_file():
        raise InputError("scene manifest not found", path=scene_path)
    from planetref.pipeline.georef import scene_input_files
    from planetref.simulate.manifest import load_manifest

    manifest, root = load_manifest(scene_path)
    identity = {"scene": str(scene_path), "config": config_digest(cfg.to_json())}
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
                )
            except (WeightsError, PlanetrefError) as exc:
                log.warning("compare: %s skipped: %s", name, exc)
                skipped[name] = str(exc)
                continue
            runs[name] = outcome.report
            _collect_figures(outcome.run_dir, run, name)
        scene_name = next((r["scene"] for r in runs.values()), scene_path.parent.name)
        report = {"scene": scene_name, "runs": runs, "skipped": skipped}
        run.write_json("report.json", report)
        tables = write_compare_tables(runs, skipped, run.path, scene=scene_name)
        files = {k: v for k, v in tables.items() if k != "markdown"}
        if runs:
            files["headline"] = str(figure_headline_bars(runs, run.file("figures", "headline.png")))
    return CompareOutcome(
        report=report, run_dir=run.path, tables_markdown=tables["markdown"], files=files
    )


def _collect_figures(run_dir: Path, run: RunDir, matcher: str) -> None:
    for png in sorted((run_dir / "figures").glob("*.png")):
        shutil.copyfile(png, run.file("figures", f"{matcher}_{png.name}"))
