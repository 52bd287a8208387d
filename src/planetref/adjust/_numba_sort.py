"""numba implementation of the layout's stable counting sort (imported lazily).

The twin of ``np.argsort(keys, kind="stable")`` for small non-negative integer keys (the
numpy reference: a test binds both). Importing this module imports numba; the function
compiles on first use or loads from numba's on-disk cache.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np


@numba.njit(cache=True, nogil=True, error_model="numpy")
def counting_order(keys: Any, n_keys: int) -> Any:
    """The stable sorting permutation of ``keys`` (integers in ``[0, n_keys)``).

    Equal to ``np.argsort(keys, kind="stable")``: one counting pass, one prefix sum, one
    scatter (O(m + n_keys) instead of a comparison sort).
    """
    m = keys.shape[0]
    start = np.zeros(n_keys + 1, np.intp)
    for i in range(m):
        start[keys[i] + 1] += 1
    for k in range(n_keys):
        start[k + 1] += start[k]
    order = np.empty(m, np.intp)
    for i in range(m):
        k = keys[i]
        order[start[k]] = i
        start[k] += 1
    return order
