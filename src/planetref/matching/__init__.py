"""Image matching: one :class:`Matcher` protocol, an explicit registry of matchers.

Pixel convention
----------------
Every keypoint that leaves this package is ``(x, y)`` = ``(column, row)`` in pixels of
the array it was detected on, with the top-left corner of the first pixel at
``(0, 0)``; the centre of the first pixel is therefore ``(0.5, 0.5)``. This is the
convention of :mod:`planetref.camera` (``sample = x``, ``line = y``). OpenCV and kornia
put pixel centres at integers; each matcher converts exactly (``+0.5``) and says so.

Importing this package loads no model and imports neither torch nor kornia; use
:func:`get_matcher` (or :data:`~planetref.matching.registry.MATCHERS`) to build one.
"""

from __future__ import annotations

from planetref.matching.base import Matcher, MatcherSpec, Matches, Paradigm
from planetref.matching.registry import MATCHERS, available_matchers, get_matcher

__all__ = [
    "MATCHERS",
    "Matcher",
    "MatcherSpec",
    "Matches",
    "Paradigm",
    "available_matchers",
    "get_matcher",
]
