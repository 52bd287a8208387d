"""The explicit registry of matchers: a dict literal, no plugin discovery.

Each factory imports its module only when called, so importing the registry (or running
``planetref matchers``) imports neither torch nor kornia.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from os import PathLike
from typing import Any, NamedTuple

from planetref.errors import InputError
from planetref.matching.base import Matcher, MatcherSpec
from planetref.matching.weights import missing_weights, resolve_weight

__all__ = ["MATCHERS", "MatcherAvailability", "available_matchers", "get_matcher"]


def _factory(module: str, cls: str, *, learned: bool) -> Callable[..., Matcher]:
    """Build a factory that imports ``planetref.matching.<module>`` on first use."""

    def make(
        *,
        weights_dir: str | PathLike[str] | None = None,
        device: Any = "cpu",
        **options: Any,
    ) -> Matcher:
        target = getattr(importlib.import_module(f"planetref.matching.{module}"), cls)
        if learned:
            options = {"weights_dir": weights_dir, "device": device, **options}
        elif str(device) not in ("cpu", "auto"):
            raise InputError(
                f"{target.name} runs on the CPU only, got device {device!r}", field="device"
            )
        accepted = set(target.option_names())
        unknown = sorted(set(options) - accepted)
        if unknown:
            raise InputError(
                f"unknown option(s) {', '.join(unknown)} for matcher {target.name!r}; "
                f"valid options: {', '.join(sorted(accepted - {'weights_dir', 'device'}))}"
            )
        return target.from_options(**options)

    make.__name__ = f"make_{cls}"
    make.__doc__ = f"Build :class:`planetref.matching.{module}.{cls}` (imported on call)."
    return make


MATCHERS: dict[str, MatcherSpec] = {
    "sift": MatcherSpec(
        name="sift",
        description="OpenCV SIFT, Lowe ratio test and mutual check",
        paradigm="handcrafted",
        weights=(),
        factory=_factory("sift", "SiftMatcher", learned=False),
    ),
    "doghardnet-lightglue": MatcherSpec(
        name="doghardnet-lightglue",
        description="DoG keypoints, HardNet descriptors, LightGlue (doghardnet)",
        paradigm="learned sparse",
        weights=("checkpoint_liberty_with_aug.pth", "doghardnet_v0-1_arxiv-pth"),
        factory=_factory("doghardnet_lightglue", "DogHardNetLightGlueMatcher", learned=True),
    ),
    "disk-lightglue": MatcherSpec(
        name="disk-lightglue",
        description="DISK (depth) keypoints and descriptors, LightGlue (disk)",
        paradigm="learned sparse",
        weights=("depth-save.pth", "disk_lightglue_v0-1_arxiv-pth"),
        factory=_factory("disk_lightglue", "DiskLightGlueMatcher", learned=True),
    ),
    "loftr": MatcherSpec(
        name="loftr",
        description="LoFTR (outdoor), detector-free coarse-to-fine transformer matching",
        paradigm="detector-free dense",
        weights=("loftr_outdoor.ckpt",),
        factory=_factory("loftr", "LoftrMatcher", learned=True),
    ),
    "aliked-lightglue": MatcherSpec(
        name="aliked-lightglue",
        description="ALIKED-N16 keypoints and descriptors, LightGlue (aliked)",
        paradigm="learned sparse",
        weights=("aliked-n16.pth", "aliked_lightglue_v0-1_arxiv-pth"),
        factory=_factory("aliked_lightglue", "AlikedLightGlueMatcher", learned=True),
    ),
    "xfeat-lighterglue": MatcherSpec(
        name="xfeat-lighterglue",
        description="XFeat sparse keypoints, LighterGlue (LightGlue xfeat)",
        paradigm="learned sparse",
        weights=("xfeat.pt", "xfeat-lighterglue.pt"),
        factory=_factory("xfeat", "XFeatLighterGlueMatcher", learned=True),
    ),
    "xfeat-star": MatcherSpec(
        name="xfeat-star",
        description="XFeat* semi-dense coarse matching with learned sub-cell refinement",
        paradigm="semi-dense",
        weights=("xfeat.pt",),
        factory=_factory("xfeat", "XFeatStarMatcher", learned=True),
    ),
    "ncc": MatcherSpec(
        name="ncc",
        description="Normalised cross-correlation of grid templates, sub-pixel peak fit",
        paradigm="area-based",
        weights=(),
        factory=_factory("ncc", "NccMatcher", learned=False),
    ),
}


def get_matcher(
    name: str,
    weights_dir: str | PathLike[str] | None = None,
    device: Any = "cpu",
    **options: Any,
) -> Matcher:
    """Build a matcher by registry name.

    Args:
        name: A key of :data:`MATCHERS`.
        weights_dir: Weights directory for learned matchers (see
            :func:`planetref.matching.weights.weights_dir`); ignored by the others.
        device: Torch device of learned matchers (``"cpu"``, ``"cuda"``...); the classical
            matchers accept only ``"cpu"``.
        **options: Matcher-specific keyword options (e.g. ``ratio`` for SIFT,
            ``max_keypoints`` for the sparse learned matchers, ``verify_weights``).

    Returns:
        A ready matcher. Learned models are loaded lazily, on the first match.

    Raises:
        InputError: Unknown name (the message lists the valid ones) or option.
        WeightsError: A weight file of a learned matcher is missing.
    """
    spec = MATCHERS.get(name)
    if spec is None:
        raise InputError(
            f"unknown matcher {name!r}; valid names: {', '.join(MATCHERS)}", field="matcher"
        )
    return spec.factory(weights_dir=weights_dir, device=device, **options)


class MatcherAvailability(NamedTuple):
    """Whether a matcher's weights are present.

    Attributes:
        name: Registry name.
        present: True when every weight file exists (always True without weights).
        missing: Cache names of the missing (or, with ``verify``, corrupt) files.
    """

    name: str
    present: bool
    missing: tuple[str, ...]


def available_matchers(
    weights_dir: str | PathLike[str] | None = None, *, verify: bool = False
) -> list[MatcherAvailability]:
    """Report, for every registered matcher, whether its weight files are present.

    Args:
        weights_dir: Weights directory (see :func:`planetref.matching.weights.weights_dir`).
        verify: Also check checksums (reads every file once per process); a corrupt file
            then counts as missing.

    Returns:
        One :class:`MatcherAvailability` ``(name, present, missing)`` per matcher, in
        registry order.
    """
    out = []
    for name, spec in MATCHERS.items():
        missing = missing_weights(spec.weights, weights_dir)
        if verify:
            from planetref.errors import WeightsError

            for f in spec.weights:
                if f in missing:
                    continue
                try:
                    resolve_weight(f, weights_dir, verify=True)
                except WeightsError:
                    missing.append(f)
        out.append(MatcherAvailability(name, not missing, tuple(missing)))
    return out
