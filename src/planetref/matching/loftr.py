"""LoFTR ("outdoor" weights), detector-free coarse-to-fine dense matching.

Images are resized to multiples of 8 (and to at most ``max_size`` pixels on the longer
side) before the network; keypoints are mapped back with the exact per-axis factors.

Pixel convention: kornia 0.9.0 documents that LoFTR's keypoints are in the frame of the
reference implementation, in which the pretrained models put the centre of pixel
``(x, y)`` at ``(x + 0.5, y + 0.5)`` (kornia's own frame is that minus 0.5). That *is*
planetref's corner convention, so no half-pixel shift is applied; in this convention a
resize by ``(sx, sy)`` maps coordinates exactly as ``x' = x * sx``.

Checkpoint: ``loftr_outdoor.ckpt`` is kornia's mirror of zju3dv's ``outdoor_ds.ckpt``, a
PyTorch Lightning checkpoint ``{"state_dict": {...}, ...}`` whose keys are those of the
``LoFTR`` module, prefixed ``matcher.`` (the Lightning module's attribute); kornia's
``LoFTR.load_state_dict`` strips that prefix, and so does this loader (unprefixed keys are
accepted too). Every key of ``kornia.feature.LoFTR`` must be present.
"""

from __future__ import annotations

import copy
from typing import Any, ClassVar

import torch

from planetref.errors import InputError, WeightsError
from planetref.matching._torch import TorchMatcher, image_tensor, load_into, resize_image
from planetref.matching.base import Matches, NormalisedPair
from planetref.matching.options import TorchSettings

__all__ = ["LoftrMatcher", "loftr_state_dict"]

LOFTR_WEIGHTS = "loftr_outdoor.ckpt"


def loftr_state_dict(raw: Any) -> dict[str, torch.Tensor]:
    """Extract the ``LoFTR`` state dict from an official (Lightning) checkpoint.

    Args:
        raw: Content of ``loftr_outdoor.ckpt``.

    Returns:
        Tensors keyed like ``kornia.feature.LoFTR().state_dict()``.

    Raises:
        WeightsError: No ``state_dict`` entry.
    """
    if not isinstance(raw, dict) or not isinstance(raw.get("state_dict"), dict):
        raise WeightsError(
            f"{LOFTR_WEIGHTS}: expected a Lightning checkpoint with a 'state_dict' dict"
        )
    return {
        (k[len("matcher.") :] if k.startswith("matcher.") else k): v
        for k, v in raw["state_dict"].items()
    }


class LoftrMatcher(TorchMatcher):
    """LoFTR outdoor matcher.

    Args:
        settings: Weights, device, polish (see
            :class:`~planetref.matching.options.TorchSettings`).
        max_size: Longer side, pixels, of the images fed to the network (downscaled above).
        confidence_threshold: Coarse matching threshold (LoFTR's ``match_coarse.thr``).
    """

    name: ClassVar[str] = "loftr"
    weight_files: ClassVar[tuple[str, ...]] = (LOFTR_WEIGHTS,)

    def __init__(
        self,
        settings: TorchSettings | None = None,
        *,
        max_size: int = 1024,
        confidence_threshold: float = 0.2,
    ) -> None:
        if int(max_size) < 32:
            raise InputError(f"must be >= 32, got {max_size}", field="max_size")
        if not 0.0 <= float(confidence_threshold) < 1.0:
            raise InputError(
                f"must be in [0, 1), got {confidence_threshold}", field="confidence_threshold"
            )
        super().__init__(settings)
        self.max_size = int(max_size)
        self.confidence_threshold = float(confidence_threshold)

    def _checkpoint(self, name: str) -> Any:
        """Load the checkpoint; a pickle that asks to import code is refused in one line."""
        import pickle

        from planetref.matching.weights import WEIGHT_FILES, weights_dir

        try:
            return super()._checkpoint(name)
        except WeightsError as exc:
            if not isinstance(exc.__cause__, pickle.UnpicklingError):
                raise
            lines = str(exc.__cause__).splitlines()
            detail = next(
                (ln.strip().rstrip(".") for ln in lines if "global" in ln.lower()),
                "not a plain tensor checkpoint",
            )
            raise WeightsError(
                f"weight file {weights_dir(self.weights_dir) / name} refused: it asks to "
                f"import code ({detail}) and nothing of it was run; replace it with the "
                f"official file from {WEIGHT_FILES[name].url}"
            ) from None

    def _build(self) -> Any:
        from kornia.feature import LoFTR
        from kornia.feature.loftr.loftr import default_cfg

        cfg = copy.deepcopy(default_cfg)
        cfg["match_coarse"]["thr"] = self.confidence_threshold
        model = LoFTR(pretrained=None, config=cfg)
        state = loftr_state_dict(self._checkpoint(LOFTR_WEIGHTS))
        return load_into(model, state, what=LOFTR_WEIGHTS).to(self.device)

    def _network_size(self, shape: tuple[int, int]) -> tuple[int, int]:
        h, w = shape
        s = min(1.0, self.max_size / max(h, w))
        return max(8, round(h * s / 8) * 8), max(8, round(w * s / 8) * 8)

    def _run(self, pair: NormalisedPair) -> Matches:
        r0, sx0, sy0 = resize_image(pair.image0, self._network_size(pair.image0.shape))
        r1, sx1, sy1 = resize_image(pair.image1, self._network_size(pair.image1.shape))
        data = {"image0": image_tensor(r0, self.device), "image1": image_tensor(r1, self.device)}
        with self._timed("forward"):
            out = self._model(data)
        k0 = out["keypoints0"].to("cpu", torch.float64).numpy() / [sx0, sy0]
        k1 = out["keypoints1"].to("cpu", torch.float64).numpy() / [sx1, sy1]
        conf = out["confidence"].to("cpu", torch.float64).numpy()
        if len(conf) == 0:
            return Matches.empty()
        return Matches(k0, k1, conf)
