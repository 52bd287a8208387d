""":class:`RpcStripCamera`: the CCD images of one strip, each with its own RPC.

Level-2 products of multi-CCD push-broom cameras (e.g. Tianwen-1 HiRIC's three TDI
CCDs) come as one image and one RPC per CCD. The strip camera puts them behind one
:class:`~planetref.camera.base.Camera` with one CCD name per image, so the pipeline
handles a strip of RPC images like a multi-CCD rigorous strip; the adjustment gives each
CCD its own bias (:mod:`planetref.adjust.models.rpc`).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.camera.base import ImagePoints, OnMiss, Terrain
from planetref.camera.rpc.bias import BiasedRpcCamera, write_refined_rpc
from planetref.camera.rpc.camera import RpcCamera
from planetref.errors import InputError

__all__ = ["RpcStripCamera", "write_refined_rpcs"]


class RpcStripCamera:
    """Several CCD images of one strip, each an :class:`RpcCamera` (or a biased one).

    Args:
        cameras: CCD name -> camera, in CCD order. All must refer to the same body and
            kind of latitude.

    Raises:
        InputError: No camera, or cameras on different bodies.
    """

    def __init__(self, cameras: Mapping[str, RpcCamera]) -> None:
        if not cameras:
            raise InputError("an RPC strip needs at least one CCD camera")
        cams = dict(cameras)
        first = next(iter(cams.values()))
        for name, cam in cams.items():
            if (cam.ellipsoid, cam.latitude_kind) != (first.ellipsoid, first.latitude_kind):
                raise InputError(
                    f"the RPCs of one strip must share a body: CCD {name!r} refers to "
                    f"{cam.ellipsoid.name!r} ({cam.latitude_kind}), the first to "
                    f"{first.ellipsoid.name!r} ({first.latitude_kind})"
                )
        self.cameras = cams
        self.ellipsoid = first.ellipsoid
        self.latitude_kind = first.latitude_kind

    def __repr__(self) -> str:
        return f"RpcStripCamera({list(self.cameras)})"

    @classmethod
    def from_files(
        cls, files: Mapping[str, str | os.PathLike[str]], **options: Any
    ) -> RpcStripCamera:
        """Read one RPC file per CCD (any format :meth:`RpcCamera.from_file` reads).

        Args:
            files: CCD name -> RPC file (a raster with RPC tags or a sidecar).
            **options: Passed to :meth:`RpcCamera.from_file` (e.g. ``body``).
        """
        return cls(
            {name: RpcCamera.from_file(Path(f), name=name, **options) for name, f in files.items()}
        )

    def _cam(self, ccd: str | None) -> RpcCamera:
        if ccd is None:
            return next(iter(self.cameras.values()))
        try:
            return self.cameras[ccd]
        except KeyError:
            raise InputError(
                f"unknown CCD {ccd!r}; this RPC strip has {list(self.cameras)}", field="ccd"
            ) from None

    @property
    def ccd_names(self) -> tuple[str, ...]:
        """The CCD names, in order."""
        return tuple(self.cameras)

    @property
    def ray_heights_m(self) -> tuple[float, float]:
        """The height range every CCD's RPC is valid for (metres)."""
        ranges = [c.ray_heights_m for c in self.cameras.values()]
        lo, hi = max(r[0] for r in ranges), min(r[1] for r in ranges)
        return (lo, hi) if hi > lo else ranges[0]

    def image_size(self, ccd: str | None = None) -> tuple[int, int]:
        """``(n_lines, n_samples)`` of a CCD image."""
        return self._cam(ccd).image_size()

    def ground_to_image(self, xyz: ArrayLike, *, ccd: str | None = None) -> ImagePoints:
        """Project body-fixed points (metres) into a CCD image."""
        return self._cam(ccd).ground_to_image(xyz)

    def image_to_ground(
        self,
        line: ArrayLike,
        sample: ArrayLike,
        terrain: Terrain | float = 0.0,
        *,
        ccd: str | None = None,
        on_miss: OnMiss = "raise",
    ) -> NDArray[np.float64]:
        """Intersect a CCD image's lines of sight with a height or a terrain."""
        return self._cam(ccd).image_to_ground(line, sample, terrain, on_miss=on_miss)


def write_refined_rpcs(
    camera: Any, folder: str | os.PathLike[str], name: str
) -> tuple[list[Path], dict[str, Any]] | None:
    """Write the refined RPC of each bias-corrected image of a camera.

    Args:
        camera: A :class:`BiasedRpcCamera` (file ``NAME``) or an :class:`RpcStripCamera`
            of them (files ``NAME_CCD``); anything else is not an RPC image.
        folder: Output folder.
        name: File-name stem.

    Returns:
        ``(paths, {ccd: report})`` (see :func:`write_refined_rpc`), or None when
        ``camera`` holds no bias-corrected RPC image.
    """
    if isinstance(camera, BiasedRpcCamera):
        images = {camera.name: (camera, name)}
    elif isinstance(camera, RpcStripCamera) and all(
        isinstance(c, BiasedRpcCamera) for c in camera.cameras.values()
    ):
        # (The filter only narrows the type: every camera passed the test above.)
        images = {
            k: (c, f"{name}_{k}")
            for k, c in camera.cameras.items()
            if isinstance(c, BiasedRpcCamera)
        }
    else:
        return None
    paths: list[Path] = []
    reports: dict[str, Any] = {}
    for ccd, (cam, stem) in images.items():
        written, reports[ccd] = write_refined_rpc(cam, folder, stem)
        paths += written
    return paths, reports
