"""The coarse stage's bounded search: its radius, and the front end's own NCC search.

A matcher with a bounded search (area-based NCC) gets, at the coarse level the front end
picks for the a-priori uncertainty (:meth:`~planetref.frontend.config.FrontendConfig.
coarse_level`), a search radius that covers that uncertainty (:func:`coarse_search_radius`;
:func:`planetref.frontend.matchers.matcher_options` gives it to the run's coarse
instance). :func:`coarse_fallback_matcher` is the same search with NCC's defaults: what
places a tile whose coarse matcher found no usable consensus (``frontend.coarse_fallback``).
"""

from __future__ import annotations

import functools
import math
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    from planetref.frontend.config import FrontendConfig
    from planetref.matching.base import Matcher

__all__ = ["COARSE_FALLBACK_MATCHER", "coarse_fallback_matcher", "coarse_search_radius"]

#: The area-based search of :func:`coarse_fallback_matcher`.
COARSE_FALLBACK_MATCHER = "ncc"


def coarse_search_radius(fe: FrontendConfig, ref_gsd_m: float) -> int:
    """A bounded coarse search's radius: the uncertainty at the coarse level, plus 4.

    Args:
        fe: The front end's settings.
        ref_gsd_m: Ground sampling distance of the reference ortho (metres).

    Returns:
        The radius, in coarse pixels; at most about ``coarse_max_px / 2 + 4``, whatever
        the uncertainty.
    """
    return math.ceil(fe.uncertainty_m / (ref_gsd_m * fe.coarse_level(ref_gsd_m))) + 4


@functools.lru_cache(maxsize=8)
def _fallback(options: tuple[tuple[str, Any], ...]) -> Matcher:
    from planetref.matching.registry import get_matcher

    return get_matcher(COARSE_FALLBACK_MATCHER, **dict(options))


def coarse_fallback_matcher(fe: FrontendConfig, ref_gsd_m: float) -> Matcher | None:
    """The front end's own coarse search, for tiles whose coarse matcher found no consensus.

    NCC's coarse-stage instance (NCC's ``coarse_defaults``, a radius of
    :func:`coarse_search_radius`; what :func:`planetref.frontend.matchers.matcher_options`
    gives NCC without user options): templates on a grid of the coarse image side, each
    searched over a radius that covers the a-priori uncertainty at the coarse level. It is
    part of the front end, not of the run's matcher, so it is the same whatever the
    matcher (``frontend.coarse_fallback``); one instance per process and settings.

    Args:
        fe: The front end's settings.
        ref_gsd_m: Ground sampling distance of the reference ortho (metres).

    Returns:
        The matcher, or None when ``fe.coarse_fallback`` is not ``"ncc"``.
    """
    if fe.coarse_fallback != "ncc":
        return None
    from planetref.matching.registry import MATCHERS

    cls = MATCHERS[COARSE_FALLBACK_MATCHER].matcher_class()
    assert cls.search_option is not None  # NCC declares a bounded search
    options = {**cls.coarse_defaults, cls.search_option: coarse_search_radius(fe, ref_gsd_m)}
    return _fallback(tuple(sorted(options.items())))
