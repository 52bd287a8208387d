"""Settings of the products stage: orthoimages through the adjusted cameras."""

from __future__ import annotations

from pydantic import Field

from planetref.runtime.settings import Settings

__all__ = ["OrthoOptions"]


class OrthoOptions(Settings):
    """The orthoimage of each CCD through the adjusted camera and the reference DEM.

    Attributes:
        enabled: Write them.
        gsd_m: Pixel size (metres); ``None``: the CCD image's own GSD.
    """

    enabled: bool = True
    gsd_m: float | None = Field(None, gt=0.0)
