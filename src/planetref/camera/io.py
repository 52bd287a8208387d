"""Open any supported camera file, detecting its format from its content.

Supported: the native line-scan JSON (``"format": "planetref-linescan"``), USGS CSM
line-scan ISDs (``"name_model": "USGS_ASTRO_LINE_SCANNER_SENSOR_MODEL"``), and RPCs in
GeoTIFF metadata, ``.RPB`` files or ``_RPC.TXT`` files.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from planetref.camera.base import Camera
from planetref.errors import MissingFileError, UnsupportedFormatError
from planetref.runtime.jsonfile import read_json

__all__ = ["detect_camera_format", "load_camera"]

CSM_LINESCAN_MODEL = "USGS_ASTRO_LINE_SCANNER_SENSOR_MODEL"


def detect_camera_format(path: str | os.PathLike[str]) -> str:
    """``"linescan"``, ``"csm"`` or ``"rpc"``, from the file's content.

    Raises:
        MissingFileError: The file does not exist.
        UnsupportedFormatError: The content is none of the supported formats.
    """
    p = Path(path)
    if not p.is_file():
        raise MissingFileError("no such camera file", path=p)
    with open(p, "rb") as fh:
        head = fh.read(4096)
    if head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return "rpc"
    text = head.decode("utf-8", errors="replace").lstrip()
    if text.startswith("{"):
        doc = read_json(p, "camera file")
        if isinstance(doc, dict):
            if doc.get("format") == "planetref-linescan":
                return "linescan"
            if doc.get("name_model") == CSM_LINESCAN_MODEL:
                return "csm"
            if "name_model" in doc:
                raise UnsupportedFormatError(
                    f"CSM model {doc['name_model']!r} is not supported (only {CSM_LINESCAN_MODEL})",
                    path=p,
                    field="name_model",
                )
        raise UnsupportedFormatError(
            "JSON file is neither a planetref line-scan camera nor a CSM line-scan ISD", path=p
        )
    upper = text.upper()
    if "LINENUMCOEF" in upper or "LINE_NUM_COEFF" in upper or "LINE_OFF" in upper:
        return "rpc"
    raise UnsupportedFormatError(
        "unrecognised camera file (expected native JSON, CSM ISD JSON, a GeoTIFF with RPCs, "
        ".RPB or _RPC.TXT)",
        path=p,
    )


def load_camera(path: str | os.PathLike[str], **options: Any) -> Camera:
    """Open a camera file of any supported format.

    Args:
        path: The camera file.
        **options: Passed to the format's reader (e.g. ``body="mars"`` for RPCs).

    Returns:
        An object implementing :class:`~planetref.camera.base.Camera`.
    """
    kind = detect_camera_format(path)
    if kind == "linescan":
        from planetref.camera.linescan import LineScanCamera

        return LineScanCamera.from_json(path)
    if kind == "csm":
        from planetref.camera.csm import CsmLineScanCamera

        return CsmLineScanCamera.from_file(path)
    from planetref.camera.rpc import RpcCamera

    return RpcCamera.from_file(path, **options)
