"""``planetref camera``: image <-> ground with any supported camera file.

Image coordinates follow planetref's convention: ``(line, sample)`` with the first
pixel's centre at ``(0.5, 0.5)`` (usgscsm's convention for CSM ISDs, GDAL's for RPCs).
Latitudes are planetocentric for Mars cameras and geodetic (planetographic) for Earth
RPCs; longitudes are east-positive degrees.
"""

from __future__ import annotations

import json
import math

import click
import numpy as np

from planetref.camera.geodesy import lonlat_to_xyz, xyz_to_lonlat
from planetref.camera.io import load_camera
from planetref.errors import GeometryError, InputError

__all__ = ["camera_group"]


def _finite(name: str, value: float | None) -> None:
    if value is not None and not math.isfinite(value):
        raise InputError(f"--{name} must be a finite number, got {value}")


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
def image_to_ground(
    camera_file: str, line: float, sample: float, height: float, ccd: str | None
) -> None:
    """Intersect the ray of an image point with a height; prints JSON.

    Output: {"x_m", "y_m", "z_m", "lat_deg", "lon_deg", "height_m"}.
    """
    for name, value in (("line", line), ("sample", sample), ("height", height)):
        _finite(name, value)
    cam = load_camera(camera_file)
    xyz = cam.image_to_ground(
        np.array([line]), np.array([sample]), height, ccd=ccd, on_miss="raise"
    )[0]
    lon, lat, h = xyz_to_lonlat(xyz, cam.ellipsoid, cam.latitude_kind)
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
def ground_to_image(
    camera_file: str,
    xyz: tuple[float, float, float] | None,
    lat: float | None,
    lon: float | None,
    height: float | None,
    ccd: str | None,
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
        point = lonlat_to_xyz(lon, lat, height, cam.ellipsoid, cam.latitude_kind)
    ip = cam.ground_to_image(point[None, :], ccd=ccd)
    if not bool(ip.valid[0]):
        raise GeometryError(
            "the point cannot be projected into the image (behind the camera "
            "or outside the camera's time span)"
        )
    out = {"line": float(ip.line[0]), "sample": float(ip.sample[0])}
    if not bool(ip.in_image[0]):
        click.echo("warning: the point projects outside the image", err=True)
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
    height_range: tuple[float, float],
    grid: tuple[int, int, int],
) -> None:
    """Fit RPCs to a rigorous camera (terrain-independent) and write them; prints JSON.

    Output: the fit report (RMS/max error in pixels on the fitting and check grids).
    """
    from planetref.camera.rpc import RpcBody, fit_rpc, write_rpc

    lo, hi = height_range
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise InputError(f"--height-range needs two finite heights, low < high, got {lo}, {hi}")
    cam = load_camera(camera_file)
    rpc, report = fit_rpc(cam, ccd=ccd, height_range_m=(lo, hi), grid=grid)
    path = write_rpc(rpc, out, body=RpcBody(cam.ellipsoid, cam.latitude_kind))
    doc = {
        "out": str(path),
        "fit_rms_px": report.fit_rms_px,
        "fit_max_px": report.fit_max_px,
        "check_rms_px": report.check_rms_px,
        "check_max_px": report.check_max_px,
        "check_max_ground_m": report.check_max_ground_m,
    }
    click.echo(json.dumps(doc))
