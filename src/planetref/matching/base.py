"""The matcher contract: :class:`Matches`, the :class:`Matcher` protocol, :class:`MatcherSpec`.

Pixel convention
----------------
Keypoints are ``(x, y)`` = ``(column, row)`` in pixels of the tile they were found on,
with the top-left corner of the first pixel at ``(0, 0)``: the centre of the first
pixel is ``(0.5, 0.5)`` and pixel ``(row r, column c)`` covers ``[c, c + 1) x [r, r + 1)``.
OpenCV and kornia put pixel centres at integer coordinates; their keypoints are moved by
``+0.5`` on the way out (each matcher module states what its library returns).

Input images are 2-D arrays of any numeric type and radiometric range. Masks are boolean
"valid pixel" arrays of the same shape (``True`` = usable). Non-finite pixels are treated as
invalid as well. A keypoint whose pixel is invalid is never returned.

This module imports neither torch nor OpenCV.
"""

from __future__ import annotations

import contextlib
import inspect
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, fields
from types import MappingProxyType
from typing import Any, ClassVar, Literal, NamedTuple, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planetref.errors import InputError
from planetref.matching.options import TorchSettings, split_options

__all__ = [
    "PARADIGMS",
    "BaseMatcher",
    "Matcher",
    "MatcherSpec",
    "Matches",
    "NormalisedPair",
    "Paradigm",
    "keypoints_on_valid_pixels",
    "prepare_image",
    "robust_normalise",
]

Paradigm = Literal[
    "handcrafted", "learned sparse", "detector-free dense", "semi-dense", "area-based"
]
PARADIGMS: tuple[str, ...] = (
    "handcrafted",
    "learned sparse",
    "detector-free dense",
    "semi-dense",
    "area-based",
)

MIN_SIDE = 16
"""Images with a side shorter than this many pixels give no matches."""


def _points(value: ArrayLike, field_name: str) -> NDArray[np.float64]:
    arr = np.array(value, dtype=np.float64, copy=True)
    if arr.size == 0:
        arr = arr.reshape(0, 2)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise InputError(f"must have shape (N, 2), got {arr.shape}", field=field_name)
    if not np.all(np.isfinite(arr)):
        raise InputError("must be finite", field=field_name)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class Matches:
    """Point correspondences between two images.

    Coordinates are ``(x, y)`` = ``(column, row)`` pixels of each image, top-left corner of
    the first pixel at ``(0, 0)`` (first pixel centre at ``(0.5, 0.5)``). Arrays are copied
    on construction and read-only afterwards.

    Attributes:
        keypoints0: ``(N, 2)`` float64 keypoints in image 0, pixels.
        keypoints1: ``(N, 2)`` float64 keypoints in image 1, pixels; row ``i`` matches row
            ``i`` of ``keypoints0``.
        confidence: ``(N,)`` float64 per-match confidence, higher is better. Its scale depends
            on the matcher (a ratio-test margin, a network score or a correlation peak), so
            compare it within one matcher only.
    """

    keypoints0: NDArray[np.float64]
    keypoints1: NDArray[np.float64]
    confidence: NDArray[np.float64]

    def __post_init__(self) -> None:
        k0 = _points(self.keypoints0, "keypoints0")
        k1 = _points(self.keypoints1, "keypoints1")
        conf = np.array(self.confidence, dtype=np.float64, copy=True)
        if conf.size == 0:
            conf = conf.reshape(0)
        if conf.ndim != 1:
            raise InputError(f"must have shape (N,), got {conf.shape}", field="confidence")
        if not (len(k0) == len(k1) == len(conf)):
            raise InputError(
                f"keypoints0, keypoints1 and confidence must have the same length, got "
                f"{len(k0)}, {len(k1)} and {len(conf)}"
            )
        if not np.all(np.isfinite(conf)):
            raise InputError("must be finite", field="confidence")
        conf.setflags(write=False)
        object.__setattr__(self, "keypoints0", k0)
        object.__setattr__(self, "keypoints1", k1)
        object.__setattr__(self, "confidence", conf)

    @classmethod
    def empty(cls) -> Matches:
        """Return a typed empty result: ``(0, 2)`` keypoints and a ``(0,)`` confidence."""
        return cls(np.empty((0, 2)), np.empty((0, 2)), np.empty(0))

    @classmethod
    def concatenate(cls, parts: Iterable[Matches]) -> Matches:
        """Stack several results (e.g. from tiles) into one, in order."""
        parts = list(parts)
        if not parts:
            return cls.empty()
        return cls(
            np.concatenate([p.keypoints0 for p in parts]),
            np.concatenate([p.keypoints1 for p in parts]),
            np.concatenate([p.confidence for p in parts]),
        )

    def __len__(self) -> int:
        return int(self.confidence.shape[0])

    def __repr__(self) -> str:
        return f"Matches(n={len(self)})"

    def select(self, selection: ArrayLike) -> Matches:
        """Return the matches picked by a boolean mask ``(N,)`` or an integer index array."""
        sel = np.asarray(selection)
        if sel.dtype == bool:
            if sel.shape != (len(self),):
                raise InputError(
                    f"boolean selection must have shape ({len(self)},), got {sel.shape}"
                )
        elif sel.size and not np.issubdtype(sel.dtype, np.integer):
            raise InputError(f"selection must be boolean or integer, got dtype {sel.dtype}")
        else:
            sel = sel.astype(np.intp).reshape(-1)
        return Matches(self.keypoints0[sel], self.keypoints1[sel], self.confidence[sel])

    def shifted(self, offset0: tuple[float, float], offset1: tuple[float, float]) -> Matches:
        """Return the matches with ``(dx, dy)`` pixels added to each image's keypoints.

        Used to move tile coordinates to full-image coordinates (add the tile origin, in
        pixels, column first).
        """
        return Matches(
            self.keypoints0 + np.asarray(offset0, np.float64),
            self.keypoints1 + np.asarray(offset1, np.float64),
            self.confidence,
        )

    @property
    def displacement(self) -> NDArray[np.float64]:
        """``keypoints1 - keypoints0``, ``(N, 2)`` pixels."""
        return self.keypoints1 - self.keypoints0

    def to_array(self) -> NDArray[np.float64]:
        """Return an ``(N, 5)`` array of ``x0, y0, x1, y1, confidence``."""
        return np.column_stack([self.keypoints0, self.keypoints1, self.confidence])


