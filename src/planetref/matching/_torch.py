"""Shared machinery of the torch/kornia matchers (imported only when one is built).

Models are built with random weights (``pretrained=None`` / ``features=None``) and the
checkpoints are loaded here with :func:`planetref.matching.weights.load_checkpoint`, so
kornia's download code is never reached and torch.hub's directory is never touched.
"""

from __future__ import annotations

import functools
import re
import threading
import time
from abc import abstractmethod
from collections.abc import Iterable, Mapping, Sequence
from typing import Any, ClassVar

import numpy as np
import torch
import torch.nn.functional as F
from numpy.typing import NDArray

from planetref.errors import InputError, WeightsError
from planetref.matching.base import (
    BaseMatcher,
    Matches,
    NormalisedPair,
    keypoints_on_valid_pixels,
)
from planetref.matching.options import LightGlueSettings, TorchSettings
from planetref.matching.weights import load_checkpoint, require_weights, weights_dir

__all__ = [
    "SparseLightGlueMatcher",
    "TorchMatcher",
    "build_lightglue",
    "image_batch",
    "lightglue_state_dict",
    "load_into",
    "padded_batch",
    "resolve_device",
]


def resolve_device(device: str | torch.device | None) -> torch.device:
    """Parse a device name and check that it can be used.

    Args:
        device: ``"cpu"``, ``"cuda"``, ``"cuda:1"``, ``"mps"``, ``"auto"`` (the first CUDA
            GPU when torch sees one, else the CPU), a ``torch.device`` or ``None`` (CPU).

    Returns:
        The device.

    Raises:
        InputError: Unknown name, or a device this machine does not have (one line saying
            why and what to use instead).
    """
    if isinstance(device, str) and device.strip().lower() == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device("cpu" if device is None else device)
    except (RuntimeError, TypeError) as exc:
        raise InputError(f"not a torch device: {device!r} ({exc})", field="device") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            build = "a CPU-only build" if torch.version.cuda is None else "no usable GPU"
            raise InputError(
                f"{device!r} requested but CUDA is not available on this machine (torch "
                f"{torch.__version__}: {build}); use cpu or auto",
                field="device",
            )
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise InputError(
                f"{device!r} requested but this machine has {torch.cuda.device_count()} "
                "CUDA device(s)",
                field="device",
            )
    if dev.type == "mps" and not torch.backends.mps.is_available():
        raise InputError("MPS is not available on this machine; use cpu or auto", field="device")
    if dev.type not in ("cpu", "cuda", "mps"):
        raise InputError(f"unsupported device type {dev.type!r}", field="device")
    return dev


def load_into(
    module: torch.nn.Module,
    state_dict: Mapping[str, torch.Tensor],
    *,
    what: str,
    derived: Iterable[str] = (),
    ignore_unexpected: str | None = None,
) -> torch.nn.Module:
    """Load a state dict, failing loudly on anything but known-harmless differences.

    Args:
        module: Module built with random weights.
        state_dict: Tensors keyed like ``module.state_dict()``.
        what: File name used in error messages.
        derived: Keys allowed to be missing: buffers the constructor computes (and
            BatchNorm's ``num_batches_tracked``, which inference does not use).
        ignore_unexpected: Regular expression of extra keys to tolerate (e.g. parts of a
            checkpoint that belong to another network).

    Returns:
        The module, in evaluation mode.

    Raises:
        WeightsError: A learned parameter is missing, a key is unexpected, or a shape differs.
    """
    if not isinstance(state_dict, Mapping) or not all(
        isinstance(v, torch.Tensor) for v in state_dict.values()
    ):
        raise WeightsError(f"{what}: not a state dict of tensors")
    try:
        result = module.load_state_dict(dict(state_dict), strict=False)
    except RuntimeError as exc:  # shape mismatch
        raise WeightsError(f"{what}: does not fit {type(module).__name__}: {exc}") from None
    allowed = set(derived)
    missing = [
        k for k in result.missing_keys if k not in allowed and not k.endswith("num_batches_tracked")
    ]
    pattern = re.compile(ignore_unexpected) if ignore_unexpected else None
    unexpected = [k for k in result.unexpected_keys if not (pattern and pattern.fullmatch(k))]
    if missing or unexpected:
        raise WeightsError(
            f"{what}: not the expected checkpoint for {type(module).__name__}: "
            f"{len(missing)} missing keys {missing[:5]}, {len(unexpected)} unexpected keys "
            f"{unexpected[:5]}"
        )
    return module.eval()


