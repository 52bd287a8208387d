"""OpenCV SIFT with Lowe's ratio test and a mutual nearest-neighbour check.

OpenCV keypoints have pixel centres at integer coordinates; planetref adds 0.5. SIFT needs
8-bit input, so the robustly normalised image is quantised to ``[0, 255]``. The keypoint
budget grows with the tile area (``keypoints_per_megapixel``), clamped to
``[min_keypoints, max_keypoints]`` (5k to 50k by default). The confidence of a match is the
ratio-test margin ``1 - d1 / d2`` (``d1``, ``d2``: distances to the nearest and second
nearest descriptor), in ``[0, 1]``.
"""

from __future__ import annotations

from typing import ClassVar

import cv2
import numpy as np
from numpy.typing import NDArray

from planetref.errors import InputError
from planetref.matching.base import BaseMatcher, Matches

__all__ = ["SiftMatcher", "keypoint_budget", "to_uint8"]


def to_uint8(image: NDArray[np.float32]) -> NDArray[np.uint8]:
    """``[0, 1]`` float image -> ``[0, 255]`` uint8 (rounded)."""
    return np.clip(np.rint(image * 255.0), 0, 255).astype(np.uint8)


def keypoint_budget(shape: tuple[int, int], per_megapixel: float, lo: int, hi: int) -> int:
    """Keypoint budget for a tile: ``per_megapixel`` per 10^6 pixels, clamped to ``[lo, hi]``."""
    return int(np.clip(round(shape[0] * shape[1] * per_megapixel / 1e6), lo, hi))


class SiftMatcher(BaseMatcher):
    """SIFT keypoints and descriptors, ratio test and mutual check.

    Args:
        ratio: Lowe ratio threshold (``d1 < ratio * d2``).
        mutual: Keep only mutual nearest neighbours.
        keypoints_per_megapixel: Keypoint budget density.
        min_keypoints: Lower bound of the budget.
        max_keypoints: Upper bound of the budget.
        contrast_threshold: OpenCV ``contrastThreshold`` (on the normalised 8-bit image);
            lower than OpenCV's 0.04 because Mars scenes are low-contrast.
        edge_threshold: OpenCV ``edgeThreshold``.
        n_octave_layers: OpenCV ``nOctaveLayers``.
        sigma: OpenCV ``sigma``.
        brute_force_limit: Above this many descriptor pairs (``N0 * N1``), approximate
            FLANN k-d trees replace exact brute force.

    Raises:
        InputError: A parameter out of range.
    """

    name: ClassVar[str] = "sift"

    def __init__(
        self,
        *,
        ratio: float = 0.8,
        mutual: bool = True,
        keypoints_per_megapixel: float = 20_000.0,
        min_keypoints: int = 5_000,
        max_keypoints: int = 50_000,
        contrast_threshold: float = 0.02,
        edge_threshold: float = 10.0,
        n_octave_layers: int = 3,
        sigma: float = 1.6,
        brute_force_limit: float = 1e8,
    ) -> None:
        super().__init__()
        if not 0.0 < float(ratio) <= 1.0:
            raise InputError(f"must be in (0, 1], got {ratio}", field="ratio")
        if not 0 < int(min_keypoints) <= int(max_keypoints):
            raise InputError(
                f"need 0 < min_keypoints <= max_keypoints, got {min_keypoints}, {max_keypoints}"
            )
        self.ratio = float(ratio)
        self.mutual = bool(mutual)
        self.keypoints_per_megapixel = float(keypoints_per_megapixel)
        self.min_keypoints = int(min_keypoints)
        self.max_keypoints = int(max_keypoints)
        self.contrast_threshold = float(contrast_threshold)
        self.edge_threshold = float(edge_threshold)
        self.n_octave_layers = int(n_octave_layers)
        self.sigma = float(sigma)
        self.brute_force_limit = float(brute_force_limit)

    def _detect(
        self, image: NDArray[np.float32], valid: NDArray[np.bool_]
    ) -> tuple[NDArray[np.float64], NDArray[np.float32]]:
        budget = keypoint_budget(
            image.shape, self.keypoints_per_megapixel, self.min_keypoints, self.max_keypoints
        )
        sift = cv2.SIFT_create(
            nfeatures=budget,
            nOctaveLayers=self.n_octave_layers,
            contrastThreshold=self.contrast_threshold,
            edgeThreshold=self.edge_threshold,
            sigma=self.sigma,
        )
        mask = None if valid.all() else valid.astype(np.uint8) * 255
        kps, desc = sift.detectAndCompute(to_uint8(image), mask)
        if desc is None or len(kps) == 0:
            return np.empty((0, 2)), np.empty((0, 128), np.float32)
        pts = np.array([k.pt for k in kps], dtype=np.float64) + 0.5  # OpenCV centres -> corner
        return pts, desc.astype(np.float32, copy=False)

    def _knn(self, query: NDArray[np.float32], train: NDArray[np.float32], k: int):
        if len(query) * len(train) <= self.brute_force_limit:
            matcher = cv2.BFMatcher(cv2.NORM_L2)
        else:
            matcher = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 128})
        return matcher.knnMatch(query, train, k=k)

    def _match_normalised(
        self,
        image0: NDArray[np.float32],
        valid0: NDArray[np.bool_],
        image1: NDArray[np.float32],
        valid1: NDArray[np.bool_],
    ) -> Matches:
        with self._timed("forward"):
            p0, d0 = self._detect(image0, valid0)
            p1, d1 = self._detect(image1, valid1)
            if len(p0) < 2 or len(p1) < 2:
                return Matches.empty()
            knn = self._knn(d0, d1, 2)
            back = self._knn(d1, d0, 1) if self.mutual else None
        # Lowe's ratio test and the mutual check on arrays of the pairs' indices and
        # distances (float32 distances, the ratio in float64 as before).
        pairs = [p for p in knn if len(p) >= 2]
        if not pairs:
            return Matches.empty()
        q = np.fromiter((p[0].queryIdx for p in pairs), np.intp, len(pairs))
        t = np.fromiter((p[0].trainIdx for p in pairs), np.intp, len(pairs))
        dist1 = np.fromiter((p[0].distance for p in pairs), np.float64, len(pairs))
        dist2 = np.fromiter((p[1].distance for p in pairs), np.float64, len(pairs))
        keep = (dist2 > 0) & (dist1 < self.ratio * dist2)
        if back is not None:
            rev = np.fromiter((b[0].trainIdx if b else -1 for b in back), np.intp, len(back))
            keep &= rev[t] == q
        if not keep.any():
            return Matches.empty()
        q, t = q[keep], t[keep]
        conf = 1.0 - dist1[keep] / dist2[keep]
        from planetref.matching.tiling import deduplicate

        # OpenCV repeats a location once per dominant orientation: one match per location pair
        return deduplicate(Matches(p0[q], p1[t], conf), radius=1e-3)