@runtime_checkable
class Matcher(Protocol):
    """Anything that finds correspondences between two single-band images.

    Attributes:
        name: Registry name of the matcher (e.g. ``"sift"``).
    """

    name: str

    def match(
        self,
        image0: ArrayLike,
        image1: ArrayLike,
        mask0: ArrayLike | None = None,
        mask1: ArrayLike | None = None,
    ) -> Matches:
        """Match two images.

        Args:
            image0: 2-D array, any numeric dtype and radiometric range.
            image1: 2-D array, any numeric dtype and radiometric range; its size may differ.
            mask0: Boolean array shaped like ``image0``, ``True`` on valid pixels; ``None``
                means every finite pixel is valid.
            mask1: Same for ``image1``.

        Returns:
            The matches, in pixel coordinates of each image (first pixel centre at
            ``(0.5, 0.5)``), none of them on an invalid pixel. An empty result when
            nothing matches.
        """
        ...


@dataclass(frozen=True)
class MatcherSpec:
    """Registry entry describing one matcher.

    Attributes:
        name: Registry name, the ``--matcher`` value of the CLI.
        description: One-line human description.
        paradigm: One of :data:`PARADIGMS`.
        weights: Cache file names of the pretrained weights it needs (see
            :mod:`planetref.matching.weights`); empty when it needs none.
        factory: Callable building the matcher. It takes ``weights_dir`` and ``device``
            keywords (ignored by matchers without weights) and matcher-specific options.
        load_class: Imports and returns the matcher's class (its declarations, e.g.
            :attr:`BaseMatcher.pixel_options`, without building it); ``None`` when the
            entry has no class.
    """

    name: str
    description: str
    paradigm: Paradigm
    weights: tuple[str, ...]
    factory: Callable[..., Matcher]
    load_class: Callable[[], type[BaseMatcher]] | None = None

    def matcher_class(self) -> type[BaseMatcher]:
        """The matcher's class (imports its module only)."""
        if self.load_class is None:
            raise InputError(f"matcher {self.name!r} has no class to describe its options")
        return self.load_class()

    def __post_init__(self) -> None:
        if self.paradigm not in PARADIGMS:
            raise InputError(f"unknown paradigm {self.paradigm!r}; expected one of {PARADIGMS}")


# --------------------------------------------------------------------------- inputs


