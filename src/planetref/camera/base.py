"""What every planetref camera and terrain provides.

Image coordinates
-----------------
All planetref cameras use one pixel convention: ``(line, sample)`` with the top-left
corner of the first pixel at ``(0, 0)``, so the centre of the first pixel is
``(0.5, 0.5)``. This is usgscsm's convention for CSM ISDs and GDAL's for RPCs.
ISIS measures (first pixel centre at ``(1, 1)``) convert with ``csm = isis - 0.5``
(see :func:`isis_to_csm`).

Terrains
--------
:class:`Terrain`, :class:`ConstantHeight` and ``OnMiss`` live in
:mod:`planetref.geometry.terrain` (with the one ray/terrain intersection and its rule at
holes) and are re-exported here.

Ground coordinates
------------------
Body-fixed XYZ in metres (see :mod:`planetref.geometry.geodesy`), or longitude/latitude
(degrees, planetocentric unless a camera's body says otherwise) and height above the
camera's ellipsoid.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.geometry.geodesy import Ellipsoid, LatitudeKind
from planetref.geometry.terrain import ConstantHeight, OnMiss, Terrain

__all__ = [
    "Camera",
    "ConstantHeight",
    "ImagePoints",
    "OnMiss",
    "Terrain",
    "isis_to_csm",
]


def isis_to_csm(line: ArrayLike, sample: ArrayLike) -> tuple[NDArray[np.float64], ...]:
    """ISIS (1-based, first pixel centre at 1.0) -> planetref/CSM (first centre at 0.5)."""
    return np.asarray(line, float) - 0.5, np.asarray(sample, float) - 0.5


@dataclass(frozen=True)
class ImagePoints:
    """Image coordinates returned by ``ground_to_image``.

    Attributes:
        line: Line coordinates (pixel convention of this module), shape ``(M,)``.
        sample: Sample coordinates, shape ``(M,)``.
        valid: False where the point could not be projected (behind the camera, no
            convergence); ``line``/``sample`` are NaN there.
        in_image: True where the point falls inside the image (``0 <= line < n_lines``
            and ``0 <= sample < n_samples``).
    """

    line: NDArray[np.float64]
    sample: NDArray[np.float64]
    valid: NDArray[np.bool_]
    in_image: NDArray[np.bool_]

    def as_array(self) -> NDArray[np.float64]:
        """``(M, 2)`` array of ``(line, sample)``."""
        return np.stack([self.line, self.sample], axis=-1)


@runtime_checkable
class Camera(Protocol):
    """The interface shared by every camera model (native line scan, CSM ISD, RPC).

    Image coordinates follow this module's convention; ground coordinates are
    body-fixed XYZ in metres.

    Attributes:
        ellipsoid: The body the camera's heights and latitudes refer to.
        latitude_kind: Which latitude the camera's lon/lat interfaces use.
        ccd_names: Names of the camera's detector arrays (one entry for a single CCD).
    """

    # Read-only members: the cameras are immutable (frozen dataclasses, properties).
    @property
    def ellipsoid(self) -> Ellipsoid:
        """The body the camera's heights and latitudes refer to."""
        ...

    @property
    def latitude_kind(self) -> LatitudeKind:
        """Which latitude the camera's lon/lat interfaces use."""
        ...

    @property
    def ccd_names(self) -> tuple[str, ...]:
        """Names of the CCDs; the first is the default."""
        ...

    def image_size(self, ccd: str | None = None) -> tuple[int, int]:
        """``(n_lines, n_samples)`` of a CCD image."""
        ...

    def image_to_ground(
        self,
        line: ArrayLike,
        sample: ArrayLike,
        terrain: Terrain | float = 0.0,
        *,
        ccd: str | None = None,
        on_miss: OnMiss = "raise",
    ) -> NDArray[np.float64]:
        """Intersect the rays of image points with the terrain.

        Args:
            line: Line coordinates, shape ``(M,)`` or scalar.
            sample: Sample coordinates, same shape.
            terrain: A :class:`Terrain`, or a height in metres above the ellipsoid.
            ccd: Which CCD the image points belong to (default: the first).
            on_miss: ``"raise"`` a :class:`~planetref.errors.GeometryError` when a ray
                misses the terrain, or return NaN rows (``"nan"``).

        Returns:
            XYZ in metres, shape ``(M, 3)``.
        """
        ...

    def ground_to_image(self, xyz: ArrayLike, *, ccd: str | None = None) -> ImagePoints:
        """Project body-fixed points (metres, shape ``(M, 3)``) into a CCD image."""
        ...
