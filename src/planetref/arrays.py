"""Array type aliases and index helpers shared by every part of the package.

One alias per array type, so a signature reads the same everywhere: ``F64`` is a numpy
array of float64 of any shape (the shape and units are stated in each docstring).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["F64", "expand_ranges"]

#: A float64 numpy array (shape and units in the docstring of whatever takes it).
F64 = NDArray[np.float64]


def expand_ranges(
    starts: NDArray[np.intp], counts: NDArray[np.intp]
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Every index of the ranges ``[starts[i], starts[i] + counts[i])``, with its range.

    Args:
        starts: First index of each range, ``(n,)``.
        counts: Length of each range, ``(n,)``.

    Returns:
        ``(owner, index)``, each ``(sum(counts),)``: the range ``i`` of each index, and
        the index, range after range.
    """
    counts = np.asarray(counts, np.intp)
    owner = np.repeat(np.arange(len(counts)), counts)
    within = np.arange(len(owner)) - np.repeat(np.cumsum(counts) - counts, counts)
    return owner, np.repeat(np.asarray(starts, np.intp), counts) + within
