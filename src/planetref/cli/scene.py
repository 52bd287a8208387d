"""``planetref scene``: make a checked scene manifest from your own files."""

from __future__ import annotations

import json
from pathlib import Path

import click

__all__ = ["scene_group"]


@click.group("scene")
def scene_group() -> None:
    """Make scene manifests (scene.toml) from CCD images, cameras and a reference."""


@scene_group.command("init")
@click.argument("scene_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option(
    "--ccd",
    "ccds",
    nargs=2,
    multiple=True,
    required=True,
    metavar="IMAGE CAMERA",
    type=click.Path(dir_okay=False, path_type=Path),
    help="A CCD image and its camera (native JSON, CSM ISD or RPC); repeat per CCD. The "
    "CCD is named after the image (ccd2.tif -> ccd2), which picks it in a multi-CCD camera.",
)
@click.option(
    "--ortho",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Reference orthoimage (any map CRS of the cameras' body); with --append, the scene's.",
)
@click.option(
    "--dem",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Reference DEM, heights in metres (any map CRS of the body); with --append, the scene's.",
)
@click.option(
    "--dem-datum",
    type=click.Choice(["body", "areoid"]),
    default=None,
    help="What the DEM's heights are above; default: told from the heights where they "
    "fit one datum only, else refused (declare it).",
)
@click.option(
    "--areoid",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Raster of the areoid's height above the body (m), for --dem-datum areoid.",
)
@click.option("--strip", "strip_id", default="strip1", show_default=True, help="Strip id.")
@click.option("--name", default=None, help="Scene name (default: the folder's name).")
@click.option(
    "--margin-m",
    type=click.FloatRange(min=0.0),
    default=600.0,
    show_default=True,
    help="Margin around the footprint of the reference window a run needs (m).",
)
@click.option(
    "--crop",
    is_flag=True,
    help="Write the ortho and DEM cut to that window into SCENE_DIR/reference/ and use them.",
)
@click.option("--overwrite", is_flag=True, help="Replace an existing SCENE_DIR/scene.toml.")
@click.option(
    "--append",
    is_flag=True,
    help="Add this strip to the existing SCENE_DIR/scene.toml (a campaign of several strips).",
)
def scene_init_command(
    scene_dir: Path,
    ccds: tuple[tuple[Path, Path], ...],
    ortho: Path | None,
    dem: Path | None,
    dem_datum: str | None,
    areoid: Path | None,
    strip_id: str,
    name: str | None,
    margin_m: float,
    crop: bool,
    overwrite: bool,
    append: bool,
) -> None:
    """Check one strip's images and cameras against a reference; write SCENE_DIR/scene.toml.

    Checks that every camera and image opens and has its camera's size, that the
    reference is on the cameras' body, how much of each CCD's footprint (through its
    camera onto the DEM) the reference covers, and the DEM's datum (refused when its
    heights cannot tell). With --append the strip is added to an existing scene (a
    campaign), on the scene's reference. Prints what it found as JSON.
    """
    from planetref.scene.init import CcdInput, init_scene

    result = init_scene(
        scene_dir,
        [CcdInput(image, camera) for image, camera in ccds],
        ortho,
        dem,
        strip_id=strip_id,
        name=name,
        dem_datum=dem_datum,
        areoid=areoid,
        margin_m=margin_m,
        crop=crop,
        overwrite=overwrite,
        append=append,
    )
    click.echo(
        json.dumps(
            {
                "scene": str(result.path),
                "body_m": list(result.body),
                "footprint_lonlat_deg": result.footprints,
                "outside_reference_share": result.outside_share,
                "dem_datum": result.dem_datum,
                "dem_datum_reason": result.datum_reason,
                "reference_window": result.crop,
                "cropped": [str(p) for p in result.cropped],
                "warnings": result.warnings,
            },
            indent=1,
        )
    )
