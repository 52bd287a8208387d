"""Which parameterisation adjusts which camera."""

from __future__ import annotations

from typing import Any

from planetref.adjust.config import AdjustConfig
from planetref.adjust.models.csm import CsmParameterization
from planetref.adjust.models.linescan import LineScanParameterization
from planetref.adjust.models.protocol import AdjustableCamera
from planetref.camera.linescan import LineScanCamera
from planetref.errors import InputError

__all__ = ["parameterize"]


def parameterize(camera_id: str, camera: Any, config: AdjustConfig) -> AdjustableCamera:
    """The parameterisation of a camera under a configuration.

    Args:
        camera_id: Id of the camera in the network.
        camera: A native line-scan, CSM line-scan or RPC camera (or a strip of RPCs).
        config: The adjustment configuration.

    Raises:
        InputError: For cameras that cannot be adjusted.
    """
    fixed = camera_id in config.fixed_cameras
    if isinstance(camera, LineScanCamera):
        return LineScanParameterization(camera_id, camera, config.linescan, fixed=fixed)
    from planetref.camera.csm import CsmLineScanCamera

    if isinstance(camera, CsmLineScanCamera):
        return CsmParameterization(camera_id, camera, config.csm, fixed=fixed)
    from planetref.camera.rpc import RpcCamera
    from planetref.camera.rpc.strip import RpcStripCamera

    if isinstance(camera, RpcCamera | RpcStripCamera):
        from planetref.adjust.models.rpc import RpcParameterization

        return RpcParameterization(camera_id, camera, config.rpc, fixed=fixed)
    raise InputError(
        f"camera {camera_id!r} ({type(camera).__name__}) cannot be adjusted; use a "
        f"native line-scan, CSM line-scan ISD or RPC camera"
    )
