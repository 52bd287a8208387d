"""Image-space bias compensation of an RPC (Grodecki & Dial 2003) and refined RPCs.

Model
-----
An RPC's systematic error over a scene of a few tens of kilometres is, to a fraction of
a pixel, a shift of the image (attitude and ephemeris biases), a drift of that shift
along the line (time) axis (gyro drift), and at most an affine distortion (Grodecki &
Dial, "Block adjustment of high-resolution satellite images described by rational
polynomials", PE&RS 69(1), 2003). The corrected camera maps ground to image as::

    line   = l + a0 + a1 u + a2 v
    sample = s + b0 + b1 u + b2 v
    u = (l - n_lines / 2) / (n_lines / 2),   v = (s - n_samples / 2) / (n_samples / 2)

where ``(l, s)`` is the RPC's projection (planetref convention) and ``u, v`` its
position in the image normalised to [-1, 1], so every coefficient is in pixels (the
correction at the image edge). The correction is a function of the RPC's own
projection, so ground -> image stays explicit and image -> ground inverts a 2 x 2
linear map exactly. Bias models (the free coefficients; the others are zero):

* ``shift``: ``a0, b0``;
* ``shift+drift``: ``a0, b0, a1, b1`` (shift and its drift with the line);
* ``affine``: all six.

Refined RPCs
------------
A shift is absorbed exactly by LINE_OFF and SAMP_OFF. A drift or affine correction is
composed with the RPC by refitting an RPC00B to the corrected camera over the RPC's own
height domain, through the regularisation ladder
(:func:`~planetref.camera.rpc.stable.fit_rpc_stable`): the corrected mapping (an affine
function of two rationals with different denominators) is not itself an RPC00B, so the
refit is not known to be well posed, and the ladder keeps a denominator pole away from
the image. Its first rung is :func:`~planetref.camera.rpc.fit.fit_rpc`'s default, and a
well-behaved refit stops there (the same RPC bit for bit); the fit's check errors are
reported (thousandths of a pixel or less for corrections of a few pixels).
"""

from __future__ import annotations

import dataclasses
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike

from planetref.arrays import F64
from planetref.camera.base import ImagePoints, OnMiss, Terrain
from planetref.camera.rpc.body import RpcBody
from planetref.camera.rpc.camera import RpcCamera
from planetref.camera.rpc.fit import FitReport
from planetref.camera.rpc.formats import write_rpc
from planetref.camera.rpc.model import Rpc
from planetref.camera.rpc.stable import fit_rpc_stable
from planetref.errors import InputError
from planetref.runtime.atomic import atomic_path

__all__ = [
    "BIAS_MODELS",
    "BIAS_TERMS",
    "BiasModel",
    "BiasedRpcCamera",
    "RpcBias",
    "refined_rpc",
    "write_refined_rpc",
]

BiasModel = Literal["shift", "shift+drift", "affine"]

#: Names of the six coefficients, in the order of :attr:`RpcBias.coefficients`:
#: ``a0, b0, a1, b1, a2, b2`` (line/sample shift, by-line terms, by-sample terms).
BIAS_TERMS: tuple[str, ...] = (
    "line_shift_px",
    "sample_shift_px",
    "line_by_line_px",
    "sample_by_line_px",
    "line_by_sample_px",
    "sample_by_sample_px",
)

#: Which coefficients each bias model adjusts (indices into :data:`BIAS_TERMS`).
BIAS_MODELS: dict[str, tuple[int, ...]] = {
    "shift": (0, 1),
    "shift+drift": (0, 1, 2, 3),
    "affine": (0, 1, 2, 3, 4, 5),
}