def prepare_image(
    image: ArrayLike, mask: ArrayLike | None = None, *, which: str = "image"
) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """Validate one input image and its mask.

    Args:
        image: 2-D numeric array (a ``numpy.ma.MaskedArray`` contributes its mask).
        mask: Optional boolean array of the same shape, ``True`` on valid pixels. Integer
            arrays are accepted as ``!= 0``.
        which: Name used in error messages (``"image0"``...).

    Returns:
        ``(image, valid)``: the image as float32 and the validity mask (the given mask, the
        masked-array mask and finiteness combined).

    Raises:
        InputError: Not 2-D, not numeric, or a mask of another shape.
    """
    ma_mask = None
    if np.ma.isMaskedArray(image):
        ma_mask = np.ma.getmaskarray(image)
        image = np.ma.getdata(image)
    arr = np.asarray(image)
    if arr.ndim != 2:
        raise InputError(f"must be a 2-D array, got shape {arr.shape}", field=which)
    if arr.dtype == bool or not (
        np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)
    ):
        raise InputError(f"must be a real numeric array, got dtype {arr.dtype}", field=which)
    img = arr.astype(np.float32, copy=False)
    valid = np.isfinite(img)
    if ma_mask is not None:
        valid &= ~ma_mask
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != arr.shape:
            raise InputError(
                f"mask shape {m.shape} differs from image shape {arr.shape}",
                field=f"mask of {which}",
            )
        valid &= m.astype(bool) if m.dtype != bool else m
    return img, valid


def robust_normalise(
    image: NDArray[np.floating],
    valid: NDArray[np.bool_],
    low: float = 0.5,
    high: float = 99.5,
    max_samples: int = 1_000_000,
) -> tuple[NDArray[np.float32], bool]:
    """Map an image to ``[0, 1]`` with percentiles of its valid pixels.

    Invalid pixels take the median of the normalised valid pixels, so the no-data border
    does not create strong artificial edges. Statistics ignore invalid pixels entirely
    (ISIS special values of -3.4e38 would otherwise wreck them).

    Args:
        image: 2-D array.
        valid: Validity mask of the same shape.
        low: Lower percentile mapped to 0.
        high: Upper percentile mapped to 1.
        max_samples: Percentiles are computed on at most this many evenly strided valid
            pixels (deterministic), to keep large tiles cheap.

    Returns:
        ``(normalised float32 image, flat)``. ``flat`` is True when the valid pixels have no
        contrast (constant, or fewer than 16 of them); the image is then all zeros.
    """
    all_valid = bool(valid.all())
    values = image.ravel() if all_valid else image[valid]
    if values.size < 16:
        return np.zeros(image.shape, np.float32), True
    if values.size > max_samples:
        values = values[:: int(np.ceil(values.size / max_samples))]
    # A float64 copy of its own: the percentiles may reorder it in place (same values).
    v64 = values.astype(np.float64)
    lo, hi = (float(v) for v in np.percentile(v64, [low, high], overwrite_input=True))
    if not hi - lo > 1e-6 * max(abs(lo), abs(hi)) + 1e-30:
        # near-constant within the percentile band: fall back to the full range before
        # declaring the image flat (a few bright features on a flat background)
        lo, hi = float(values.min()), float(values.max())
        if not hi - lo > 1e-6 * max(abs(lo), abs(hi)) + 1e-30:
            return np.zeros(image.shape, np.float32), True
    # In place on one float64 array: the same operations, and values, as
    # clip((image - lo) / (hi - lo), 0, 1) (invalid pixels take the fill below).
    out = image.astype(np.float64)
    if not all_valid:
        out[~valid] = lo
    out -= lo
    out /= hi - lo
    np.clip(out, 0.0, 1.0, out=out)
    res = out.astype(np.float32)
    if not all_valid:  # the fill (a median over the valid pixels) only where it is used
        v64 -= lo
        v64 /= hi - lo
        res[~valid] = float(np.median(np.clip(v64, 0.0, 1.0, out=v64), overwrite_input=True))
    return res, False


def keypoints_on_valid_pixels(
    keypoints: NDArray[np.floating], valid: NDArray[np.bool_]
) -> NDArray[np.bool_]:
    """Say which keypoints fall on a valid pixel.

    Args:
        keypoints: ``(N, 2)`` ``(x, y)`` pixels, first pixel centre at ``(0.5, 0.5)``.
        valid: Validity mask ``(H, W)``.

    Returns:
        ``(N,)`` boolean, False outside the image or on an invalid pixel.
    """
    kp = np.asarray(keypoints, np.float64).reshape(-1, 2)
    finite = np.all(np.isfinite(kp), axis=1)
    col = np.floor(np.where(finite, kp[:, 0], -1.0)).astype(np.int64)
    row = np.floor(np.where(finite, kp[:, 1], -1.0)).astype(np.int64)
    h, w = valid.shape
    inside = finite & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    ok = np.zeros(len(kp), bool)
    ok[inside] = valid[row[inside], col[inside]]
    return ok


