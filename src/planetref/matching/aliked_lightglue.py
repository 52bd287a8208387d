"""ALIKED ("aliked-n16") keypoints and descriptors matched by LightGlue("aliked").

kornia's ALIKED returns sub-pixel ``(x, y)`` with pixel centres at integers (it maps its
``[-1, 1]`` grid with ``align_corners=True``: -1 is the centre of the first pixel);
planetref adds 0.5. ALIKED pads internally to multiples of 32 around the image and crops
its maps back, so no resizing happens for images up to ``max_size``.

Checkpoints: ``aliked-n16.pth`` is Shiaoming/ALIKED's raw state dict (the derived buffer
``dkd.hw_grid`` is not stored); ``aliked_lightglue_v0-1_arxiv-pth`` is cvg/LightGlue's
release asset, a raw state dict in the later ``transformers.<i>.*`` layout.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
import torch
from numpy.typing import NDArray

from planetref.matching._torch import (
    SparseLightGlueMatcher,
    image_batch,
    load_into,
)
from planetref.matching.options import LightGlueSettings

__all__ = ["AlikedLightGlueMatcher"]

ALIKED_WEIGHTS = "aliked-n16.pth"
LIGHTGLUE_WEIGHTS = "aliked_lightglue_v0-1_arxiv-pth"


class AlikedLightGlueMatcher(SparseLightGlueMatcher):
    """ALIKED-N16 + LightGlue, a learned sparse matcher.

    Args:
        settings: Keypoint budget, model image size, LightGlue thresholds, weights, device,
            polish (see :class:`~planetref.matching.options.LightGlueSettings`).
        detection_threshold: ALIKED score threshold; a value ``<= 0`` selects top-k mode
            (the ``max_keypoints`` strongest maxima), which suits low-contrast Mars scenes
            better than the upstream threshold of 0.2.
        nms_radius: ALIKED NMS radius, pixels.
    """

    name: ClassVar[str] = "aliked-lightglue"
    weight_files: ClassVar[tuple[str, ...]] = (ALIKED_WEIGHTS, LIGHTGLUE_WEIGHTS)
    lightglue_features: ClassVar[str] = "aliked"
    lightglue_weights: ClassVar[str] = LIGHTGLUE_WEIGHTS

    def __init__(
        self,
        settings: LightGlueSettings | None = None,
        *,
        detection_threshold: float = 0.0,
        nms_radius: int = 2,
    ) -> None:
        super().__init__(settings)
        self.detection_threshold = float(detection_threshold)
        self.nms_radius = int(nms_radius)

    def _build_extractor(self) -> Any:
        from kornia.feature import ALIKED

        aliked = ALIKED(
            "aliked-n16",
            max_num_keypoints=self.settings.max_keypoints,
            detection_threshold=self.detection_threshold,
            nms_radius=self.nms_radius,
        )
        return load_into(
            aliked, self._checkpoint(ALIKED_WEIGHTS), what=ALIKED_WEIGHTS, derived=("dkd.hw_grid",)
        )

    def _extract_batch(
        self, images: Sequence[NDArray[np.float32]]
    ) -> list[dict[str, torch.Tensor]]:
        batch = self._model["extractor"](image_batch(images, self.device, channels=3))
        return [{"keypoints": f.keypoints, "descriptors": f.descriptors} for f in batch]