@dataclass(frozen=True)
class RpcBias:
    """An image-space correction of one RPC image (see the module doc).

    Attributes:
        image_size: ``(n_lines, n_samples)`` of the image (defines ``u, v``).
        coefficients: ``(a0, b0, a1, b1, a2, b2)`` in pixels (:data:`BIAS_TERMS`).
    """

    image_size: tuple[int, int]
    coefficients: tuple[float, ...] = (0.0,) * 6

    def __post_init__(self) -> None:
        c = tuple(float(v) for v in self.coefficients)
        if len(c) != 6 or not all(math.isfinite(v) for v in c):
            raise InputError(f"expected 6 finite coefficients, got {self.coefficients!r}")
        object.__setattr__(self, "coefficients", c)

    @property
    def _half(self) -> tuple[float, float]:
        return 0.5 * self.image_size[0], 0.5 * self.image_size[1]

    def normalized(self, line: ArrayLike, sample: ArrayLike) -> tuple[F64, F64]:
        """``(u, v)``: image coordinates (pixels) normalised to [-1, 1] over the image."""
        hl, hs = self._half
        return (np.asarray(line, np.float64) - hl) / hl, (np.asarray(sample, np.float64) - hs) / hs

    def apply(self, line: ArrayLike, sample: ArrayLike) -> tuple[F64, F64]:
        """Corrected image coordinates of the RPC's projection ``(line, sample)``."""
        a0, b0, a1, b1, a2, b2 = self.coefficients
        u, v = self.normalized(line, sample)
        return (
            np.asarray(line, np.float64) + a0 + a1 * u + a2 * v,
            np.asarray(sample, np.float64) + b0 + b1 * u + b2 * v,
        )

    def matrix(self) -> F64:
        """``d(line, sample) / d(l, s)`` of the correction, ``(2, 2)``."""
        _, _, a1, b1, a2, b2 = self.coefficients
        hl, hs = self._half
        return np.array([[1.0 + a1 / hl, a2 / hs], [b1 / hl, 1.0 + b2 / hs]])

    def invert(self, line: ArrayLike, sample: ArrayLike) -> tuple[F64, F64]:
        """The RPC's ``(l, s)`` whose corrected coordinates are ``(line, sample)`` (exact)."""
        ln = np.asarray(line, np.float64)
        sm = np.asarray(sample, np.float64)
        r0l, r0s = self.apply(np.zeros(()), np.zeros(()))
        inv = np.linalg.inv(self.matrix())
        dl, ds = ln - r0l, sm - r0s
        return inv[0, 0] * dl + inv[0, 1] * ds, inv[1, 0] * dl + inv[1, 1] * ds

    def partials(self, line: ArrayLike, sample: ArrayLike) -> F64:
        """``d(line, sample)/d(coefficients)`` at the RPC's projection, ``(..., 2, 6)``."""
        u, v = self.normalized(line, sample)
        one, zero = np.ones_like(u), np.zeros_like(u)
        return np.stack(
            [
                np.stack([one, zero, u, zero, v, zero], axis=-1),
                np.stack([zero, one, zero, u, zero, v], axis=-1),
            ],
            axis=-2,
        )

    def is_shift(self) -> bool:
        """True when only the shift terms are non-zero."""
        return not any(self.coefficients[2:])

    def with_coefficients(self, coefficients: ArrayLike) -> RpcBias:
        """The same image with other coefficients."""
        return dataclasses.replace(self, coefficients=tuple(np.asarray(coefficients, float)))


class BiasedRpcCamera(RpcCamera):
    """An :class:`RpcCamera` with an image-space :class:`RpcBias` correction.

    Everything an :class:`RpcCamera` does, through the corrected image coordinates:
    ``project`` and ``ground_to_image`` apply the correction to the RPC's projection,
    ``localize`` and ``image_to_ground`` remove it first (exactly) and then invert the
    RPC.

    Args:
        base: The uncorrected camera (its RPC, body, size and name are used).
        bias: The correction.
    """

    def __init__(self, base: RpcCamera, bias: RpcBias) -> None:
        super().__init__(
            base.rpc, base.ellipsoid, base.latitude_kind, base.image_size(), name=base.name
        )
        self.base = base
        self.bias = bias
        self.source = getattr(base, "source", None)

    def __repr__(self) -> str:
        terms = ", ".join(
            f"{n}={v:.4g}" for n, v in zip(BIAS_TERMS, self.bias.coefficients, strict=True)
        )
        return f"BiasedRpcCamera({self.base!r}, {terms})"

    def project(
        self, lon_deg: ArrayLike, lat_deg: ArrayLike, height_m: ArrayLike
    ) -> tuple[F64, F64]:
        """Ground (lon, lat degrees; h metres) to corrected image coordinates."""
        return self.bias.apply(*self.rpc.project(lon_deg, lat_deg, height_m))

    def localize(
        self, line: ArrayLike, sample: ArrayLike, height_m: ArrayLike, *, tol_px: float = 1e-8
    ) -> tuple[F64, F64]:
        """Corrected image coordinates to lon/lat (degrees) at heights (metres)."""
        return super().localize(*self.bias.invert(line, sample), height_m, tol_px=tol_px)

    def ground_to_image(self, xyz: ArrayLike, *, ccd: str | None = None) -> ImagePoints:
        """Project body-fixed points (metres) into the corrected image."""
        ip = super().ground_to_image(xyz, ccd=ccd)
        line, sample = self.bias.apply(ip.line, ip.sample)
        n_lines, n_samples = self.image_size()
        with np.errstate(invalid="ignore"):
            inside = ip.valid & (line >= 0) & (line < n_lines) & (sample >= 0)
            inside &= sample < n_samples
        return ImagePoints(line, sample, ip.valid, inside)

    def image_to_ground(
        self,
        line: ArrayLike,
        sample: ArrayLike,
        terrain: Terrain | float = 0.0,
        *,
        ccd: str | None = None,
        on_miss: OnMiss = "raise",
    ) -> F64:
        """Intersect the corrected lines of sight with a height or a terrain."""
        raw_line, raw_sample = self.bias.invert(line, sample)
        return super().image_to_ground(raw_line, raw_sample, terrain, ccd=ccd, on_miss=on_miss)