# --------------------------------------------------------------------------- base class


class NormalisedPair(NamedTuple):
    """Two images robustly normalised to ``[0, 1]`` (invalid pixels filled) and their masks.

    What :meth:`BaseMatcher._match_normalised` receives (unpacked) and the torch matchers'
    ``_run`` receives whole.
    """

    image0: NDArray[np.float32]
    valid0: NDArray[np.bool_]
    image1: NDArray[np.float32]
    valid1: NDArray[np.bool_]


class BaseMatcher(ABC):
    """Shared input handling for planetref matchers.

    :meth:`match` validates the inputs, normalises both images robustly over their valid
    pixels (see :func:`robust_normalise`), short-circuits to an empty result for a flat or
    tiny image, calls :meth:`_match_normalised`, and finally drops every match whose
    keypoint lies on an invalid pixel in either image.

    After each call, :attr:`timings` holds seconds spent per stage: ``"normalise"``,
    ``"forward"`` (the detector/descriptor/matcher or the correlation itself), ``"build"``
    (loading weights, first call only), ``"other"`` (conversion and post-processing) and
    ``"total"``.
    """

    name: ClassVar[str] = "base"
    #: type of the settings value the constructor takes first (``None``: keywords only)
    settings_type: ClassVar[type[TorchSettings] | None] = None
    #: Options that are lengths in pixels of the grid the matcher works on. The front end
    #: sets them in reference pixels and scales them to its fine grid, so a finer grid keeps
    #: their ground size.
    pixel_options: ClassVar[tuple[str, ...]] = ()
    #: The option that bounds the search around the same pixel of the other image (an
    #: area-based matcher), or ``None`` for a matcher that searches the whole window. The
    #: front end sets it to cover the window's pad (fine stage) or the a-priori
    #: uncertainty (coarse stage), so such a matcher gets its own coarse-stage instance.
    search_option: ClassVar[str | None] = None
    #: Options of the coarse-stage instance (under the user's own), for a matcher with a
    #: :attr:`search_option`.
    coarse_defaults: ClassVar[Mapping[str, Any]] = MappingProxyType({})
    #: The option giving the radius (pixels of the grid it matches on) of the square
    #: window one match is computed from, for a matcher whose neighbouring matches share
    #: those pixels (area-based); ``None`` for sparse feature matchers. The adjustment's
    #: stochastic model weights such matches by their effective independence.
    support_option: ClassVar[str | None] = None
    #: The option that turns on dense mode (one match per grid cell of this many pixels),
    #: which the front end uses on the fine stage when the matcher takes it.
    dense_option: ClassVar[str] = "dense_spacing_px"

    def __init__(self) -> None:
        self.timings: dict[str, float] = {}

    @classmethod
    def option_names(cls) -> tuple[str, ...]:
        """The flat option names :meth:`from_options` accepts (registry/configuration keys).

        The fields of :attr:`settings_type`, then the constructor's keyword-only arguments.
        """
        shared = [] if cls.settings_type is None else [f.name for f in fields(cls.settings_type)]
        own = [
            p.name
            for p in inspect.signature(cls).parameters.values()
            if p.kind is inspect.Parameter.KEYWORD_ONLY
        ]
        return (*shared, *own)

    @classmethod
    def runs_dense(cls) -> bool:
        """Whether the matcher takes :attr:`dense_option` (has a dense mode)."""
        return cls.dense_option in cls.option_names()

    @classmethod
    def option_default(cls, option: str) -> Any:
        """The constructor's default of one keyword option."""
        return inspect.signature(cls).parameters[option].default

    @classmethod
    def from_options(cls, **options: Any) -> BaseMatcher:
        """Build the matcher from flat options (see :meth:`option_names`).

        Keys that are fields of :attr:`settings_type` make the settings value; the others are
        passed as the constructor's own keywords.
        """
        if cls.settings_type is None:
            return cls(**options)
        settings, own = split_options(cls.settings_type, options)
        return cls(settings, **own)  # type: ignore[call-arg]  # settings-taking subclasses

    @contextlib.contextmanager
    def _timed(self, key: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.timings[key] = self.timings.get(key, 0.0) + time.perf_counter() - start

    def match(
        self,
        image0: ArrayLike,
        image1: ArrayLike,
        mask0: ArrayLike | None = None,
        mask1: ArrayLike | None = None,
    ) -> Matches:
        """Match two images; see :meth:`Matcher.match` for the contract.

        Args:
            image0: 2-D array, any numeric dtype and radiometric range.
            image1: 2-D array, any numeric dtype and radiometric range.
            mask0: Boolean valid-pixel mask of ``image0`` or ``None``.
            mask1: Boolean valid-pixel mask of ``image1`` or ``None``.

        Returns:
            Matches in pixel coordinates (first pixel centre at ``(0.5, 0.5)``).

        Raises:
            InputError: Malformed images or masks.
        """
        self.timings = {}
        start = time.perf_counter()
        inputs = self._normalised(image0, image1, mask0, mask1)
        if inputs is None:
            result = Matches.empty()
        else:
            result = self._valid_only(self._match_normalised(*inputs), inputs.valid0, inputs.valid1)
        self._close_timings(time.perf_counter() - start)
        return result

    def _normalised(
        self,
        image0: ArrayLike,
        image1: ArrayLike,
        mask0: ArrayLike | None,
        mask1: ArrayLike | None,
    ) -> NormalisedPair | None:
        """Validated, robustly normalised ``(image0, valid0, image1, valid1)``; None if flat."""
        with self._timed("normalise"):
            img0, valid0 = prepare_image(image0, mask0, which="image0")
            img1, valid1 = prepare_image(image1, mask1, which="image1")
            if min(img0.shape) < MIN_SIDE or min(img1.shape) < MIN_SIDE:
                return None
            norm0, flat0 = robust_normalise(img0, valid0)
            norm1, flat1 = robust_normalise(img1, valid1)
        if flat0 or flat1:
            return None
        return NormalisedPair(norm0, valid0, norm1, valid1)

    @staticmethod
    def _valid_only(
        result: Matches, valid0: NDArray[np.bool_], valid1: NDArray[np.bool_]
    ) -> Matches:
        """Drop every match whose keypoint lies on an invalid pixel in either image."""
        keep = keypoints_on_valid_pixels(result.keypoints0, valid0) & keypoints_on_valid_pixels(
            result.keypoints1, valid1
        )
        return result if keep.all() else result.select(keep)

    def _close_timings(self, total: float) -> None:
        self.timings["total"] = total
        self.timings["other"] = max(
            0.0,
            total - sum(self.timings.get(k, 0.0) for k in ("normalise", "forward", "build")),
        )

    def match_many(self, pairs: Iterable[Sequence[Any]], *, batch_size: int = 1) -> list[Matches]:
        """Match several pairs with the same matcher.

        Args:
            pairs: Iterable of ``(image0, image1)`` or ``(image0, image1, mask0, mask1)``.
            batch_size: Images of the same shape run through the network together, up to
                this many at a time, where the matcher batches (the learned sparse
                matchers' detectors); the results equal one pair at a time (to float
                tolerance). Others match one pair at a time.

        Returns:
            One :class:`Matches` per pair, in order. :attr:`timings` then sums over all
            pairs.
        """
        if int(batch_size) < 1:
            raise InputError(f"must be >= 1, got {batch_size}", field="batch_size")
        pairs = list(pairs)
        for pair in pairs:
            if len(pair) not in (2, 4):
                raise InputError(
                    f"each pair must be (image0, image1[, mask0, mask1]), got {len(pair)} items"
                )
        start = time.perf_counter()
        self.timings = {}
        inputs = [
            self._normalised(*pair, *((None, None) if len(pair) == 2 else ())) for pair in pairs
        ]
        done = self._match_normalised_many([x for x in inputs if x is not None], int(batch_size))
        out, it = [], iter(done)
        for x in inputs:
            out.append(
                Matches.empty() if x is None else self._valid_only(next(it), x.valid0, x.valid1)
            )
        self._close_timings(time.perf_counter() - start)
        return out

    def _match_normalised_many(
        self, inputs: list[NormalisedPair], batch_size: int
    ) -> list[Matches]:
        """:meth:`_match_normalised` of several pairs (one at a time unless overridden)."""
        return [self._match_normalised(*x) for x in inputs]

    @abstractmethod
    def _match_normalised(
        self,
        image0: NDArray[np.float32],
        valid0: NDArray[np.bool_],
        image1: NDArray[np.float32],
        valid1: NDArray[np.bool_],
    ) -> Matches:
        """Match two images already normalised to ``[0, 1]`` (invalid pixels filled)."""
