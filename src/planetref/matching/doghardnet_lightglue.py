"""DoG keypoints, HardNet descriptors, LightGlue("doghardnet").

The pipeline of cvg/LightGlue's ``DoGHardNet`` extractor (on which the ``doghardnet``
LightGlue weights were trained): OpenCV DoG/SIFT detection, local affine frames of
scale ``6 * KeyPoint.size`` (12 sigma) and orientation ``KeyPoint.angle`` built with
``kornia.feature.laf_from_center_scale_ori``, HardNet descriptors of the 32x32 patches
(``kornia.feature.LAFDescriptor``), and LightGlue with the keypoint scale and orientation
(``add_scale_ori``; kornia's configuration multiplies the LAF scale by 1/6, so the network
sees ``KeyPoint.size``, and takes the orientation in radians in ``[0, 2 pi)``). OpenCV's
keypoints have pixel centres at integers; planetref adds 0.5 on output.

Checkpoints (neither is available on the development machines):

- ``checkpoint_liberty_with_aug.pth``: DagnyT/hardnet's training checkpoint,
  ``{"epoch": int, "state_dict": {...}}`` with keys ``features.<i>.weight`` (convolutions
  0, 3, 6, 9, 12, 15, 19, no biases) and ``features.<i>.running_mean/var`` (BatchNorm 1, 4,
  7, 10, 13, 16, 20); kornia's ``HardNet(True)`` reads ``["state_dict"]`` strictly.
- ``doghardnet_v0-1_arxiv-pth``: cvg/LightGlue's release asset ``doghardnet_lightglue.pth``,
  a raw state dict of cvg's ``LightGlue`` (``posenc.Wr.weight`` of shape ``(32, 4)`` since
  scale and orientation are encoded, ``input_proj.*``, ``transformers.<i>.*`` or, in the
  first-release layout, ``self_attn.<i>.*``/``cross_attn.<i>.*``, ``log_assignment.<i>.*``,
  ``token_confidence.<i>.*``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import cv2
import numpy as np
import torch
from numpy.typing import NDArray

from planetref.errors import WeightsError
from planetref.matching._torch import (
    SparseLightGlueMatcher,
    image_tensor,
    load_into,
)
from planetref.matching.options import LightGlueSettings
from planetref.matching.sift import to_uint8

__all__ = ["DogHardNetLightGlueMatcher", "hardnet_state_dict"]

HARDNET_WEIGHTS = "checkpoint_liberty_with_aug.pth"
LIGHTGLUE_WEIGHTS = "doghardnet_v0-1_arxiv-pth"


def hardnet_state_dict(raw: Any) -> dict[str, torch.Tensor]:
    """Extract HardNet's state dict from DagnyT/hardnet's ``{"state_dict": ...}`` checkpoint.

    Raises:
        WeightsError: No ``state_dict`` entry.
    """
    if not isinstance(raw, dict) or not isinstance(raw.get("state_dict"), dict):
        raise WeightsError(
            f"{HARDNET_WEIGHTS}: expected a checkpoint dict with a 'state_dict' entry"
        )
    return dict(raw["state_dict"])


class DogHardNetLightGlueMatcher(SparseLightGlueMatcher):
    """DoG + HardNet + LightGlue, a learned sparse matcher.

    Args:
        settings: Keypoint budget (DoG keeps the strongest responses), model image size,
            LightGlue thresholds, weights, device, polish (see
            :class:`~planetref.matching.options.LightGlueSettings`).
        contrast_threshold: OpenCV SIFT ``contrastThreshold`` of the DoG detector.
        edge_threshold: OpenCV SIFT ``edgeThreshold``.
        n_octave_layers: OpenCV SIFT ``nOctaveLayers`` (4, as cvg/LightGlue's DoGHardNet).
    """

    name: ClassVar[str] = "doghardnet-lightglue"
    weight_files: ClassVar[tuple[str, ...]] = (HARDNET_WEIGHTS, LIGHTGLUE_WEIGHTS)
    lightglue_features: ClassVar[str] = "doghardnet"
    lightglue_weights: ClassVar[str] = LIGHTGLUE_WEIGHTS

    def __init__(
        self,
        settings: LightGlueSettings | None = None,
        *,
        contrast_threshold: float = 0.01,
        edge_threshold: float = 10.0,
        n_octave_layers: int = 4,
    ) -> None:
        super().__init__(settings)
        self.contrast_threshold = float(contrast_threshold)
        self.edge_threshold = float(edge_threshold)
        self.n_octave_layers = int(n_octave_layers)

    def _build_extractor(self) -> Any:
        from kornia.feature import HardNet, LAFDescriptor

        hardnet = HardNet(pretrained=False)
        load_into(
            hardnet, hardnet_state_dict(self._checkpoint(HARDNET_WEIGHTS)), what=HARDNET_WEIGHTS
        )
        return LAFDescriptor(hardnet, patch_size=32, grayscale_descriptor=True).eval()

    def _extract_batch(
        self, images: Sequence[NDArray[np.float32]]
    ) -> list[dict[str, torch.Tensor]]:
        # OpenCV's DoG detector takes one image at a time.
        return [self._extract_one(image) for image in images]

    def _extract_one(self, image: NDArray[np.float32]) -> dict[str, torch.Tensor]:
        from kornia.feature import laf_from_center_scale_ori

        sift = cv2.SIFT_create(
            nfeatures=self.settings.max_keypoints,
            nOctaveLayers=self.n_octave_layers,
            contrastThreshold=self.contrast_threshold,
            edgeThreshold=self.edge_threshold,
        )
        kps = sift.detect(to_uint8(image), None)
        if not kps:
            empty = torch.empty(0, device=self.device)
            return {
                "keypoints": empty.view(0, 2),
                "descriptors": empty.view(0, 128),
                "scales": empty,
                "oris": empty,
            }
        pts = np.array([k.pt for k in kps], np.float32)
        size = np.array([k.size for k in kps], np.float32)
        angle = np.array([k.angle for k in kps], np.float32) % 360.0
        # OpenCV repeats a location once per dominant orientation: keep the first (strongest)
        _, first = np.unique(pts, axis=0, return_index=True)
        first.sort()
        pts, size, angle = pts[first], size[first], angle[first]
        xy = torch.from_numpy(pts).to(self.device)
        laf_scale = torch.from_numpy(6.0 * size).to(self.device)
        ori_deg = torch.from_numpy(angle).to(self.device)
        lafs = laf_from_center_scale_ori(
            xy[None], laf_scale.view(1, -1, 1, 1), ori_deg.view(1, -1, 1)
        )
        desc = self._model["extractor"](image_tensor(image, self.device), lafs)[0]
        return {
            "keypoints": xy,
            "descriptors": desc,
            "scales": laf_scale,
            "oris": torch.deg2rad(ori_deg),
        }