def refined_rpc(
    camera: BiasedRpcCamera, *, grid: tuple[int, int, int] = (21, 21, 9)
) -> tuple[Rpc, FitReport | None]:
    """An RPC00B of a bias-corrected camera.

    A pure shift changes LINE_OFF and SAMP_OFF only (exact; no report). Any other
    correction is composed by refitting (:func:`fit_rpc_stable`, the regularisation
    ladder) to the corrected camera over the RPC's height domain ``HEIGHT_OFF ±
    HEIGHT_SCALE``.

    Args:
        camera: The corrected camera.
        grid: Fitting grid ``(n_lines, n_samples, n_heights)`` of a refit.

    Returns:
        ``(rpc, report)``; ``report`` is None for the exact shift.
    """
    rpc, bias = camera.rpc, camera.bias
    if bias.is_shift():
        a0, b0 = bias.coefficients[:2]
        return dataclasses.replace(
            rpc, line_off=rpc.line_off + a0, samp_off=rpc.samp_off + b0
        ), None
    h0, hs = rpc.height_off, abs(rpc.height_scale)
    model, report = fit_rpc_stable(camera, height_range_m=(h0 - hs, h0 + hs), grid=grid)
    # The RPC's error terms still describe the corrected model's accuracy best.
    return dataclasses.replace(model, err_bias=rpc.err_bias, err_rand=rpc.err_rand), report


def _format_of(source: Path | None) -> str:
    """``rpb``, ``txt`` or ``geotiff``: the RPC format of an input file (``txt`` if unknown)."""
    if source is None:
        return "txt"
    name = source.name.lower()
    if name.endswith(".rpb"):
        return "rpb"
    if name.endswith((".tif", ".tiff")):
        return "geotiff"
    return "txt"


def write_refined_rpc(
    camera: BiasedRpcCamera, folder: str | os.PathLike[str], name: str
) -> tuple[list[Path], dict[str, Any]]:
    """Write the refined RPC of a bias-corrected camera in its input's format.

    The format is that of the file the RPC was read from (``camera.source``): an
    ``.RPB`` gives ``NAME.RPB``, an ``_RPC.TXT`` gives ``NAME_RPC.TXT``, a GeoTIFF
    gives a copy ``NAME.tif`` of the image with the refined RPC in its tags (other
    rasters, or a camera not read from a file: ``NAME_RPC.TXT``). Every file is
    written to a temporary name and renamed; the input is never written over.

    Args:
        camera: The adjusted camera.
        folder: Output folder (created if needed).
        name: File-name stem.

    Returns:
        ``(paths, report)``: the files written and a summary (bias model and
        coefficients, ``method`` ``"exact"`` (shift absorbed by LINE_OFF/SAMP_OFF) or
        ``"refit"`` with the refit's errors against the corrected camera, pixels).

    Raises:
        InputError: If the output would be the input file.
    """
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    model, fit = refined_rpc(camera)
    fmt = _format_of(camera.source)
    target = {
        "rpb": out / f"{name}.RPB",
        "txt": out / f"{name}_RPC.TXT",
        "geotiff": out / f"{name}.tif",
    }[fmt]
    src = camera.source
    if src is not None and target.exists() and os.path.samefile(target, src):
        raise InputError("refusing to write the refined RPC over its input", path=src)
    body = RpcBody(camera.ellipsoid, camera.latitude_kind)
    if fmt == "geotiff" and src is not None:
        with atomic_path(target) as tmp:
            shutil.copyfile(src, tmp)
        try:
            write_rpc(model, target, fmt="geotiff", body=body)
        except BaseException:
            # Never leave the copy behind with the input's (unrefined) RPC.
            target.unlink(missing_ok=True)
            raise
    else:
        write_rpc(model, target, fmt=fmt, body=body)  # type: ignore[arg-type]
    report: dict[str, Any] = {
        "coefficients_px": dict(zip(BIAS_TERMS, camera.bias.coefficients, strict=True)),
        "method": "exact" if fit is None else "refit",
        "format": fmt,
        "fit_rms_px": 0.0 if fit is None else fit.fit_rms_px,
        "check_rms_px": 0.0 if fit is None else fit.check_rms_px,
        "check_max_px": 0.0 if fit is None else fit.check_max_px,
    }
    if fit is not None:
        report["min_abs_denominator"] = fit.min_abs_denominator
    return [target], report
