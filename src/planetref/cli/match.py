"""``planetref matchers`` and ``planetref match``: list the matchers, match two rasters.

Both commands are plain click commands; :mod:`planetref.cli` registers them. Errors end
the command with a one-line message (``click.ClickException``), never a traceback.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from pathlib import Path

import click
import numpy as np
from numpy.typing import NDArray

from planetref.cli.weights import WEIGHTS_DIR_OPTION
from planetref.errors import (
    InputError,
    MatchingError,
    MissingFileError,
    PlanetrefError,
    library_reason,
)
from planetref.matching.registry import MATCHERS, available_matchers, get_matcher
from planetref.runtime.atomic import atomic_path

__all__ = ["match_command", "matchers_command", "read_band", "write_matches_csv"]

ISIS_SPECIAL_BELOW = -3.0e38
"""Float32 ISIS special pixels (NULL, LRS, LIS, HIS, HRS) are all about -3.4e38."""


def read_band(path: str | os.PathLike[str]) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """Read the first band of a raster and its valid-pixel mask.

    Invalid pixels: GDAL's mask (nodata, per-dataset masks), non-finite values, and ISIS
    special pixels (NULL, LRS, LIS, HIS, HRS, all below -3e38 in float32 cubes; GDAL's
    nodata covers only NULL).

    Args:
        path: Any raster rasterio/GDAL can read.

    Returns:
        ``(image float32 (H, W), valid bool (H, W))``.

    Raises:
        MissingFileError: The file does not exist.
        InputError: Not a readable raster.
    """
    import rasterio
    from rasterio.errors import RasterioError

    p = Path(path)
    if not p.exists():
        raise MissingFileError("no such file", path=p)
    try:
        with rasterio.open(p) as ds:
            band = ds.read(1)
            gdal_mask = ds.read_masks(1) > 0
    except RasterioError as exc:
        raise InputError(f"not a readable raster ({library_reason(exc)})", path=p) from None
    image = band.astype(np.float32, copy=False)
    valid = gdal_mask & np.isfinite(image)
    if np.issubdtype(band.dtype, np.floating):
        valid &= image > ISIS_SPECIAL_BELOW
    if not valid.any():
        raise InputError("the image has no valid pixel (all nodata, NaN or ISIS special)", path=p)
    values = image[valid]
    if float(values.max()) == float(values.min()):
        raise InputError(
            f"the image is constant ({float(values[0]):g} at every valid pixel): nothing to match",
            path=p,
        )
    return image, valid


def _atomic_write(path: Path, write: Callable[[str], None], suffix: str) -> None:
    """Write through a temporary file in the destination folder, then rename over ``path``."""
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise MissingFileError("output folder does not exist", path=folder)
    with atomic_path(path) as tmp:
        write(str(tmp))


def write_matches_csv(path: str | os.PathLike[str], keypoints0, keypoints1, confidence) -> None:
    """Write ``x0,y0,x1,y1,confidence`` rows atomically (temporary file + rename).

    Coordinates are pixels with the first pixel centre at ``(0.5, 0.5)``, x = column.
    """
    rows = np.column_stack([keypoints0, keypoints1, confidence])

    def write(tmp: str) -> None:
        with open(tmp, "w", encoding="ascii", newline="\n") as fh:
            fh.write("x0,y0,x1,y1,confidence\n")
            np.savetxt(fh, rows, fmt=["%.4f", "%.4f", "%.4f", "%.4f", "%.6g"], delimiter=",")
            fh.flush()
            os.fsync(fh.fileno())

    _atomic_write(Path(path), write, ".csv.tmp")


def _figure(
    path: Path,
    image0,
    valid0,
    image1,
    valid1,
    k0,
    k1,
    title: str,
    max_lines: int = 80,
    inliers=None,
) -> None:
    """Side-by-side images with the matches (see ``report.figures_matching``)."""
    from planetref.report.figures_matching import figure_pair_matches

    figure_pair_matches(
        path,
        image0,
        valid0,
        image1,
        valid1,
        k0,
        k1,
        title,
        max_lines,
        inliers=inliers,
        labels=("image0", "image1"),
    )


def _refined(matches, img0, valid0, img1, valid1, method: str):
    """Refine ``matches`` in place of their image-1 points; drop the failures."""
    from planetref.matching.base import Matches
    from planetref.matching.refine import RefineConfig, refine_matches

    res = refine_matches(
        img0,
        img1,
        matches.keypoints0,
        matches.keypoints1,
        RefineConfig(method=method),  # type: ignore[arg-type]
        valid0,
        valid1,
    )
    kept = Matches(matches.keypoints0, res.points1, matches.confidence).select(res.ok)
    return kept, res.counts()


def _check_outputs(
    image0: str, image1: str, out: str, figure: str | None, *, overwrite: bool
) -> None:
    """Refuse outputs that are an input or each other, or exist without ``--overwrite``."""
    from planetref.pipeline.rundir import check_output_file

    check_output_file(out, [image0, image1], overwrite=overwrite, option="--out")
    if figure:
        check_output_file(figure, [image0, image1, out], overwrite=overwrite, option="--figure")


@click.command("matchers")
@WEIGHTS_DIR_OPTION
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of a table.")
def matchers_command(weights_dir: str | None, as_json: bool) -> None:
    """List every matcher, its paradigm and whether its weights are present."""
    from planetref.matching.weights import fix_command
    from planetref.matching.weights import weights_dir as resolve_dir

    rows = []
    for avail in available_matchers(weights_dir):
        spec = MATCHERS[avail.name]
        rows.append(
            {
                "name": spec.name,
                "paradigm": spec.paradigm,
                "description": spec.description,
                "weights": list(spec.weights),
                "present": avail.present,
                "missing": list(avail.missing),
                "fix": f"planetref weights download {spec.name}"
                + (" --unverified" if "--unverified" in fix_command(avail.missing) else "")
                if avail.missing
                else None,
            }
        )
    if as_json:
        click.echo(
            json.dumps({"weights_dir": str(resolve_dir(weights_dir)), "matchers": rows}, indent=2)
        )
        return
    click.echo(f"weights: {resolve_dir(weights_dir)}")
    width = max(len(r["name"]) for r in rows)
    pwidth = max(len(r["paradigm"]) for r in rows)
    for r in rows:
        if not r["weights"]:
            status = "ready (no weights needed)"
        elif r["present"]:
            status = "ready"
        else:
            status = "missing: " + ", ".join(r["missing"]) + f"  -> {r['fix']}"
        click.echo(f"{r['name']:<{width}}  {r['paradigm']:<{pwidth}}  {status}")
    click.echo("weight files, sha256, URLs and licences: planetref weights list")


@click.command("match")
@click.argument("image0", type=click.Path(dir_okay=False))
@click.argument("image1", type=click.Path(dir_okay=False))
@click.option(
    "--matcher",
    "matcher_name",
    default="sift",
    show_default=True,
    type=click.Choice(list(MATCHERS)),
    help="Matcher (see `planetref matchers`).",
)
@click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(dir_okay=False),
    help="Output CSV: x0,y0,x1,y1,confidence per verified match.",
)
@click.option(
    "--figure",
    type=click.Path(dir_okay=False),
    default=None,
    help="Optional PNG figure of the verified matches.",
)
@click.option(
    "--overwrite",
    is_flag=True,
    help="Replace an existing --out / --figure (never an input image).",
)
@WEIGHTS_DIR_OPTION
@click.option(
    "--device",
    default="cpu",
    show_default=True,
    help="Torch device of learned matchers (cpu, cuda, cuda:1..., or auto: the GPU when "
    "torch sees one, else the CPU).",
)
@click.option(
    "--tile-size",
    default=1024,
    show_default=True,
    type=click.IntRange(64),
    help="Images larger than this are matched in tiles (pixels).",
)
@click.option(
    "--overlap",
    default=128,
    show_default=True,
    type=click.IntRange(0),
    help="Tile overlap (pixels).",
)
@click.option(
    "--model",
    "model",
    default="homography",
    show_default=True,
    type=click.Choice(["homography", "affine", "fundamental"]),
    help="Geometric model of the MAGSAC++ verification.",
)
@click.option(
    "--threshold",
    default=3.0,
    show_default=True,
    type=click.FloatRange(min=0, min_open=True),
    help="Inlier threshold of the verification (pixels).",
)
@click.option(
    "--refine",
    "refine",
    default="none",
    show_default=True,
    type=click.Choice(["none", "lsm", "ncc"]),
    help="Sub-pixel refinement of the verified matches (least-squares matching with NCC "
    "fallback, or NCC alone); matches whose refinement fails are dropped.",
)
def match_command(
    image0: str,
    image1: str,
    matcher_name: str,
    out: str,
    figure: str | None,
    overwrite: bool,
    weights_dir: str | None,
    device: str,
    tile_size: int,
    overlap: int,
    model: str,
    threshold: float,
    refine: str,
) -> None:
    """Match IMAGE0 against IMAGE1 and write the verified matches to a CSV.

    Coordinates are pixels of each image (x = column, first pixel centre at 0.5, 0.5).
    Prints one JSON line: {"matcher", "ncp", "seconds", "refine"} where "refine" counts the
    refined matches per method and the drops per reason (empty without --refine).
    """
    from planetref.matching.ransac import verify_matches
    from planetref.matching.tiling import match_tiled

    start = time.perf_counter()
    try:
        if overlap >= tile_size:
            raise InputError(
                f"--overlap ({overlap}) must be smaller than --tile-size ({tile_size})"
            )
        _check_outputs(image0, image1, out, figure, overwrite=overwrite)
        img0, valid0 = read_band(image0)
        img1, valid1 = read_band(image1)
        matcher = get_matcher(matcher_name, weights_dir=weights_dir, device=device)
        found = match_tiled(
            matcher, img0, img1, valid0, valid1, tile_size=tile_size, overlap=overlap
        )
        verdict = verify_matches(found, model, threshold=threshold)  # type: ignore[arg-type]
        inliers = found.select(verdict.inliers)
        refine_counts: dict[str, int] = {}
        if refine != "none" and len(inliers):
            inliers, refine_counts = _refined(inliers, img0, valid0, img1, valid1, refine)
        if len(inliers) == 0:
            raise MatchingError(
                f"no verified matches between {image0} and {image1} with matcher {matcher_name} "
                f"({len(found)} tentative matches, model {model}, threshold {threshold} px)"
            )
        write_matches_csv(out, inliers.keypoints0, inliers.keypoints1, inliers.confidence)
        if figure:
            _figure(
                Path(figure),
                img0,
                valid0,
                img1,
                valid1,
                found.keypoints0,
                found.keypoints1,
                f"{matcher_name}, {model} verification",
                inliers=verdict.inliers,
            )
    except PlanetrefError as exc:
        raise click.ClickException(" ".join(str(exc).split())) from None
    except (MemoryError, OSError, RuntimeError) as exc:  # e.g. out of (GPU) memory
        raise click.ClickException(f"{type(exc).__name__}: {exc}".splitlines()[0]) from None
    seconds = time.perf_counter() - start
    click.echo(
        json.dumps(
            {
                "matcher": matcher_name,
                "ncp": len(inliers),
                "seconds": round(seconds, 3),
                "refine": refine_counts,
            }
        )
    )
