"""``planetref camera``: image <-> ground with any supported camera file.

Image coordinates follow planetref's convention: ``(line, sample)`` with the first
pixel's centre at ``(0.5, 0.5)`` (usgscsm's convention for CSM ISDs, GDAL's for RPCs).
Latitudes are planetocentric for Mars cameras and geodetic (planetographic) for Earth
RPCs; longitudes are east-positive degrees.
"""

from __future__ import annotations

import json
import logging
import math
from typing import Any

import click
import numpy as np

from planetref.errors import GeometryError, InputError
from planetref.geometry.geodesy import lonlat_to_xyz, xyz_to_lonlat
from planetref.runtime.atomic import json_safe

__all__ = ["EXTRAPOLATION_MARGIN", "HEIGHT_LIMIT_FRACTION", "camera_group"]

EXTRAPOLATION_MARGIN = 0.1
"""Image points this far outside the image (fraction of its size, at least 64 px) are
refused unless ``--extrapolate``: the camera model is not known there."""
HEIGHT_LIMIT_FRACTION = 0.01
"""Heights are accepted within +-1 % of the body's equatorial radius (+-33.96 km on Mars,
+-63.8 km on Earth): every terrain and no orbit."""


def _finite(name: str, value: float | None) -> None:
    if value is not None and not math.isfinite(value):
        raise InputError(f"--{name} must be a finite number, got {value}")


def load_camera(path: str) -> Any:
    """Load a camera file; a pathologically nested JSON is an error naming the file."""
    from planetref.camera.io import load_camera as _load

    try:
        return _load(path)
    except RecursionError:
        raise InputError("the file is nested too deeply to be a camera file", path=path) from None


#: ``camera fit-rpc`` warns when the RPC misses the camera by more than this (pixels).
RPC_WARN_MAX_PX = 1.0


def _check_height(cam: Any, height: float, name: str = "height") -> None:
    limit = HEIGHT_LIMIT_FRACTION * float(cam.ellipsoid.semi_major_m)
    if abs(height) > limit:
        what = "--xyz: the point's height" if name == "xyz" else f"--{name}"
        raise InputError(
            f"{what} {height:g} m is outside the physically meaningful range "
            f"[-{limit:.0f}, {limit:.0f}] m (1 % of the body's radius) of the camera's body"
        )


def _check_in_image(
    cam: Any, ccd: str | None, line: float, sample: float, extrapolate: bool, what: str
) -> None:
    if extrapolate:
        return
    n_lines, n_samples = cam.image_size(ccd)
    for name, value, n in (("line", line, n_lines), ("sample", sample, n_samples)):
        margin = max(64.0, EXTRAPOLATION_MARGIN * n)
        if not (-margin <= value <= n + margin):
            raise InputError(
                f"{what} {name} {value:g} is more than {margin:g} px outside the image "
                f"(0 to {n}); the camera model is not known there: pass --extrapolate "
                "to compute it anyway"
            )


@click.group("camera")
def camera_group() -> None:
    """Project between image and ground with a camera file."""


@camera_group.command("image-to-ground")
@click.argument("camera_file", metavar="CAMERA", type=click.Path(dir_okay=False))
@click.option("--line", "line", type=float, required=True, help="Line coordinate (px).")
@click.option("--sample", "sample", type=float, required=True, help="Sample coordinate (px).")
@click.option(
    "--height",
    type=float,
    default=0.0,
    show_default=True,
    help="Height above the camera's reference body (m).",
)
@click.option("--ccd", default=None, help="CCD name (default: the camera's first CCD).")
@click.option(
    "--extrapolate",
    is_flag=True,
    help="Accept image points far outside the image (the model is extrapolated).",
)
def image_to_ground(
    camera_file: str,
    line: float,
    sample: float,
    height: float,
    ccd: str | None,
    extrapolate: bool,
) -> None:
    """Intersect the ray of an image point with a height; prints JSON.

    Output: {"x_m", "y_m", "z_m", "lat_deg", "lon_deg", "height_m"}.
    """
    for name, value in (("line", line), ("sample", sample), ("height", height)):
        _finite(name, value)
    cam = load_camera(camera_file)
    _check_height(cam, height)
    _check_in_image(cam, ccd, line, sample, extrapolate, "--line/--sample:")
    xyz = cam.image_to_ground(
        np.array([line]), np.array([sample]), height, ccd=ccd, on_miss="raise"
    )[0]
    lon, lat, h = xyz_to_lonlat(xyz, cam.ellipsoid, cam.latitude_kind)
    if not (np.all(np.isfinite(xyz)) and abs(float(h) - height) <= 1.0):
        raise GeometryError(
            f"the ray of ({line:g}, {sample:g}) does not reach the height {height:g} m "
            f"in front of the camera (got {float(h):.1f} m)"
        )
    click.echo(
        json.dumps(
            {
                "x_m": float(xyz[0]),
                "y_m": float(xyz[1]),
                "z_m": float(xyz[2]),
                "lat_deg": float(lat),
                "lon_deg": float(lon),
                "height_m": float(h),
            }
        )
    )


