"""``planetref georef``, ``planetref compare`` and ``planetref demo``."""

from __future__ import annotations

import functools
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from planetref.errors import InputError

if TYPE_CHECKING:  # pragma: no cover
    from planetref.runtime.execute import SchedulerSpec

__all__ = [
    "DEMO_COSTS",
    "DemoCost",
    "compare_command",
    "demo_command",
    "demo_cost_notice",
    "georef_command",
]


def _check_scheduler(ctx: click.Context, param: click.Parameter, value: str | None) -> Any:
    """Parse ``--scheduler`` once into a typed spec (an InputError is one line)."""
    from planetref.runtime.execute import parse_scheduler

    return parse_scheduler(value)


@dataclass(frozen=True)
class _RunOptions:
    """The options of every run command (:func:`_common`): config, weights, threads..."""

    config_path: str | None
    weights_dir: str | None
    overwrite: bool
    scheduler: SchedulerSpec
    threads: int | None
    device: str

    def run_kwargs(self, progress: bool) -> dict[str, Any]:
        """Apply the thread budget and load the config (:func:`_runtime`).

        Returns:
            The keywords of ``run_georef`` and ``run_compare`` these options set.
        """
        config, device = _runtime(self.config_path, self.threads, self.device, self.scheduler)
        return {
            "config": config,
            "device": device,
            "weights_dir": self.weights_dir,
            "overwrite": self.overwrite,
            "progress": progress,
            "executor": self.scheduler,
        }


def _common(command: Any) -> Any:
    """Add the shared options; ``command`` gets them as one ``run: _RunOptions``."""

    @functools.wraps(command)
    def f(
        *args: Any,
        config_path: str | None,
        weights_dir: str | None,
        overwrite: bool,
        scheduler: SchedulerSpec,
        threads: int | None,
        device: str,
        **kwargs: Any,
    ) -> Any:
        run = _RunOptions(config_path, weights_dir, overwrite, scheduler, threads, device)
        return command(*args, run=run, **kwargs)

    f = click.option(
        "--config",
        "config_path",
        type=click.Path(dir_okay=False),
        default=None,
        help="TOML with [frontend], [adjust], [mcp], [ortho], [matchers.NAME].",
    )(f)
    f = click.option(
        "--weights-dir",
        type=click.Path(file_okay=False),
        default=None,
        help="Pretrained weights (default: $PLANETREF_WEIGHTS, $TORCH_HOME, the torch hub cache).",
    )(f)
    f = click.option(
        "--overwrite",
        is_flag=True,
        help="Replace a different earlier run in --out (never other files).",
    )(f)
    f = click.option(
        "--threads",
        type=click.IntRange(min=1),
        default=None,
        help="Threads of torch, OpenCV and BLAS in all [default: the cores available]; "
        "each pool/dask-local worker gets threads / workers.",
    )(f)
    f = click.option(
        "--device",
        default="cpu",
        show_default=True,
        help="Torch device of the learned matchers (cpu, cuda, cuda:1..., or auto: the GPU "
        "when torch sees one, else the CPU).",
    )(f)
    f = click.option(
        "--scheduler",
        default=None,
        metavar="SPEC",
        callback=_check_scheduler,
        help="Where tiles are matched: inprocess (default), pool:N, "
        "dask-local:N, or tcp://HOST:PORT.",
    )(f)
    return f


def _runtime(
    config_path: str | None, threads: int | None, device: str, scheduler: SchedulerSpec
) -> tuple[Any, str]:
    """Apply the thread budget, load the config and resolve the device.

    Returns:
        ``(config, device)``: the settings and the torch device of the learned matchers
        (``"auto"`` resolved to the device it stands for, so the run's identity names the
        real one), a run option passed to the matchers when they are built.
    """
    from planetref.pipeline.config import load_config
    from planetref.runtime.threads import ThreadBudget, apply_thread_budget

    apply_thread_budget(ThreadBudget.resolve(threads, scheduler.local_workers))
    cfg = load_config(config_path)
    if device != "cpu":
        # Checked here, before any work (one line when the device does not exist).
        from planetref.matching._torch import resolve_device

        device = str(resolve_device(device))
    return cfg, device


def _quiet(ctx: click.Context) -> bool:
    return bool(ctx.obj and ctx.obj.get("quiet"))


@click.command("georef")
@click.argument("scene", type=click.Path())
@click.option("--matcher", required=True, help="Matcher name (see planetref matchers).")
@click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(file_okay=False),
    help="Run directory (re-running resumes finished tiles).",
)
@_common
@click.pass_context
def georef_command(
    ctx: click.Context,
    scene: str,
    matcher: str,
    out: str,
    run: _RunOptions,
) -> None:
    """Georeference SCENE (scene.toml or its folder) with one matcher.

    Tiling, matching, MCPs, bundle adjustment, metrics, report, adjusted cameras and
    orthoimages. Prints the report's headline as JSON.
    """
    from planetref.pipeline.georef import run_georef

    outcome = run_georef(scene, matcher, out, **run.run_kwargs(progress=not _quiet(ctx)))
    r = outcome.report
    click.echo(
        json.dumps(
            {
                "matcher": r["matcher"],
                "ncp": r["matching"]["ncp"],
                "sdu_pct": r["matching"]["sdu_pct"],
                "rmse_px": r["adjustment"]["rmse_px"],
                "geoloc_rmse_m": (r["check"] or {}).get("geoloc_rmse_m"),
                "report": str(outcome.run_dir / "report.json"),
            }
        )
    )


