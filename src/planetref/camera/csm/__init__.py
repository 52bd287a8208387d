"""USGS CSM line-scan ISDs and a camera model that follows usgscsm.

Modules: :mod:`~planetref.camera.csm.isd` (typed ISD, writer),
:mod:`~planetref.camera.csm.reader` (parsing), :mod:`~planetref.camera.csm.orientation`
(quaternions), :mod:`~planetref.camera.csm.interpolation` (ephemeris interpolation),
:mod:`~planetref.camera.csm.ephemeris` (the resampled position, pointing and time tables),
:mod:`~planetref.camera.csm.distortion` (lens distortion),
:mod:`~planetref.camera.csm.camera` (:class:`CsmLineScanCamera`),
:mod:`~planetref.camera.csm.export` (native line-scan cameras written as ISDs).
"""

from planetref.camera.csm.camera import CsmLineScanCamera
from planetref.camera.csm.export import linescan_to_isd, write_linescan_isds
from planetref.camera.csm.isd import (
    CORRECTION_PARAMETER_NAMES,
    CSM_LINE_SCANNER_MODEL,
    CsmCorrection,
    CsmIsd,
    CsmOrientations,
    CsmStates,
    write_isd,
)
from planetref.camera.csm.reader import read_isd

__all__ = [
    "CORRECTION_PARAMETER_NAMES",
    "CSM_LINE_SCANNER_MODEL",
    "CsmCorrection",
    "CsmIsd",
    "CsmLineScanCamera",
    "CsmOrientations",
    "CsmStates",
    "linescan_to_isd",
    "read_isd",
    "write_isd",
    "write_linescan_isds",
]
