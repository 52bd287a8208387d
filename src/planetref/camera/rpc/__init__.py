"""Rational polynomial cameras (RPC00B): files, projection, localisation and fitting.

Modules: :mod:`~planetref.camera.rpc.model` (the RPC00B polynomials),
:mod:`~planetref.camera.rpc.body` (the body and latitude an RPC refers to),
:mod:`~planetref.camera.rpc.formats` (GeoTIFF, ``.RPB`` and ``_RPC.TXT`` readers and
writers), :mod:`~planetref.camera.rpc.camera` (:class:`RpcCamera`),
:mod:`~planetref.camera.rpc.fit` (:func:`fit_rpc`), :mod:`~planetref.camera.rpc.bias`
(image-space bias compensation, :class:`BiasedRpcCamera`, refined RPCs) and
:mod:`~planetref.camera.rpc.strip` (:class:`RpcStripCamera`, one RPC per CCD image).
"""

from planetref.camera.rpc.bias import BiasedRpcCamera, RpcBias
from planetref.camera.rpc.body import EARTH_BODY, MARS_BODY, RpcBody
from planetref.camera.rpc.camera import RpcCamera
from planetref.camera.rpc.fit import FitReport, fit_rpc
from planetref.camera.rpc.formats import (
    read_rpc,
    read_rpc_body,
    rpc_sidecar_path,
    write_rpc,
    write_rpc_geotiff,
    write_rpc_rpb,
    write_rpc_txt,
)
from planetref.camera.rpc.model import Rpc
from planetref.camera.rpc.strip import RpcStripCamera

__all__ = [
    "EARTH_BODY",
    "MARS_BODY",
    "BiasedRpcCamera",
    "FitReport",
    "Rpc",
    "RpcBias",
    "RpcBody",
    "RpcCamera",
    "RpcStripCamera",
    "fit_rpc",
    "read_rpc",
    "read_rpc_body",
    "rpc_sidecar_path",
    "write_rpc",
    "write_rpc_geotiff",
    "write_rpc_rpb",
    "write_rpc_txt",
]
