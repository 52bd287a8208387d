"""``planetref simulate``: write a synthetic Mars scene with exact ground truth."""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

__all__ = ["simulate_command", "simulate_run"]


def simulate_run(
    cfg: Any,
    out_dir: str | os.PathLike[str],
    *,
    overwrite: bool = False,
    preview: bool = False,
    progress: bool = False,
    log: Callable[[str], None] | None = None,
) -> Any:
    """Simulate a scene into a planetref run folder (see :mod:`planetref.pipeline.rundir`).

    The scene is built beside the folder, then its files are moved in one by one and
    recorded in the folder's manifest; ``overwrite`` removes only the files of the
    previous scene, never the user's.

    Returns:
        The :class:`~planetref.simulate.scene.SceneResult` (``root`` is ``out_dir``).
    """
    from planetref.pipeline.rundir import RunDir, config_digest
    from planetref.runtime.atomic import TEMP_PREFIX
    from planetref.simulate.scene import simulate_scene

    out = Path(out_dir).resolve()
    identity = {
        "scene": cfg.name,
        "seed": cfg.seed,
        "config": config_digest(cfg.model_dump(mode="json")),
    }
    run = RunDir(out, "simulate", identity, overwrite=overwrite, resumable=False)
    with run.logging_to_file():
        # Built inside the run folder under a temporary name (TEMP_PREFIX): an
        # interrupted simulation leaves nothing beside it, and the next run (or demo)
        # removes the folder under the lock and starts again.
        tmp = out / f"{TEMP_PREFIX}simulate"
        shutil.rmtree(tmp, ignore_errors=True)
        try:
            result = simulate_scene(cfg, tmp / "scene", preview=preview, progress=progress, log=log)
            files = sorted(p for p in (tmp / "scene").rglob("*") if p.is_file())
            # scene.toml last: a scene folder with a scene.toml is whole (demo reuses it).
            files.sort(key=lambda p: p.name == "scene.toml")
            for src in files:
                os.replace(src, run.file(*src.relative_to(tmp / "scene").parts))
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    result.root = out
    result.manifest_path = out / "scene.toml"
    return result


@click.command("simulate")
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option(
    "--preset",
    default="hiric-strip",
    show_default=True,
    help="Scene preset: tiny (quick), hiric-strip (the demo's), hiric (HiRIC-sized).",
)
@click.option(
    "--difficulty",
    type=click.Choice(["easy", "moderate", "realistic", "hard", "extreme"]),
    default=None,
    help="Difficulty level merged over the preset (default: the preset as is, moderate).",
)
@click.option(
    "--initial-errors",
    "initial_errors",
    type=click.Choice(["100m", "1km", "2km"]),
    default=None,
    help="Magnitude of the initial cameras' error on the ground, from every physical term "
    "(position, attitude incl. yaw, altitude, focal length; sourced values), with its "
    "a-priori uncertainty declared in scene.toml (default: the preset's, ~110 m, undeclared).",
)
@click.option(
    "--seed",
    type=click.IntRange(min=0),
    default=None,
    help="Seed of every random draw (default: the preset's).",
)
@click.option(
    "--config",
    "config_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="TOML file whose tables override the preset's.",
)
@click.option("--preview", is_flag=True, help="Also write OUT_DIR/preview.png.")
@click.option(
    "--overwrite",
    is_flag=True,
    help="Replace the scene planetref wrote in OUT_DIR (only its files; never other files).",
)
@click.pass_context
def simulate_command(
    ctx: click.Context,
    out_dir: Path,
    preset: str,
    difficulty: str | None,
    initial_errors: str | None,
    seed: int | None,
    config_path: Path | None,
    preview: bool,
    overwrite: bool,
) -> None:
    """Simulate a synthetic Mars scene with exact ground truth into OUT_DIR.

    The scene (reference ortho and DEM, HiRIC-like CCD images, their cameras and the
    truth) is described by OUT_DIR/scene.toml. The same preset, overrides and seed
    always give byte-identical rasters.
    """
    from planetref.simulate.config import load_config

    quiet = bool(ctx.obj and ctx.obj.get("quiet"))
    cfg = load_config(
        preset, config_path, seed=seed, difficulty=difficulty, initial_errors=initial_errors
    )

    def log(msg: str) -> None:
        if not quiet:
            click.echo(msg, err=True)

    result = simulate_run(
        cfg, out_dir, overwrite=overwrite, preview=preview, progress=not quiet, log=log
    )
    if quiet:
        return
    click.echo(f"scene '{cfg.name}' (seed {cfg.seed}) written to {result.root}")
    for strip_id, rep in result.errors.items():
        if not isinstance(rep, dict) or "initial_errors" not in rep:
            continue
        g = rep["initial_errors"]["ground_m"]
        p = rep["initial_errors"]["image_px"]
        click.echo(
            f"  {strip_id}: initial geolocation error {g['horizontal']['rms']:.1f} m RMS "
            f"(max {g['horizontal']['max']:.1f} m; along {g['along']['mean']:+.1f} m, "
            f"cross {g['cross']['mean']:+.1f} m), {p['distance']['rms']:.1f} px RMS"
        )
    total = sum(result.timings_s.values())
    click.echo(
        f"  {total:.1f} s (" + ", ".join(f"{k} {v:.1f}" for k, v in result.timings_s.items()) + ")"
    )
    if preview:
        click.echo(f"  preview: {result.root / 'preview.png'}")