@camera_group.command("ground-to-image")
@click.argument("camera_file", metavar="CAMERA", type=click.Path(dir_okay=False))
@click.option("--xyz", nargs=3, type=float, default=None, help="Body-fixed X Y Z (m).")
@click.option("--lat", type=float, default=None, help="Latitude (deg).")
@click.option("--lon", type=float, default=None, help="East longitude (deg).")
@click.option("--height", type=float, default=None, help="Height (m), with --lat/--lon.")
@click.option("--ccd", default=None, help="CCD name (default: the camera's first CCD).")
@click.option(
    "--extrapolate",
    is_flag=True,
    help="Accept points that project far outside the image.",
)
def ground_to_image(
    camera_file: str,
    xyz: tuple[float, float, float] | None,
    lat: float | None,
    lon: float | None,
    height: float | None,
    ccd: str | None,
    extrapolate: bool,
) -> None:
    """Project a ground point into the image; prints JSON {"line", "sample"}."""
    by_xyz = xyz is not None
    by_geo = lat is not None or lon is not None or height is not None
    if by_xyz == by_geo:
        raise click.UsageError("give either --xyz X Y Z or all of --lat, --lon, --height")
    cam = load_camera(camera_file)
    if by_xyz:
        for v in xyz:
            _finite("xyz", v)
        point = np.asarray(xyz, dtype=np.float64)
    else:
        if lat is None or lon is None or height is None:
            raise click.UsageError("--lat, --lon and --height go together")
        for name, value in (("lat", lat), ("lon", lon), ("height", height)):
            _finite(name, value)
        if abs(lat) > 90:
            raise InputError(f"--lat must be within [-90, 90], got {lat}")
        _check_height(cam, height)
        point = lonlat_to_xyz(lon, lat, height, cam.ellipsoid, cam.latitude_kind)
    if by_xyz:
        with np.errstate(all="ignore"):  # the body's centre has no height: refused below
            height = float(xyz_to_lonlat(point, cam.ellipsoid, cam.latitude_kind)[2])
        _check_height(cam, height if math.isfinite(height) else -math.inf, "xyz")
    ip = cam.ground_to_image(point[None, :], ccd=ccd)
    if not bool(ip.valid[0]):
        raise GeometryError(
            "the point cannot be projected into the image (behind the camera "
            "or outside the camera's time span)"
        )
    out = {"line": float(ip.line[0]), "sample": float(ip.sample[0])}
    if not (math.isfinite(out["line"]) and math.isfinite(out["sample"])):
        raise GeometryError("the point cannot be projected into the image (no finite result)")
    _check_in_image(cam, ccd, out["line"], out["sample"], extrapolate, "the point projects to")
    if not bool(ip.in_image[0]):
        logging.getLogger("planetref.camera").warning("the point projects outside the image")
    click.echo(json.dumps(out))