def lightglue_state_dict(raw: Mapping[str, Any], n_layers: int) -> dict[str, torch.Tensor]:
    """Map a LightGlue checkpoint onto kornia's ``LightGlue`` key names.

    Handles the layouts of the official files: cvg/LightGlue's first release
    (``self_attn.<i>.*`` / ``cross_attn.<i>.*``), its later one (``transformers.<i>.*``), and
    verlab's LighterGlue (keys prefixed ``matcher.``, next to ``extractor.*`` keys of the
    XFeat backbone, which are dropped). The same renaming as kornia's own loader, restricted
    to leading key components.

    Args:
        raw: State dict as stored in the file.
        n_layers: Number of transformer layers of the configuration.

    Returns:
        A state dict keyed like ``kornia.feature.LightGlue``.
    """
    out: dict[str, torch.Tensor] = {}
    for key, value in raw.items():
        if key.startswith("extractor."):
            continue
        if key.startswith("matcher."):
            key = key[len("matcher.") :]
        for block in ("self_attn", "cross_attn"):
            m = re.match(rf"{block}\.(\d+)\.(.*)", key)
            if m and int(m.group(1)) < n_layers:
                key = f"transformers.{m.group(1)}.{block}.{m.group(2)}"
        out[key] = value
    return out


def build_lightglue(
    features: str, raw_state: Mapping[str, Any], *, what: str, **overrides: Any
) -> torch.nn.Module:
    """Build kornia's LightGlue for ``features`` and load a checkpoint into it.

    Args:
        features: A key of ``kornia.feature.LightGlue.features`` (``"disk"``, ``"aliked"``,
            ``"xfeat"``, ``"doghardnet"``).
        raw_state: The checkpoint's state dict (see :func:`lightglue_state_dict`).
        what: File name used in error messages.
        **overrides: Configuration entries such as ``filter_threshold``,
            ``depth_confidence`` or ``width_confidence``.

    Returns:
        The model in evaluation mode.
    """
    from kornia.feature import LightGlue

    conf = {k: v for k, v in LightGlue.features[features].items() if k != "weights"}
    conf.update(overrides)
    model = LightGlue(None, **conf)
    state = lightglue_state_dict(raw_state, model.conf.n_layers)
    load_into(
        model,
        state,
        what=what,
        derived=("confidence_thresholds",),
        # the first release stores an unused per-layer temperature ``log_assignment.<i>.r``
        ignore_unexpected=r"log_assignment\.\d+\.r",
    )
    fused = fused_cross_block()
    for layer in model.transformers:
        layer.cross_attn.__class__ = fused  # same weights and keys, another forward
    return model.eval()


