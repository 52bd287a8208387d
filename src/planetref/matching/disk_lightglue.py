"""DISK ("depth" weights) keypoints and descriptors matched by LightGlue("disk").

kornia's DISK returns integer ``(x, y)`` heatmap maxima with pixel centres at integers
(kornia's local-feature frame); planetref adds 0.5. The image is replicate-padded to a
multiple of 16 at the bottom/right (padding, not resizing, so coordinates are unchanged)
and maxima in the padding are discarded.

Checkpoints: ``depth-save.pth`` is cvlab-epfl/disk's file, ``{"extractor": state_dict}``
with keys ``unet.*`` (what ``DISK.from_pretrained`` reads); ``disk_lightglue_v0-1_arxiv-pth``
is cvg/LightGlue's release asset, a raw state dict in the first-release layout
(``self_attn.<i>.*``, ``cross_attn.<i>.*``, plus unused ``log_assignment.<i>.r``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
import torch
from numpy.typing import NDArray

from planetref.errors import WeightsError
from planetref.matching._torch import (
    SparseLightGlueMatcher,
    load_into,
    padded_batch,
    unpadded,
)
from planetref.matching.options import LightGlueSettings

__all__ = ["DiskLightGlueMatcher"]

DISK_WEIGHTS = "depth-save.pth"
LIGHTGLUE_WEIGHTS = "disk_lightglue_v0-1_arxiv-pth"


class DiskLightGlueMatcher(SparseLightGlueMatcher):
    """DISK + LightGlue, a learned sparse matcher.

    Args:
        settings: Keypoint budget (DISK keeps the strongest maxima), model image size,
            LightGlue thresholds, weights, device, polish (see
            :class:`~planetref.matching.options.LightGlueSettings`).
        nms_window: DISK non-maximum suppression window, pixels.
        score_threshold: DISK heatmap threshold (maxima strictly above it are kept).
    """

    name: ClassVar[str] = "disk-lightglue"
    weight_files: ClassVar[tuple[str, ...]] = (DISK_WEIGHTS, LIGHTGLUE_WEIGHTS)
    lightglue_features: ClassVar[str] = "disk"
    lightglue_weights: ClassVar[str] = LIGHTGLUE_WEIGHTS
    pad_multiple: ClassVar[int] = 16

    def __init__(
        self,
        settings: LightGlueSettings | None = None,
        *,
        nms_window: int = 5,
        score_threshold: float = 0.0,
    ) -> None:
        super().__init__(settings)
        self.nms_window = int(nms_window)
        self.score_threshold = float(score_threshold)

    def _build_extractor(self) -> Any:
        from kornia.feature import DISK

        raw = self._checkpoint(DISK_WEIGHTS)
        if not isinstance(raw, dict) or "extractor" not in raw:
            raise WeightsError(f"{DISK_WEIGHTS}: expected a dict with an 'extractor' state dict")
        return load_into(DISK(desc_dim=128), raw["extractor"], what=DISK_WEIGHTS)

    def _extract_batch(
        self, images: Sequence[NDArray[np.float32]]
    ) -> list[dict[str, torch.Tensor]]:
        t = padded_batch(images, self.device, self.pad_multiple, channels=3)
        batch = self._model["extractor"](
            t, n=None, window_size=self.nms_window, score_threshold=self.score_threshold
        )
        out = []
        for feats, image in zip(batch, images, strict=True):
            kpts, desc, scores = feats.keypoints, feats.descriptors, feats.detection_scores
            inside = unpadded(kpts, image.shape)
            kpts, desc, scores = kpts[inside], desc[inside], scores[inside]
            if len(scores) > self.settings.max_keypoints:
                top = torch.topk(scores, self.settings.max_keypoints).indices
                kpts, desc = kpts[top], desc[top]
            out.append({"keypoints": kpts, "descriptors": desc})
        return out
