"""The rigorous push-broom (line-scan) camera.

* :mod:`~planetref.camera.linescan.model` - the camera (orientation image model).
* :mod:`~planetref.camera.linescan.sensor` - its fixed parts: line-rate table, interior
  orientation, CCD placement.
* :mod:`~planetref.camera.linescan.kernel` - the one projection-and-partials kernel
  (ground -> image with every partial), called by the camera and the adjustment.
* :mod:`~planetref.camera.linescan.schema` - validation of the native JSON file.
"""

from planetref.camera.linescan.model import (
    FORMAT_NAME,
    FORMAT_VERSION,
    CcdGeometry,
    ImagePartials,
    InteriorOrientation,
    LineRateTable,
    LineScanCamera,
)

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "CcdGeometry",
    "ImagePartials",
    "InteriorOrientation",
    "LineRateTable",
    "LineScanCamera",
]