def _fused_cross_forward(
    self: Any, x0: torch.Tensor, x1: torch.Tensor, mask: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``forward`` of kornia's ``CrossBlock`` with both directions fused off CUDA."""
    if mask is not None or x0.device.type == "cuda":
        from kornia.feature.lightglue import CrossBlock

        return CrossBlock.forward(self, x0, x1, mask)  # type: ignore[no-any-return]
    qk0, qk1 = self.to_qk(x0), self.to_qk(x1)
    v0, v1 = self.to_v(x0), self.to_v(x1)
    qk0, qk1, v0, v1 = (
        t.unflatten(-1, (self.heads, -1)).transpose(1, 2) for t in (qk0, qk1, v0, v1)
    )
    m0 = F.scaled_dot_product_attention(qk0, qk1, v1, scale=self.scale)
    m1 = F.scaled_dot_product_attention(qk1, qk0, v0, scale=self.scale)
    m0, m1 = (self.to_out(t.transpose(1, 2).flatten(start_dim=-2)) for t in (m0, m1))
    x0 = x0 + self.ffn(torch.cat([x0, m0], -1))
    x1 = x1 + self.ffn(torch.cat([x1, m1], -1))
    return x0, x1


@functools.cache
def fused_cross_block() -> type[torch.nn.Module]:
    """The ``CrossBlock`` of kornia's LightGlue with both attention directions fused off CUDA.

    kornia fuses the two directions with ``F.scaled_dot_product_attention`` on CUDA only;
    elsewhere it builds the whole ``(M, N)`` similarity matrix, a transposed copy and two
    softmaxes in memory (on the CPU about 60 % of LightGlue's time at 4000 keypoints:
    ``bmm``, ``softmax``, ``copy_``). Two calls of ``scaled_dot_product_attention``
    (``softmax(q0 q1^T / sqrt(d)) v1`` and ``softmax(q1 q0^T / sqrt(d)) v0``; kornia scales
    each side by ``d^-1/4``) are the same arithmetic without the matrix, as the official
    LightGlue's ``flash`` path: the results agree to float32 rounding. The subclass adds
    no parameter, so a loaded block takes it by ``block.__class__ = fused_cross_block()``
    with its weights and state-dict keys unchanged; masked calls (padded static lengths)
    and CUDA keep kornia's own paths.
    """
    from kornia.feature.lightglue import CrossBlock

    return type("FusedCrossBlock", (CrossBlock,), {"forward": _fused_cross_forward})


def image_tensor(
    image: NDArray[np.float32], device: torch.device, channels: int = 1
) -> torch.Tensor:
    """``(H, W)`` array -> ``(1, channels, H, W)`` float32 tensor on ``device``."""
    t = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32))[None, None]
    if channels > 1:
        t = t.expand(1, channels, *image.shape).contiguous()
    return t.to(device)


def image_batch(
    images: Sequence[NDArray[np.float32]], device: torch.device, channels: int = 1
) -> torch.Tensor:
    """``B`` arrays of one ``(H, W)`` shape -> ``(B, channels, H, W)`` float32 on ``device``."""
    if len({im.shape for im in images}) != 1:
        raise InputError(f"a batch needs images of one shape, got {[im.shape for im in images]}")
    if len(images) == 1:
        return image_tensor(images[0], device, channels)
    t = torch.from_numpy(np.stack([np.asarray(im, np.float32) for im in images]))[:, None]
    if channels > 1:
        t = t.expand(len(images), channels, *images[0].shape).contiguous()
    return t.to(device)


def pad_to_multiple(t: torch.Tensor, multiple: int) -> torch.Tensor:
    """Replicate-pad a ``(B, C, H, W)`` tensor at the bottom/right to multiples of ``multiple``.

    Padding (not resizing) keeps pixel coordinates unchanged.
    """
    h, w = t.shape[-2:]
    ph, pw = (-h) % multiple, (-w) % multiple
    if ph == 0 and pw == 0:
        return t
    return F.pad(t, (0, pw, 0, ph), mode="replicate")


def padded_batch(
    images: Sequence[NDArray[np.float32]], device: torch.device, multiple: int, channels: int = 1
) -> torch.Tensor:
    """Images whose sides round up to the same multiples of ``multiple``, as one batch.

    Each is replicate-padded at the bottom/right on its own (:func:`pad_to_multiple`), so
    every image of the batch is the very tensor it would be alone.
    """
    if len(images) == 1:
        return pad_to_multiple(image_tensor(images[0], device, channels), multiple)
    same = {im.shape for im in images}
    if len(same) == 1:
        return pad_to_multiple(image_batch(images, device, channels), multiple)
    parts = [pad_to_multiple(image_tensor(im, device, channels), multiple) for im in images]
    if len({p.shape for p in parts}) != 1:
        raise InputError(
            f"a batch needs images of one padded shape, got {[im.shape for im in images]}"
        )
    return torch.cat(parts)


