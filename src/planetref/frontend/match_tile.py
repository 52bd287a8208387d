"""Former home of the tile algorithm, kept so that older imports keep working.

The concepts now live in modules of their own: :mod:`~planetref.frontend.result`
(:class:`TileResult`, :class:`StripMatches`), :mod:`~planetref.frontend.robust` (robust
fits), :mod:`~planetref.frontend.tile` (:func:`match_tile`),
:mod:`~planetref.frontend.journal` and :mod:`~planetref.frontend.strip`
(:func:`match_strip`).
"""

from __future__ import annotations

from planetref.frontend.result import STATUSES, StageDebug, StripMatches, TileResult, TileStatus
from planetref.frontend.robust import robust_translation, verify_points
from planetref.frontend.strip import match_strip
from planetref.frontend.tile import match_tile

__all__ = [
    "STATUSES",
    "StageDebug",
    "StripMatches",
    "TileResult",
    "TileStatus",
    "match_strip",
    "match_tile",
    "robust_translation",
    "verify_points",
]
