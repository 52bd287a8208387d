"""``planetref info``: versions of planetref and its geospatial and deep-learning stack."""

from __future__ import annotations

import json
import os
from importlib.metadata import PackageNotFoundError, version

import click

__all__ = ["collect_info", "info_command"]


def _version(dist: str) -> str | None:
    try:
        return version(dist)
    except PackageNotFoundError:
        return None


def collect_info() -> dict[str, object]:
    """Versions of planetref, torch, kornia, rasterio, GDAL, PROJ, and the weights folder."""
    import pyproj
    import rasterio

    from planetref import __version__

    info: dict[str, object] = {
        "planetref": __version__,
        "python": ".".join(map(str, __import__("sys").version_info[:3])),
        "numpy": _version("numpy"),
        "torch": _version("torch"),
        "kornia": _version("kornia"),
        "opencv": _version("opencv-python-headless") or _version("opencv-python"),
        "rasterio": rasterio.__version__,
        "gdal": rasterio.__gdal_version__,
        "pyproj": pyproj.__version__,
        "proj": pyproj.proj_version_str,
    }
    try:
        from planetref.matching.weights import weights_dir

        info["weights_dir"] = str(weights_dir())
    except ImportError:
        info["weights_dir"] = os.environ.get("PLANETREF_WEIGHTS")
    return info


@click.command("info")
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of text.")
def info_command(as_json: bool) -> None:
    """Print versions of planetref, torch, kornia, rasterio, GDAL, PROJ and the weights dir."""
    info = collect_info()
    if as_json:
        click.echo(json.dumps(info, indent=2))
        return
    width = max(len(k) for k in info)
    for key, value in info.items():
        click.echo(f"{key:<{width}}  {value if value is not None else '(not installed)'}")