def unpadded(keypoints: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """Say which ``(N, 2)`` ``(x, y)`` keypoints of a padded image lie in the original.

    The counterpart of :func:`pad_to_multiple`: ``shape`` is the ``(H, W)`` before padding,
    keypoints in the added bottom/right margin are ``False``.
    """
    h, w = shape
    return (keypoints[:, 0] < w) & (keypoints[:, 1] < h)


def resize_image(
    image: NDArray[np.float32], size_hw: tuple[int, int]
) -> tuple[NDArray[np.float32], float, float]:
    """Resize an image to ``(H', W')`` with area averaging (down) or bilinear (up).

    Returns:
        ``(resized, sx, sy)`` with ``sx = W'/W`` and ``sy = H'/H``. In planetref's corner
        convention a coordinate maps exactly as ``x' = x * sx``, ``y' = y * sy``.
    """
    import cv2

    h, w = image.shape
    nh, nw = size_hw
    if (nh, nw) == (h, w):
        return image, 1.0, 1.0
    interp = cv2.INTER_AREA if nh * nw < h * w else cv2.INTER_LINEAR
    out = cv2.resize(image, (nw, nh), interpolation=interp)
    return out.astype(np.float32, copy=False), nw / w, nh / h


class TorchMatcher(BaseMatcher):
    """A matcher with a torch model built lazily, once per instance.

    Args:
        settings: Weights directory, device, checksum check and polish (see
            :class:`~planetref.matching.options.TorchSettings`); ``None``: the defaults.

    Raises:
        WeightsError: A weight file is missing (checked at construction, without hashing).
        InputError: Unusable device, or settings of the wrong type.
    """

    weight_files: ClassVar[tuple[str, ...]] = ()
    settings_type: ClassVar[type[TorchSettings]] = TorchSettings

    def __init__(self, settings: TorchSettings | None = None) -> None:
        super().__init__()
        if settings is None:
            settings = self.settings_type()
        if not isinstance(settings, self.settings_type):
            raise InputError(
                f"{self.name} takes {self.settings_type.__name__}, got {type(settings).__name__}",
                field="settings",
            )
        self.settings = settings
        # resolved once, so that a later change of the environment does not move the files
        self.weights_dir = weights_dir(settings.weights_dir)
        self.device = resolve_device(settings.device)
        require_weights(self.weight_files, self.weights_dir)
        self._model: Any = None
        self._lock = threading.Lock()

    def _checkpoint(self, name: str) -> Any:
        return load_checkpoint(name, self.weights_dir, verify=self.settings.verify_weights)

    def build(self) -> None:
        """Load the weights and build the model now (otherwise done on the first match)."""
        with self._lock:
            if self._model is None:
                start = time.perf_counter()
                self._model = self._build()
                self.timings["build"] = time.perf_counter() - start

    @abstractmethod
    def _build(self) -> Any:
        """Return the model(s), on :attr:`device`, in evaluation mode."""

    def _match_normalised(
        self,
        image0: NDArray[np.float32],
        valid0: NDArray[np.bool_],
        image1: NDArray[np.float32],
        valid1: NDArray[np.bool_],
    ) -> Matches:
        pair = NormalisedPair(image0, valid0, image1, valid1)
        if self._model is None:
            self.build()
        with torch.inference_mode():
            result = self._run(pair)
        return self._polished([pair], [result])[0]

    def _polished(self, pairs: Sequence[NormalisedPair], results: list[Matches]) -> list[Matches]:
        """The results, each refined by NCC when :attr:`settings` ask for ``polish="ncc"``."""
        if self.settings.polish != "ncc":
            return results
        from planetref.matching.ncc import refine_matches_ncc

        with self._timed("polish"):
            return [refine_matches_ncc(*p, m) for p, m in zip(pairs, results, strict=True)]

    @abstractmethod
    def _run(self, pair: NormalisedPair) -> Matches:
        """Match normalised images under ``torch.inference_mode``."""


class SparseLightGlueMatcher(TorchMatcher):
    """Detector/descriptor + LightGlue, the shared pipeline of the learned sparse matchers.

    Subclasses set :attr:`lightglue_features` and :attr:`lightglue_weights` and implement
    :meth:`_build_extractor` and :meth:`_extract`; :meth:`_build` loads LightGlue and
    :meth:`_run` does the rest (resizing, coordinate conversion, LightGlue inputs, scores).
    Keypoints on invalid pixels are dropped before LightGlue sees them.

    Args:
        settings: Keypoint budget, model image size, LightGlue thresholds, weights, device
            and polish (see :class:`~planetref.matching.options.LightGlueSettings`);
            ``None``: the defaults.
    """

    settings_type: ClassVar[type[LightGlueSettings]] = LightGlueSettings
    settings: LightGlueSettings
    #: key of ``kornia.feature.LightGlue.features`` (``"disk"``, ``"aliked"``, ...)
    lightglue_features: ClassVar[str] = ""
    #: cache file name of the LightGlue checkpoint (see :func:`build_lightglue`)
    lightglue_weights: ClassVar[str] = ""
    #: the detector pads its input to multiples of this (:func:`padded_batch`), so images
    #: whose sides round up alike share a batch; 0: only images of one shape do
    pad_multiple: ClassVar[int] = 0

    def _build(self) -> dict[str, torch.nn.Module]:
        """Build ``{"extractor": ..., "matcher": LightGlue}`` on :attr:`device`."""
        extractor = self._build_extractor()
        matcher = build_lightglue(
            self.lightglue_features,
            self._checkpoint(self.lightglue_weights),
            what=self.lightglue_weights,
            **self.settings.lightglue_overrides(),
        )
        return {"extractor": extractor.to(self.device), "matcher": matcher.to(self.device)}

    @abstractmethod
    def _build_extractor(self) -> torch.nn.Module:
        """Return the detector/descriptor with its weights loaded, in evaluation mode.

        It is moved to :attr:`device` by :meth:`_build` and called by :meth:`_extract` as
        ``self._model["extractor"]``.
        """

    @abstractmethod
    def _extract_batch(
        self, images: Sequence[NDArray[np.float32]]
    ) -> list[dict[str, torch.Tensor]]:
        """Detect and describe on normalised images, all of one shape, in one forward pass.

        (Of one padded shape where :attr:`pad_multiple` is set.)

        Each image's features do not depend on the others of the batch (to float
        tolerance): one image at a time and a batch give the same features.

        Returns:
            Per image: ``keypoints`` ``(N, 2)`` in the library's pixel-centre-at-integer
            frame of the given image, ``descriptors`` ``(N, D)``, and for DoG features
            ``scales`` and ``oris`` ``(N,)`` as LightGlue expects them.
        """

    def _extract(self, image: NDArray[np.float32]) -> dict[str, torch.Tensor]:
        """:meth:`_extract_batch` of one image."""
        return self._extract_batch([image])[0]

    def _model_image(self, image: NDArray[np.float32]) -> tuple[NDArray[np.float32], float, float]:
        """The image the network sees (downscaled beyond ``max_size``) and its scale factors."""
        h, w = image.shape
        max_size = self.settings.max_size
        if max_size is not None and max(h, w) > max_size:
            s = max_size / max(h, w)
            size = (max(16, round(h * s)), max(16, round(w * s)))
            return resize_image(image, size)
        return image, 1.0, 1.0

    def _keep_valid(
        self,
        feats: dict[str, torch.Tensor],
        model: tuple[NDArray[np.float32], float, float],
        valid: NDArray[np.bool_],
    ) -> dict[str, Any]:
        """Features of one image in planetref's corner frame, those on invalid pixels dropped."""
        model_image, scale_x, scale_y = model
        kpts = feats["keypoints"].detach().to("cpu", torch.float64).numpy().reshape(-1, 2)
        # library frame (centres at integers) -> corner frame, then back to full resolution
        corner = (kpts + 0.5) / np.array([scale_x, scale_y])
        keep = keypoints_on_valid_pixels(corner, valid)
        idx = torch.from_numpy(np.flatnonzero(keep)).to(feats["keypoints"].device)
        out = {k: v.index_select(0, idx) for k, v in feats.items()}
        out["corner"] = corner[keep]
        out["image_size"] = (model_image.shape[1], model_image.shape[0])
        return out

    def _features(self, image: NDArray[np.float32], valid: NDArray[np.bool_]) -> dict[str, Any]:
        model = self._model_image(image)
        with self._timed("forward"):
            feats = self._extract(model[0])
        return self._keep_valid(feats, model, valid)

    def _features_batched(
        self, images: Sequence[NDArray[np.float32]], valids: Sequence[NDArray[np.bool_]], batch: int
    ) -> list[dict[str, Any]]:
        """:meth:`_features` of many images: those of one model shape ``batch`` at a time."""
        models = [self._model_image(im) for im in images]
        groups: dict[tuple[int, ...], list[int]] = {}
        k = self.pad_multiple
        for i, m in enumerate(models):
            shape = m[0].shape if k < 1 else tuple(-(-n // k) * k for n in m[0].shape)
            groups.setdefault(shape, []).append(i)
        feats: list[dict[str, torch.Tensor] | None] = [None] * len(images)
        for members in groups.values():
            for a in range(0, len(members), batch):
                part = members[a : a + batch]
                with self._timed("forward"):
                    got = self._extract_batch([models[i][0] for i in part])
                for i, f in zip(part, got, strict=True):
                    feats[i] = f
        return [
            self._keep_valid(f, m, v)  # type: ignore[arg-type]  # every entry is set above
            for f, m, v in zip(feats, models, valids, strict=True)
        ]

    def _run(self, pair: NormalisedPair) -> Matches:
        return self._glue(
            self._features(pair.image0, pair.valid0), self._features(pair.image1, pair.valid1)
        )

    def _match_normalised_many(
        self, inputs: list[NormalisedPair], batch_size: int
    ) -> list[Matches]:
        """Features of all images in batches of one shape, then LightGlue pair by pair.

        kornia's LightGlue runs the pairs of a batch one at a time when its adaptive
        pruning is on (planetref's default), so only the detectors are batched.
        """
        if batch_size <= 1 or len(inputs) <= 1:
            return [self._match_normalised(*x) for x in inputs]
        if self._model is None:
            self.build()
        with torch.inference_mode():
            images = [im for x in inputs for im in (x.image0, x.image1)]
            valids = [v for x in inputs for v in (x.valid0, x.valid1)]
            feats = self._features_batched(images, valids, batch_size)
            out = [self._glue(feats[2 * i], feats[2 * i + 1]) for i in range(len(inputs))]
        return self._polished(inputs, out)

    def _glue(self, f0: dict[str, Any], f1: dict[str, Any]) -> Matches:
        """LightGlue on the features of two images."""
        if len(f0["corner"]) < 2 or len(f1["corner"]) < 2:
            return Matches.empty()
        data = {}
        for key, f in (("image0", f0), ("image1", f1)):
            entry = {
                "keypoints": f["keypoints"][None].float(),
                "descriptors": f["descriptors"][None].float(),
                "image_size": torch.tensor(
                    [f["image_size"]], device=self.device, dtype=torch.float32
                ),
            }
            for extra in ("scales", "oris"):
                if extra in f:
                    entry[extra] = f[extra][None].float()
            data[key] = entry
        with self._timed("forward"):
            out = self._model["matcher"](data)
        pairs = out["matches"][0].to("cpu").numpy()
        scores = out["scores"][0].to("cpu", torch.float64).numpy()
        if len(pairs) == 0:
            return Matches.empty()
        return Matches(f0["corner"][pairs[:, 0]], f1["corner"][pairs[:, 1]], scores)
