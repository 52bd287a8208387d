"""Typed settings shared by the torch matchers: one frozen, validated value per family.

Every torch matcher takes one :class:`TorchSettings` (where the weights are, which device,
whether to check checksums, whether to polish matches); the LightGlue family (DISK, ALIKED,
DoG+HardNet, XFeat sparse) takes a :class:`LightGlueSettings`, which adds the keypoint
budget, the model image size and LightGlue's own thresholds. A matcher's own settings
(ALIKED's NMS radius, LoFTR's coarse threshold...) stay keyword arguments of that matcher.

Users keep writing flat options (``get_matcher("disk-lightglue", max_keypoints=2048)``, or a
``[matchers.disk-lightglue]`` table of a georef configuration):
:meth:`planetref.matching.base.BaseMatcher.from_options` sends each key to the settings
value or to the matcher's own keywords. This module imports neither torch nor kornia.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields
from os import PathLike
from typing import Any, Literal

from planetref.errors import InputError

__all__ = ["LightGlueSettings", "TorchSettings", "split_options"]


def _coerced(value: Any, kind: Callable[[Any], Any], field: str) -> Any:
    """``kind(value)`` (``int``, ``float``, ``bool``); a value that does not convert is one line."""
    try:
        return kind(value)
    except (TypeError, ValueError):
        raise InputError(f"expected {kind.__name__}, got {value!r}", field=field) from None


@dataclass(frozen=True, kw_only=True)
class TorchSettings:
    """What every torch matcher needs to run.

    Attributes:
        weights_dir: Weights directory (see :func:`planetref.matching.weights.weights_dir`);
            ``None``: ``$PLANETREF_WEIGHTS``, then the torch hub cache. Resolved when the
            matcher is created.
        device: Torch device for inference: ``"cpu"`` (default), ``"cuda"``, ``"cuda:1"``,
            ``"mps"``, ``"auto"`` or a ``torch.device`` (checked when the matcher is created,
            see :func:`planetref.matching._torch.resolve_device`).
        verify_weights: Check each file's sha256 before loading it. ``False`` only for
            checkpoints that are known not to be the official files (tests with random
            weights in the official format).
        polish: ``None`` (the network's own keypoints) or ``"ncc"``: refine every match by
            local normalised cross-correlation
            (:func:`~planetref.matching.ncc.refine_matches_ncc`: 15 px templates centred on
            the image-0 pixel, +-3 px search), for sub-pixel accuracy; matches that do not
            correlate are dropped.

    Raises:
        InputError: ``polish`` is neither ``None`` nor ``"ncc"``.
    """

    weights_dir: str | PathLike[str] | None = None
    device: Any = "cpu"
    verify_weights: bool = True
    polish: Literal["ncc"] | None = None

    def __post_init__(self) -> None:
        if self.polish not in (None, "ncc"):
            raise InputError(f"must be None or 'ncc', got {self.polish!r}", field="polish")
        object.__setattr__(self, "verify_weights", bool(self.verify_weights))


@dataclass(frozen=True, kw_only=True)
class LightGlueSettings(TorchSettings):
    """Settings of a detector/descriptor + LightGlue matcher (plus :class:`TorchSettings`).

    Attributes:
        max_keypoints: Keypoint budget per image (>= 2).
        max_size: Images whose longer side exceeds this many pixels are downscaled (area
            averaging) for the network; keypoints are mapped back exactly. ``None``: never
            downscale. At least 32.
        filter_threshold: LightGlue's match score threshold, in ``[0, 1]`` (score of the
            assignment matrix).
        depth_confidence: LightGlue's early stopping (``-1`` disables; ``None`` keeps the
            configuration's default, 0.95).
        width_confidence: LightGlue's point pruning (``-1`` disables; ``None`` keeps the
            configuration's default, 0.99).

    Raises:
        InputError: ``max_keypoints < 2``, ``max_size < 32``, a bad ``polish``, or a value
            that is not a number (one line naming the field).
    """

    max_keypoints: int = 4096
    max_size: int | None = 2048
    filter_threshold: float = 0.1
    depth_confidence: float | None = None
    width_confidence: float | None = None

    def __post_init__(self) -> None:
        max_keypoints = _coerced(self.max_keypoints, int, "max_keypoints")
        if max_keypoints < 2:
            raise InputError(f"must be >= 2, got {self.max_keypoints}", field="max_keypoints")
        max_size = None if self.max_size is None else _coerced(self.max_size, int, "max_size")
        if max_size is not None and max_size < 32:
            raise InputError(f"must be >= 32 or None, got {self.max_size}", field="max_size")
        super().__post_init__()
        values = {"max_keypoints": max_keypoints, "max_size": max_size}
        for name in ("filter_threshold", "depth_confidence", "width_confidence"):
            value = getattr(self, name)
            values[name] = None if value is None else _coerced(value, float, name)
        for name, value in values.items():
            object.__setattr__(self, name, value)

    def lightglue_overrides(self) -> dict[str, float]:
        """The entries of kornia's LightGlue configuration these settings replace."""
        conf = {"filter_threshold": self.filter_threshold}
        for name in ("depth_confidence", "width_confidence"):
            value = getattr(self, name)
            if value is not None:
                conf[name] = value
        return conf


def split_options(
    settings_type: type[TorchSettings], options: dict[str, Any]
) -> tuple[TorchSettings, dict[str, Any]]:
    """Split flat options into a settings value and the matcher's own keywords.

    Args:
        settings_type: :class:`TorchSettings` or a subclass.
        options: Flat keyword options (registry / configuration keys).

    Returns:
        ``(settings, own)``: the settings built from the keys that are its fields, and the
        remaining keys.
    """
    shared = {f.name for f in fields(settings_type)}
    settings = settings_type(**{k: v for k, v in options.items() if k in shared})
    return settings, {k: v for k, v in options.items() if k not in shared}