@camera_group.command("fit-rpc")
@click.argument("camera_file", metavar="CAMERA", type=click.Path(dir_okay=False))
@click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(dir_okay=False),
    help="Output: NAME.RPB, NAME_RPC.TXT, or an existing GeoTIFF to embed them in.",
)
@click.option("--ccd", default=None, help="CCD name (default: the camera's first CCD).")
@click.option(
    "--overwrite",
    is_flag=True,
    help="Replace an existing .RPB/_RPC.TXT, or the RPCs a GeoTIFF already holds.",
)
@click.option(
    "--height-range",
    nargs=2,
    type=float,
    default=(-8000.0, 8000.0),
    show_default=True,
    help="Lowest and highest terrain height of the fit (m).",
)
@click.option(
    "--grid",
    nargs=3,
    type=int,
    default=(21, 21, 7),
    show_default=True,
    help="Fitting grid: lines, samples, heights.",
)
def fit_rpc_command(
    camera_file: str,
    out: str,
    ccd: str | None,
    overwrite: bool,
    height_range: tuple[float, float],
    grid: tuple[int, int, int],
) -> None:
    """Fit RPCs to a rigorous camera (terrain-independent) and write them; prints JSON.

    Output: the fit report (RMS/max error in pixels on the fitting and check grids).
    """
    from planetref.camera.rpc import RpcBody, write_rpc
    from planetref.camera.rpc.stable import fit_rpc_stable

    lo, hi = height_range
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise InputError(f"--height-range needs two finite heights, low < high, got {lo}, {hi}")
    _check_rpc_output(camera_file, out, overwrite)
    cam = load_camera(camera_file)
    _check_height(cam, lo, "height-range")
    _check_height(cam, hi, "height-range")
    _check_rpc_raster_size(out, cam, ccd)
    rpc, report = fit_rpc_stable(cam, ccd=ccd, height_range_m=(lo, hi), grid=grid)
    if not (math.isfinite(report.fit_rms_px) and math.isfinite(report.check_rms_px)):
        raise GeometryError(
            f"the RPC fit failed (fit RMS {report.fit_rms_px}, check RMS "
            f"{report.check_rms_px} px): the camera's rays miss the heights "
            f"{lo:g} to {hi:g} m somewhere on the grid; nothing was written",
        )
    path = write_rpc(rpc, out, body=RpcBody(cam.ellipsoid, cam.latitude_kind))
    if report.check_max_px > RPC_WARN_MAX_PX:
        logging.getLogger("planetref.camera").warning(
            "%s: the RPC reproduces the camera to %.3g px RMS only (max %.3g px on the check "
            "grid): a third-order RPC cannot follow this camera over its whole image and "
            "%g to %g m; use the rigorous camera, or a narrower --height-range",
            path,
            report.check_rms_px,
            report.check_max_px,
            lo,
            hi,
        )
    doc = {
        "out": str(path),
        "fit_rms_px": report.fit_rms_px,
        "fit_max_px": report.fit_max_px,
        "check_rms_px": report.check_rms_px,
        "check_max_px": report.check_max_px,
        "check_max_ground_m": report.check_max_ground_m,
    }
    click.echo(json.dumps(json_safe(doc), allow_nan=False))


def _check_rpc_raster_size(out: str, cam: Any, ccd: str | None) -> None:
    """Refuse to embed RPCs in an existing GeoTIFF whose pixels are not the camera's image.

    RPCs in a GeoTIFF describe that file's pixels: a fit to a camera of another size (e.g.
    a CTX ISD's 11264 x 5000 lines into a 1024 x 1024 crop) would silently give the image
    a wrong geolocation.
    """
    from pathlib import Path

    p = Path(out)
    if p.suffix.lower() not in (".tif", ".tiff") or not p.is_file():
        return
    import rasterio
    from rasterio.errors import RasterioError

    try:
        with rasterio.open(p) as ds:
            shape = (ds.height, ds.width)
    except RasterioError:
        return  # write_rpc reports an unreadable GeoTIFF itself
    name = ccd or cam.ccd_names[0]
    size = tuple(int(v) for v in cam.image_size(name))
    if shape != size:
        raise InputError(
            f"--out is a {shape[0]} x {shape[1]} raster but CCD {name} of the camera is "
            f"{size[0]} x {size[1]} (lines x samples): RPCs embedded in it would describe "
            "other pixels; write a NAME.RPB or NAME_RPC.TXT instead",
            path=p,
        )


def _check_rpc_output(camera_file: str, out: str, overwrite: bool) -> None:
    """Never write over the camera; replace existing RPCs only with ``--overwrite``."""
    from pathlib import Path

    from planetref.pipeline.rundir import check_output_file

    p = Path(out)
    if p.suffix.lower() not in (".tif", ".tiff"):
        check_output_file(p, [camera_file], overwrite=overwrite)
        return
    check_output_file(p, [camera_file], overwrite=True)
    if not p.is_file() or overwrite:
        return
    import rasterio
    from rasterio.errors import RasterioError

    try:
        with rasterio.open(p) as ds:
            has_rpc = bool(ds.tags(ns="RPC"))
    except RasterioError:
        return  # write_rpc reports an unreadable GeoTIFF itself
    if has_rpc:
        raise InputError("--out already holds RPCs; pass --overwrite to replace them", path=p)
