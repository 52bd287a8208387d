"""XFeat matchers: sparse XFeat + LighterGlue, and semi-dense XFeat*.

Both use kornia 0.9.0's ``kornia.feature.XFeat`` network (``XFeatModel``, weights
``xfeat.pt``, a raw state dict of ``XFeatModel``) and, for the sparse variant,
``LightGlue("xfeat")`` loaded from verlab's ``xfeat-lighterglue.pt`` (keys prefixed
``matcher.``, next to ``extractor.*`` keys that are dropped).

Sparse XFeat
    ``XFeat.detectAndCompute`` returns integer heatmap maxima with pixel centres at
    integers, scaled by the ratio of the input size to its internal multiple-of-32 size.
    planetref replicate-pads the image to multiples of 32 instead, so that ratio is exactly
    1, and adds 0.5. The detector fires on whole pixels of 8x8 cells and is not repeatable
    to better than about one pixel when the image shifts by a non-multiple of 8 pixels;
    ``polish="ncc"`` gives sub-pixel matches.

    The keypoints also stay partly with each image's pixel grid, so the displacement the
    matches measure between two images falls short of the true one (an error of the sign
    opposite to the displacement's, not a constant offset): 0.04 to 0.08 pixel for
    displacements between a quarter and 1.75 pixels of identical textures, 0.1 to 0.3
    pixel for displacements of 1 to 2 pixels on the front end's fine-stage pairs of the
    simulated hiric-strip scene, where ALIKED and SIFT fall short by less than 0.03
    pixel on the same pairs. XFeat's own decoding does the same
    (``benchmarks/bench_subpixel_bias.py``). The front end places the fine window on the
    coarse offset rounded to whole reference pixels; where the coarse errors share a sign,
    this becomes a bias common to the tiles. Sub-pixel refinement (the front end's
    ``refine``, or ``polish``) removes most of it.

XFeat* (semi-dense)
    Implemented here from kornia's building blocks rather than with
    ``XFeat.match_xfeat_star``, to keep the coordinates exact: kornia resizes twice
    (``scale_factor`` 0.6 / 1.3, then to multiples of 32) and reports ``x / s`` with the
    nominal ``s``, which is off by a fraction of a pixel. Here each scale resizes once, to
    multiples of 32, with the exact per-axis factors ``(sx, sy)`` (corner-convention
    coordinates scale exactly: ``x = x' / sx``). Cells of the 1/8 map are matched by mutual
    nearest neighbour over both scales (the XFeat* recipe), then the ``fine_matcher`` head
    predicts, for each coarse match, a distribution over the 8x8 pixels of the image-0 cell
    (index ``8 * row + column``, the layout of XFeat's training labels), decoded by its
    expectation ``E`` (softmax temperature 3, as upstream).

    Which image-1 point that distribution refers to is not stated upstream: the reference
    code reports ``8 * cell + E - 4`` in image 0 against ``8 * cell`` in image 1, and
    transposes ``E``; kornia keeps the ``- 4`` and fixes the transposition. Measured on real
    HiRISE crops and synthetic textures with known shifts (identical images: ``E`` = 2.9 px
    on both axes; the argmax is pixel 3), the head's zero is pixel index 3, not 4. planetref
    therefore reports image-1 keypoints at the centre of pixel ``8 * cell + 3``, i.e.
    ``(8 * (c, r) + 3.5) / (sx, sy)``, and image-0 keypoints at
    ``(8 * (c, r) + E + 0.5) / (sx, sy)``, both in the corner convention. kornia's decoding
    is about 1 px off on the same data. The head compresses offsets of more than about
    2 px towards the cell centre (gain about 0.8), so XFeat* matches are accurate to about
    one pixel, not to a fraction of one; ``polish="ncc"`` refines each match by local
    normalised cross-correlation when sub-pixel accuracy matters.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
import torch
import torch.nn.functional as F
from numpy.typing import NDArray

from planetref.errors import InputError
from planetref.matching._torch import (
    SparseLightGlueMatcher,
    TorchMatcher,
    image_tensor,
    load_into,
    padded_batch,
    unpadded,
)
from planetref.matching.base import Matches, NormalisedPair, keypoints_on_valid_pixels
from planetref.matching.options import LightGlueSettings, TorchSettings

__all__ = ["XFeatLighterGlueMatcher", "XFeatStarMatcher"]

XFEAT_WEIGHTS = "xfeat.pt"
LIGHTERGLUE_WEIGHTS = "xfeat-lighterglue.pt"


def _build_xfeat(raw: Any, top_k: int, detection_threshold: float) -> Any:
    from kornia.feature import XFeat

    xfeat = XFeat(top_k=top_k, detection_threshold=detection_threshold)
    load_into(xfeat.net, raw, what=XFEAT_WEIGHTS)
    return xfeat.eval()


class XFeatLighterGlueMatcher(SparseLightGlueMatcher):
    """XFeat sparse keypoints + LighterGlue, a learned sparse matcher.

    Args:
        settings: Keypoint budget, model image size, LightGlue thresholds, weights, device,
            polish (see :class:`~planetref.matching.options.LightGlueSettings`).
        detection_threshold: XFeat keypoint-heatmap threshold.
    """

    name: ClassVar[str] = "xfeat-lighterglue"
    weight_files: ClassVar[tuple[str, ...]] = (XFEAT_WEIGHTS, LIGHTERGLUE_WEIGHTS)
    lightglue_features: ClassVar[str] = "xfeat"
    lightglue_weights: ClassVar[str] = LIGHTERGLUE_WEIGHTS
    pad_multiple: ClassVar[int] = 32

    def __init__(
        self,
        settings: LightGlueSettings | None = None,
        *,
        detection_threshold: float = 0.05,
    ) -> None:
        super().__init__(settings)
        self.detection_threshold = float(detection_threshold)

    def _build_extractor(self) -> Any:
        return _build_xfeat(
            self._checkpoint(XFEAT_WEIGHTS), self.settings.max_keypoints, self.detection_threshold
        )

    def _extract_batch(
        self, images: Sequence[NDArray[np.float32]]
    ) -> list[dict[str, torch.Tensor]]:
        t = padded_batch(images, self.device, self.pad_multiple)
        out = []
        feats = self._model["extractor"].detectAndCompute(t, top_k=self.settings.max_keypoints)
        for f, image in zip(feats, images, strict=True):
            kpts = f["keypoints"].float()
            inside = unpadded(kpts, image.shape)
            out.append({"keypoints": kpts[inside], "descriptors": f["descriptors"][inside]})
        return out


class XFeatStarMatcher(TorchMatcher):
    """XFeat*: semi-dense matching of XFeat's 1/8-resolution cells with sub-cell refinement.

    Args:
        top_k: Cells kept per image, by XFeat's reliability map, over all scales.
        scales: Image scales at which cells are extracted; the first gets 20 % of ``top_k``,
            the others share the rest equally (XFeat*'s 0.6 / 1.3 recipe by default).
        fine_confidence: Minimum confidence of the refinement head (XFeat* uses 0.25).
        max_size: Longer image sides above this many pixels scale all ``scales`` down.
        settings: Weights, device, polish (``None``: XFeat* as published) (see
            :class:`~planetref.matching.options.TorchSettings`).
    """

    name: ClassVar[str] = "xfeat-star"
    weight_files: ClassVar[tuple[str, ...]] = (XFEAT_WEIGHTS,)

    #: pixel index (within the 8x8 cell) at which the refinement head reports no offset
    head_zero: ClassVar[float] = 3.0

    def __init__(
        self,
        settings: TorchSettings | None = None,
        *,
        top_k: int = 8000,
        scales: tuple[float, ...] = (0.6, 1.3),
        fine_confidence: float = 0.25,
        max_size: int | None = 2048,
    ) -> None:
        if int(top_k) < 2:
            raise InputError(f"must be >= 2, got {top_k}", field="top_k")
        scales = tuple(float(s) for s in scales)
        if not scales or any(not (0.05 <= s <= 8.0) for s in scales):
            raise InputError(f"scales must be in [0.05, 8], got {scales}", field="scales")
        super().__init__(settings)
        self.top_k = int(top_k)
        self.scales = scales
        self.fine_confidence = float(fine_confidence)
        self.max_size = None if max_size is None else int(max_size)

    def _build(self) -> Any:
        return _build_xfeat(self._checkpoint(XFEAT_WEIGHTS), self.top_k, 0.05).to(self.device)

    def _budgets(self) -> list[int]:
        if len(self.scales) == 1:
            return [self.top_k]
        first = int(0.2 * self.top_k)
        rest = self.top_k - first
        n = len(self.scales) - 1
        return [first] + [rest // n + (1 if i < rest % n else 0) for i in range(n)]

    def _cells(
        self, image: NDArray[np.float32], valid: NDArray[np.bool_]
    ) -> tuple[NDArray[np.float64], torch.Tensor, NDArray[np.float64]]:
        """Extract cells at all scales.

        Returns:
            ``grid`` ``(N, 2)``: ``8 * (c, r)`` of each cell in pixels of its resized image;
            ``feats`` ``(N, 64)``; ``cell_px`` ``(N, 2)``: size of one resized pixel in
            full-image pixels (``1 / sx, 1 / sy``).
        """
        h, w = image.shape
        base = image_tensor(image, self.device)
        limit = 1.0 if self.max_size is None else min(1.0, self.max_size / max(h, w))
        anchors, feats, cell_px = [], [], []
        for s, budget in zip(self.scales, self._budgets(), strict=True):
            if budget < 1:
                continue
            hs = max(32, round(h * s * limit / 32) * 32)
            ws = max(32, round(w * s * limit / 32) * 32)
            sx, sy = ws / w, hs / h
            x = (
                base
                if (hs, ws) == (h, w)
                else F.interpolate(base, (hs, ws), mode="bilinear", align_corners=False)
            )
            with self._timed("forward"):
                desc, _, reliability = self._model.net(x)
            _, c, hc, wc = desc.shape
            desc = desc[0].permute(1, 2, 0).reshape(-1, c)
            rel = reliability[0, 0].reshape(-1)
            rows, cols = np.divmod(np.arange(hc * wc), wc)
            grid = np.column_stack([8.0 * cols, 8.0 * rows])
            # a cell whose reference pixel is no-data cannot be matched
            ref = (grid + self.head_zero + 0.5) / [sx, sy]
            ok = keypoints_on_valid_pixels(np.minimum(ref, [w - 1e-6, h - 1e-6]), valid)
            ok_idx = np.flatnonzero(ok)
            if ok_idx.size == 0:
                continue
            rel_ok = rel[torch.from_numpy(ok_idx).to(rel.device)]
            k = min(budget, ok_idx.size)
            top = torch.topk(rel_ok, k).indices.cpu().numpy()
            pick = ok_idx[top]
            anchors.append(grid[pick])
            feats.append(desc[torch.from_numpy(pick).to(desc.device)])
            cell_px.append(np.tile([1.0 / sx, 1.0 / sy], (len(pick), 1)))
        if not anchors:
            return np.empty((0, 2)), torch.empty(0, 64, device=self.device), np.empty((0, 2))
        return np.concatenate(anchors), torch.cat(feats), np.concatenate(cell_px)

    def _run(self, pair: NormalisedPair) -> Matches:
        a0, f0, px0 = self._cells(pair.image0, pair.valid0)
        a1, f1, px1 = self._cells(pair.image1, pair.valid1)
        if len(a0) < 2 or len(a1) < 2:
            return Matches.empty()
        with self._timed("forward"):
            sim = f0 @ f1.t()
            nn01 = sim.argmax(dim=1)
            nn10 = sim.argmax(dim=0)
            i0 = torch.nonzero(nn10[nn01] == torch.arange(len(nn01), device=sim.device)).flatten()
            i1 = nn01[i0]
            logits = self._model.net.fine_matcher(torch.cat([f0[i0], f1[i1]], dim=-1))
            prob = torch.softmax(3.0 * logits, dim=-1)
            conf = prob.max(dim=-1).values
            grid = torch.arange(8, device=prob.device, dtype=prob.dtype)
            p = prob.view(-1, 8, 8)  # [row, column] of the image-0 cell
            e_col = (p.sum(dim=1) * grid).sum(dim=-1)
            e_row = (p.sum(dim=2) * grid).sum(dim=-1)
        i0n, i1n = i0.cpu().numpy(), i1.cpu().numpy()
        expect = torch.stack([e_col, e_row], dim=-1).to("cpu", torch.float64).numpy()
        # corner convention: pixel index k of a resized image spans [k, k + 1)
        k0 = (a0[i0n] + expect + 0.5) * px0[i0n]
        k1 = (a1[i1n] + self.head_zero + 0.5) * px1[i1n]
        good = conf.cpu().numpy() > self.fine_confidence
        return Matches(k0[good], k1[good], conf.to("cpu", torch.float64).numpy()[good])
