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
from planetref.matching.base import BaseMatcher, Matcher, MatcherSpec, Paradigm
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


def _spec(
    name: str, paradigm: Paradigm, target: str, description: str, weights: tuple[str, ...] = ()
) -> MatcherSpec:
    """A registry entry; ``target`` is ``"<module>.<class>"`` inside ``planetref.matching``.

    A matcher with weight files is a learned (torch) one: its factory passes it the weights
    directory and the device.
    """
    module, cls = target.split(".")
    factory = _factory(module, cls, learned=bool(weights))

    def load_class() -> type[BaseMatcher]:
        return getattr(importlib.import_module(f"planetref.matching.{module}"), cls)  # type: ignore[no-any-return]

    return MatcherSpec(name, description, paradigm, weights, factory, load_class)


MATCHERS: dict[str, MatcherSpec] = {
    spec.name: spec
    for spec in (
        _spec(
            "sift",
            "handcrafted",
            "sift.SiftMatcher",
            "OpenCV SIFT, Lowe ratio test and mutual check",
        ),
        _spec(
            "doghardnet-lightglue",
            "learned sparse",
            "doghardnet_lightglue.DogHardNetLightGlueMatcher",
            "DoG keypoints, HardNet descriptors, LightGlue (doghardnet)",
            ("checkpoint_liberty_with_aug.pth", "doghardnet_v0-1_arxiv-pth"),
        ),
        _spec(
            "disk-lightglue",
            "learned sparse",
            "disk_lightglue.DiskLightGlueMatcher",
            "DISK (depth) keypoints and descriptors, LightGlue (disk)",
            ("depth-save.pth", "disk_lightglue_v0-1_arxiv-pth"),
        ),
        _spec(
            "loftr",
            "detector-free dense",
            "loftr.LoftrMatcher",
            "LoFTR (outdoor), detector-free coarse-to-fine transformer matching",
            ("loftr_outdoor.ckpt",),
        ),
        _spec(
            "aliked-lightglue",
            "learned sparse",
            "aliked_lightglue.AlikedLightGlueMatcher",
            "ALIKED-N16 keypoints and descriptors, LightGlue (aliked)",
            ("aliked-n16.pth", "aliked_lightglue_v0-1_arxiv-pth"),
        ),
        _spec(
            "xfeat-lighterglue",
            "learned sparse",
            "xfeat.XFeatLighterGlueMatcher",
            "XFeat sparse keypoints, LighterGlue (LightGlue xfeat)",
            ("xfeat.pt", "xfeat-lighterglue.pt"),
        ),
        _spec(
            "xfeat-star",
            "semi-dense",
            "xfeat.XFeatStarMatcher",
            "XFeat* semi-dense coarse matching with learned sub-cell refinement",
            ("xfeat.pt",),
        ),
        _spec(
            "ncc",
            "area-based",
            "ncc.NccMatcher",
            "Normalised cross-correlation of grid templates, sub-pixel peak fit",
        ),
    )
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