@click.command("compare")
@click.argument("scenes", nargs=-1, required=True, type=click.Path())
@click.option(
    "--matchers", default="all", show_default=True, help="Comma-separated matcher names, or 'all'."
)
@click.option("--out", "out", required=True, type=click.Path(file_okay=False))
@_common
@click.pass_context
def compare_command(
    ctx: click.Context,
    scenes: tuple[str, ...],
    matchers: str,
    out: str,
    run: _RunOptions,
) -> None:
    """Run georef on SCENES once per matcher and tabulate the results side by side.

    With several scenes each comparison goes to OUT/<scene folder name>, and OUT gets
    the rankings over the scenes: mean and spread per matcher, paired differences, which
    gaps are beyond noise (seeds.json, report.md, report.html).
    """
    from planetref.pipeline.compare import run_compare, summarize_compares

    kwargs = run.run_kwargs(progress=not _quiet(ctx))
    if len(scenes) == 1:
        outcome = run_compare(scenes[0], matchers, out, **kwargs)
        click.echo(outcome.tables_markdown)
        click.echo(f"report: {outcome.run_dir / 'report.html'} (and report.md, report.json)")
        return
    dirs: dict[str, Path] = {}
    for scene in scenes:
        p = Path(scene)
        label = (p.parent if p.suffix == ".toml" else p).resolve().name or "scene"
        label = label if label not in dirs else f"{label}-{len(dirs)}"
        dirs[label] = run_compare(scene, matchers, Path(out) / label, **kwargs).run_dir
        click.echo(f"{label}: {dirs[label] / 'report.html'}")
    summary = summarize_compares(dirs, out, title=f"Matchers over {len(dirs)} scenes")
    click.echo(summary.markdown)
    click.echo(f"report: {summary.folder / 'report.html'} (and report.md, seeds.json)")


def _default_demo_dir() -> Path:
    return Path(os.environ.get("PLANETREF_DEMO_DIR", "planetref-demo"))


@dataclass(frozen=True)
class DemoCost:
    """What one ``planetref demo`` of a preset costs, as measured (one seed).

    Attributes:
        cpu_s: CPU seconds of the whole demo (simulation and comparison), or None where
            not measured.
        peak_rss_gb: Peak resident memory in GB, or None.
        written_gb: Disk written (scene and comparison folders) in GB, or None.
        matchers: The matchers the figures were measured with.
        source: Where and how they were measured.
    """

    cpu_s: float | None
    peak_rss_gb: float | None
    written_gb: float | None
    matchers: str
    source: str


DEMO_COSTS: dict[str, DemoCost] = {
    "tiny": DemoCost(
        cpu_s=422.0,
        peak_rss_gb=2.0,
        written_gb=0.08,
        matchers="the six matchers with weights",
        source="CPU: benchmarks/results/bench_demo_tiny_all.json (422 CPU-s, 4:15 wall on "
        "an idle 2-core AMD EPYC, scene and numba cache in place, with the second fine "
        "pass, 2026-12-06; 277 CPU-s before it); memory: "
        "issue 32; disk: du of the scene (7 MB) and the sift (16 MB) and ncc (56 MB) runs",
    ),
    "hiric-strip": DemoCost(
        cpu_s=1470.0,
        peak_rss_gb=2.8,
        written_gb=1.9,
        matchers="the six matchers with weights",
        source="CPU: benchmarks/results/bench_demo_hiric_strip_all.json (simulation 139 "
        "CPU-s, the demo of six matchers 1331 CPU-s, with the second fine pass, "
        "2026-12-06; the machine also ran the test suite for about half of it, so an "
        "upper bound; 873 CPU-s before the second pass); memory and disk: issue 32, "
        "main 2553f7b",
    ),
    "hiric": DemoCost(
        cpu_s=None,
        peak_rss_gb=None,
        written_gb=None,
        matchers="",
        source="not measured; 6x the pixels of hiric-strip (3 x 6144 x 16000)",
    ),
}
"""The cost of the demo per preset: the one table ``demo``'s notice is drawn from."""


