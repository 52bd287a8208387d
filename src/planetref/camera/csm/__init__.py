"""USGS CSM line-scan ISDs and a camera model that follows usgscsm."""

from planetref.camera.csm.isd import *  # noqa: F403
from planetref.camera.csm.isd import _apply_distortion, _remove_distortion  # noqa: F401
