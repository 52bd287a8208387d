"""``planetref simulate``: write a synthetic Mars scene with exact ground truth."""

from __future__ import annotations

from pathlib import Path

import click

__all__ = ["simulate_command"]


def _preset_names() -> str:
    from planetref.simulate.config import available_presets

    return ", ".join(available_presets())


@click.command("simulate")
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option(
    "--preset", default="hiric-strip", show_default=True, help="Scene preset (tiny, hiric-strip)."
)
@click.option(
    "--difficulty",
    type=click.Choice(["easy", "moderate", "hard", "extreme"]),
    default=None,
    help="Difficulty level merged over the preset (default: the preset as is, moderate).",
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
@click.option("--overwrite", is_flag=True, help="Replace OUT_DIR if it exists and is not empty.")
@click.pass_context
def simulate_command(
    ctx: click.Context,
    out_dir: Path,
    preset: str,
    difficulty: str | None,
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
    from planetref.simulate.scene import simulate_scene

    quiet = bool(ctx.obj and ctx.obj.get("quiet"))
    cfg = load_config(preset, config_path, seed=seed, difficulty=difficulty)

    def log(msg: str) -> None:
        if not quiet:
            click.echo(msg, err=True)

    result = simulate_scene(
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
