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
from planetref.arrays import F64
from planetref.camera.rpc import RpcCamera
from planetref.camera.rpc.bias import BIAS_MODELS, BIAS_TERMS, BiasedRpcCamera, RpcBias
from planetref.camera.rpc.strip import RpcStripCamera
from planetref.errors import AdjustmentError
from planetref.geometry.geodesy import lonlat_xyz_jacobian, xyz_to_lonlat

__all__ = ["RpcParameterization"]


class RpcParameterization:
    """The bias coefficients of one RPC image, or of each CCD image of an RPC strip.

    Local parameters are, per CCD (in CCD order), the coefficients of the bias model;
    for a strip they are named ``CCD.term``. Each CCD is one pattern.

    Args:
        camera_id: The image's (strip's) id.
        camera: An :class:`RpcCamera` or an :class:`RpcStripCamera`; a
            :class:`BiasedRpcCamera`'s correction is the starting point (its coefficients
            outside the bias model stay as they are).
        config: The bias model, mode and sigma.
        fixed: Hold every coefficient fixed.
    """

    def __init__(
        self,
        camera_id: str,
        camera: RpcCamera | RpcStripCamera,
        config: RpcParameters,
        *,
        fixed: bool = False,
    ) -> None:
        self.camera_id = camera_id
        self.camera = camera
        self.config = config
        self._strip = isinstance(camera, RpcStripCamera)
        cams = camera.cameras if isinstance(camera, RpcStripCamera) else {camera.name: camera}
        self._bases: list[RpcCamera] = []
        self._biases: list[RpcBias] = []
        for cam in cams.values():
            if isinstance(cam, BiasedRpcCamera):
                self._bases.append(cam.base)
                self._biases.append(cam.bias)
            else:
                self._bases.append(cam)
                self._biases.append(RpcBias(cam.image_size()))
        self._ccds = tuple(cams)
        self._index = np.array(BIAS_MODELS[config.bias], np.intp)
        q = len(self._index)
        terms = [BIAS_TERMS[i] for i in self._index]
        self.names = (
            tuple(f"{c}.{t}" for c in self._ccds for t in terms) if self._strip else tuple(terms)
        )
        n = len(self.names)
        self.units = ("px",) * n
        self.x0 = np.concatenate(
            [np.asarray(b.coefficients, np.float64)[self._index] for b in self._biases]
        )
        self.mode, self.sigma = mode_and_sigma(config.mode, config.sigma_px, n, fixed)
        self.pattern_columns = np.arange(n, dtype=np.intp).reshape(len(self._ccds), q)
        #: No linear pseudo-observations between the coefficients.
        self.constraints: tuple[F64, F64] | None = None

    def _bias_at(self, x: F64, k: int) -> RpcBias:
        q = len(self._index)
        full = np.asarray(self._biases[k].coefficients, np.float64).copy()
        full[self._index] = np.asarray(x, np.float64)[k * q : (k + 1) * q]
        return self._biases[k].with_coefficients(full)

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
        """Project into CCD ``ccd`` with analytic partials.

        Args:
            x: The bias coefficients (pixels).
            xyz: Ground points (metres), ``(m, 3)``.
            ccd: CCD index (0 for a single image).
            line_guess: Unused (an RPC is explicit).
            rate_guess: Unused.
            partials: ``False`` projects only.
        """
        xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
        m = len(xyz)
        cam = self._bases[ccd]
        bias = self._bias_at(x, ccd)
        pattern = np.full(m, ccd, np.intp)
        lon, lat, h = xyz_to_lonlat(xyz, cam.ellipsoid, cam.latitude_kind)
        if not partials:
            raw_l, raw_s = cam.rpc.project(lon, lat, h)
            line, samp = bias.apply(raw_l, raw_s)
            valid = np.isfinite(line) & np.isfinite(samp)
            return Evaluation(
                np.where(valid, line, np.nan),
                np.where(valid, samp, np.nan),
                valid,
                pattern,
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
            pattern,
            d_params,
            d_ground,
        )

    def build(self, x: F64) -> BiasedRpcCamera | RpcStripCamera:
        """The corrected camera (or strip of corrected cameras) with coefficients ``x``."""
        cams = [BiasedRpcCamera(b, self._bias_at(x, k)) for k, b in enumerate(self._bases)]
        if not self._strip:
            return cams[0]
        return RpcStripCamera(dict(zip(self._ccds, cams, strict=True)))

    def physical(self, x: F64) -> dict[str, Any]:
        """The bias model and all six coefficients per CCD (pixels at the image edge)."""
        out: dict[str, Any] = {"bias_model": self.config.bias}
        for k, c in enumerate(self._ccds):
            coeffs = dict(zip(BIAS_TERMS, self._bias_at(x, k).coefficients, strict=True))
            out |= {f"{c}.{t}": v for t, v in coeffs.items()} if self._strip else coeffs
        return out

    def coverage(self, ccd: NDArray[np.intp], line: F64) -> list[CoverageIssue]:
        """Each image needs more observations (2 equations each) than free coefficients."""
        issues = []
        for k, rows in enumerate(self.pattern_columns):
            free = rows[self.mode[rows] != 2]
            need = math.ceil(len(free) / 2) + 1 if free.size else 0
            count = int(np.count_nonzero(np.asarray(ccd) == k))
            if count < need:
                label = f"image {self.camera_id!r}" + (
                    f" CCD {self._ccds[k]}" if self._strip else ""
                )
                issues.append(CoverageIssue(label, tuple(int(i) for i in free), count, need))
        return issues

    def check_geometry(self, ccd: NDArray[np.intp], line: F64, sample: F64) -> None:
        """Refuse bias coefficients the observations' geometry cannot determine.

        Counting observations (:meth:`coverage`) is not enough: MCPs on one image line
        cannot fix a drift, MCPs along any straight line cannot fix an affine correction
        (``[1, u, v]`` is then of rank 2), and the solver "converges" to one of the
        infinitely many solutions and writes a degenerate RPC. The rank of each image's
        design for its free (unweighted) coefficients is judged from its singular values
        (relative tolerance 1e-8, columns scaled to unit norm).

        Raises:
            AdjustmentError: Naming the image, the rank, and a smaller bias model.
        """
        ccd = np.asarray(ccd)
        for k, rows in enumerate(self.pattern_columns):
            free = [j for j, col in enumerate(rows) if self.mode[col] == 0]
            sel = ccd == k
            if not free or not np.any(sel):
                continue
            u, v = self._biases[k].normalized(np.asarray(line)[sel], np.asarray(sample)[sel])
            basis = {0: np.ones_like(u), 1: u, 2: v}  # a0 b0 | a1 b1 | a2 b2
            design = np.zeros((2 * u.size, len(free)))
            for c, j in enumerate(free):
                term = int(self._index[j])
                design[term % 2 :: 2, c] = basis[term // 2]
            norms = np.linalg.norm(design, axis=0)
            sv = np.linalg.svd(design / np.where(norms > 0, norms, 1.0), compute_uv=False)
            rank = int(np.count_nonzero(sv > 1e-8 * max(float(sv[0]), 1e-300)))
            if rank < len(free):
                label = f"image {self.camera_id!r}" + (
                    f" CCD {self._ccds[k]}" if self._strip else ""
                )
                raise AdjustmentError(
                    f"RPC {label}: the {int(np.count_nonzero(sel))} observation(s) cannot "
                    f"determine its {len(free)} free bias coefficient(s) ({self.config.bias}): "
                    f"their positions in the image are degenerate (collinear or on one "
                    f"line; rank {rank} of {len(free)}); add observations elsewhere in the "
                    "image or choose a smaller bias model (rpc.bias = 'shift')"
                )

    def weaken(self, issues: list[CoverageIssue]) -> tuple[RpcParameterization, list[str]]:
        """Too few observations for an image's bias: always an error.

        Returns:
            ``(self, [])`` when there are no issues.

        Raises:
            AdjustmentError: Naming the image, the counts and a smaller bias model.
        """
        if not issues:
            return self, []
        i = issues[0]
        raise AdjustmentError(
            f"RPC {i.label}: {i.count} observation(s) cannot determine its "
            f"{len(i.indices)} bias coefficient(s) ({self.config.bias}); add observations "
            f"or choose a smaller bias model (rpc.bias = 'shift')"
        )
