"""The image-space bias of an RPC image as adjustment unknowns (Grodecki & Dial 2003).

Each RPC camera (one image, one CCD) gets the coefficients of its bias model
(:mod:`planetref.camera.rpc.bias`: ``shift``, ``shift+drift`` or ``affine``, in pixels).
Partials are analytic: with respect to the coefficients they are ``1, u, v`` at the
RPC's projection; with respect to the ground point they chain the RPC's partials in
longitude, latitude and height (:meth:`~planetref.camera.rpc.model.Rpc.
project_with_partials`) through the geodesy's (:func:`~planetref.geometry.geodesy.
lonlat_xyz_jacobian`) and the correction's 2 x 2 matrix.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planetref.adjust.models.protocol import CoverageIssue, Evaluation, mode_and_sigma
from planetref.adjust.rpc_config import RpcParameters
from planetref.camera.rpc import RpcCamera
from planetref.camera.rpc.bias import BIAS_MODELS, BIAS_TERMS, BiasedRpcCamera, RpcBias
from planetref.errors import AdjustmentError
from planetref.geometry.geodesy import lonlat_xyz_jacobian, xyz_to_lonlat

__all__ = ["RpcParameterization"]

F64 = NDArray[np.float64]


class RpcParameterization:
    """The bias coefficients of one RPC image.

    Args:
        camera_id: The image's id.
        camera: An :class:`RpcCamera`, or a :class:`BiasedRpcCamera` whose correction is
            the starting point (its coefficients outside the bias model stay as they are).
        config: The bias model, mode and sigma.
        fixed: Hold every coefficient fixed.
    """

    def __init__(
        self, camera_id: str, camera: RpcCamera, config: RpcParameters, *, fixed: bool = False
    ) -> None:
        self.camera_id = camera_id
        self.camera = camera
        self.config = config
        if isinstance(camera, BiasedRpcCamera):
            self._base_camera: RpcCamera = camera.base
            self._bias = camera.bias
        else:
            self._base_camera = camera
            self._bias = RpcBias(camera.image_size())
        self._index = np.array(BIAS_MODELS[config.bias], np.intp)
        n = len(self._index)
        self.names = tuple(BIAS_TERMS[i] for i in self._index)
        self.units = ("px",) * n
        self.x0 = np.asarray(self._bias.coefficients, np.float64)[self._index].copy()
        self.mode, self.sigma = mode_and_sigma(config.mode, config.sigma_px, n, fixed)
        self.pattern_columns = np.arange(n, dtype=np.intp)[None, :]
        #: No linear pseudo-observations between the coefficients.
        self.constraints: tuple[F64, F64] | None = None

    def _bias_at(self, x: F64) -> RpcBias:
        full = np.asarray(self._bias.coefficients, np.float64).copy()
        full[self._index] = np.asarray(x, np.float64)
        return self._bias.with_coefficients(full)

    @property
    def bias_model(self) -> str:
        """The bias model's name (``shift``, ``shift+drift`` or ``affine``)."""
        return self.config.bias

    def evaluate(
        self,
        x: F64,
        xyz: F64,
        ccd: int,
        line_guess: F64,
        rate_guess: F64 | None = None,
        partials: bool = True,
    ) -> Evaluation:
        """Project into the image with analytic partials.

        Args:
            x: The bias coefficients (pixels).
            xyz: Ground points (metres), ``(m, 3)``.
            ccd: Must be 0 (one CCD per RPC image).
            line_guess: Unused (an RPC is explicit).
            rate_guess: Unused.
            partials: ``False`` projects only.
        """
        xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
        m = len(xyz)
        cam = self._base_camera
        bias = self._bias_at(x)
        lon, lat, h = xyz_to_lonlat(xyz, cam.ellipsoid, cam.latitude_kind)
        if not partials:
            raw_l, raw_s = cam.rpc.project(lon, lat, h)
            line, samp = bias.apply(raw_l, raw_s)
            valid = np.isfinite(line) & np.isfinite(samp)
            return Evaluation(
                np.where(valid, line, np.nan),
                np.where(valid, samp, np.nan),
                valid,
                np.zeros(m, np.intp),
                np.empty((m, 2, 0)),
                np.empty((m, 2, 0)),
            )
        raw_l, raw_s, d_llh = cam.rpc.project_with_partials(lon, lat, h)
        line, samp = bias.apply(raw_l, raw_s)
        jac = lonlat_xyz_jacobian(xyz, cam.ellipsoid, cam.latitude_kind)
        d_ground = np.einsum("ij,mjk,mkl->mil", bias.matrix(), d_llh, jac)
        d_params = bias.partials(raw_l, raw_s)[:, :, self._index]
        valid = np.isfinite(line) & np.isfinite(samp)
        valid &= np.all(np.isfinite(d_ground), axis=(1, 2))
        bad = ~valid
        d_params[bad] = 0.0
        d_ground[bad] = 0.0
        return Evaluation(
            np.where(valid, line, np.nan),
            np.where(valid, samp, np.nan),
            valid,
            np.zeros(m, np.intp),
            d_params,
            d_ground,
        )

    def build(self, x: F64) -> BiasedRpcCamera:
        """The corrected camera with coefficients ``x``."""
        return BiasedRpcCamera(self._base_camera, self._bias_at(x))

    def physical(self, x: F64) -> dict[str, Any]:
        """The bias model and all six coefficients (pixels at the image edge)."""
        coeffs = self._bias_at(x).coefficients
        return {"bias_model": self.config.bias} | dict(zip(BIAS_TERMS, coeffs, strict=True))

    def coverage(self, ccd: NDArray[np.intp], line: F64) -> list[CoverageIssue]:
        """The image needs more observations (2 equations each) than free coefficients."""
        free = np.flatnonzero(self.mode != 2)
        need = math.ceil(len(free) / 2) + 1 if free.size else 0
        if len(line) < need:
            return [
                CoverageIssue(
                    f"image {self.camera_id!r}", tuple(int(i) for i in free), len(line), need
                )
            ]
        return []

    def weaken(self, issues: list[CoverageIssue]) -> list[str]:
        """Too few observations for an image's bias: always an error.

        Raises:
            AdjustmentError: Naming the image, the counts and a smaller bias model.
        """
        if not issues:
            return []
        i = issues[0]
        raise AdjustmentError(
            f"RPC image {self.camera_id!r}: {i.count} observation(s) cannot determine its "
            f"{len(i.indices)} bias coefficient(s) ({self.config.bias}); add observations "
            f"or choose a smaller bias model (rpc.bias = 'shift')"
        )
