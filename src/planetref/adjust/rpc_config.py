"""Settings of RPC cameras in the adjustment: the image-space bias model.

See :mod:`planetref.camera.rpc.bias` for the model (Grodecki & Dial 2003).
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import model_validator

from planetref.runtime.settings import Settings

__all__ = ["RpcParameters"]


class RpcParameters(Settings):
    """Unknowns of RPC cameras: an image-space correction per image (per CCD).

    Attributes:
        bias: ``"shift"`` (line and sample offsets), ``"shift+drift"`` (offsets and
            their linear drift with the line, i.e. with time) or ``"affine"`` (six
            terms). Coefficients are in pixels: the correction at the image edge.
        mode: ``free``, ``fixed`` or ``weighted`` (every coefficient with
            ``sigma_px`` around its initial value, zero).
        sigma_px: A-priori sigma of each coefficient (pixels), for ``weighted``.
    """

    bias: Literal["shift", "shift+drift", "affine"] = "affine"
    mode: Literal["free", "fixed", "weighted"] = "free"
    sigma_px: float | None = None

    @model_validator(mode="after")
    def _check_sigma(self) -> RpcParameters:
        s = self.sigma_px
        if s is not None and not (math.isfinite(s) and s > 0):
            raise ValueError(f"sigma_px must be a finite number > 0, got {s}")
        if self.mode == "weighted" and s is None:
            raise ValueError("mode 'weighted' needs sigma_px")
        return self