def demo_cost_notice(preset: str, n_seeds: int = 1) -> str:
    """The one line ``demo`` prints before it starts: time, memory and disk of the preset.

    Args:
        preset: The simulator preset.
        n_seeds: Number of scenes (time and disk add up per seed; memory does not).
    """
    cost = DEMO_COSTS.get(preset)
    if cost is None or cost.cpu_s is None:
        why = cost.source if cost is not None else "not measured"
        return (
            f"the {preset} demo's time, memory and disk are not known ({why}); "
            "try --preset tiny first"
        )
    per = f" per seed, {n_seeds} seeds" if n_seeds > 1 else ""
    parts = [f"about {cost.cpu_s:,.0f} CPU seconds (~{cost.cpu_s / 60:.0f} min on one core){per}"]
    if cost.peak_rss_gb is not None:
        parts.append(f"about {cost.peak_rss_gb:.1f} GB of memory at its peak")
    parts.append(
        f"about {cost.written_gb:.1f} GB of disk{per}"
        if cost.written_gb is not None
        else "disk not measured"
    )
    return (
        f"the {preset} demo takes {', '.join(parts)} (measured with {cost.matchers}; "
        "it depends on the matchers: --matchers sift is the quickest; a cached scene "
        "is reused)"
    )


@click.command("demo")
@click.option(
    "--out",
    "out",
    type=click.Path(file_okay=False),
    default=None,
    help="Folder for the scene (cached) and the results [default: ./planetref-demo].",
)
@click.option(
    "--preset", default="hiric-strip", show_default=True, help="Simulator preset of the scene."
)
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
@click.option(
    "--seeds",
    "n_seeds",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    help="Number of scenes (seeds SEED .. SEED+N-1): rankings over them with mean, "
    "spread and the gaps beyond noise.",
)
@click.option(
    "--difficulty",
    type=click.Choice(["easy", "moderate", "realistic", "hard", "extreme"]),
    default="moderate",
    show_default=True,
    help="Difficulty of the simulated scene (see docs/scene-manifest.md).",
)
@click.option(
    "--matchers",
    default="all",
    show_default=True,
    help="Comma-separated matcher names, or 'all' (those with weights).",
)
@_common
@click.pass_context
def demo_command(
    ctx: click.Context,
    out: str | None,
    preset: str,
    seed: int,
    n_seeds: int,
    difficulty: str,
    matchers: str,
    run: _RunOptions,
) -> None:
    """Simulate a realistic Mars scene (cached) and compare the matchers on it.

    With ``--seeds N``: N scenes (seeds SEED .. SEED+N-1), one comparison each, and the
    rankings over them (mean and spread per matcher, paired differences, which gaps are
    beyond noise) in ``seeds-<preset>-seed<first>-<last>/``.
    """
    from planetref.cli.simulate import simulate_run
    from planetref.pipeline.compare import resolve_matchers, run_compare, summarize_compares
    from planetref.simulate.config import load_config as load_sim_config

    quiet = _quiet(ctx)
    # Every name is checked before the first scene is simulated (minutes of work): an
    # unknown preset, difficulty or matcher, or matchers none of which can run, is one
    # line naming the valid values, and nothing is written.
    level = None if difficulty == "moderate" else difficulty
    configs = {
        s: load_sim_config(preset, seed=s, difficulty=level) for s in range(seed, seed + n_seeds)
    }
    names, skipped = resolve_matchers(matchers, run.weights_dir)
    if not names:
        raise InputError(
            "none of the matchers can run: "
            + "; ".join(f"{n}: {why}" for n, why in skipped.items())
        )
    base = Path(out) if out else _default_demo_dir()
    tag = preset if difficulty == "moderate" else f"{preset}-{difficulty}"
    kwargs = run.run_kwargs(progress=not quiet)
    if not quiet:
        click.echo(demo_cost_notice(preset, n_seeds), err=True)
    dirs: dict[str, Path] = {}
    for s, sim_config in configs.items():
        scene_dir = base / f"scene-{tag}-seed{s}"
        if not (scene_dir / "scene.toml").is_file():
            if not quiet:
                click.echo(f"simulating the {tag} scene (seed {s}) into {scene_dir} ...", err=True)
            simulate_run(
                sim_config,
                scene_dir,
                overwrite=run.overwrite,
                preview=True,
                progress=not quiet,
            )
        elif not quiet:
            click.echo(f"using the cached scene {scene_dir}", err=True)
        compare_dir = base / f"compare-{tag}-seed{s}"
        outcome = run_compare(scene_dir, matchers, compare_dir, **kwargs)
        dirs[f"seed{s}"] = outcome.run_dir
        if n_seeds == 1:
            click.echo(outcome.tables_markdown)
            click.echo(f"report:  {outcome.run_dir / 'report.html'} (and report.md, report.json)")
            click.echo(f"figures: {outcome.run_dir / 'figures'}")
            click.echo(f"scene:   {scene_dir} (preview.png)")
        else:
            click.echo(f"seed {s}: {outcome.run_dir / 'report.html'}")
    if n_seeds > 1:
        last = seed + n_seeds - 1
        summary = summarize_compares(
            dirs,
            base / f"seeds-{tag}-seed{seed}-{last}",
            title=f"Matchers on {tag} over {n_seeds} seeds ({seed}-{last})",
        )
        click.echo(summary.markdown)
        click.echo(f"report:  {summary.folder / 'report.html'} (and report.md, seeds.json)")
